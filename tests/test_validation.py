"""Integer arguments accept every integral value a user may hold: ``numbers.Integral``
(``np.int64`` from a NumPy loop, a 0-d integer tensor) and integral floats (``100.0``), and
are stored as Python ``int``; everything else is a ValueError naming the argument."""

import numpy as np
import pytest
import torch

import torchmcmcpf as tp
from torchmcmcpf._validation import check_positive_int
from torchmcmcpf.filters.ipmcmc import IPMCMCSettings
from torchmcmcpf.filters.mcmc import MCMCSettings
from torchmcmcpf.filters.pmmh import PMMHSettings
from torchmcmcpf.scenarios import ground_radar


@pytest.mark.parametrize("value", [100, np.int64(100), np.int32(100), 100.0, np.float32(100), torch.tensor(100)])
def test_integral_values_are_accepted_as_int(value):
    out = check_positive_int(value, "num_particles")
    assert out == 100 and type(out) is int


@pytest.mark.parametrize("value", [True, 100.5, "100", float("nan"), float("inf"), 0, np.int64(-3), None,
                                   torch.tensor([100]), torch.tensor(1.5)])
def test_non_integral_values_are_refused_naming_the_argument(value):
    with pytest.raises(ValueError, match=r"num_particles must be an integer >= 1, got"):
        check_positive_int(value, "num_particles")


def test_filters_and_settings_store_python_ints():
    motion, sensor = tp.ConstantVelocity(1.0, 1.0), tp.LinearGaussian.position(1.0)
    filt = tp.IPMCMCFilter(motion, sensor, np.int64(40), num_chains=np.int64(4), burn_in=5.0)
    assert (filt.num_particles, filt.settings.num_chains, filt.settings.burn_in) == (40, 4, 5)
    assert all(type(v) is int for v in (filt.num_particles, filt.settings.num_chains, filt.settings.burn_in))
    assert type(MCMCSettings(num_chains=np.int16(2), thinning=3.0).thinning) is int
    assert type(IPMCMCSettings(max_extensions=np.uint8(1)).max_extensions) is int
    assert type(PMMHSettings(num_candidates=np.int64(4), burn_in=np.int64(1)).burn_in) is int
    with pytest.raises(ValueError, match="num_chains"):
        MCMCSettings(num_chains=2.5)
    # the filter runs with them: a NumPy loop variable as the particle count
    g = torch.Generator().manual_seed(0)
    sc = ground_radar(np.int64(1), np.int64(2), np.int64(1), generator=g)
    x0 = sc.initial_particles(np.int64(40), generator=g)
    radar = tp.SIRFilter(sc.motion, sc.sensor, np.float64(40.0))
    result = radar(sc.measurements, init=x0, generator=g)
    assert result.mean.shape == (2, 1, 1, 5) and bool(torch.isfinite(result.mean).all())
