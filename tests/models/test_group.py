"""Virtual-leader group model, group structures and pairwise Kalman marginalisation
(Septier, Pang, Godsill and Carmi 2009, paper 004)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from torchmcmcpf.models import (
    GroupExistence,
    GroupStructurePrior,
    VirtualLeaderMotion,
    group_structures,
    pairwise_kalman_init,
    pairwise_kalman_predict,
    pairwise_kalman_sample,
    pairwise_kalman_update,
)
from torchmcmcpf.models.group import KalmanStats, bell_number, structure_index, to_axes

TABLE1 = dict(alpha=0.0006, beta=0.05, gamma1=0.001, gamma2=0.001, sigma_x=0.2, sigma_g=0.5, dt=5.0)
AREA = ((0.0, 5000.0), (0.0, 5000.0))


def motion(**kw):
    return VirtualLeaderMotion(**{**TABLE1, **kw})


# -- item 1: exact discretisation ---------------------------------------------------------
def _integrate(A: np.ndarray, L: np.ndarray, tau: float, steps: int = 20000):
    """F by RK4 on dPhi/ds = A Phi, then R (eq. 15) and Q (eq. 16) by composite Simpson on
    the same grid: float64, errors ~1e-14 for these step sizes."""
    d = A.shape[0]
    h = tau / steps
    phi = np.eye(d)
    phis = [phi]
    for _ in range(steps):
        k1 = A @ phi
        k2 = A @ (phi + 0.5 * h * k1)
        k3 = A @ (phi + 0.5 * h * k2)
        k4 = A @ (phi + h * k3)
        phi = phi + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        phis.append(phi)
    phis = np.stack(phis)  # Phi(s) on s = 0, h, ..., tau
    w = np.ones(steps + 1)
    w[1:-1:2], w[2:-1:2] = 4, 2
    w *= h / 3
    R = np.einsum("s,sij->ij", w, phis)  # int_0^tau e^{A s} ds (= eq. 15 with s = t + tau - l)
    Q = np.einsum("s,sij,jk,slk->il", w, phis, L, phis)
    return phis[-1], R, Q


@pytest.mark.parametrize("n", [1, 2, 3])
def test_matrices_match_numerical_integration(n):
    m = motion(r1=8.0, r2=12.0)
    F, R, Q = m.matrices(n)
    A, L = m.generator_matrices(n)
    assert F.shape == R.shape == Q.shape == (4 * (n + 1),) * 2 and F.dtype == torch.float64
    F_ref, R_ref, Q_ref = _integrate(A.numpy(), L.numpy(), m.dt)
    for got, ref in ((F, F_ref), (R, R_ref), (Q, Q_ref)):
        rel = np.linalg.norm(got.numpy() - ref) / np.linalg.norm(ref)
        assert rel < 1e-9, rel


def test_generator_matrix_layout():
    """Eq. 4-6 in the state order of eq. 3 for one member: [x, y, xd, yd, vx, vy, vdx, vdy]."""
    m = motion()
    A, L = m.generator_matrices(1)
    a, b, g1, g2 = m.alpha, m.beta, m.gamma1, m.gamma2
    expected = torch.tensor([
        [0, 0, 1, 0, 0, 0, 0, 0],
        [0, 0, 0, 1, 0, 0, 0, 0],
        [-a, 0, -b - g1, 0, a, 0, b, 0],
        [0, -a, 0, -b - g1, 0, a, 0, b],
        [0, 0, 0, 0, 0, 0, 1, 0],
        [0, 0, 0, 0, 0, 0, 0, 1],
        [0, 0, 0, 0, 0, 0, -g2, 0],
        [0, 0, 0, 0, 0, 0, 0, -g2]], dtype=torch.float64)
    assert torch.equal(A, expected)
    qc = torch.tensor([0, 0, 0.2**2, 0.2**2, 0, 0, 0.5**2, 0.5**2], dtype=torch.float64)
    assert torch.equal(torch.diagonal(L), qc)


@pytest.mark.parametrize("n", [1, 2, 4])
def test_Q_symmetric_positive_definite(n):
    _, _, Q = motion().matrices(n)
    assert torch.equal(Q, Q.T)
    assert float(torch.linalg.eigvalsh(Q).min()) > 0


def test_repulsion_pairwise_sum():
    m = motion(r1=8.0, r2=12.0)
    pos = torch.tensor([[0.0, 0.0], [30.0, 40.0], [100.0, 0.0], [7.0, 7.0]], dtype=torch.float64)
    labels = torch.tensor([0, 0, 0, 1])
    active = torch.tensor([True, True, True, True])
    rep = m.repulsion(pos, labels, active)
    ref = torch.zeros(4, 2, dtype=torch.float64)
    for i in range(3):
        for j in range(3):
            if i != j:
                d = (pos[i] - pos[j]).norm()
                ref[i] += 8.0 / (d + 12.0) / d * (pos[i] - pos[j])
    torch.testing.assert_close(rep, ref, rtol=1e-12, atol=0)
    assert torch.equal(motion().repulsion(pos, labels, active), torch.zeros_like(pos))


# -- item 2: group structures and their prior ----------------------------------------------
def test_structures_are_bell_many_and_canonical():
    for n, bell in zip(range(1, 8), [1, 2, 5, 15, 52, 203, 877]):
        s = group_structures(n)
        assert s.shape == (bell, n) and s.dtype == torch.int64 and bell_number(n) == bell
        assert len({tuple(r) for r in s.tolist()}) == bell
        assert (s[:, 0] == 0).all()
        assert (s[:, 1:] <= s.cummax(1).values[:, :-1] + 1).all()  # restricted growth
        assert torch.equal(structure_index(s), torch.arange(bell))
    table2 = torch.tensor([
        [1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1],
        [1, 1, 1, 1, 1, 2, 2, 2, 2, 2, 2, 2, 2, 2, 2],
        [1, 1, 2, 2, 2, 1, 1, 1, 2, 2, 2, 3, 3, 3, 3],
        [1, 2, 1, 2, 3, 1, 2, 3, 1, 2, 3, 1, 2, 3, 4]]).T - 1
    assert torch.equal(group_structures(4), table2)


def test_structure_index_of_any_labelling():
    assert structure_index(torch.tensor([[3, 3, 1, 1], [2, 0, 2, 0]])).tolist() == [3, 6]


def test_structure_index_compiled_same_and_without_the_cache_warning():
    """Under torch.compile the table is built without its cache, whose wrapper Dynamo warns
    about (every compiled group filter printed the warning); the same indices.
    """
    import warnings

    torch._dynamo.reset()
    labels = torch.tensor([[3, 3, 1, 1], [2, 0, 2, 0], [0, 1, 2, 3], [1, 1, 1, 1]])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = torch.compile(structure_index, backend="eager", fullgraph=True)(labels)
    assert torch.equal(got, structure_index(labels)) and got.tolist() == [3, 6, 14, 0]
    assert not [w for w in caught if "lru_cache" in str(w.message)]


def test_structure_prior_normalised(gen):
    prior = GroupStructurePrior(0.6, 0.05)
    pos = 1000 * torch.rand(3, 5, 4, 2, generator=gen, dtype=torch.float64)
    exists = torch.rand(3, 5, 4, generator=gen) < 0.6
    prev = torch.randint(0, 15, (3, 5), generator=gen)
    lp = prior.log_probs(prev, pos, exists)
    assert lp.shape == (3, 5, 15)
    torch.testing.assert_close(torch.logsumexp(lp, -1), torch.zeros(3, 5, dtype=torch.float64), atol=1e-12, rtol=0)
    # eq. 19: the previous structure gets at least P_NC
    assert (lp.gather(-1, prev.unsqueeze(-1)) >= math.log(0.6) - 1e-12).all()


def test_structure_scores_eq21():
    """pi(h) propto prod q_ij over pairs together, prod (1 - q_ij) over pairs apart."""
    prior = GroupStructurePrior(0.6, 0.05, scale=100.0)
    pos = torch.tensor([[0.0, 0.0], [50.0, 0.0], [400.0, 0.0]], dtype=torch.float64)
    exists = torch.tensor([True, True, False])
    log_pi = prior.log_scores(pos, exists)
    q01 = math.exp(-0.5 * 0.25)
    q = {(0, 1): q01, (0, 2): 0.05, (1, 2): 0.05}
    f = []
    for row in group_structures(3).tolist():
        f.append(math.prod(q[p] if row[p[0]] == row[p[1]] else 1 - q[p] for p in q))
    ref = torch.tensor(f, dtype=torch.float64)
    torch.testing.assert_close(log_pi, (ref / ref.sum()).log(), rtol=1e-12, atol=1e-12)


def test_structure_prior_sample_frequencies(gen):
    prior = GroupStructurePrior(0.3, 0.05, scale=200.0)
    pos = torch.tensor([[0.0, 0.0], [100.0, 0.0], [150.0, 80.0]], dtype=torch.float64)
    exists = torch.tensor([True, True, True])
    n = 20000
    draws = prior.sample(torch.full((n,), 2), pos.expand(n, 3, 2), exists.expand(n, 3), generator=gen)
    p = prior.log_probs(torch.tensor(2), pos, exists).exp()
    freq = torch.bincount(draws, minlength=5).double() / n
    assert (freq - p).abs().max() < 5 * (p * (1 - p) / n).sqrt().max()


# -- configurations: sample / log_prob, merge and split -----------------------------------
def _existence():
    return GroupExistence(0.2, 0.05, AREA, velocity_std=3.0)


def _config(gen, shape=(2,), k=4):
    x = torch.empty(shape + (k, 4), dtype=torch.float64)
    x[..., 0::2] = 2000 + 300 * torch.rand(shape + (k, 2), generator=gen, dtype=torch.float64)
    x[..., 1::2] = 3 * torch.randn(shape + (k, 2), generator=gen, dtype=torch.float64)
    v = x.clone()
    return x, v


def test_transition_of_fixed_structure_is_the_paper_matrices():
    """Structure [0, 0, 1], all alive, no repulsion: Psi and Q per axis are F_2, F_1 and
    Q_2, Q_1 of eqs. 14 and 16, rearranged."""
    m, ex = motion(), _existence()
    k = 3
    labels = torch.tensor([0, 0, 1])
    alive = torch.ones(k, dtype=torch.bool)
    tr = m.transition(torch.zeros(k, 2, dtype=torch.float64), labels, labels, alive, alive, existence=ex)
    Psi = torch.zeros(2 * 4 * k, 2 * 4 * k, dtype=torch.float64)
    Qb = torch.zeros_like(Psi)
    for axis in range(2):
        sl = slice(axis * 4 * k, (axis + 1) * 4 * k)
        Psi[sl, sl], Qb[sl, sl] = tr.Psi, tr.Q
    for members, leader in (([0, 1], 0), ([2], 1)):
        F, _, Q = m.matrices(len(members))
        idx = torch.tensor(_paper_order(members, leader, k))
        torch.testing.assert_close(Psi[idx][:, idx], F, rtol=1e-12, atol=1e-15)
        torch.testing.assert_close(Qb[idx][:, idx], Q, rtol=1e-12, atol=1e-15)
    assert torch.equal(tr.r, torch.zeros(2, 4 * k, dtype=torch.float64))


def _paper_order(members, leader, k):
    """Indices into the flattened (2, 4K) per-axis state of a group's eq. 3 state."""
    def at(axis, comp, slot):
        return axis * 4 * k + comp * k + slot
    return ([at(0, 0, i) for i in members] + [at(1, 0, i) for i in members]
            + [at(0, 1, i) for i in members] + [at(1, 1, i) for i in members]
            + [at(0, 2, leader), at(1, 2, leader), at(0, 3, leader), at(1, 3, leader)])


def test_merge_averages_leaders_and_split_keeps_them(gen):
    """Noise-free means: a merge (eq. 38) propagates the average of the merging leaders; a
    split propagates the common previous leader in both parts."""
    m, ex = motion(), _existence()
    x, v = _config(gen, (1,))
    alive = torch.ones(1, 4, dtype=torch.bool)
    s = to_axes(x, v)
    k = 4
    Fll = m.F_ll
    # merge [0, 0, 1, 1] -> [0, 0, 0, 0]
    tr = m.transition(x[..., 0::2], torch.tensor([[0, 0, 1, 1]]), torch.tensor([[0, 0, 0, 0]]), alive, alive,
                      existence=ex)
    mean = s @ tr.Psi.mT + tr.r
    vbar = 0.5 * (v[0, 0] + v[0, 1])
    for axis in range(2):
        lead = torch.stack([vbar[2 * axis], vbar[2 * axis + 1]])
        torch.testing.assert_close(mean[0, axis, [2 * k, 3 * k]], Fll @ lead, rtol=1e-12, atol=1e-9)
        # the members follow the averaged leader too
        mem = torch.stack([x[0, 2, 2 * axis], x[0, 2, 2 * axis + 1]])
        torch.testing.assert_close(mean[0, axis, [2, k + 2]], m.F_ss @ mem + m.F_sl @ lead, rtol=1e-12, atol=1e-9)
    # split [0, 0, 0, 0] -> [0, 0, 1, 1]: both new leaders come from old leader 0
    tr = m.transition(x[..., 0::2], torch.tensor([[0, 0, 0, 0]]), torch.tensor([[0, 0, 1, 1]]), alive, alive,
                      existence=ex)
    mean = s @ tr.Psi.mT + tr.r
    for axis in range(2):
        lead = torch.stack([v[0, 0, 2 * axis], v[0, 0, 2 * axis + 1]])
        for h in (0, 1):
            torch.testing.assert_close(mean[0, axis, [2 * k + h, 3 * k + h]], Fll @ lead, rtol=1e-12, atol=1e-9)


def test_sample_deaths_births_and_log_prob(gen):
    """Dead slots at x_death, leaders of all-dead groups at v_death, new groups' leaders
    near their newborns; log_prob is finite for sampled configurations and -inf for a
    newborn outside the area."""
    m, ex = motion(r1=8.0, r2=12.0), _existence()
    x, v = _config(gen, (3,))
    lp = torch.tensor([[0, 0, 1, 1], [0, 0, 1, 1], [0, 1, 2, 3]])
    lab = torch.tensor([[0, 0, 1, 1], [0, 0, 1, 2], [0, 0, 1, 1]])
    ep = torch.tensor([[1, 1, 1, 1], [1, 1, 0, 0], [1, 0, 0, 0]]).bool()
    e = torch.tensor([[1, 1, 0, 0], [1, 1, 1, 1], [1, 1, 1, 1]]).bool()
    xn, vn = m.sample(x, v, lp, lab, ep, e, existence=ex, generator=gen)
    assert torch.equal(xn[0, 2:], torch.zeros(2, 4, dtype=torch.float64))  # dead -> x_death
    assert torch.equal(vn[0, 1:], torch.zeros(3, 4, dtype=torch.float64))  # group 1 all dead, 2-3 unused
    # run 1: slots 2, 3 born in new groups 1 and 2: each new leader near its newborn (eq. 35)
    assert ((vn[1, 1:3, 0::2] - xn[1, 2:4, 0::2]).abs() < 50 * 8).all()
    # run 2: slot 1 is a group birth (joins survivor 0), slots 2-3 a new group
    assert ((xn[2, 1, 0::2] - xn[2, 0, 0::2]).abs() < 50 * 8).all()
    lpr = m.log_prob(xn, vn, x, v, lp, lab, ep, e, existence=ex)
    assert lpr.shape == (3,) and torch.isfinite(lpr).all()
    bad = xn.clone()
    bad[1, 2, 0] = -10.0  # independent newborn outside the area
    assert m.log_prob(bad, vn, x, v, lp, lab, ep, e, existence=ex)[1] == -math.inf


def test_log_prob_matches_sample_moments(gen):
    """Monte Carlo: given the independent newborns' positions, the residuals of sampled
    configurations have mean 0 and the covariance Q that log_prob scores (merge, group
    birth, independent birth with a new leader, repulsion), within 5 standard errors."""
    m, ex = motion(r1=8.0, r2=12.0), _existence()
    x, v = _config(gen, (1,), 5)
    lp, lab = torch.tensor([[0, 0, 1, 1, 2]]), torch.tensor([[0, 0, 0, 0, 1]])
    ep, e = torch.tensor([[1, 1, 1, 0, 0]]).bool(), torch.tensor([[1, 1, 1, 1, 1]]).bool()
    n = 20000
    ns = lambda t: t.expand((n,) + t.shape[1:])  # noqa: E731
    xs, vs = m.sample(ns(x), ns(v), ns(lp), ns(lab), ns(ep), ns(e), existence=ex, generator=gen)
    tr = m.transition(ns(x)[..., 0::2], ns(lp), ns(lab), ns(ep), ns(e), existence=ex, pos_born=xs[..., 0::2])
    resid = to_axes(xs, vs) - (to_axes(ns(x), ns(v)) @ tr.Psi.mT + tr.r)  # (n, 2, 20)
    Q, rnd = tr.Q[0], tr.random[0]
    assert rnd.sum() == 4 + 5 + 2 + 2 and tr.free_birth[0].tolist() == [False] * 4 + [True]
    sd = torch.diagonal(Q).sqrt()
    z = resid.mean(0) / (sd / math.sqrt(n)).clamp(min=1e-12)
    assert (z.abs()[:, rnd] < 5).all()
    assert (resid[:, :, ~rnd] == 0).all()
    emp = torch.einsum("nai,naj->ij", resid, resid) / (2 * n)
    corr_err = (emp - Q) / (sd.unsqueeze(0) * sd.unsqueeze(1)).clamp(min=1e-12)
    assert corr_err[rnd][:, rnd].abs().max() < 5 * math.sqrt(2 / (2 * n))
    # the new leader (slot 1) sits on its newborn (slot 4) up to Q_bVL
    assert Q[5 + 1, 5 + 4] == 0 and Q[15 + 1, 5 + 4] == pytest.approx(ex.velocity_std**2)


# -- item 5: pairwise Kalman marginalisation ------------------------------------------------
def _simulate_fixed(m, ex, labels, k, steps, gen):
    x, v = _config(gen, (1,), k)
    alive = torch.ones(1, k, dtype=torch.bool)
    xs = [x]
    for _ in range(steps):
        x, v = m.sample(x, v, labels, labels, alive, alive, existence=ex, generator=gen)
        xs.append(x)
    return torch.stack(xs)[:, 0]  # (T + 1, K, 4)


def test_pairwise_kalman_equals_joint_gaussian_and_full_kalman(gen):
    """No repulsion, fixed structure [0, 0, 1]: (a) the sequential product of eq. 58 equals
    the joint density of the stacked positions x_p,1:T from brute-force conditioning of the
    full linear model built from the paper's F_n, Q_n; (b) the marginalised statistics equal
    a standard Kalman filter on the full state that observes the positions exactly."""
    m, ex = motion(), _existence()
    k, steps = 3, 8
    labels = torch.tensor([[0, 0, 1]])
    alive = torch.ones(1, k, dtype=torch.bool)
    traj = _simulate_fixed(m, ex, labels, k, steps, gen)
    pos = traj[..., 0::2]  # (T + 1, K, 2)
    # prior on w_0 per axis (shared covariance); leader slot 2 unused (v_death, no variance)
    d = 3 * k
    A = torch.randn(d, d, generator=gen, dtype=torch.float64)
    used = torch.tensor([1, 1, 1, 1, 1, 0, 1, 1, 0], dtype=torch.float64)
    P0 = (A @ A.T + d * torch.eye(d, dtype=torch.float64)) * used * used.unsqueeze(-1)
    m0 = torch.stack([torch.cat([traj[0, :, 1 + a], torch.tensor([2100.0, 2200.0, 0.0], dtype=torch.float64),
                                 torch.tensor([1.0, -1.0, 0.0], dtype=torch.float64)]) for a in (0, 2)]) * \
        torch.cat([torch.ones(k), used[k:]]).double()
    stats = KalmanStats(m0.unsqueeze(0), P0.unsqueeze(0))
    total = torch.zeros(1, dtype=torch.float64)
    means, covs = [], []
    for t in range(1, steps + 1):
        tr = m.transition(pos[t - 1].unsqueeze(0), labels, labels, alive, alive, existence=ex)
        pred = pairwise_kalman_predict(stats, pos[t - 1].unsqueeze(0), tr)
        lp, stats = pairwise_kalman_update(pred, pos[t].unsqueeze(0))
        total += lp
        means.append(stats.mean[0])
        covs.append(stats.cov[0])

    # the full model on the used components, both axes, from the paper's matrices
    groups = (([0, 1], 0), ([2], 1))
    idx = torch.tensor([i for mem, h in groups for i in _paper_order(mem, h, k)])  # into (2, 4K) flat
    D = idx.numel()
    F = torch.zeros(D, D, dtype=torch.float64)
    Q = torch.zeros(D, D, dtype=torch.float64)
    o = 0
    for mem, h in groups:
        Fn, _, Qn = m.matrices(len(mem))
        F[o:o + Fn.shape[0], o:o + Fn.shape[0]], Q[o:o + Fn.shape[0], o:o + Fn.shape[0]] = Fn, Qn
        o += Fn.shape[0]
    flat = lambda a, comp, slot: a * 4 * k + comp * k + slot  # noqa: E731
    pos_idx = [flat(a, 0, i) for a in range(2) for i in range(k)]
    H = torch.zeros(len(pos_idx), D, dtype=torch.float64)
    where = {int(j): n for n, j in enumerate(idx)}
    for r, j in enumerate(pos_idx):
        H[r, where[j]] = 1.0
    # initial moments in the full layout
    full_m = torch.cat([pos[0].T, m0], -1).reshape(-1)
    full_P = torch.zeros(8 * k, 8 * k, dtype=torch.float64)
    for a in range(2):
        sl = slice(a * 4 * k + k, (a + 1) * 4 * k)
        full_P[sl, sl] = P0
    mu, P = full_m[idx], full_P[idx][:, idx]

    # (a) brute force: joint Gaussian of the stacked positions 1..T
    mus, Sig = [mu], [P]
    for t in range(steps):
        mus.append(F @ mus[-1])
        Sig.append(F @ Sig[-1] @ F.T + Q)
    big = torch.zeros(steps * H.shape[0], steps * H.shape[0], dtype=torch.float64)
    for t in range(1, steps + 1):
        for u in range(1, t + 1):
            C = H @ torch.linalg.matrix_power(F, t - u) @ Sig[u] @ H.T  # Cov(x_t, x_u)
            r, c = slice((t - 1) * H.shape[0], t * H.shape[0]), slice((u - 1) * H.shape[0], u * H.shape[0])
            big[r, c], big[c, r] = C, C.T
    mean_big = torch.cat([H @ mus[t] for t in range(1, steps + 1)])
    obs_big = torch.cat([pos[t].T.reshape(-1) for t in range(1, steps + 1)])
    ref = torch.distributions.MultivariateNormal(mean_big, big).log_prob(obs_big)
    assert abs(float(total[0] - ref)) / abs(float(ref)) < 1e-8, (float(total[0]), float(ref))

    # (b) standard Kalman filter on the full state, positions observed without noise
    loglik = 0.0
    for t in range(1, steps + 1):
        mu, P = F @ mu, F @ P @ F.T + Q
        S = H @ P @ H.T
        y = pos[t].T.reshape(-1)
        loglik += float(torch.distributions.MultivariateNormal(H @ mu, S).log_prob(y))
        G = torch.linalg.solve(S, H @ P).T
        mu, P = mu + G @ (y - H @ mu), P - G @ S @ G.T
        # compare the w components
        w_idx = [n for n, j in enumerate(idx.tolist()) if j not in pos_idx]
        w_flat = [idx[n].item() for n in w_idx]
        got_m = torch.cat([torch.zeros(2, k, dtype=torch.float64), means[t - 1]], -1).reshape(-1)[w_flat]
        torch.testing.assert_close(got_m, mu[w_idx], rtol=1e-9, atol=1e-7)
        full_cov = torch.zeros(8 * k, 8 * k, dtype=torch.float64)
        for a in range(2):
            sl = slice(a * 4 * k + k, (a + 1) * 4 * k)
            full_cov[sl, sl] = covs[t - 1]
        torch.testing.assert_close(full_cov[w_flat][:, w_flat], P[w_idx][:, w_idx], rtol=1e-8, atol=1e-8)
    assert abs(float(total[0]) - loglik) / abs(loglik) < 1e-8


def test_pairwise_kalman_through_births_deaths_merges(gen):
    """With repulsion, group and independent births, a death and a merge, the sequential
    product of eq. 58 equals the joint Gaussian of the observed positions under the affine
    transitions (eq. 42), by brute-force conditioning; batched over 2 x 3 particles."""
    m, ex = motion(r1=8.0, r2=12.0), _existence()
    k = 4
    # group birth, merge, death + split, two independent births with new leaders, merge of
    # those new groups
    labs = [torch.tensor([0, 0, 1, 2]), torch.tensor([0, 0, 1, 1]), torch.tensor([0, 0, 0, 0]),
            torch.tensor([0, 0, 0, 1]), torch.tensor([0, 1, 0, 2]), torch.tensor([0, 1, 0, 1])]
    ex_seq = [torch.tensor([1, 1, 1, 0]), torch.tensor([1, 1, 1, 1]), torch.tensor([1, 1, 1, 1]),
              torch.tensor([1, 0, 1, 0]), torch.tensor([1, 1, 1, 1]), torch.tensor([1, 1, 1, 1])]
    ex_seq = [e.bool() for e in ex_seq]
    shape = (2, 3)
    x, v = _config(gen, shape, k)
    x = torch.where(ex_seq[0].unsqueeze(-1), x, torch.zeros_like(x))
    xs, vs = [x], [v]
    for t in range(1, len(labs)):
        x, v = m.sample(x, v, labs[t - 1].expand(shape + (k,)), labs[t].expand(shape + (k,)),
                        ex_seq[t - 1].expand(shape + (k,)), ex_seq[t].expand(shape + (k,)),
                        existence=ex, generator=gen)
        xs.append(x)
        vs.append(v)
    # marginalised: start from the exact w_0 (zero covariance)
    s0 = to_axes(xs[0], vs[0])
    stats = KalmanStats(s0[..., k:], torch.zeros(shape + (3 * k, 3 * k), dtype=torch.float64))
    total = torch.zeros(shape, dtype=torch.float64)
    trs = []
    for t in range(1, len(labs)):
        args = (xs[t - 1][..., 0::2], labs[t - 1].expand(shape + (k,)), labs[t].expand(shape + (k,)),
                ex_seq[t - 1].expand(shape + (k,)), ex_seq[t].expand(shape + (k,)))
        tr = m.transition(*args, existence=ex)
        pred = pairwise_kalman_predict(stats, xs[t - 1][..., 0::2], tr)
        lp, stats = pairwise_kalman_update(pred, xs[t][..., 0::2])
        total += lp
        trs.append(m.transition(*args, existence=ex, pos_born=xs[t][..., 0::2]))
    # brute force per particle: propagate mean and cross-covariances of the full state
    for b in range(shape[0]):
        for n in range(shape[1]):
            mus, Sig, Phi = [s0[b, n]], [torch.zeros(4 * k, 4 * k, dtype=torch.float64)], []
            for tr in trs:
                Psi, r, Q = tr.Psi[b, n], tr.r[b, n], tr.Q[b, n]
                mus.append(mus[-1] @ Psi.T + r)
                Sig.append(Psi @ Sig[-1] @ Psi.T + Q)
                Phi.append(Psi)
            obs = [tr.observed[b, n] for tr in trs]
            blocks, means, ys = [], [], []
            for t in range(1, len(labs)):
                o = obs[t - 1].nonzero().squeeze(-1)
                blocks.append(o)
                means.append(mus[t][:, o])
                ys.append(xs[t][b, n][o][:, 0::2].T)
            sizes = [len(o) for o in blocks]
            tot = sum(sizes)
            big = torch.zeros(tot, tot, dtype=torch.float64)
            offs = np.cumsum([0] + sizes)
            for t in range(1, len(labs)):
                for u in range(1, t + 1):
                    T = torch.eye(4 * k, dtype=torch.float64)
                    for j in range(u, t):
                        T = Phi[j] @ T
                    C = (T @ Sig[u])[blocks[t - 1]][:, blocks[u - 1]]
                    big[offs[t - 1]:offs[t], offs[u - 1]:offs[u]] = C
                    big[offs[u - 1]:offs[u], offs[t - 1]:offs[t]] = C.T
            ref = 0.0
            for a in range(2):  # axes independent, same covariance
                mean_a = torch.cat([mm[a] for mm in means])
                y_a = torch.cat([yy[a] for yy in ys])
                ref += float(torch.distributions.MultivariateNormal(mean_a, big).log_prob(y_a))
            assert abs(float(total[b, n]) - ref) / abs(ref) < 1e-8, (float(total[b, n]), ref)


def test_kalman_sample_moments_and_init(gen):
    """Positions drawn by pairwise_kalman_sample have the predictive moments of eq. 58;
    an all-inactive start predicts nothing observed."""
    m, ex = motion(r1=8.0, r2=12.0), _existence()
    k, n = 3, 20000
    labels, alive = torch.tensor([0, 0, 1]).expand(n, k), torch.ones(n, k, dtype=torch.bool)
    x, v = _config(gen, (1,), k)
    s = to_axes(x, v)
    stats = KalmanStats(s[..., k:].expand(n, 2, 3 * k), torch.eye(3 * k, dtype=torch.float64).expand(n, -1, -1))
    pos_prev = x[..., 0::2].expand(n, k, 2)
    pred = pairwise_kalman_predict(stats, pos_prev, m.transition(pos_prev, labels, labels, alive, alive,
                                                                 existence=ex))
    draws = pairwise_kalman_sample(pred, generator=gen)  # (n, K, 2)
    mean, cov = pred.position_mean[0], pred.position_cov[0]
    se = (torch.diagonal(cov) / n).sqrt().unsqueeze(-1)
    assert ((draws.mean(0) - mean).abs() < 5 * se).all()
    c = draws - mean
    emp = torch.einsum("nia,nja->ij", c, c) / (2 * n)
    sd = torch.diagonal(cov).sqrt()
    assert ((emp - cov) / (sd.unsqueeze(0) * sd.unsqueeze(1))).abs().max() < 5 * math.sqrt(2 / (2 * n))
    init = pairwise_kalman_init((2,), 3, existence=ex)
    assert init.mean.shape == (2, 2, 9) and init.cov.shape == (2, 9, 9) and (init.cov == 0).all()
    dead = torch.zeros(2, 3, dtype=torch.bool)
    tr = m.transition(torch.zeros(2, 3, 2, dtype=torch.float64), torch.zeros(2, 3, dtype=torch.long),
                      torch.zeros(2, 3, dtype=torch.long), dead, dead, existence=ex)
    lp, st = pairwise_kalman_update(pairwise_kalman_predict(init, torch.zeros(2, 3, 2, dtype=torch.float64), tr),
                                    torch.zeros(2, 3, 2, dtype=torch.float64))
    assert torch.equal(lp, torch.zeros(2, dtype=torch.float64)) and torch.isfinite(st.cov).all()


def test_same_seed_same_draw(gen):
    m, ex = motion(r1=8.0, r2=12.0), _existence()
    x, v = _config(gen, (2,))
    args = (x, v, torch.tensor([[0, 0, 1, 1]] * 2), torch.tensor([[0, 0, 0, 1]] * 2),
            torch.ones(2, 4, dtype=torch.bool), torch.tensor([[1, 1, 1, 0], [1, 1, 1, 1]]).bool())
    a = m.sample(*args, existence=ex, generator=torch.Generator().manual_seed(9))
    b = m.sample(*args, existence=ex, generator=torch.Generator().manual_seed(9))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_bad_input():
    with pytest.raises(ValueError, match="alpha"):
        motion(alpha=-1.0)
    with pytest.raises(ValueError, match="r1"):
        motion(r1=8.0)
    with pytest.raises(ValueError, match="p_nc"):
        GroupStructurePrior(1.5, 0.05)
    with pytest.raises(ValueError, match="p_q"):
        GroupStructurePrior(0.6, 0.0)
    with pytest.raises(ValueError, match="n must be"):
        group_structures(0)
    with pytest.raises(ValueError, match="group_birth_std"):
        GroupExistence(0.2, 0.05, AREA, group_birth_std=(1.0,))
    with pytest.raises(ValueError, match="area"):
        GroupExistence(0.2, 0.05, ((0, -1), (0, 1)))
    with pytest.raises(ValueError, match="generator or eps"):
        m, ex = motion(), _existence()
        lab, alive = torch.zeros(1, 2, dtype=torch.long), torch.ones(1, 2, dtype=torch.bool)
        pos = torch.zeros(1, 2, 2, dtype=torch.float64)
        pred = pairwise_kalman_predict(pairwise_kalman_init((1,), 2, existence=ex), pos,
                                       m.transition(pos, lab, lab, alive, alive, existence=ex))
        pairwise_kalman_sample(pred)


@pytest.mark.compile
def test_compiled_update_equals_eager(gen):
    """transition + predict + update compile with fullgraph and give the eager result."""
    m, ex = motion(r1=8.0, r2=12.0), _existence()
    n, k = 16, 4
    table = group_structures(k)
    lp = table[torch.randint(0, 15, (n,), generator=gen)]
    lab = table[torch.randint(0, 15, (n,), generator=gen)]
    ep, e = torch.rand(n, k, generator=gen) < 0.7, torch.rand(n, k, generator=gen) < 0.7
    pos_prev = 2000 + 300 * torch.rand(n, k, 2, generator=gen, dtype=torch.float64)
    pos = pos_prev + torch.randn(n, k, 2, generator=gen, dtype=torch.float64)
    A = torch.randn(n, 3 * k, 3 * k, generator=gen, dtype=torch.float64)
    mean, cov = torch.randn(n, 2, 3 * k, generator=gen, dtype=torch.float64), A @ A.mT

    def update(mean, cov, pos_prev, pos, lp, lab, ep, e):
        tr = m.transition(pos_prev, lp, lab, ep, e, existence=ex)
        log_pred, st = pairwise_kalman_update(pairwise_kalman_predict(KalmanStats(mean, cov), pos_prev, tr), pos)
        return log_pred, st.mean, st.cov

    args = (mean, cov, pos_prev, pos, lp, lab, ep, e)
    for got, ref in zip(torch.compile(update, fullgraph=True)(*args), update(*args)):
        torch.testing.assert_close(got, ref, rtol=1e-9, atol=1e-9)


# -- the Bayes limit of detection (issue 23 item 1) ---------------------------------------
LAW = dict(p_birth=0.2, p_death=0.05, p_d1=0.7, p_fa=0.002, p_here=1e-4)


def _brute_posterior(d, p_birth, p_death, p_d1, p_fa, p_here, p_alive):
    """P(alive at T | d_1:T) by summing the probability of every hidden path e_0..e_T."""
    num = den = 0.0
    for path in itertools.product((0, 1), repeat=len(d) + 1):
        p = p_alive if path[0] else 1 - p_alive
        for prev, cur, obs in zip(path, path[1:], d):
            p *= ((1 - p_death) if cur else p_death) if prev else ((p_birth * p_here) if cur else 1 - p_birth * p_here)
            p *= (p_d1 if obs else 1 - p_d1) if cur else (p_fa if obs else 1 - p_fa)
        den += p
        num += p * path[-1]
    return num / den


@pytest.mark.parametrize("p_alive", [0.0, 0.3, 1.0])
def test_localised_existence_equals_brute_force_over_hidden_paths(p_alive):
    from torchmcmcpf.models.group import localised_existence

    law = {**LAW, "p_here": 0.05}  # a large p_here exercises the birth branch
    seqs = torch.tensor(list(itertools.product((False, True), repeat=5)))  # every detection sequence of length 5
    post = localised_existence(seqs, **law, p_alive=p_alive)
    for s in range(seqs.shape[0]):
        for t in range(1, 6):
            ref = _brute_posterior(seqs[s, :t].tolist(), **law, p_alive=p_alive)
            assert math.isclose(float(post[s, t - 1]), ref, rel_tol=1e-12, abs_tol=1e-15)


def test_existence_limit_is_the_mean_over_detection_sequences():
    """The per-step mean is the probability-weighted mean over every detection sequence (an
    independent brute-force sum), and the bracket beyond the window holds the exact value."""
    from torchmcmcpf.models.group import existence_limit, localised_existence

    lim = existence_limit(8, **LAW, window=6)
    for t in range(1, 9):
        ref = 0.0
        for seq in itertools.product((False, True), repeat=t):
            p = math.prod(LAW["p_d1"] if s else 1 - LAW["p_d1"] for s in seq)
            ref += p * float(localised_existence(torch.tensor([seq]), **LAW)[0, -1])
        assert abs(float(lim.per_step[t - 1]) - ref) <= float(lim.per_step_error[t - 1]) + 1e-12
        if t <= 6:
            assert float(lim.per_step_error[t - 1]) == 0.0
    # issue 23: four targets at P_d,1 = 0.7 allow about 3.67, at the paper's 17 dB (0.885) 3.82
    full = existence_limit(60, **LAW)
    assert abs(4 * full.stationary - 3.670) < 1e-3 and full.stationary_error < 1e-5
    assert abs(4 * existence_limit(60, **{**LAW, "p_d1": 0.885}).stationary - 3.825) < 1e-3
    # 1, 2, 3 misses after a long detected run: 0.85, 0.56, 0.25 (issue 23)
    after = localised_existence(torch.tensor([[True] * 30 + [False] * 3]), **LAW, p_alive=1.0)[0, -3:]
    torch.testing.assert_close(after, torch.tensor([0.8506, 0.5586, 0.2537], dtype=torch.float64), atol=1e-4,
                               rtol=0)
    with pytest.raises(ValueError, match="p_d1"):
        existence_limit(5, **{**LAW, "p_d1": 0.001})


def test_closeness_power_and_scenario_scale():
    from torchmcmcpf.models.group import gaussian_closeness
    from torchmcmcpf.scenarios.group_merge import group_merge

    a, b = torch.zeros(2, dtype=torch.float64), torch.tensor([300.0, 400.0], dtype=torch.float64)  # 500 m apart
    assert math.isclose(float(gaussian_closeness(500.0)(a, b)), math.exp(-0.5), rel_tol=1e-12)
    assert math.isclose(float(gaussian_closeness(500.0, 4.0)(a, b)), math.exp(-0.5), rel_tol=1e-12)
    assert math.isclose(float(gaussian_closeness(1000.0, 4.0)(a, b)), math.exp(-0.5 / 16), rel_tol=1e-12)
    # the scenario's prior scores two groups of two before the merge and one group after
    scn = group_merge(1, generator=torch.Generator().manual_seed(0))
    pi = scn.structure_prior.log_scores(scn.positions[:, 0], scn.exists[:, 0]).exp()  # (T, 15)
    assert float(pi[10:45, [3, 6, 8]].sum(-1).mean()) > 0.9 and float(pi[45:, 0].mean()) > 0.98
