"""GroupMCMCFilter (paper 004 sec. 4): each move leaves its target invariant; contract checks.

Invariance: two slots, a 6 x 6 pixel grid and a cloud of three previous particles (both
alive in one group, one alive, none alive). The reference is the target of eq. 43 written
out independently of the filter's caches (``w_j p(g|j) p(e|e^j) p(x|j,g,e) p(Z|x,e)`` with
the pairwise Kalman predictive and ``p_0``), integrated by importance sampling stratified over
the 24 discrete classes with the positions drawn from their prior. Chains started from that target (resampled
from the pool) are moved a few times by one move; the move is invariant if the discrete
marginals (ancestor, structure, existence pattern) and the mean positions stay within Monte
Carlo error (5 standard errors: chains plus reference).
"""

import pytest
import torch

from torchmcmcpf.filters.group import (
    GroupMCMCFilter,
    GroupState,
    Models,
    draw_joint_noise,
    draw_refine_noise,
    joint_move,
    make_chain,
    make_cloud,
    refine_move,
)
from torchmcmcpf.models.group import (
    GroupExistence,
    GroupStructurePrior,
    KalmanStats,
    VirtualLeaderMotion,
    group_structures,
    pairwise_kalman_predict,
    pairwise_kalman_sample,
    structure_index,
)
from torchmcmcpf.models.sensors.pixels import ThresholdedPixels
from torchmcmcpf.scenarios.group_merge import TABLE1

DT = torch.float64
K, C, POOL = 2, 4000, 480_000


def small_problem():
    sensor = ThresholdedPixels((6, 6), 50.0, p_fa=0.05, p_d1=0.7)
    motion = VirtualLeaderMotion(**TABLE1)
    existence = GroupExistence(0.3, 0.2, sensor.area, velocity_std=5.0)
    prior = GroupStructurePrior(0.6, 0.05, scale=150.0)
    pos = torch.tensor([[[100.0, 120.0], [160.0, 150.0]], [[200.0, 80.0], [0.0, 0.0]], [[0.0, 0.0], [0.0, 0.0]]],
                       dtype=DT)
    exists = torch.tensor([[True, True], [True, False], [False, False]])
    labels = torch.tensor([[0, 0], [0, 1], [0, 1]])
    vel = torch.tensor([[[3.0, -1.0], [2.0, 1.0]], [[-2.0, 2.0], [0.0, 0.0]], [[0.0, 0.0], [0.0, 0.0]]], dtype=DT)
    x = torch.stack([pos[..., 0], vel[..., 0], pos[..., 1], vel[..., 1]], -1).unsqueeze(0)  # (1, 3, K, 4)
    w_mean = torch.zeros(1, 3, 2, 3 * K, dtype=DT)
    w_mean[..., :K] = vel.transpose(-1, -2).unsqueeze(0)
    w_mean[..., K:2 * K] = pos.mean(-2, keepdim=True).transpose(-1, -2).unsqueeze(0)  # leaders near the members
    A = torch.tensor([[15.0, 4.0, 0.5, 0.0, 0.2, 0.0], [0.0, 12.0, 0.0, 0.4, 0.0, 0.1], [0.0, 0.0, 30.0, 5.0, 0.0, 0.0],
                      [0.0, 0.0, 0.0, 30.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 1.0, 0.2], [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]],
                     dtype=DT)
    w_cov = (A @ A.T).expand(1, 3, 6, 6).contiguous()
    state = GroupState(x, torch.log(torch.tensor([[0.5, 0.3, 0.2]], dtype=DT)), exists.unsqueeze(0),
                       labels.unsqueeze(0), w_mean, w_cov,
                       torch.zeros(1, 6, 6, dtype=torch.bool).index_put_((torch.tensor([0, 0]), torch.tensor([2, 4]),
                                                                          torch.tensor([2, 1])), torch.tensor(True)))
    z = torch.zeros(1, 6, 6, dtype=torch.bool)
    z[0, 2, 2] = z[0, 3, 3] = z[0, 4, 1] = z[0, 0, 5] = True
    return sensor, motion, existence, prior, state, z


def reference(sensor, motion, existence, prior, state, z, generator):
    """Importance sample of the target, stratified over the 24 discrete classes ``(j, g, e)``:
    within a class the positions are drawn from their prior ``p(x | j, g, e)`` (the Kalman
    predictive by :func:`pairwise_kalman_sample`, ``p_0`` for free births), so the weight is
    ``w_j p(g|j) p(e|e^j) p(Z|x, e)``. Returns ``(j, g, e, pos, log weight)``, each ``(1, M)``."""
    n = state.x.shape[1]
    table = group_structures(K)
    pats = torch.tensor([[False, False], [False, True], [True, False], [True, True]])
    jj, gg, pp = torch.meshgrid(torch.arange(n), torch.arange(table.shape[0]), torch.arange(4), indexing="ij")
    m = POOL // jj.numel()
    j = jj.reshape(1, -1, 1).expand(1, jj.numel(), m).reshape(1, -1)
    g = gg.reshape(1, -1, 1).expand(1, jj.numel(), m).reshape(1, -1)
    e = pats[pp.reshape(-1)].reshape(1, -1, 1, K).expand(1, jj.numel(), m, K).reshape(1, -1, K)

    def take(t):
        return t[0, j[0]].unsqueeze(0)

    pos_prev, lab_prev, e_prev = take(state.x[..., 0::2]), take(state.labels), take(state.exists)
    lab = table[g]
    tr = motion.transition(pos_prev, lab_prev, lab, e_prev, e, existence=existence)
    pred = pairwise_kalman_predict(KalmanStats(take(state.w_mean), take(state.w_cov)), pos_prev, tr)
    born = existence.sample_p0_position(e.shape, generator=generator, dtype=DT)
    pos = torch.where(tr.observed.unsqueeze(-1), pairwise_kalman_sample(pred, generator=generator),
                      torch.where(tr.free_birth.unsqueeze(-1), born, torch.zeros_like(born)))
    log_t = take(state.log_w.unsqueeze(-1)).squeeze(-1)
    log_t = log_t + prior.log_prob(g, structure_index(lab_prev), pos_prev, e_prev)
    log_t = log_t + existence.log_prob_exists(e, e_prev).sum(-1)
    x4 = torch.stack([pos[..., 0], pos[..., 0] * 0, pos[..., 1], pos[..., 1] * 0], -1)
    return j, g, e, pos, log_t + sensor.log_likelihood(x4, z, e)


def summaries(j, g, e, pos):
    """(S, M) statistics per sample: one-hot ancestor, structure, existence pattern; e_i x_i."""
    pattern = e[..., 0].long() * 2 + e[..., 1].long()
    one_hot = torch.nn.functional.one_hot
    cols = [one_hot(j, 3), one_hot(g, 2), one_hot(pattern, 4)]
    ex = (pos * e.unsqueeze(-1)).flatten(-2) / 100.0
    return torch.cat([c.to(DT) for c in cols] + [ex], -1)[0]  # (M, 13)


@pytest.fixture(scope="module")
def setup():
    sensor, motion, existence, prior, state, z = small_problem()
    g = torch.Generator().manual_seed(11)
    j, s, e, pos, log_w = reference(sensor, motion, existence, prior, state, z, g)
    w = torch.softmax(log_w[0], -1)
    stats = summaries(j, s, e, pos)
    ref_mean = (w.unsqueeze(-1) * stats).sum(0)
    ref_var = (w.unsqueeze(-1) * (stats - ref_mean).square()).sum(0)
    ref_se2 = (w.square().unsqueeze(-1) * (stats - ref_mean).square()).sum(0)  # self-normalised IS (delta method)
    pick = torch.multinomial(w, C, replacement=True, generator=g).unsqueeze(0)
    start = (j[0, pick[0]].unsqueeze(0), group_structures(K)[s[0, pick[0]]].unsqueeze(0), e[0, pick[0]].unsqueeze(0),
             pos[0, pick[0]].unsqueeze(0))
    return (sensor, motion, existence, prior, state, z), start, ref_mean, ref_var, ref_se2


@pytest.mark.parametrize("move", ["joint", "refine"])
def test_move_leaves_target_invariant(setup, move):
    (sensor, motion, existence, prior, state, z), start, ref_mean, ref_var, ref_se2 = setup
    assert float(ref_se2.max().sqrt()) < 0.02  # the reference is precise enough for the tolerance below
    models = Models(motion, sensor, existence, 0.01, 0.5)
    from torchmcmcpf.filters.group import GroupMCMCSettings

    cloud = make_cloud(state, z, structure_prior=prior, models=models, settings=GroupMCMCSettings(p_a=0.5, p_i=0.01))
    chain = make_chain(*start, cloud, z, models)
    g = torch.Generator().manual_seed(3)
    accepted = []
    for _ in range(4):
        if move == "joint":
            chain, acc = joint_move(chain, draw_joint_noise((1, C, K), generator=g, dtype=DT), cloud, z, models)
        else:
            chain, _, acc = refine_move(chain, draw_refine_noise((1, C, K), generator=g, dtype=DT), cloud, z, models)
        accepted.append(acc.to(DT).mean())
    assert 0.05 < float(torch.stack(accepted).mean()) < 0.99  # the move does move
    s = structure_index(chain.labels)
    est = summaries(chain.j, s, chain.exists, chain.pos).mean(0)
    tol = 5 * (ref_var / C + ref_se2).sqrt() + 1e-12
    assert bool(((est - ref_mean).abs() <= tol).all()), ((est - ref_mean) / tol)


# ----------------------------------------------------------------------------- contract
def tiny_filter(compile_step=False, marginalise=True):
    from torchmcmcpf.scenarios.group_merge import group_merge

    scn = group_merge(2, generator=torch.Generator().manual_seed(0), num_steps=4, merge_step=3)
    filt = GroupMCMCFilter(scn.motion, scn.sensor, 8, existence=scn.existence, structure_prior=scn.structure_prior,
                           num_chains=4, burn_in=3, thinning=2, marginalise=marginalise, compile_step=compile_step)
    return filt, scn.frames, filt.init_inactive(2)


def test_outputs_shapes_and_public_api():
    import torchmcmcpf

    assert torchmcmcpf.GroupMCMCFilter is GroupMCMCFilter and callable(torchmcmcpf.group_mcmc_step)
    filt, frames, init = tiny_filter()
    res = filt(frames, init=init, generator=torch.Generator().manual_seed(1))
    t, b = frames.shape[:2]
    assert res.mean.shape == (t, b, 4, 4) and res.exists_prob.shape == (t, b, 4)
    ex = res.info.extras
    assert ex["structure_prob"].shape == (t, b, 15)
    torch.testing.assert_close(ex["structure_prob"].sum(-1), torch.ones(t, b, dtype=DT))
    torch.testing.assert_close(ex["expected_count"], res.exists_prob.sum(-1))
    assert res.info.acceptance.shape == (t, b) and bool(torch.isfinite(res.info.acceptance).all())
    assert bool(torch.isnan(res.info.ess).all()) and bool(torch.isnan(res.log_evidence).all())
    st = res.state
    assert st.x.shape == (b, 8, 4, 4) and st.w_mean.shape == (b, 8, 2, 12) and st.w_cov.shape == (b, 8, 12, 12)
    assert bool(torch.isfinite(st.x).all())
    # velocities are the Kalman means: the dead slots carry x_death
    assert bool((st.x[~st.exists] == 0).all())


def test_same_seed_same_bits_and_checkpoint_resume(tmp_path):
    filt, frames, init = tiny_filter()
    a = filt(frames, init=init, generator=torch.Generator().manual_seed(5))
    b = filt(frames, init=init, generator=torch.Generator().manual_seed(5))
    c = filt(frames, init=init, generator=torch.Generator().manual_seed(6))
    assert torch.equal(a.mean, b.mean) and torch.equal(a.state.x, b.state.x)
    assert not torch.equal(a.state.x, c.state.x)
    g = torch.Generator().manual_seed(5)
    first = filt(frames[:2], init=init, generator=g)
    torch.save({"state": first.state, "generator": g.get_state()}, tmp_path / "ckpt.pt")
    ckpt = torch.load(tmp_path / "ckpt.pt")  # weights_only=True: GroupState is a safe global
    g2 = torch.Generator()
    g2.set_state(ckpt["generator"])
    rest = filt(frames[2:], init=ckpt["state"], generator=g2)
    assert torch.equal(torch.cat([first.mean, rest.mean]), a.mean) and torch.equal(rest.state.x, a.state.x)


def test_without_marginalisation_carries_point_masses():
    filt, frames, init = tiny_filter(marginalise=False)
    res = filt(frames, init=init, generator=torch.Generator().manual_seed(2))
    assert bool((res.state.w_cov == 0).all()) and bool(torch.isfinite(res.state.w_mean).all())


@pytest.mark.compile
def test_compiled_moves_equal_eager_bit_for_bit():
    eager, frames, init = tiny_filter()
    compiled, _, _ = tiny_filter(compile_step=True)
    torch._dynamo.reset()
    a = eager(frames[:2], init=init, generator=torch.Generator().manual_seed(9))
    b = compiled(frames[:2], init=init, generator=torch.Generator().manual_seed(9))
    assert torch.equal(a.state.x, b.state.x) and torch.equal(a.exists_prob, b.exists_prob)


def test_bad_input_names_the_argument():
    filt, frames, init = tiny_filter()
    g = torch.Generator().manual_seed(0)
    with pytest.raises(ValueError, match="measurements"):
        filt(frames[:, :, :5], init=init, generator=g)
    with pytest.raises(ValueError, match="binary"):
        filt(frames.double() * 2, init=init, generator=g)
    with pytest.raises(ValueError, match="init must be a GroupState"):
        filt(frames, init=init.x, generator=g)
    with pytest.raises(ValueError, match="z has shape"):
        filt.step(init, frames[0, :1], generator=g)
    with pytest.raises(ValueError, match="num_particles .* multiple of num_chains"):
        GroupMCMCFilter(filt.motion, filt.sensor, 10, existence=filt.existence, structure_prior=filt.structure_prior,
                        num_chains=4)
    with pytest.raises(ValueError, match="xi must be a probability"):
        GroupMCMCFilter(filt.motion, filt.sensor, 8, existence=filt.existence, structure_prior=filt.structure_prior,
                        xi=1.5)
    with pytest.raises(ValueError, match="existence must be a GroupExistence"):
        GroupMCMCFilter(filt.motion, filt.sensor, 8, existence=None, structure_prior=filt.structure_prior)
