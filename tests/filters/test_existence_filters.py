"""Filters with births and deaths on point measurements in Poisson clutter.

Reasoning for the thresholds (L_C = 10 clutter points over V = 2.5e7 m^2, L_x = 4 points
per target, 10 m noise, P_B = P_D = 0.02):
- clutter only: a slot that claims a target pays exp(-L_x) = 0.018 per frame and gains a
  factor ~ 1 + L_x N(z; Hx, R) V / L_C only on the rare clutter point it sits on; the
  posterior existence of a slot stays of order P_B exp(-L_x) (1 + L_x) ~ 2e-3, so 0.25 for
  the expected number of 3 slots is two orders of magnitude above it.
- a target that appears: its 4 points give a Bayes factor of order 1e3 per point for a
  newborn placed by the measurement-driven birth proposal, so it exists with
  probability > 0.5 within a frame or two; we allow 3.
- a target that dies: each frame without its points multiplies the odds of life by
  (1 - P_D) / P_D * exp(-L_x) = 0.9, then by ~0.02 per further frame: dropped (< 0.5)
  within 2 frames; we allow 3.
"""

import pytest
import torch

from torchmcmcpf.filters.sir import SIRFilter
from torchmcmcpf.models.existence import BirthDeath, existence_estimate
from torchmcmcpf.models.motion import ConstantVelocity
from torchmcmcpf.models.sensors.points import PoissonClutterPoints
from torchmcmcpf.scenarios.septier import stack_frames

AREA = ((0.0, 5000.0), (0.0, 5000.0))
B, N, K, T = 3, 400, 3, 26
BORN, DIES = 5, 18  # the target exists for frames BORN .. DIES - 1


def models():
    motion = ConstantVelocity(1.0, 1.0).double()
    sensor = PoissonClutterPoints(10.0, 4.0, AREA, noise_std=10.0).double()
    existence = BirthDeath(0.02, 0.02, AREA, velocity_std=5.0, birth_std=10.0).double()
    return motion, sensor, existence


def data(gen, *, with_target: bool):
    motion, sensor, _ = models()
    x = torch.tensor([2000.0, 3.0, 2500.0, -2.0], dtype=torch.float64).expand(B, 1, 4)
    frames, alive = [], []
    for t in range(T):
        x = motion.sample(x, generator=gen)
        live = torch.full((B, 1), with_target and BORN <= t < DIES)
        alive.append(live[:, 0])
        frames.append(sensor.simulate(x, exists=live, generator=gen))
    return stack_frames(frames), torch.stack(alive)


def run_sir(z, gen):
    motion, sensor, existence = models()
    filt = SIRFilter(motion, sensor, N, existence=existence)
    return filt(z, init=torch.zeros(B, N, K, 4, dtype=torch.float64), generator=gen)


def test_clutter_only_keeps_the_expected_count_near_zero(gen):
    z, _ = data(gen, with_target=False)
    result = run_sir(z, gen)
    count = result.exists_prob.sum(-1)  # (T, B)
    assert result.exists_prob.shape == (T, B, K)
    assert float(count.max()) < 0.25


def test_a_target_is_picked_up_and_dropped(gen):
    z, alive = data(gen, with_target=True)
    result = run_sir(z, gen)
    count = result.exists_prob.sum(-1)  # (T, B)
    assert float(count[:BORN].max()) < 0.25
    assert bool((count[BORN + 3: DIES] > 0.5).all()), count.T
    assert bool((count[DIES + 3:] < 0.5).all()), count.T
    # the reported slot sits on the target while it lives
    est = existence_estimate(result.state)
    assert est.expected_count.shape == (B,)
    assert float(count[BORN + 3: DIES].mean()) == pytest.approx(1.0, abs=0.2)


def test_same_seed_same_result():
    z, _ = data(torch.Generator().manual_seed(0), with_target=True)
    a = run_sir(type(z)(z.z[:8], z.mask[:8]), torch.Generator().manual_seed(1))
    b = run_sir(type(z)(z.z[:8], z.mask[:8]), torch.Generator().manual_seed(1))
    assert torch.equal(a.state.x, b.state.x) and torch.equal(a.exists_prob, b.exists_prob)


def test_estimate_is_the_mean_given_existence(gen):
    z, alive = data(gen, with_target=True)
    motion, sensor, existence = models()
    filt = SIRFilter(motion, sensor, N, existence=existence)
    state = filt.init(torch.zeros(B, N, K, 4, dtype=torch.float64))
    for t in range(BORN + 6):
        state, _ = filt.step(state, type(z)(z.z[t], z.mask[t]), generator=gen)
    est = existence_estimate(state)
    assert torch.allclose(filt.estimate(state), est.mean)
    # the one present slot per run is within a few noise sd of the target's points
    pts, mask = z.z[BORN + 5], z.mask[BORN + 5]
    assert est.present.sum(-1).tolist() == [1] * B
    for b in range(B):
        (k,) = est.present[b].nonzero()[0].tolist()
        d = (pts[b][mask[b]] - est.mean[b, k, [0, 2]]).norm(dim=-1)
        assert int((d < 40).sum()) >= 1
