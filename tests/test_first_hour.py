"""Issue 52 ("First hour, part 2"): what a new user met, each friction pinned by a test.

- the demo on a loaded machine picks a safe thread count itself and says so;
- every scenario builds on the requested device (no tensor made without ``device=``), and
  every study's quick mode runs on CUDA when a GPU is present;
- guards: a memory estimate before a large allocation, resume across filter kinds refused,
  shape errors that name the layouts, CLI argument errors before any file is touched, a
  memory budget below 1 MiB refused, no spurious ArviZ warning, one time for ``bench``.
"""

from __future__ import annotations

import argparse
import inspect
import json
import re
import warnings
from pathlib import Path

import pytest
import torch
from torch.overrides import TorchFunctionMode

import torchmcmcpf as tp
from torchmcmcpf import __main__ as cli
from torchmcmcpf import runtime
from torchmcmcpf.__main__ import main

ROOT = Path(__file__).resolve().parents[1]
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


@pytest.fixture
def budget():
    """Set the allocation budget for one test, restored after it."""
    old = runtime.set_allocation_budget(None)
    yield runtime.set_allocation_budget
    runtime.set_allocation_budget(old)


# ----------------------------------------------------------------------------- the demo under load
def test_demo_picks_one_thread_on_a_loaded_machine(monkeypatch):
    """The demo kept torch's default thread count on a loaded 2-core machine (38.5 s a step):
    without ``--threads`` it now runs on 1 thread and says so; ``--threads`` wins."""
    args = argparse.Namespace(filter="ipmcmc", quick=False, threads=None, **cli.DEMO_DEFAULTS)
    monkeypatch.setattr(cli, "load_average", lambda: (9.0, 2))
    monkeypatch.setattr(cli, "torch_threads", lambda: 2)
    threads, note = cli.demo_threads(args)
    assert threads == 1 and "load average 9.0 on 2 cores" in note and "running torch on 1 thread" in note
    args.threads = 2
    assert cli.demo_threads(args) == (2, None)  # the user's choice stands
    args.threads = None
    monkeypatch.setattr(cli, "load_average", lambda: (0.5, 2))
    assert cli.demo_threads(args) == (None, None)  # a quiet machine: torch's own count


def test_demo_runs_on_one_thread_under_load_and_restores_torch(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(cli, "load_average", lambda: (9.0, 2))
    monkeypatch.setattr(cli, "torch_threads", lambda: 2)
    before = torch.get_num_threads()
    out = tmp_path / "demo"
    assert main(["demo", "--steps", "1", "--particles", "40", "--chains", "4", "--burn-in", "2", "--targets", "2",
                 "--runs", "1", "--out", out, "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "running torch on 1 thread" in printed and "--threads N overrides" in printed
    assert json.loads((out / "metrics.json").read_text())["settings"]["threads"] == 1
    assert torch.get_num_threads() == before


# ----------------------------------------------------------------------------- the command line
def test_demo_argument_errors_come_before_any_file(tmp_path, capsys):
    """``demo --chains 1`` printed that it replaced the results folder, then failed."""
    out = tmp_path / "demo"
    with pytest.raises(SystemExit) as err:
        main(["demo", "--chains", "1", "--out", out, "--no-progress"])
    assert err.value.code == 2
    captured = capsys.readouterr()
    assert "argument --chains" in captured.err and "num_chains must be an integer >= 2" in captured.err
    assert "replacing" not in captured.out and not out.exists()


@pytest.mark.parametrize("value", ["10", "0", "1000000", "1.5k"])
def test_memory_budget_below_one_mib_is_refused(value, tmp_path, capsys):
    with pytest.raises(SystemExit) as err:
        main(["demo", "--quick", "--memory-budget", value, "--out", tmp_path / "d", "--no-progress"])
    assert err.value.code == 2
    assert "argument --memory-budget: must be a number of bytes >= 1048576" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()
    with pytest.raises(ValueError, match=r"memory_budget \(bytes\) must be an integer >= 1048576"):
        runtime.set_memory_budget(10)


def test_memory_budget_takes_suffixes():
    from torchmcmcpf.experiments._options import memory_budget_arg

    assert memory_budget_arg("512M") == 512 * 2**20 and memory_budget_arg("2G") == 2 * 2**30
    assert memory_budget_arg(str(2**20)) == 2**20


def test_bench_states_one_time():
    """``bench --help`` said 5-8 minutes, the READMEs 4-6: one figure, the benchmarks README's."""
    parser = argparse.ArgumentParser()
    cli._bench_parser(parser.add_subparsers())
    help_text = " ".join(parser._subparsers._group_actions[0].choices["bench"].format_help().split())
    bench_readme = " ".join((ROOT / "benchmarks" / "README.md").read_text().split())
    readme = " ".join((ROOT / "README.md").read_text().split())
    stated = re.search(r"about (\d+-\d+) minutes on 2 quiet cores", bench_readme).group(1)
    assert f"About {stated} minutes" in help_text
    assert f"bench [--quick]` (about {stated} minutes" in readme
    assert set(re.findall(r"(\d+-\d+) minutes", help_text)) == {stated}


# ----------------------------------------------------------------------------- allocation guard
def test_initial_particles_refuses_beyond_the_budget(budget):
    """``initial_particles(10**8)`` ended in torch's raw allocator error."""
    from torchmcmcpf.scenarios import ground_radar

    g = torch.Generator().manual_seed(0)
    scn = ground_radar(2, 1, 2, generator=g)
    budget(10**9)
    with pytest.raises(ValueError, match=r"initial_particles\(num_particles=100000000\) .* needs an estimated 16 GB "
                                         r"\(16,000,000,000 bytes\), above the allocation budget of 1 GB"):
        scn.initial_particles(10**8, generator=g)
    assert scn.initial_particles(10, generator=g).shape == (2, 10, 2, 5)  # small ones pass
    budget(None)  # the default: the memory available now, which no machine has for this
    with pytest.raises(ValueError, match="initial_particles.*above the allocation budget .*the memory available"):
        scn.initial_particles(10**13, generator=g)


def test_filters_refuse_a_problem_beyond_the_budget(budget):
    motion, sensor = tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0)
    filt = tp.SIRFilter(motion, sensor, 1000)
    x = torch.zeros(2, 1000, 2, 4)
    need = filt.working_bytes(2, 2, torch.float32)
    assert need == 4 * 2 * 1000 * (2 * 4 * 4 + 4 + 2)
    budget(need - 1)
    with pytest.raises(ValueError, match=r"SIRFilter with N=1000 particles, B=2 runs, K=2 targets .* needs an "
                                         r"estimated .* above the allocation budget .*set_allocation_budget"):
        filt.init(x)
    with pytest.raises(ValueError, match="SIRFilter with N=1000"):
        filt(torch.zeros(3, 2, 2, 2), init=x, generator=torch.Generator())
    budget(need + 2 * 1000 * 38)  # room for the working copies, not for a history of 3 steps
    filt.init(x)
    with pytest.raises(ValueError, match=r"history of 3 steps\).* or history=False"):
        filt(torch.zeros(3, 2, 2, 2), init=x, generator=torch.Generator(), history=True)


# ----------------------------------------------------------------------------- resume across kinds
def _states():
    motion, sensor = tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0)
    z, g = torch.zeros(2, 2, 2, 2), torch.Generator().manual_seed(0)
    x = torch.zeros(2, 40, 2, 4)
    sir, pmmh = tp.SIRFilter(motion, sensor, 40), tp.PMMHFilter(motion, sensor, 40)
    ipmcmc = tp.IPMCMCFilter(motion, sensor, 40, num_chains=4, burn_in=2)
    return z, g, sir, pmmh, ipmcmc, sir(z, init=x, generator=g).state, pmmh(z, init=x, generator=g).state


def test_pmmh_refuses_an_sir_state():
    """A PMMHFilter given an SIRFilter's state restarted its parameter search without a word."""
    z, g, sir, pmmh, _, sir_state, _ = _states()
    message = r"state.extras has no \['pmmh'\], which the states of PMMHFilter"
    with pytest.raises(ValueError, match=message):
        pmmh(z, init=sir_state, generator=g)
    with pytest.raises(ValueError, match=message):
        pmmh.step(sir_state, z[0], generator=g)
    pmmh(z, init=pmmh.init(sir_state.x), generator=g)  # a fresh start from the particles is fine


def test_ipmcmc_refuses_a_pmmh_state():
    z, g, _, pmmh, ipmcmc, _, pmmh_state = _states()
    message = r"state.extras holds \['pmmh'\], .* IPMCMCFilter .* of PMMHFilter"
    with pytest.raises(ValueError, match=message):
        ipmcmc(z, init=pmmh_state, generator=g)
    with pytest.raises(ValueError, match=message):
        ipmcmc.step(pmmh_state, z[0], generator=g)
    pmmh(z, init=pmmh_state, generator=g)  # its own filter resumes it
    pmmh.step(pmmh_state, z[0], generator=g)


# ----------------------------------------------------------------------------- layouts named
def test_errors_name_the_layouts():
    from torchmcmcpf.scenarios import ground_radar

    g = torch.Generator().manual_seed(0)
    scn = ground_radar(2, 2, 2, generator=g)
    filt = tp.SIRFilter(scn.motion, scn.sensor, 50)
    x0 = scn.initial_particles(50, generator=g)
    # one frame without the time axis: it said "measurements has batch size 36 ... expected 2"
    with pytest.raises(ValueError, match=r"expected \(T, B, \*grid\) with B = 2 runs .* without the time axis"):
        filt(scn.measurements[0], init=x0, generator=g)
    # init without the run axis: it said "expected (*, 50, *, 5)"
    with pytest.raises(ValueError, match=r"init has shape \(50, 2, 5\) \(3 dims\), expected \(B, N, K, D\) = "
                                         r"\(B, 50, K, 5\)"):
        filt(scn.measurements, init=x0[0], generator=g)
    with pytest.raises(ValueError, match=r"expected \(B, N, K, D\) = \(\*, 50, \*, 5\)"):
        filt(scn.measurements, init=x0[:, :10], generator=g)
    # step on the bare particles: point to init
    with pytest.raises(ValueError, match=r"state must be a ParticleState, got Tensor .* state = filt.init\(x\)"):
        filt.step(x0, scn.measurements[0], generator=g)


# ----------------------------------------------------------------------------- ArviZ
def test_to_arviz_gives_no_chains_than_draws_warning():
    """ArviZ warned "More chains (20) than draws (10)" on arrays that are (chain, draw)."""
    pytest.importorskip("arviz")
    motion, sensor = tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0)
    filt = tp.IPMCMCFilter(motion, sensor, 200, num_chains=20, burn_in=2)
    res = filt(torch.zeros(1, 1, 2, 2), init=torch.zeros(1, 200, 2, 4), generator=torch.Generator().manual_seed(0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        data = res.to_arviz()
    assert dict(data.posterior.sizes)["chain"] == 20 and dict(data.posterior.sizes)["draw"] == 10


# ----------------------------------------------------------------------------- devices
_FACTORIES = {torch.tensor, torch.as_tensor, torch.zeros, torch.ones, torch.full, torch.empty, torch.arange,
              torch.linspace, torch.eye, torch.rand, torch.randn, torch.randint}


class _Undeviced(TorchFunctionMode):
    """Record the tensor factories that code in ``torchmcmcpf.scenarios`` calls without
    ``device=`` (on a GPU those tensors land on the CPU next to CUDA ones)."""

    def __init__(self):
        super().__init__()
        self.found: list[str] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in _FACTORIES and "device" not in kwargs:
            caller = inspect.currentframe().f_back
            module = caller.f_globals.get("__name__", "")
            if module.startswith("torchmcmcpf.scenarios"):
                self.found.append(f"{module}:{caller.f_lineno} {func.__name__}")
        return func(*args, **kwargs)


def _build_every_scenario(device):
    from torchmcmcpf.scenarios import crossing, ground_radar, group_merge, ling, maroulas, septier

    g = torch.Generator(device).manual_seed(0)
    made = {
        "ground_radar": ground_radar(2, 2, 2, generator=g, device=device),
        "crossing": crossing(2, 3, 2, generator=g, device=device),
        "ling": ling([10.0, 12.0], 2, generator=g, num_steps=2, device=device),
        "septier": septier(2, 3, generator=g),
        "group_merge": group_merge(2, generator=g, num_steps=3, merge_step=2),
        "maroulas": maroulas.simulate(2, 3, sensor=maroulas.paper_sensor("linear").to(device), generator=g,
                                      device=device),
    }
    made["initial_particles"] = made["ground_radar"].initial_particles(5, generator=g)
    made["birth_particles"] = maroulas.birth_particles(maroulas.paper_sensor("linear").to(device),
                                                       made["maroulas"].z_slot[0], 5, generator=g)
    return made


def _tensors(obj, seen=None):
    """Every tensor in a scenario: fields, models' parameters and buffers, nested tuples."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return
    seen.add(id(obj))
    if torch.is_tensor(obj):
        yield obj
    elif isinstance(obj, torch.nn.Module):
        yield from obj.parameters()
        yield from obj.buffers()
    elif isinstance(obj, tuple):
        for item in obj:
            yield from _tensors(item, seen)
    elif hasattr(obj, "__dataclass_fields__"):
        for name in obj.__dataclass_fields__:
            yield from _tensors(getattr(obj, name), seen)


def test_scenarios_make_no_tensor_without_a_device():
    """group_merge made ``aim`` (and ling its SNRs) without ``device=``: CPU tensors that met
    CUDA ones (``reproduce septier-groups --quick --device cuda`` crashed). A tensor the
    scenario code makes on the CPU on purpose says ``device="cpu"``."""
    with _Undeviced() as mode:
        _build_every_scenario("cpu")
    assert mode.found == [], mode.found


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=CUDA)])
def test_every_scenario_tensor_lives_on_the_requested_device(device):
    for name, made in _build_every_scenario(device).items():
        found = {str(t.device) for t in _tensors(made)}
        assert found == {str(torch.device(device, 0) if device == "cuda" else torch.device(device))}, (name, found)


@CUDA
@pytest.mark.parametrize("name", ["bocquel-sir-ablation", "bocquel-table2", "crossing", "group-merge-scenario",
                                  "ling-rmse-vs-snr", "maroulas-hmc", "septier-birth-death", "septier-groups", "soak"])
def test_every_study_quick_runs_on_cuda(name, tmp_path):
    """Every study's quick mode on the GPU (issue 52; a GPU machine runs these)."""
    from torchmcmcpf import experiments

    assert name in experiments.discover()
    assert main(["reproduce", name, "--quick", "--device", "cuda", "--out", tmp_path, "--no-progress"]) == 0


def test_the_cuda_study_list_is_complete():
    from torchmcmcpf import experiments

    marker = next(m for m in test_every_study_quick_runs_on_cuda.pytestmark if m.name == "parametrize")
    assert sorted(marker.args[1]) == sorted(experiments.discover())
