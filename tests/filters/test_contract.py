"""One contract, every filter (torchfilter-style contract test, issue 9).

Every algorithm is built as ``Filter(motion, sensor, num_particles, *, settings...,
compile_step=...)`` and checked for: the shapes of ``FilterResult``; same seed -> identical
bits; checkpoint (``torch.save`` of the state and the generator state, plain
``torch.load``) and resume -> identical bits to the uninterrupted run; ``compile_step=True``
-> identical bits to eager (one iteration/step kernel compiled with ``fullgraph=True``, so a
graph break fails the test); each bad input -> ``ValueError`` naming the argument, raised
before the first step; the ``StepInfo`` fields. Add a new filter to ``FILTERS`` and it is
covered (with its own problem in ``PROBLEMS`` when it needs other models, as the group filter's
pixel frames and virtual-leader motion).
"""

import copy
import functools
import math

import pytest
import torch
from torch.utils._pytree import tree_flatten

from torchmcmcpf import (
    ConstantVelocity,
    FilterResult,
    LinearGaussian,
    ParticleState,
    StepInfo,
    _native,
)
from torchmcmcpf.filters import (
    GroupMCMCFilter,
    IPMCMCFilter,
    MCMCFilter,
    PartitionedSIRFilter,
    PMMHFilter,
    ResampleMoveFilter,
    SIRFilter,
)
from torchmcmcpf.kernels.hmc_refine import HMCRefine
from torchmcmcpf.models.sensors.radar import RangeDopplerBearingTBD

DT = torch.float64
B, N, K, T = 2, 16, 2, 4


@functools.cache
def _group_scenario():
    from torchmcmcpf.scenarios.group_merge import group_merge

    return group_merge(B, generator=torch.Generator().manual_seed(0), num_steps=T, merge_step=3)


def group_problem():
    """Paper 004's scenario, 4 steps: 0/1 frames (float64), all slots inactive at the start."""
    scn = _group_scenario()
    return scn.motion, scn.sensor, scn.frames.to(DT), torch.zeros(B, N, 4, 4, dtype=DT)


def _group(m, s, c):
    scn = _group_scenario()
    return GroupMCMCFilter(m, s, N, existence=scn.existence, structure_prior=scn.structure_prior, num_chains=4,
                           burn_in=3, thinning=2, xi=0.5, lag=1, p_past=0.25, p_window_birth=0.25, alpha="predictive",
                           birth="frame", compile_step=c)

#: name -> (factory(motion, sensor, compile_step), what StepInfo computes: ess, log_evidence, acceptance, extras)
FILTERS = {
    "sir": (lambda m, s, c: SIRFilter(m, s, N, compile_step=c), (True, True, False, set())),
    "mcmc": (lambda m, s, c: MCMCFilter(m, s, N, num_chains=4, burn_in=3, thinning=2, compile_step=c),
             (False, False, True, {"acceptance_joint", "acceptance_refine"})),
    "ipmcmc": (lambda m, s, c: IPMCMCFilter(m, s, N, num_chains=4, burn_in=3, compile_step=c),
               (False, False, True, {"rhat", "rhat_slot", "rhat_dim", "extensions"})),
    # the HMC refinement option (issue 13 item 5): runs eagerly inside both MCMC filters
    "mcmc_hmc": (lambda m, s, c: MCMCFilter(m, s, N, num_chains=4, burn_in=3, thinning=2, compile_step=c,
                                            hmc=HMCRefine(step_size=0.5, num_leapfrog=2, every=2)),
                 (False, False, True, {"acceptance_joint", "acceptance_refine", "acceptance_hmc"})),
    "ipmcmc_hmc": (lambda m, s, c: IPMCMCFilter(m, s, N, num_chains=4, burn_in=3, compile_step=c,
                                                hmc=HMCRefine(step_size=0.5, num_leapfrog=2, every=2)),
                   (False, False, True, {"rhat", "rhat_slot", "rhat_dim", "extensions", "acceptance_hmc"})),
    "resample_move": (lambda m, s, c: ResampleMoveFilter(m, s, N, num_hmc_steps=3, step_size=0.3, compile_step=c),
                      (True, True, True, {"ess_after_move"})),
    "pmmh": (lambda m, s, c: PMMHFilter(m, s, N, num_candidates=4, compile_step=c),
             (True, True, True, {"theta_mean", "candidate_ess"})),
    "partitioned": (lambda m, s, c: PartitionedSIRFilter(m, s, N, compile_step=c), (True, False, False, {"ess_min"})),
    # paper 004's group filter with the past and window birth moves (issue 23): extras of shape (B, ...)
    "group": (_group, (False, False, True, {"acceptance_joint", "acceptance_structure", "acceptance_target",
                                            "acceptance_past", "acceptance_birth", "structure_prob", "exists_prob",
                                            "expected_count", "all_exist_prob", "structure_prob_all_exist"})),
}
#: filters that need a problem of their own (default :func:`problem`)
PROBLEMS = {"group": group_problem}


def problem():
    motion, sensor = ConstantVelocity(1.0, 1.0).to(DT), LinearGaussian.position(1.0).to(DT)
    g = torch.Generator().manual_seed(0)
    x = torch.tensor([[0.0, 1.0, 0.0, 0.5], [20.0, -1.0, 5.0, 0.0]], dtype=DT).expand(B, K, 4)
    zs = []
    for _ in range(T):
        x = motion.sample(x, generator=g)
        zs.append(x[..., [0, 2]] + torch.randn(B, K, 2, generator=g, dtype=DT))
    init = x.new_zeros(B, N, K, 4) + 3.0 * torch.randn(B, N, K, 4, generator=g, dtype=DT)
    return motion, sensor, torch.stack(zs), init


def build(name, compile_step=False):
    motion, sensor, zs, init = PROBLEMS.get(name, problem)()
    return FILTERS[name][0](motion, sensor, compile_step), zs, init


def run(filt, zs, init, seed):
    return filt(zs, init=init, generator=torch.Generator().manual_seed(seed))


def _same_bits(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Equal values with NaN where the other has NaN (a move never picked in a step)."""
    return a.shape == b.shape and bool(((a == b) | (torch.isnan(a) & torch.isnan(b))).all())


def assert_same(a: FilterResult, b: FilterResult):
    assert torch.equal(a.mean, b.mean)
    assert torch.equal(a.state.x, b.state.x) and torch.equal(a.state.log_w, b.state.log_w)
    for f in ("ess", "log_evidence", "acceptance"):
        assert _same_bits(getattr(a.info, f), getattr(b.info, f))
    assert a.info.extras.keys() == b.info.extras.keys()
    for k in a.info.extras:
        assert _same_bits(a.info.extras[k], b.info.extras[k]), k


@pytest.mark.parametrize("name", FILTERS)
def test_shapes_and_info_fields(name):
    filt, zs, init = build(name)
    res = run(filt, zs, init, 1)
    k = init.shape[2]
    assert res.mean.shape == (T, B, k, 4) and res.mean.dtype == DT
    assert res.state.x.shape == (B, N, k, 4) and res.state.log_w.shape == (B, N)
    torch.testing.assert_close(torch.logsumexp(res.state.log_w, -1), torch.zeros(B, dtype=DT))
    assert StepInfo._fields == ("ess", "log_evidence", "acceptance", "extras")
    has_ess, has_ev, has_acc, extras = FILTERS[name][1]
    for field, computed in (("ess", has_ess), ("log_evidence", has_ev), ("acceptance", has_acc)):
        value = getattr(res.info, field)
        assert value.shape == (T, B)
        assert bool(torch.isfinite(value).all()) if computed else bool(torch.isnan(value).all())
    assert set(res.info.extras) == extras
    assert all(v.shape[:2] == (T, B) for v in res.info.extras.values())
    assert res.log_evidence.shape == (B,)
    assert bool(torch.isfinite(res.log_evidence).all()) == has_ev
    # one step through the public step() gives the same types
    state, info = filt.step(filt.init(init), zs[0], generator=torch.Generator().manual_seed(1))
    assert isinstance(state, ParticleState) and isinstance(info, StepInfo) and info.ess.shape == (B,)


@pytest.mark.parametrize("name", FILTERS)
def test_same_seed_same_bits(name):
    filt, zs, init = build(name)
    a, b, c = run(filt, zs, init, 5), run(filt, zs, init, 5), run(filt, zs, init, 6)
    assert_same(a, b)
    assert not torch.equal(a.state.x, c.state.x)


@pytest.mark.parametrize("name", FILTERS)
def test_checkpoint_and_resume_same_bits(name, tmp_path):
    filt, zs, init = build(name)
    whole = run(filt, zs, init, 7)
    g = torch.Generator().manual_seed(7)
    first = filt(zs[:2], init=init, generator=g)
    torch.save({"state": first.state, "generator": g.get_state()}, tmp_path / "ckpt.pt")
    ckpt = torch.load(tmp_path / "ckpt.pt")  # default weights_only=True
    g2 = torch.Generator()
    g2.set_state(ckpt["generator"])
    rest = filt(zs[2:], init=ckpt["state"], generator=g2)
    assert torch.equal(torch.cat([first.mean, rest.mean]), whole.mean)
    assert torch.equal(rest.state.x, whole.state.x) and torch.equal(rest.state.log_w, whole.state.log_w)
    for f in ("ess", "log_evidence", "acceptance"):
        joined = torch.cat([getattr(first.info, f), getattr(rest.info, f)])
        assert torch.equal(joined, getattr(whole.info, f)) or bool(torch.isnan(joined).all())


@pytest.mark.compile
@pytest.mark.parametrize("name", FILTERS)
def test_compiled_step_equals_eager_bit_for_bit(name):
    eager, zs, init = build(name)
    compiled, _, _ = build(name, compile_step=True)
    torch._dynamo.reset()
    assert_same(run(eager, zs, init, 9), run(compiled, zs, init, 9))  # fullgraph=True: no graph break


@pytest.mark.parametrize("name", FILTERS)
def test_result_travels(name, tmp_path):
    filt, zs, init = build(name)
    res = run(filt, zs, init, 3)
    torch.save(res, tmp_path / "res.pt")
    back = torch.load(tmp_path / "res.pt")  # weights_only=True: containers are safe globals
    assert isinstance(back, FilterResult) and isinstance(back.state, ParticleState)
    assert_same(res, back)
    arrays = res.to_numpy()
    k = init.shape[2]
    assert arrays["mean"].shape == (T, B, k, 4) and arrays["state.x"].shape == (B, N, k, 4)
    assert arrays["info.ess"].shape == (T, B)
    assert all(arrays[f"info.{key}"].shape[:2] == (T, B) for key in res.info.extras)
    text = repr(res)
    assert len(text) < 1500 and f"mean=float64(4, 2, {k}, 4)" in text and "tensor(" not in text


# ----------------------------------------------------------------------------- bad input
def _bad_inputs(zs, init):
    meta = torch.empty(zs.shape, device="meta", dtype=DT)
    return {
        "float32 measurements, float64 init": (zs.float(), init, "measurements has dtype torch.float32"),
        "integer measurements": (zs.round().long(), init, "measurements has dtype torch.int64"),
        "measurements on meta": (meta, init, "measurements is on the meta device"),
        "init on meta": (zs, torch.empty(init.shape, device="meta", dtype=DT), "init is on the meta device"),
        "time axis of length 0": (zs[:0], init, "measurements has shape .*time axis of length 0"),
        "NaN in the last frame": (torch.cat([zs[:-1], zs[-1:] * math.nan]), init,
                                  rf"measurements\[{T - 1}\] contains {zs[-1].numel()} NaN"),
        "wrong batch": (zs[:, :1], init, r"expected \(T, B, \*grid\) with B = \d+ runs .* got 1"),
        "NaN in init": (zs, init * math.nan, "init contains"),
    }


@pytest.mark.parametrize("name", FILTERS)
@pytest.mark.parametrize("case", list(_bad_inputs(torch.zeros(T, B, K, 2), torch.zeros(B, N, K, 4))))
def test_bad_input_raises_before_the_first_step(name, case, monkeypatch):
    filt, zs, init = build(name)
    z_bad, init_bad, message = _bad_inputs(zs, init)[case]
    steps = []
    monkeypatch.setattr(filt, "_step", lambda *a: steps.append(1))
    with pytest.raises(ValueError, match=message):
        filt(z_bad, init=init_bad, generator=torch.Generator().manual_seed(0))
    assert not steps  # validated once, before any step ran


@pytest.mark.parametrize("name", FILTERS)
def test_step_validates_like_forward(name):
    filt, zs, init = build(name)
    state, g = filt.init(init), torch.Generator().manual_seed(0)
    with pytest.raises(ValueError, match=f"z contains {zs[0].numel()} NaN"):
        filt.step(state, zs[0] * math.nan, generator=g)  # an all-NaN frame
    with pytest.raises(ValueError, match="z has dtype torch.float32"):
        filt.step(state, zs[0].float(), generator=g)
    with pytest.raises(ValueError, match="z has dtype torch.int64"):
        filt.step(state, zs[0].long(), generator=g)
    with pytest.raises(ValueError, match="generator"):
        filt.step(state, zs[0], generator=None)
    with pytest.raises(ValueError, match="state must be a ParticleState"):
        filt.step(init, zs[0], generator=g)


@pytest.mark.parametrize("name", FILTERS)
def test_models_on_another_device_are_refused(name):
    filt, zs, init = build(name)
    filt = copy.deepcopy(filt).to("meta")  # a copy: the group problem's models are shared (functools.cache)
    with pytest.raises(ValueError, match="the models' parameters are on meta, expected cpu"):
        filt(zs, init=init, generator=torch.Generator().manual_seed(0))
    if torch.cuda.is_available():
        with pytest.raises(ValueError, match="measurements is on cuda"):
            build(name)[0](zs.cuda(), init=init, generator=torch.Generator().manual_seed(0))


@pytest.mark.parametrize("name", [name for name in FILTERS if name not in PROBLEMS])  # radar sensor filters
def test_negative_radar_amplitude_is_refused(name):
    deg = math.pi / 180
    sensor = RangeDopplerBearingTBD.uniform((2740, 2850), (-8, 8), (-5 * deg, 4 * deg)).to(DT)
    motion = ConstantVelocity(1.0, 1.0, amplitude_q=0.01).to(DT)
    filt = FILTERS[name][0](motion, sensor, False)
    init = torch.zeros(B, N, K, 5, dtype=DT)
    init[..., 0], init[..., 4] = 2800.0, 5.0
    init[0, 3, 1, 4] = -1.0
    z = torch.zeros((1, B) + tuple(sensor.frame_shape), dtype=DT)
    with pytest.raises(ValueError, match="init .signal component. has negative value"):
        filt(z, init=init, generator=torch.Generator().manual_seed(0))


# ----------------------------------------------------------------------------- births and deaths
def existence_problem():
    from torchmcmcpf.models.existence import BirthDeath
    from torchmcmcpf.models.sensors.points import PoissonClutterPoints
    from torchmcmcpf.scenarios.septier import stack_frames

    area = ((0.0, 5000.0), (0.0, 5000.0))
    motion = ConstantVelocity(1.0, 1.0).to(DT)
    sensor = PoissonClutterPoints(10.0, 4.0, area, noise_std=10.0).to(DT)
    existence = BirthDeath(0.05, 0.05, area, velocity_std=5.0, birth_std=10.0).to(DT)
    g = torch.Generator().manual_seed(0)
    x = torch.tensor([2000.0, 3.0, 2500.0, -2.0], dtype=DT).expand(B, 1, 4)
    frames = []
    for _ in range(T):
        x = motion.sample(x, generator=g)
        frames.append(sensor.simulate(x, exists=torch.ones(B, 1, dtype=torch.bool), generator=g))
    z = stack_frames(frames)  # padded to a common M
    return motion, sensor, existence, z, torch.zeros(B, N, K, 4, dtype=DT)


EXISTENCE_FILTERS = {
    "sir": lambda m, s, e: SIRFilter(m, s, N, existence=e),
    "mcmc": lambda m, s, e: MCMCFilter(m, s, N, num_chains=4, burn_in=3, existence=e),
    "ipmcmc": lambda m, s, e: IPMCMCFilter(m, s, N, num_chains=4, burn_in=3, existence=e),
    "resample_move": lambda m, s, e: ResampleMoveFilter(m, s, N, num_hmc_steps=2, existence=e),
}


@pytest.mark.parametrize("name", EXISTENCE_FILTERS)
def test_births_and_deaths_same_contract(name, tmp_path):
    """Every filter takes a BirthDeath model the same way: shapes, same seed -> same bits,
    checkpoint/resume -> same bits (the flags travel in the ParticleState)."""
    motion, sensor, existence, z, init = existence_problem()
    filt = EXISTENCE_FILTERS[name](motion, sensor, existence)
    whole = filt(z, init=init, generator=torch.Generator().manual_seed(2))
    again = filt(z, init=init, generator=torch.Generator().manual_seed(2))
    assert whole.exists_prob.shape == (T, B, K) and whole.state.exists.shape == (B, N, K)
    assert torch.equal(whole.exists_prob, again.exists_prob) and torch.equal(whole.state.x, again.state.x)
    g = torch.Generator().manual_seed(2)
    first = filt(type(z)(z.z[:2], z.mask[:2]), init=init, generator=g)
    torch.save({"state": first.state, "generator": g.get_state()}, tmp_path / "ckpt.pt")
    ckpt = torch.load(tmp_path / "ckpt.pt")
    g2 = torch.Generator()
    g2.set_state(ckpt["generator"])
    rest = filt(type(z)(z.z[2:], z.mask[2:]), init=ckpt["state"], generator=g2)
    assert torch.equal(torch.cat([first.exists_prob, rest.exists_prob]), whole.exists_prob)
    assert torch.equal(rest.state.x, whole.state.x) and torch.equal(rest.state.exists, whole.state.exists)


# ----------------------------------------------------------------------------- bind once
def _step_function(name):
    """The public step function of a filter of :data:`FILTERS` and its keyword models besides
    ``motion``, ``sensor``, ``settings``, ``existence``."""
    from torchmcmcpf.filters import (
        group_mcmc_step,
        ipmcmc_step,
        mcmc_step,
        partitioned_sir_step,
        pmmh_step,
        resample_move_step,
        sir_step,
    )

    fn = {"sir": sir_step, "mcmc": mcmc_step, "mcmc_hmc": mcmc_step, "ipmcmc": ipmcmc_step,
          "ipmcmc_hmc": ipmcmc_step, "resample_move": resample_move_step, "pmmh": pmmh_step,
          "partitioned": partitioned_sir_step, "group": group_mcmc_step}[name]
    return fn


def _first_state(filt, name, init):
    return filt.init_inactive(B, 4, dtype=DT) if name == "group" else filt.init(init)


@pytest.fixture
def no_setup_in_steps(monkeypatch):
    """From now on building a TargetDynamics, calling active_prior or applying an existence
    proposal raises: a step must find all of it in the filter's bound object."""
    from torchmcmcpf.filters import _bound
    from torchmcmcpf.models.existence import BirthDeath, TargetDynamics

    calls: list[str] = []

    def refuse(*args, **kwargs):
        calls.append("setup")
        raise AssertionError("a step re-derived its setup (TargetDynamics, active_prior or with_proposal)")

    def arm():
        monkeypatch.setattr(TargetDynamics, "__new__", refuse)
        monkeypatch.setattr(_bound, "active_prior", refuse)
        monkeypatch.setattr(BirthDeath, "with_proposal", refuse)
        return calls
    return arm


@pytest.mark.parametrize("name", FILTERS)
def test_a_step_re_derives_nothing(name, no_setup_in_steps):
    """Bind once, step many: after construction a filter's steps build no TargetDynamics, call
    no active_prior and apply no existence proposal (all of it is in ``filt.bound``)."""
    filt, zs, init = build(name)
    state = _first_state(filt, name, init)
    calls = no_setup_in_steps()
    state, _ = filt.step(state, zs[0], generator=torch.Generator().manual_seed(0))
    filt.step(state, zs[1], generator=torch.Generator().manual_seed(1))
    result = filt(zs, init=init if name != "group" else state, generator=torch.Generator().manual_seed(2))
    assert calls == [] and result.mean.shape[:2] == zs.shape[:2]  # every step ran on the bound setup alone


@pytest.mark.parametrize("name", EXISTENCE_FILTERS)
def test_a_step_with_births_re_derives_nothing(name, no_setup_in_steps):
    motion, sensor, existence, z, init = existence_problem()
    filt = EXISTENCE_FILTERS[name](motion, sensor, existence)
    calls = no_setup_in_steps()
    result = filt(z, init=init, generator=torch.Generator().manual_seed(2))
    assert calls == [] and result.mean.shape[0] == len(result.info.ess)


def _assert_same_step(a, b):
    (sa, ia), (sb, ib) = a, b
    assert torch.equal(sa.x, sb.x) and torch.equal(sa.log_w, sb.log_w)
    assert (sa.exists is None) == (sb.exists is None) and (sa.exists is None or torch.equal(sa.exists, sb.exists))
    assert (sa.extras or {}).keys() == (sb.extras or {}).keys()
    for k in sa.extras or {}:  # a tensor, or a typed value (the group filter's GroupState): leaf by leaf
        la, spec_a = tree_flatten(sa.extras[k])
        lb, spec_b = tree_flatten(sb.extras[k])
        assert spec_a == spec_b and all(x is y or torch.equal(x, y) for x, y in zip(la, lb)), k
    for f in ("ess", "log_evidence", "acceptance"):
        assert _same_bits(getattr(ia, f), getattr(ib, f)), f
    assert ia.extras.keys() == ib.extras.keys()
    for k in ia.extras:
        assert _same_bits(ia.extras[k], ib.extras[k]), k


@pytest.mark.parametrize("name", FILTERS)
def test_public_step_function_gives_the_filters_bits(name):
    """``xxx_step(state, z, *, motion, sensor, settings, generator, existence)`` (the design's
    signature: an eager bind, then the bound step) gives ``filt.step``'s bits, two steps on."""
    filt, zs, init = build(name)
    kwargs = dict(motion=filt.motion, sensor=filt.sensor, settings=filt.settings, existence=filt.existence)
    if name == "group":
        kwargs["structure_prior"] = filt.structure_prior
    fn = _step_function(name)
    ours = theirs = (_first_state(filt, name, init), None)
    for t in range(2):
        ours = filt.step(ours[0], zs[t], generator=torch.Generator().manual_seed(t))
        theirs = fn(theirs[0], zs[t], generator=torch.Generator().manual_seed(t), **kwargs)
        _assert_same_step(ours, theirs)


def test_births_public_step_function_gives_the_filters_bits():
    from torchmcmcpf.filters import mcmc_step

    motion, sensor, existence, z, init = existence_problem()
    filt = EXISTENCE_FILTERS["mcmc"](motion, sensor, existence)  # its existence proposal applied once
    frame = type(z)(z.z[0], z.mask[0])
    _assert_same_step(filt.step(filt.init(init), frame, generator=torch.Generator().manual_seed(0)),
                      mcmc_step(filt.init(init), frame, motion=motion, sensor=sensor, settings=filt.settings,
                                existence=existence, generator=torch.Generator().manual_seed(0)))


def test_the_bound_object_travels_with_the_filter():
    """``filt.bound`` holds the filter's own models (``.to`` moves them in place), a pickled
    copy binds its program again (a compiled one does not pickle), and setting
    ``compile_step`` binds the program again."""
    import pickle

    from torchmcmcpf.runtime import Program

    filt, zs, init = build("mcmc", compile_step=True)
    bound = filt.bound
    assert bound.motion is filt.motion and bound.sensor is filt.sensor and filt.settings is bound.settings
    assert filt.dynamics is bound.dynamics and bound.dynamics.motion is filt.motion
    filt.to(torch.float32).to(DT)
    assert filt.bound is bound and bound.motion is filt.motion
    for clone in (pickle.loads(pickle.dumps(filt)), copy.deepcopy(filt)):
        assert clone.compile_step and clone.settings == filt.settings
        assert clone.bound.motion is clone.motion and clone.bound.program is not None
    ipmcmc = build("ipmcmc", compile_step=True)[0]
    assert isinstance(pickle.loads(pickle.dumps(ipmcmc)).bound.program, Program)
    ipmcmc.compile_step = False
    assert not isinstance(ipmcmc.bound.program, Program)
    eager = build("ipmcmc")[0]
    assert_same(run(ipmcmc, zs, init, 3), run(eager, zs, init, 3))


def test_a_filter_pickled_before_binding_once_loads():
    """A filter pickled when its settings and compile flag were attributes (no bound object)
    loads, binds and steps as a new one."""
    new, zs, init = build("pmmh")
    d = new.__getstate__()
    d.update(settings=d.pop("_bound").settings, compile_step=d.pop("_compile_step"), _compiled=None)
    old = PMMHFilter.__new__(PMMHFilter)
    old.__setstate__(d)
    assert old.settings == new.settings and old.bound.motion is old.motion and not old.compile_step
    assert_same(run(old, zs, init, 2), run(new, zs, init, 2))


# ----------------------------------------------------------------------------- the library's select
@pytest.mark.skipif(not _native.available(), reason="the C loops are not built on this machine")
@pytest.mark.parametrize("name", list(FILTERS) + [f"existence-{n}" for n in EXISTENCE_FILTERS])
def test_the_select_loop_keeps_every_filters_bits(name, monkeypatch):
    """Every select of every filter through the C loop (``MIN_ELEMENTS = 1``: the contract's
    tensors are small) gives the bits of ATen's ``where`` (``torch.where`` everywhere)."""
    from torchmcmcpf._native import select

    if name.startswith("existence-"):
        motion, sensor, existence, zs, init = existence_problem()
        filt = EXISTENCE_FILTERS[name.removeprefix("existence-")](motion, sensor, existence)
    else:
        filt, zs, init = build(name)
    results = []
    for threshold in (1, 1 << 62):
        monkeypatch.setattr(select, "MIN_ELEMENTS", threshold)
        results.append(run(filt, zs, init, 3))
    assert_same(*results)
    if name.startswith("existence-"):
        assert torch.equal(results[0].state.exists, results[1].state.exists)
