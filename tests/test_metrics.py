import math

import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment

import torchmcmcpf as tp
from torchmcmcpf.metrics import (
    match_tracks,
    optimal_assignment,
    position_error,
    position_rmse,
    track_loss,
    track_loss_rate,
)


def _tracks(T, B, K, D=4):
    return torch.zeros(T, B, K, D, dtype=torch.float64)


# -- RMSE and track loss on hand-made tracks ---------------------------------------------

def test_position_rmse_known_values():
    # Errors (x, y): run 0 has (3, 4) on target 0 at t = 0 only; run 1 has (1, 0) everywhere.
    # Squared errors [t, b, k]: t0 = [[25, 0], [1, 1]], t1 = [[0, 0], [1, 1]].
    truth = _tracks(2, 2, 2)
    est = truth.clone()
    est[0, 0, 0, 0], est[0, 0, 0, 2] = 3.0, 4.0
    est[:, 1, :, 0] = 1.0
    est[..., 1] = 100.0  # velocities must not count
    est[..., 3] = -7.0
    r = position_rmse(est, truth)
    assert torch.allclose(r.per_step, torch.tensor([math.sqrt(27 / 4), math.sqrt(2 / 4)], dtype=torch.float64))
    assert torch.allclose(r.per_run, torch.tensor([math.sqrt(25 / 4), 1.0], dtype=torch.float64))
    assert torch.allclose(r.overall, torch.tensor(math.sqrt(29 / 8), dtype=torch.float64))
    assert torch.allclose(position_error(est, truth)[0, 0], torch.tensor([5.0, 0.0], dtype=torch.float64))


def test_track_loss_on_crafted_runs():
    # run 0: one 25 m error once (lost); run 1: at most exactly 20 m (kept, the rule is > 20);
    # run 2: 19 m everywhere (kept); run 3: a NaN estimate (lost).
    truth = _tracks(3, 4, 2)
    est = truth.clone()
    est[1, 0, 1, 2] = 25.0
    est[2, 1, 0, 0] = 20.0
    est[:, 2, :, 0] = 19.0
    est[0, 3, 0, 0] = float("nan")
    assert track_loss(est, truth).tolist() == [True, False, False, True]
    assert track_loss_rate(est, truth).item() == pytest.approx(0.5)
    assert track_loss(est, truth, threshold=18.0).tolist() == [True, True, True, True]


def _shuffled(gen, T=6, B=4, K=5):
    # well-separated straight tracks, estimates = truth + 0.5 m noise, labels shuffled per run
    start = 200.0 * torch.randn(B, K, 2, generator=gen, dtype=torch.float64)
    vel = 5.0 * torch.randn(B, K, 2, generator=gen, dtype=torch.float64)
    t = torch.arange(T, dtype=torch.float64)[:, None, None, None]
    pos = start + t * vel  # (T, B, K, 2)
    truth = torch.stack([pos[..., 0], vel[..., 0].expand(T, B, K), pos[..., 1], vel[..., 1].expand(T, B, K)], -1)
    noisy = truth + 0.5 * torch.randn(truth.shape, generator=gen, dtype=torch.float64)
    sigma = torch.stack([torch.randperm(K, generator=gen) for _ in range(B)])  # (B, K)
    est = noisy.gather(2, sigma[None, :, :, None].expand(truth.shape))  # est[:, b, j] = noisy[:, b, sigma[b, j]]
    return truth, noisy, est, sigma


def test_match_tracks_recovers_shuffled_labels(gen):
    truth, noisy, est, sigma = _shuffled(gen)
    matched, perm = match_tracks(est, truth)
    assert torch.equal(perm, torch.argsort(sigma, dim=-1))
    assert torch.equal(matched, noisy)
    ref = position_rmse(noisy, truth)
    got = position_rmse(est, truth, match=True)
    assert torch.allclose(got.overall, ref.overall) and torch.allclose(got.per_step, ref.per_step)
    assert position_rmse(est, truth).overall > 10 * ref.overall  # unmatched labels are wrong
    assert not track_loss(est, truth, match=True).any()


def test_match_tracks_whole_track_vs_per_step():
    # Two targets far apart whose estimates swap labels at t = 2 (of 4): the whole-track
    # assignment keeps one labelling, so half the steps carry the swap error; per step,
    # every frame is matched exactly.
    truth = _tracks(4, 1, 2)
    truth[:, 0, 1, 0] = 100.0
    est = truth.clone()
    est[2:, 0] = truth[2:, 0].flip(1)  # swap the two slots
    matched, perm = match_tracks(est, truth)
    assert perm.shape == (1, 2)
    assert position_rmse(matched, truth).overall.item() == pytest.approx(math.sqrt(0.5 * 100.0**2))
    matched_t, perm_t = match_tracks(est, truth, per_step=True)
    assert perm_t.shape == (4, 1, 2)
    assert torch.equal(matched_t, truth)


def test_metric_shape_errors():
    with pytest.raises(ValueError, match="estimate"):
        position_rmse(_tracks(2, 1, 2), _tracks(2, 1, 3))
    with pytest.raises(ValueError, match="truth"):
        track_loss(torch.zeros(2, 2, 4), torch.zeros(2, 2, 4))
    with pytest.raises(ValueError, match="threshold"):
        track_loss(_tracks(2, 1, 2), _tracks(2, 1, 2), threshold=-1.0)


# -- optimal assignment ------------------------------------------------------------------

def _total(cost, perm):
    rows = np.nonzero(perm >= 0)[0]
    return cost[rows, perm[rows]].sum()


@pytest.mark.parametrize("shape", [(3, 3), (5, 5), (9, 9), (4, 6), (6, 4)])
@pytest.mark.parametrize("method", ["auto", "dp", "auction"])
def test_assignment_matches_scipy(gen, shape, method):
    n, m = shape
    cost = torch.rand((40, n, m), generator=gen, dtype=torch.float64) * 10 - 3
    perm = optimal_assignment(cost, method=method)
    assert perm.shape == (40, n) and perm.dtype == torch.long
    for c, p in zip(cost.numpy(), perm.numpy()):
        rows, cols = linear_sum_assignment(c)
        assigned = p[p >= 0]
        assert len(assigned) == min(n, m) and len(set(assigned.tolist())) == len(assigned)
        # Continuous random costs have a unique optimum almost surely: same assignment.
        ref = np.full(n, -1)
        ref[rows] = cols
        assert np.array_equal(p, ref)


@pytest.mark.parametrize("method", ["dp", "auction"])
def test_assignment_with_ties_reaches_optimal_total(gen, method):
    # integer costs with many ties (several optimal assignments): compare the total cost
    cost = torch.randint(0, 3, (50, 7, 7), generator=gen).double()
    cost[0] = 0.0
    perm = optimal_assignment(cost, method=method)
    for c, p in zip(cost.numpy(), perm.numpy()):
        rows, cols = linear_sum_assignment(c)
        assert sorted(p.tolist()) == list(range(7))
        assert _total(c, p) == c[rows, cols].sum()


def test_auction_tolerance_bound(gen):
    # With a loose rtol the auction's total cost is within rtol * (max - min cost) of the
    # optimum (epsilon-complementary slackness, see metrics._auction).
    rtol = 0.05
    cost = torch.rand((100, 12, 12), generator=gen, dtype=torch.float64)
    perm = optimal_assignment(cost, method="auction", rtol=rtol)
    for c, p in zip(cost.numpy(), perm.numpy()):
        rows, cols = linear_sum_assignment(c)
        assert _total(c, p) <= c[rows, cols].sum() + rtol * (c.max() - c.min()) + 1e-12


def test_assignment_batched_leading_dims_and_float32(gen):
    cost = torch.rand((2, 3, 5, 5), generator=gen)
    perm = optimal_assignment(cost)
    assert perm.shape == (2, 3, 5)
    flat = optimal_assignment(cost.reshape(6, 5, 5))
    assert torch.equal(perm.reshape(6, 5), flat)
    assert torch.equal(optimal_assignment(torch.ones(3, 1)), torch.tensor([0, -1, -1]))


def test_assignment_bad_input():
    with pytest.raises(ValueError, match="cost"):
        optimal_assignment(torch.ones(4))
    with pytest.raises(ValueError, match="cost"):
        optimal_assignment(torch.tensor([[0.0, float("nan")], [1.0, 2.0]]))
    with pytest.raises(ValueError, match="method"):
        optimal_assignment(torch.ones(2, 2), method="greedy")
    with pytest.raises(ValueError, match="dp"):
        optimal_assignment(torch.ones(17, 17), method="dp")


# -- long runs: coverage, identity switches, OSPA parts (issue 22) -------------------------
def _states(points):
    """(T, B, K, 2) positions -> (T, B, K, 4) states [x, vx, y, vy]."""
    p = torch.as_tensor(points, dtype=torch.float64)
    z = torch.zeros_like(p[..., 0])
    return torch.stack([p[..., 0], z, p[..., 1], z], -1)


def test_slot_coverage_counts_slots_near_each_target():
    truth = _states([[[[0.0, 0.0], [100.0, 0.0]]]])  # T = B = 1, two targets
    # both slots on target 0 (5 m and 12 m away): target 0 doubled, target 1 uncovered
    est = _states([[[[5.0, 0.0], [0.0, 12.0]]]])
    cov = tp.metrics.slot_coverage(est, truth, radius=20.0)
    assert cov.tolist() == [[[2, 0]]]
    # a label swap changes nothing; a slot at 20 m exactly is not within 20 m
    est = _states([[[[100.0, 1.0], [20.0, 0.0]]]])
    assert tp.metrics.slot_coverage(est, truth, radius=20.0).tolist() == [[[0, 1]]]
    # masks: a slot not reported does not cover, an absent target counts 0
    est = _states([[[[0.0, 0.0], [100.0, 0.0]]]])
    cov = tp.metrics.slot_coverage(est, truth, estimate_mask=torch.tensor([[[True, False]]]),
                                   truth_mask=torch.tensor([[[False, True]]]))
    assert cov.tolist() == [[[0, 0]]]
    with pytest.raises(ValueError, match="radius"):
        tp.metrics.slot_coverage(est, truth, radius=0.0)
    with pytest.raises(ValueError, match="estimate_mask"):
        tp.metrics.slot_coverage(est, truth, estimate_mask=torch.ones(1, 1, 3, dtype=torch.bool))


def test_amplitude_swapped_marks_slots_on_each_others_targets():
    """The slot of the largest amplitude nearest another target than the strongest, whatever
    the labels; a NaN estimate is never swapped; a state without an amplitude is refused."""
    def radar(rows):  # (T, B, K, 5): [x, vx, y, vy, rho]
        t = torch.tensor(rows, dtype=torch.float64)
        return torch.stack([t[..., 0], torch.zeros_like(t[..., 0]), t[..., 1], torch.zeros_like(t[..., 0]),
                            t[..., 2]], -1)

    truth = radar([[[[0.0, 0.0, 12.0], [100.0, 0.0, 6.0]]]] * 3)  # (T = 3, B = 1, 2, 5)
    est = radar([[[[3.0, 0.0, 12.5], [95.0, 0.0, 6.1]]],  # each slot on its own target
                 [[[3.0, 0.0, 6.1], [60.0, 5.0, 12.5]]],  # the strong slot nearer the weak target
                 [[[float("nan"), 0.0, float("nan")], [float("nan"), 0.0, float("nan")]]]])
    assert tp.metrics.amplitude_swapped(est, truth).tolist() == [[False], [True], [False]]
    with pytest.raises(ValueError, match="an amplitude"):
        tp.metrics.amplitude_swapped(est[..., :4], truth[..., :4])


def test_longest_run_of_uncovered_steps():
    flags = torch.tensor([[1, 0], [1, 1], [0, 1], [1, 1], [1, 0]], dtype=torch.bool)  # (T = 5, 2)
    assert tp.metrics.longest_run(flags).tolist() == [2, 3]
    assert tp.metrics.longest_run(torch.zeros(4, 3, dtype=torch.bool)).tolist() == [0, 0, 0]


def test_identity_switches_count_label_changes_within_the_gate():
    # two targets that swap their slots at step 2 (one switch per target = 2), run 1 never swaps
    a, b = [0.0, 0.0], [100.0, 0.0]
    truth = _states([[[a, b], [a, b]]] * 4)  # (T = 4, B = 2, K = 2, 2)
    est = _states([[[a, b], [a, b]], [[a, b], [a, b]], [[b, a], [a, b]], [[b, a], [a, b]]])
    assert tp.metrics.identity_switches(est, truth).tolist() == [2, 0]
    # an estimate beyond the gate is no assignment: a slot that leaves and comes back with
    # the same label is no switch
    far = [1000.0, 0.0]
    est = _states([[[a, b]], [[far, b]], [[a, b]], [[a, b]]])
    truth1 = truth[:, :1]
    assert tp.metrics.identity_switches(est, truth1, gate=20.0).tolist() == [0]
    # per-step assignment RMSE: a swap costs nothing, whole-track matching charges it
    est = _states([[[a, b]], [[a, b]], [[b, a]], [[b, a]]])
    assert float(tp.metrics.position_rmse(est, truth1, match="step").overall) == 0.0
    assert float(tp.metrics.position_rmse(est, truth1, match="track").overall) > 50.0
    with pytest.raises(ValueError, match="match"):
        tp.metrics.position_rmse(est, truth1, match="sometimes")


def test_ospa_parts_split_localisation_and_cardinality():
    x = torch.tensor([[[0.0, 0.0], [3.0, 4.0]]], dtype=torch.float64)  # 2 estimates
    y = torch.tensor([[[0.0, 0.0], [0.0, 0.0], [50.0, 50.0]]], dtype=torch.float64)  # 3 truths, one far
    parts = tp.metrics.ospa_parts(x, y, c=10.0, p=2.0)
    # the 2 estimates pair with the 2 truths at the origin: distances 0 and 5; one missed
    assert parts.localisation.item() == pytest.approx(math.sqrt(25.0 / 3))
    assert parts.cardinality.item() == pytest.approx(math.sqrt(100.0 / 3))
    assert parts.total.item() == pytest.approx(tp.metrics.ospa(x, y, c=10.0, p=2.0).item())
    assert parts.total.item() ** 2 == pytest.approx(parts.localisation.item() ** 2 + parts.cardinality.item() ** 2)
    empty = tp.metrics.ospa_parts(x[:, :0], y[:, :0], c=10.0)
    assert empty.total.item() == 0.0 and empty.cardinality.item() == 0.0


def test_pcrb_position_rmse_is_the_kalman_steady_state():
    """On a linear-Gaussian position sensor the PCRB floor is the Kalman filter's
    steady-state position error, sqrt(P_xx + P_yy) of the Riccati fixed point: the Monte
    Carlo Fisher information (4000 frames, relative error about 2 %) moves the floor by
    about 1 %; tolerance 4 %."""
    from torchmcmcpf.models import ConstantVelocity, LinearGaussian

    dt64 = torch.float64
    motion = ConstantVelocity(1.0, q=0.5).to(dt64)
    sensor = LinearGaussian.position(noise_std=3.0).to(dt64)
    x = torch.tensor([[[0.0, 1.0, 0.0, -1.0], [100.0, 0.0, 50.0, 0.0]]], dtype=dt64)  # (B, J, D)
    g = torch.Generator().manual_seed(0)
    floor = tp.metrics.pcrb_position_rmse(sensor, motion, x, generator=g, num_frames=4000)
    F, Q = motion.F.to(dt64), motion.Q.to(dt64)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=dt64)
    R = 9.0 * torch.eye(2, dtype=dt64)
    P = 100.0 * torch.eye(4, dtype=dt64)
    for _ in range(500):
        Pp = F @ P @ F.T + Q
        K = Pp @ H.T @ torch.linalg.inv(H @ Pp @ H.T + R)
        P = (torch.eye(4, dtype=dt64) - K @ H) @ Pp
    exact = float((P[0, 0] + P[2, 2]).sqrt())
    assert floor.shape == (1, 2)
    torch.testing.assert_close(floor, torch.full((1, 2), exact, dtype=dt64), rtol=0.04, atol=0.0)


def test_pcrb_position_rmse_bad_input():
    from torchmcmcpf.models import ConstantVelocity, LinearGaussian

    motion, sensor = ConstantVelocity(1.0, q=1.0), LinearGaussian.position(noise_std=1.0)
    g = torch.Generator().manual_seed(0)
    with pytest.raises(ValueError, match="x has shape"):
        tp.metrics.pcrb_position_rmse(sensor, motion, torch.zeros(2, 4), generator=g)
    with pytest.raises(ValueError, match="num_frames"):
        tp.metrics.pcrb_position_rmse(sensor, motion, torch.zeros(1, 1, 4), generator=g, num_frames=1)


def test_map_trajectory_is_the_rts_smoother_on_a_linear_gaussian_model():
    """On a linear-Gaussian model the posterior over a window is Gaussian, so its maximum is
    the Kalman (RTS) smoother's mean: two runs, two independent targets, 12 frames, from a
    start 30 m off everywhere; L-BFGS in float64 reaches it to 1e-5 m."""
    from _kalman import kalman_filter, rts_smoother

    from torchmcmcpf.models import ConstantVelocity, LinearGaussian

    dt64 = torch.float64
    motion = ConstantVelocity(1.0, q=0.5).to(dt64)
    sensor = LinearGaussian.position(noise_std=3.0).to(dt64)
    g = torch.Generator().manual_seed(3)
    T, B, K = 12, 2, 2
    x0 = torch.tensor([[0.0, 1.0, 0.0, -1.0], [100.0, 0.0, 50.0, 2.0]], dtype=dt64).expand(B, K, 4)
    truth = [x0]
    for _ in range(T - 1):
        truth.append(motion.sample(truth[-1], generator=g))
    truth = torch.stack(truth)  # (T, B, K, D)
    z = torch.stack([sensor.simulate(truth[t], generator=g) for t in range(T)])  # (T, B, K, 2)
    F, Q = motion.F.to(dt64), motion.Q.to(dt64)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=dt64)
    R = 9.0 * torch.eye(2, dtype=dt64)
    m0, P0 = x0 + 5.0, 25.0 * torch.eye(4, dtype=dt64)  # the prior one step before frame 0
    means, covs = kalman_filter(F, Q, H, R, m0, P0, z)
    smoothed = rts_smoother(F, Q, means, covs)  # (T, B, K, D)
    res = tp.metrics.map_trajectory(sensor, motion, z, truth + 30.0, prior_mean=m0 @ F.mT,
                                    prior_cov=F @ P0 @ F.mT + Q)
    assert res.x.shape == (T, B, K, 4) and res.log_posterior.shape == (B,) and res.log_lik.shape == (T, B)
    torch.testing.assert_close(res.x, smoothed, rtol=0.0, atol=1e-5)
    assert bool((res.grad_norm < 1e-4).all())
    # without a prior the first frame is free: a different (flat-start) smoother, still a maximum
    free = tp.metrics.map_trajectory(sensor, motion, z, truth + 30.0)
    assert (free.x[0] - smoothed[0]).abs().max() > 1e-3  # the prior mattered
    assert bool((free.grad_norm < 1e-4).all())


def test_map_trajectory_bad_input():
    from torchmcmcpf.models import ConstantVelocity, LinearGaussian

    motion, sensor = ConstantVelocity(1.0, q=1.0), LinearGaussian.position(noise_std=1.0)
    z = torch.zeros(3, 1, 1, 2)
    with pytest.raises(ValueError, match="start has shape"):
        tp.metrics.map_trajectory(sensor, motion, z, torch.zeros(3, 1, 4))
    with pytest.raises(ValueError, match="leading T = 4"):
        tp.metrics.map_trajectory(sensor, motion, z, torch.zeros(4, 1, 1, 4))
    with pytest.raises(ValueError, match="given together"):
        tp.metrics.map_trajectory(sensor, motion, z, torch.zeros(3, 1, 1, 4), prior_mean=torch.zeros(1, 1, 4))
    with pytest.raises(ValueError, match="prior_cov has shape"):
        tp.metrics.map_trajectory(sensor, motion, z, torch.zeros(3, 1, 1, 4), prior_mean=torch.zeros(1, 1, 4),
                                  prior_cov=torch.eye(3))
    with pytest.raises(ValueError, match="start"):
        tp.metrics.map_trajectory(sensor, motion, z, torch.full((3, 1, 1, 4), float("nan")))


def test_map_trajectory_counts_the_exclusion_factor():
    """With an exclusion factor the objective gains ``sum_t log Phi(x_t)``: at the returned
    trajectory ``log_posterior`` is the frames' log-likelihoods, the transitions and that sum,
    recomputed here from the models. On radar frames of one target, two slots started 0.3
    cells apart on it stay unresolved without the factor (the returns add coherently) and are
    pushed at least a cell apart with it."""
    from torchmcmcpf.models.multitarget import Exclusion, log_exclusion
    from torchmcmcpf.scenarios import crossing
    from torchmcmcpf.typing import Y

    g = torch.Generator().manual_seed(0)
    # the targets 400 m apart: each frame's part near target 0 holds one return
    scn = crossing(2, 6, 1, generator=g, miss_distance=400.0, dtype=torch.float64)
    z = scn.measurements
    start = scn.truth[:, :, :1].repeat(1, 1, 2, 1).clone()  # (T, 1, 2, D) both slots on target 0
    start[..., 1, Y] += 0.3 * 2800.0 * math.radians(1.0)  # 0.3 bearing cells across the line of sight (bearing 0)
    excl = Exclusion()
    plain = tp.metrics.map_trajectory(scn.sensor, scn.motion, z, start, max_iter=200)
    held = tp.metrics.map_trajectory(scn.sensor, scn.motion, z, start, exclusion=excl, max_iter=200)
    x = held.x
    expected = (scn.sensor.log_likelihood(x.reshape(-1, 1, 2, x.shape[-1]), z.reshape((-1,) + z.shape[2:]))[:, 0].sum()
                + scn.motion.log_prob(x[1:], x[:-1]).sum() + log_exclusion(excl, scn.sensor, x).sum())
    torch.testing.assert_close(held.log_posterior.sum(), expected, rtol=1e-10, atol=1e-8)

    def cells_apart(traj):  # (T,) distance between the two slots in resolution cells
        u = scn.sensor.resolution_coords(traj[:, 0])  # (T, K, r)
        return (u[:, 0] - u[:, 1]).norm(dim=-1)

    assert float(cells_apart(start[:, :1]).max()) < 0.35
    assert float(cells_apart(plain.x).max()) < 1.0
    assert float(cells_apart(held.x).min()) > 1.0
    with pytest.raises(ValueError, match="exclusion must be an Exclusion"):
        tp.metrics.map_trajectory(scn.sensor, scn.motion, z, start, exclusion=1.0)
