"""The exchange move's caches are speed choices: the chains' resolution coordinates and the
sensor's move terms (kept in their state, the moved slots' made with the segment's proposals)
equal the recomputed ones and give the same decisions, and the frame's detections made once
per step give the same draws from the data."""

import math

import pytest
import torch

from torchmcmcpf.kernels.exchange import (
    ExchangeChains,
    close_pairs,
    draw_exchange_noise,
    exchange_iteration,
    propose_slots,
    with_accepted_amplitudes,
)
from torchmcmcpf.models.existence import TargetDynamics
from torchmcmcpf.models.multitarget import Exclusion, Recapture
from torchmcmcpf.scenarios.ground_radar import ground_radar

DT = torch.float64


def _problem(n=60, c=8, k=3, dtype=DT):
    """A 3-target ground-radar frame in ``dtype`` (float64 unless said), previous particles
    around the truth, the chains' starting states and the slots' joint model with re-capture."""
    scn = ground_radar(num_targets=k, num_steps=2, batch_size=2, generator=torch.Generator().manual_seed(4))
    sensor, motion = scn.sensor.to(dtype), scn.motion.to(dtype)
    z = scn.measurements[1].to(dtype)
    x_prev = scn.initial_particles(n, generator=torch.Generator().manual_seed(5)).to(dtype)
    dynamics = TargetDynamics(motion, None, Recapture(), sensor)
    y = motion.sample(x_prev[:, :c], generator=torch.Generator().manual_seed(6))
    return sensor, dynamics, z, x_prev, y


def _iterations(sensor, dynamics, z, x_prev, y, keep_coords, steps=24, pair_every=4, keep_terms=False):
    """``steps`` exchange iterations with exclusion (every ``pair_every``-th a two-slot move),
    the chains keeping their coordinates or not, their move terms or not; returns the chains
    after each and the acceptances."""
    b, n, k, _ = x_prev.shape
    DT = x_prev.dtype
    c = y.shape[1]
    g = torch.Generator().manual_seed(7)
    log_w = torch.full((b, n), -math.log(n), dtype=DT)
    pairs = close_pairs(sensor.resolution_coords(x_prev.mean(1)), 1e3)  # every pair of slots is close
    exclusion = Exclusion()
    source = torch.arange(c).reshape(1, c, 1).repeat(b, 1, k)  # the chains started from particles 0 .. C - 1
    chains = ExchangeChains(y, sensor.log_likelihood(y, z), None, torch.zeros(y.shape[:-1], dtype=DT),
                            torch.ones(y.shape[:-1], dtype=torch.int8), source, torch.full(y.shape[:-1], -math.log(n),
                                                                                           dtype=DT),
                            sensor.amplitude_cache(y),
                            sensor.resolution_coords(y) if keep_coords else None,
                            sensor.move_terms(y) if keep_terms else None)
    out, accepted = [], []
    for t in range(steps):
        noise = draw_exchange_noise(log_w, 1, c, k, dynamics=dynamics, generator=g, dtype=DT, z=z,
                                    pairs=pairs if (t + 1) % pair_every == 0 else None)
        noise = noise._replace(proposal=propose_slots(noise, x_prev, None, dynamics=dynamics,
                                                      sensor=sensor if keep_coords else None,
                                                      terms_of=sensor if keep_terms else None))
        first = noise._replace(**{f: None if v is None else (v[0] if torch.is_tensor(v) else type(v)(*(
            None if a is None else a[0] for a in v))) for f, v in noise._asdict().items()})
        new, acc, update = exchange_iteration(chains, x_prev, None, z, first, dynamics=dynamics, sensor=sensor,
                                              exclusion=exclusion)
        chains = with_accepted_amplitudes(new, chains.amplitude, update, acc, sensor)
        out.append(chains)
        accepted.append(acc)
    return out, torch.stack(accepted)


def test_kept_coordinates_equal_recomputed_and_give_the_same_moves():
    """The chains' kept resolution coordinates stay those of their states (to the last bits
    of float64: the same map, applied to a different batch), one- and two-slot moves, and the
    moves are those of mapping every slot at every iteration."""
    sensor, dynamics, z, x_prev, y = _problem()
    kept, acc_kept = _iterations(sensor, dynamics, z, x_prev, y, keep_coords=True)
    fresh, acc_fresh = _iterations(sensor, dynamics, z, x_prev, y, keep_coords=False)
    assert torch.equal(acc_kept, acc_fresh)
    assert 0.02 < float(acc_kept.double().mean()) < 0.98  # both decisions are covered
    for a, b in zip(kept, fresh):
        assert torch.equal(a.y, b.y) and torch.equal(a.log_lik, b.log_lik)
        assert torch.equal(a.log_r, b.log_r) and torch.equal(a.kind, b.kind) and torch.equal(a.source, b.source)
        assert b.coords is None
        torch.testing.assert_close(a.coords, sensor.resolution_coords(a.y), rtol=1e-14, atol=1e-12)


def test_kept_move_terms_equal_recomputed_and_give_the_same_moves():
    """The radar's move terms kept by the chains (float32: where its C loop serves the cached
    moves) stay those of their states, and the chains are those of mapping the moved slots'
    states at every iteration: the same states and decisions, the likelihoods and amplitudes
    to float32 round-off; one- and two-slot moves. In float64 the sensor keeps none (the
    tensor path). Not to the bit here: ATen's ``atan2`` (the bearing) rounds differently in
    its vector and scalar loops, so a state's bearing can depend on the layout of the batch it
    is mapped in (2 % of this frame's bearings, by an ulp; in the filters' layouts the crossing's
    and the ground radar's IP-MCMC-PF runs are the same bits with and without the terms)."""
    from torchmcmcpf.models.sensors.grid import native

    if not native.available():
        pytest.skip("no C compiler: the sensor keeps no move terms")
    sensor, dynamics, z, x_prev, y = _problem(dtype=torch.float32)
    assert sensor.move_terms(y.double()) is None and sensor.move_terms(y).shape == y.shape[:-1] + (4,)
    kept, acc_kept = _iterations(sensor, dynamics, z, x_prev, y, keep_coords=True, keep_terms=True)
    fresh, acc_fresh = _iterations(sensor, dynamics, z, x_prev, y, keep_coords=True)
    assert torch.equal(acc_kept, acc_fresh)
    assert 0.02 < float(acc_kept.double().mean()) < 0.98  # both decisions are covered
    for a, b in zip(kept, fresh):
        assert torch.equal(a.y, b.y) and b.terms is None
        torch.testing.assert_close(a.log_lik, b.log_lik, rtol=1e-6, atol=1e-3)  # sums of ~1e3 nats, float32
        torch.testing.assert_close(a.amplitude, b.amplitude, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(a.terms, sensor.move_terms(a.y), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("scored", [False, True])
def test_detections_made_once_give_the_same_draws(scored):
    """``sample_from_data`` with the frame's detections handed in (``found``, made once per
    step) draws exactly what it draws finding them itself."""
    sensor, _, z, _, _ = _problem()
    shape = (2, 50, 3)
    mask = torch.rand(shape, generator=torch.Generator().manual_seed(8)) < 0.3 if scored else None
    found = sensor.frame_detections(z)
    a = sensor.sample_from_data(z, shape, generator=torch.Generator().manual_seed(9), dtype=DT, scored=mask)
    b = sensor.sample_from_data(z, shape, generator=torch.Generator().manual_seed(9), dtype=DT, scored=mask,
                                found=found)
    assert torch.equal(found[0], sensor.detections(z)[0]) and torch.equal(found[1], sensor.detections(z)[1])
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_point_sensor_prepares_nothing():
    """A sensor whose data are points has no detections to prepare (``frame_detections`` is
    None) and draws the same with ``found=None``."""
    from torchmcmcpf.scenarios.septier import septier

    scn = septier(2, 2, generator=torch.Generator().manual_seed(3))
    z = type(scn.measurements)(scn.measurements.z[0], scn.measurements.mask[0])  # the first frame
    assert scn.sensor.frame_detections(z) is None
    a = scn.sensor.sample_from_data(z, (2, 5), generator=torch.Generator().manual_seed(1))
    b = scn.sensor.sample_from_data(z, (2, 5), generator=torch.Generator().manual_seed(1), found=None)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def _tensor_path_only():
    """The exchange iteration without its one-call C commit (the tensor path throughout)."""
    from unittest import mock

    from torchmcmcpf.kernels import _exchange_native

    return mock.patch.object(_exchange_native, "applies", lambda *tensors: False)


def _counting_commits():
    """Counts the iterations the C calls serve inside the block: ``calls[0]`` one-call commits,
    ``calls[1]`` iterations of segment runs (``exchange_run``)."""
    from unittest import mock

    from torchmcmcpf.kernels import _exchange_native

    calls, commit, segment = [0, 0], _exchange_native.commit, _exchange_native.segment

    def counted(*args, **kwargs):
        calls[0] += 1
        return commit(*args, **kwargs)

    def counted_segment(*args, **kwargs):
        calls[1] += args[7].u.shape[0]  # the segment's iterations (single: leading L)
        return segment(*args, **kwargs)

    patches = mock.patch.multiple(_exchange_native, commit=counted, segment=counted_segment)
    return calls, patches


def test_one_call_iteration_is_the_tensor_path_to_the_bit():
    """The exchange iteration's C commit (the MH decision with exclusion, re-capture and the
    pair's source term, every chain field written, the cache advanced in place) gives the
    tensor path's chains, decisions and amplitude cache to the bit, one- and two-slot moves
    mixed (the two-slot ones: the second slot's exclusion factors see the first moved, the
    cached ratios converted between the moves' epsilon)."""
    from torchmcmcpf.models.sensors.grid import native

    if not native.available():
        pytest.skip("no C compiler: no one-call iteration")
    sensor, dynamics, z, x_prev, y = _problem(dtype=torch.float32)
    calls, counting = _counting_commits()
    with counting:
        fast, acc_fast = _iterations(sensor, dynamics, z, x_prev, y, keep_coords=True, keep_terms=True)
    assert calls == [24, 0]  # every iteration, one- and two-slot moves (every 4th)
    with _tensor_path_only():
        slow, acc_slow = _iterations(sensor, dynamics, z, x_prev, y, keep_coords=True, keep_terms=True)
    assert torch.equal(acc_fast, acc_slow)
    assert 0.02 < float(acc_fast.double().mean()) < 0.98  # both decisions are covered
    for a, b in zip(fast, slow):
        for name in ("y", "log_lik", "log_r", "kind", "source", "log_w_source", "coords", "terms", "amplitude"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name


@pytest.mark.parametrize("terms", [{}, {"exclusion": None, "recapture": None}, {"joint_pairs": 1.5}],
                         ids=["defaults", "paper", "joint pairs"])
def test_filters_with_the_one_call_iteration_are_the_same_bits(terms):
    """The IP-MCMC-PF on the crossing (its defaults, paper 000's target, joint pairs) gives
    the same particles and estimates with the one-call iteration as on tensors."""
    from torchmcmcpf.filters import IPMCMCFilter
    from torchmcmcpf.models.sensors.grid import native
    from torchmcmcpf.scenarios.crossing import crossing

    if not native.available():
        pytest.skip("no C compiler: no one-call iteration")
    scn = crossing(2, 5, 2, generator=torch.Generator().manual_seed(0))
    init = scn.initial_particles(100, generator=torch.Generator().manual_seed(1))
    filt = IPMCMCFilter(scn.motion, scn.sensor, 100, num_chains=10, burn_in=20, **terms)
    calls, counting = _counting_commits()
    with torch.inference_mode(), counting:
        fast = filt(scn.measurements, init=init, generator=torch.Generator().manual_seed(2))
    # every iteration in segment calls; joint pairs' one-slot moves read their chain's pair
    # (made in the iteration): commits
    commits, runs = calls
    if "joint_pairs" in terms:
        assert commits > 100 and runs == 0
    else:
        assert runs > 100 and commits == 0
    with torch.inference_mode(), _tensor_path_only():
        slow = filt(scn.measurements, init=init, generator=torch.Generator().manual_seed(2))
    assert torch.equal(fast.mean, slow.mean) and torch.equal(fast.state.x, slow.state.x)
    assert torch.equal(fast.state.log_w, slow.state.log_w)


def test_delta_rows_read_in_the_loop_equal_the_gathered_rows():
    """The radar's one-slot move read from the chains' rows inside its C loop equals the rows
    gathered and interleaved (the base method): the same change, cells and cache change."""
    from torchmcmcpf.models.base import SensorModel
    from torchmcmcpf.models.sensors.grid import native

    if not native.available():
        pytest.skip("no C compiler")
    sensor, dynamics, z, x_prev, y = _problem(dtype=torch.float32)
    g = torch.Generator().manual_seed(11)
    terms = sensor.move_terms(y)
    slot = torch.randint(0, y.shape[-2], y.shape[:2] + (1,), generator=g)
    moved = y.gather(2, slot[..., None].expand(slot.shape + (y.shape[-1],))) \
        + 30.0 * torch.randn(slot.shape + (y.shape[-1],), generator=g)
    terms_new = sensor.move_terms(moved)
    cache = sensor.amplitude_cache(y)
    ours = sensor.log_likelihood_delta_rows(cache, terms, slot, terms_new, z)
    gathered = SensorModel.log_likelihood_delta_rows(sensor, cache, terms, slot, terms_new, z)
    assert ours[0].shape == y.shape[:2] and bool((ours[0] != 0).any())
    for a, b in zip(ours, gathered):
        assert torch.equal(a, b)


def test_prepared_frames_follow_the_frame():
    """The radar loop's prepared frames are reused for the same unmodified frame only: a frame
    changed in place, or another tensor, is prepared afresh."""
    from torchmcmcpf.models.sensors.grid import native

    if not native.available():
        pytest.skip("no C compiler")
    sensor, _, z, _, _ = _problem(dtype=torch.float32)
    z = z.clone()
    first = native._frames(sensor, z)
    assert native._frames(sensor, z) is first  # reused
    z.mul_(2.0)
    again = native._frames(sensor, z)
    assert again is not first
    fresh = torch.nn.functional.pad(sensor.prepare_frame(z).reshape(z.shape[0], -1), (0, 8))
    assert torch.equal(again, fresh)
    other = z.clone()
    assert native._frames(sensor, other) is not again


@pytest.mark.compile
def test_a_compiled_filter_runs_its_one_slot_moves_in_the_c_calls():
    """``compile_step=True`` on the CPU: the iterations run eagerly in their C calls
    (``Program.eager_when``: faster than the compiled graph), so the compiled filter is the
    eager one."""
    from torchmcmcpf.filters import IPMCMCFilter
    from torchmcmcpf.models.sensors.grid import native
    from torchmcmcpf.scenarios.crossing import crossing

    if not native.available():
        pytest.skip("no C compiler: no one-call iteration")
    scn = crossing(2, 3, 2, generator=torch.Generator().manual_seed(0))
    init = scn.initial_particles(100, generator=torch.Generator().manual_seed(1))
    results = []
    for compile_step in (True, False):
        filt = IPMCMCFilter(scn.motion, scn.sensor, 100, num_chains=10, burn_in=20, compile_step=compile_step)
        calls, counting = _counting_commits()
        with torch.inference_mode(), counting:
            results.append(filt(scn.measurements, init=init, generator=torch.Generator().manual_seed(2)))
        assert sum(calls) >= 3 * 30  # 3 steps of at least 30 iterations
    compiled, eager = results
    assert torch.equal(compiled.mean, eager.mean) and torch.equal(compiled.state.x, eager.state.x)


def test_commit_refuses_rows_of_another_dtype():
    """The one-call commit copies rows as bytes: a row of another dtype or shape than its
    field is a ValueError naming both, not a silent reinterpretation."""
    from torchmcmcpf.kernels import _exchange_native

    b, c, k = 1, 2, 3
    log_lik = torch.zeros(b, c)
    cache, cells, change = torch.zeros(b, c, 4), torch.zeros(b, c, 1, dtype=torch.int64), torch.zeros(b, c, 1)
    y, row = torch.zeros(b, c, k, 5), torch.zeros(b, c, 1, 5, dtype=torch.float64)
    with pytest.raises(ValueError, match="dtype and row shape"):
        _exchange_native.commit(log_lik, log_lik, log_lik + 0.5, None, torch.zeros(b, c, 1, dtype=torch.int64), None,
                                None, None, 1.0, -50.0, None, None, None, [(y, row)], cache, cells, change)


def _run_problem(steps=12, pairs=False):
    """float32 chains with every field a run writes (coordinates, terms, ratios, kinds,
    sources) and ``steps`` iterations' noise with the segment's proposals: one-slot moves, or
    with ``pairs`` two-slot ones (every pair of slots close)."""
    sensor, dynamics, z, x_prev, y = _problem(dtype=torch.float32)
    b, n, k, _ = x_prev.shape
    c = y.shape[1]
    log_w = torch.full((b, n), -math.log(n))
    source = torch.arange(c).reshape(1, c, 1).repeat(b, 1, k)
    chains = ExchangeChains(y, sensor.log_likelihood(y, z), None, torch.zeros(y.shape[:-1]),
                            torch.ones(y.shape[:-1], dtype=torch.int8), source, torch.full(y.shape[:-1], -math.log(n)),
                            sensor.amplitude_cache(y), sensor.resolution_coords(y), sensor.move_terms(y))
    close = close_pairs(sensor.resolution_coords(x_prev.mean(1)), 1e3) if pairs else None
    noise = draw_exchange_noise(log_w, steps, c, k, dynamics=dynamics, generator=torch.Generator().manual_seed(8),
                                dtype=torch.float32, z=z, pairs=close)
    noise = noise._replace(proposal=propose_slots(noise, x_prev, None, dynamics=dynamics, sensor=sensor,
                                                  terms_of=sensor), birth=None, relocation=None)
    return sensor, dynamics, z, x_prev, chains, noise


def _rows_of(noise, t):
    """Iteration ``t`` of a noise with leading ``L`` (leading ``(B, C)``)."""
    return type(noise)(*(None if v is None else (v[t] if torch.is_tensor(v) else type(v)(*(
        None if a is None else a[t] for a in v))) for v in noise))


def _tensor_path_steps(chains, iterations, x_prev, z, sensor, dynamics, exclusion):
    """The tensor path's iterations (a list of one iteration's noise each) one by one: the
    chains after each (with a copy of the cache), the decisions and each iteration's log
    acceptance ratio (read from its MH test)."""
    from unittest import mock

    from torchmcmcpf.kernels import exchange
    from torchmcmcpf.kernels.mh import mh_accept

    seen = []

    def reading(log_alpha, u):
        seen.append(log_alpha)
        return mh_accept(log_alpha, u)

    kept, accepted = [], []
    with _tensor_path_only(), mock.patch.object(exchange, "mh_accept", reading):
        for nz in iterations:
            new, acc, update = exchange_iteration(chains, x_prev, None, z, nz, dynamics=dynamics, sensor=sensor,
                                                  exclusion=exclusion)
            chains = with_accepted_amplitudes(new, chains.amplitude, update, acc, sensor)
            kept.append(chains._replace(amplitude=chains.amplitude.clone()))  # the cache moves in place
            accepted.append(acc)
    return kept, torch.stack(accepted), torch.stack(seen)


def _at_the_boundary(log_alpha, accepted):
    """Uniforms each 1e-3 nats on the side of its chain's log acceptance ratio that keeps the
    decision: the same decisions on the tensor path, and any change of a ratio by more than
    1e-3 (a term left out or misread) flips one."""
    shift = torch.where(accepted, -1e-3, 1e-3)
    return torch.exp((log_alpha + shift).clamp(-80.0, 80.0))


def test_a_run_of_one_slot_moves_is_the_iterations_to_the_bit():
    """``exchange_run`` (a run of one-slot iterations in one C call: the radar's change by its
    C entry, then the commit, chain by chain) gives the chains, amplitude cache, acceptances
    and recorded trace of the iterations one by one on tensors, to the bit."""
    from torchmcmcpf.kernels.exchange_segment import exchange_run, run_serves
    from torchmcmcpf.models.sensors.grid import native

    if not native.available():
        pytest.skip("no C compiler: no runs in C")
    sensor, dynamics, z, x_prev, chains, noise = _run_problem()
    exclusion, steps, record = Exclusion(), noise.u.shape[0], 5
    fresh = lambda: chains._replace(amplitude=chains.amplitude.clone())  # noqa: E731 (the cache moves in place)
    _, accepted, log_alpha = _tensor_path_steps(fresh(), [_rows_of(noise, t) for t in range(steps)], x_prev, z,
                                                sensor, dynamics, exclusion)
    noise = noise._replace(u=_at_the_boundary(log_alpha, accepted))
    kept, at_boundary, _ = _tensor_path_steps(fresh(), [_rows_of(noise, t) for t in range(steps)], x_prev, z,
                                              sensor, dynamics, exclusion)
    assert torch.equal(at_boundary, accepted)  # the same decisions, each 1e-3 nats from flipping
    slow = kept[-1]
    assert run_serves(chains, z, noise, dynamics=dynamics, sensor=sensor, exclusion=exclusion)
    fast, count, trace = exchange_run(fresh(), z, noise, dynamics=dynamics, sensor=sensor, exclusion=exclusion,
                                      record_from=record)
    assert torch.equal(count, accepted.sum(0).to(count.dtype))
    assert 0.02 < float(count.mean()) / steps < 0.98  # both decisions are covered
    for name in ("y", "log_lik", "log_r", "kind", "source", "log_w_source", "coords", "terms", "amplitude"):
        assert torch.equal(getattr(fast, name), getattr(slow, name)), name
    assert trace.y.shape[0] == steps - record and trace.exists is None and trace.amplitude is None
    for name in ("y", "log_lik", "log_r", "kind", "source"):
        assert torch.equal(getattr(trace, name), torch.stack([getattr(ch, name) for ch in kept[record:]])), name


def test_runs_serve_only_sensors_with_a_c_entry():
    """Without the sensor's C entry (the tensor path) ``run_serves`` is false and
    ``exchange_run`` refuses with a ValueError, rather than running another arithmetic."""
    from torchmcmcpf.kernels.exchange_segment import exchange_run, run_serves

    sensor, dynamics, z, _, chains, noise = _run_problem(steps=2)
    with _tensor_path_only():
        assert not run_serves(chains, z, noise, dynamics=dynamics, sensor=sensor, exclusion=Exclusion())
        with pytest.raises(ValueError, match="run_serves"):
            exchange_run(chains, z, noise, dynamics=dynamics, sensor=sensor, exclusion=Exclusion())


def test_a_segment_with_two_slot_moves_is_the_iterations_to_the_bit():
    """A segment in C calls, runs of one-slot moves with two-slot ones between them (each after
    its source term read from the chains; the cached ratios converted between the moves'
    epsilon by kind in the loop), gives the tensor path's chains, cache, acceptances and
    recorded trace to the bit; the trace recorded from an iteration inside a run."""
    from torchmcmcpf.kernels.exchange_segment import exchange_run, run_serves
    from torchmcmcpf.models.sensors.grid import native

    if not native.available():
        pytest.skip("no C compiler: no runs in C")
    sensor, dynamics, z, x_prev, chains, single = _run_problem(steps=10)
    pairs = _run_problem(steps=3, pairs=True)[-1]
    at_pairs, record, exclusion = (2, 5, 9), 4, Exclusion()
    assert pairs.slot.shape[-1] == 2 and dynamics.recapture.p_propose_pair != dynamics.recapture.p_propose

    def iterations(single, pairs):
        return [_rows_of(pairs, at_pairs.index(t)) if t in at_pairs else _rows_of(single, t) for t in range(10)]

    fresh = lambda: chains._replace(amplitude=chains.amplitude.clone())  # noqa: E731 (the cache moves in place)
    _, accepted, log_alpha = _tensor_path_steps(fresh(), iterations(single, pairs), x_prev, z, sensor, dynamics,
                                                exclusion)
    u = _at_the_boundary(log_alpha, accepted)
    single = single._replace(u=torch.stack([single.u[t] if t in at_pairs else u[t] for t in range(10)]))
    pairs = pairs._replace(u=u[list(at_pairs)])
    kept, at_boundary, _ = _tensor_path_steps(fresh(), iterations(single, pairs), x_prev, z, sensor, dynamics,
                                              exclusion)
    assert torch.equal(at_boundary, accepted)  # the same decisions, each 1e-3 nats from flipping
    assert 0.02 < float(accepted.double().mean()) < 0.98  # both decisions are covered
    assert bool(accepted[list(at_pairs)].any())  # a two-slot move accepted
    served = dict(dynamics=dynamics, sensor=sensor, exclusion=exclusion, pairs=pairs)
    assert run_serves(chains, z, single, **served)
    fast, count, trace = exchange_run(fresh(), z, single, at_pairs=at_pairs, record_from=record, **served)
    assert torch.equal(count, accepted.sum(0).to(count.dtype))
    for name in ("y", "log_lik", "log_r", "kind", "source", "log_w_source", "coords", "terms", "amplitude"):
        assert torch.equal(getattr(fast, name), getattr(kept[-1], name)), name
    for name in ("y", "log_lik", "log_r", "kind", "source"):
        assert torch.equal(getattr(trace, name), torch.stack([getattr(ch, name) for ch in kept[record:]])), name
    with pytest.raises(ValueError, match="at_pairs"):
        exchange_run(fresh(), z, single, at_pairs=(2, 5), **served)
