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
