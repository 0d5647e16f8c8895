"""The progress bar of a compiled filter says that its first step compiles (issue 25)."""

import torch

from torchmcmcpf import ConstantVelocity, LinearGaussian, SIRFilter
from torchmcmcpf.filters import IPMCMCFilter


def test_first_compiled_step_is_announced_once_per_shape(capsys):
    motion, sensor = ConstantVelocity(1.0, 1.0), LinearGaussian.position(1.0)
    filt = IPMCMCFilter(motion, sensor, 40, num_chains=4, compile_step=True)
    x = torch.zeros(2, 40, 1, 4)
    bar, note = filt._progress(3, x, True)
    bar.close()
    assert note == f"compiling (first call, about {filt.compile_seconds:.0f} s)" == "compiling (first call, about 14 s)"
    assert note in capsys.readouterr().err  # shown while the first step runs
    bar, note = filt._progress(3, x, True)  # the same shape again: compiled already
    bar.close()
    assert note is None
    bar, note = filt._progress(3, torch.zeros(3, 40, 1, 4), True)  # a new batch size recompiles
    bar.close()
    assert note is not None
    eager = SIRFilter(motion, sensor, 40)
    assert eager._progress(3, x, True)[1] is None and eager._progress(3, x, False) == (range(3), None)
