"""MCMCFilter against the exact Kalman filter, sample bookkeeping, determinism, settings."""

import math

import pytest
import torch
from _kalman import kalman_filter

import torchmcmcpf.filters.mcmc as mcmc_module
from torchmcmcpf import ConstantVelocity, LinearGaussian, ParticleState
from torchmcmcpf.filters.mcmc import MCMCFilter, MCMCSettings, mcmc_step

DT = torch.float64


def _problem(gen, B=16, K=2, T=3, N=200):
    """One measurement sequence (the same for all B runs) of K independent CV targets, the
    initial cloud drawn from N(m0, P0), and the Kalman filter of each target."""
    motion = ConstantVelocity(1.0, 1.0).to(DT)
    sensor = LinearGaussian.position(2.0).to(DT)
    m0 = torch.tensor([[0.0, 1.0, 0.0, 0.5], [20.0, -1.0, 5.0, 0.0]], dtype=DT)
    P0 = torch.diag(torch.tensor([1.0, 0.25, 1.0, 0.25], dtype=DT))
    x = m0 + torch.randn(K, 4, generator=gen, dtype=DT) @ P0.sqrt()
    zs = []
    for _ in range(T):
        x = motion.sample(x, generator=gen)
        zs.append(sensor.simulate(x.unsqueeze(0), generator=gen))
    zs = torch.cat(zs).unsqueeze(1).expand(T, B, K, 2).contiguous()
    init = m0 + torch.randn(B, N, K, 4, generator=gen, dtype=DT) @ P0.sqrt()
    means, covs = kalman_filter(motion.F, motion.Q, sensor.H, sensor.R, m0, P0, zs[:, 0])
    return motion, sensor, zs, init, means, covs


def _burn_in(motion, sensor, zs, means, covs, xi, tv=1e-2):
    """Burn-in from the Doeblin bound of the joint draw (see tests/kernels/test_moves.py):
    ``(1 - xi eps)^m <= tv`` with ``eps = min_k p(z_k | z_{1:k-1}) / max_x p(z_k | x)``. The
    evidence is that of the particle mixture; we use the Kalman predictive density halved
    (the N = 200 particle estimate is within a factor 2 of it with overwhelming probability)."""
    K = zs.shape[2]
    H, R = sensor.H, sensor.R
    zero = torch.zeros(2, dtype=DT)
    m = torch.tensor([[0.0, 1.0, 0.0, 0.5], [20.0, -1.0, 5.0, 0.0]], dtype=DT)
    P = torch.diag(torch.tensor([1.0, 0.25, 1.0, 0.25], dtype=DT))
    eps = 1.0
    for k in range(zs.shape[0]):
        mp, Pp = m @ motion.F.mT, motion.F @ P @ motion.F.mT + motion.Q
        S = H @ Pp @ H.mT + R
        log_eps = (torch.distributions.MultivariateNormal(zero, S).log_prob(zs[k, 0] - mp @ H.mT).sum()
                   - K * torch.distributions.MultivariateNormal(zero, R).log_prob(zero))
        eps = min(eps, 0.5 * float(log_eps.exp()))
        m, P = means[k], covs[k]
    return math.ceil(math.log(tv) / math.log1p(-xi * eps))


SETTINGS = {
    "mixture": dict(moves="mixture"),  # joint draw w.p. 0.75, else a refinement sweep
    "joint_random_walk": dict(moves=[("joint", 0.75), ("random_walk", 0.25)], rw_scale=0.5),
    # full per-target covariance adapted during the burn-in, frozen for the kept samples
    "joint_adaptive_random_walk": dict(moves=[("joint", 0.75), ("random_walk", 0.25)], rw_scale="adaptive"),
}


@pytest.mark.parametrize("name", list(SETTINGS))
def test_matches_the_kalman_filter(name, gen):
    """Posterior mean and variance of every target component at every step vs Kalman.

    All B = 16 runs filter the same measurements with independent randomness, so their
    errors e_b = (estimate_b - kalman) / kalman_sd are i.i.d. with mean equal to the
    filter's bias. A correct filter's bias is O(1/N) (a ratio-estimator effect of the
    particle approximation, about 0.005 sd at N = 200) plus the burn-in bias, at most 1e-2
    times a few sd by the choice of burn-in (:func:`_burn_in`): ~0.03 sd. We test |mean_b e_b| <= 5 se with se =
    std_b(e_b) / sqrt(B), estimated from the runs themselves, so the MCMC correlation and the
    error carried over from earlier steps (both of which inflate std_b(e_b)) are accounted
    for without a model of them. 24 comparisons: chance failure < 24 x 6e-7 (the t-statistic
    with 15 dof has heavier tails: < 24 x 1.3e-4 = 3e-3 for |t| > 5, a conservative bound).
    The same with the particle variance against the Kalman variance.
    Power: a filter that skipped the update would be off by the Kalman correction, which is
    checked to exceed 10 se.
    """
    motion, sensor, zs, init, km, kP = _problem(gen)
    burn_in = _burn_in(motion, sensor, zs, km, kP, xi=0.75)
    assert burn_in < 1000
    filt = MCMCFilter(motion, sensor, 200, num_chains=20, burn_in=burn_in, thinning=2, **SETTINGS[name]).to(DT)
    res = filt(zs, init=init, generator=gen)
    sd = torch.diagonal(kP, dim1=-2, dim2=-1).sqrt().unsqueeze(1)  # (T, 1, K, D)
    B = zs.shape[1]

    e = (res.mean - km.unsqueeze(1)) / sd  # (T, B, K, D)
    se = e.std(1) / math.sqrt(B)
    assert (e.mean(1).abs() <= 5 * se).all(), f"bias in se: {(e.mean(1).abs() / se).max():.2f}"

    var = res.state.x.var(1)  # final step (B, K, D)
    rel = var / torch.diagonal(kP[-1], dim1=-2, dim2=-1) - 1
    assert (rel.mean(0).abs() <= 5 * rel.std(0) / math.sqrt(B)).all()

    correction = (km[1:] - km[:-1] @ motion.F.mT) / sd[1:, 0]  # what the update step adds
    assert (correction.abs() / se[1:]).max() > 10

    acc = res.info.extras
    assert set(acc) == {f"acceptance_{n}" for n, _ in filt.settings.moves}
    assert res.info.acceptance.shape == (zs.shape[0], B)
    for rate in acc.values():
        assert rate.shape == (zs.shape[0], B) and ((rate > 0) & (rate < 1)).all()


def test_kept_samples_honour_burn_in_and_thinning(monkeypatch, gen):
    """Instrumented run: a fake iteration writes its iteration number m into the chain, so
    the output shows which iterations were kept (chain-major order)."""
    motion, sensor, zs, init, _, _ = _problem(gen, B=2, N=12)
    calls = []

    def fake_iteration(chain, noise, **kwargs):
        calls.append(kwargs["move"])
        acc = torch.zeros(chain.x.shape[:2], dtype=DT)
        return chain._replace(x=torch.full_like(chain.x, float(len(calls)))), acc

    monkeypatch.setattr(mcmc_module, "mcmc_iteration", fake_iteration)
    state = ParticleState(init[:, :12], torch.full((2, 12), -math.log(12), dtype=DT))
    burn_in, thinning, C = 7, 3, 4
    out, info = mcmc_step(state, zs[0], motion=motion, sensor=sensor, generator=gen,
                          settings=MCMCSettings(num_chains=C, burn_in=burn_in, thinning=thinning))
    S = 12 // C
    assert len(calls) == burn_in + thinning * S
    assert out.x.shape == (2, 12, 2, 4)
    expected = torch.tensor([burn_in + thinning * (s + 1) for s in range(S)], dtype=DT)
    kept = out.x[..., 0, 0].reshape(2, C, S)
    assert torch.equal(kept, expected.expand(2, C, S))
    torch.testing.assert_close(out.log_w, torch.full((2, 12), -math.log(12), dtype=DT))


def test_same_seed_same_result(gen):
    motion, sensor, zs, init, _, _ = _problem(gen, B=2, T=2, N=40)
    filt = MCMCFilter(motion, sensor, 40, num_chains=4, burn_in=5, thinning=2).to(DT)
    a = filt(zs, init=init, generator=torch.Generator().manual_seed(3))
    b = filt(zs, init=init, generator=torch.Generator().manual_seed(3))
    assert torch.equal(a.state.x, b.state.x) and torch.equal(a.mean, b.mean)
    assert torch.equal(a.info.acceptance, b.info.acceptance)
    for name in a.info.extras:
        assert torch.equal(a.info.extras[name], b.info.extras[name])
    c = filt(zs, init=init, generator=torch.Generator().manual_seed(4))
    assert not torch.equal(a.state.x, c.state.x)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(thinning=0), "thinning"),
        (dict(thinning=1.5), "thinning"),
        (dict(burn_in=-1), "burn_in"),
        (dict(num_chains=3), "num_particles"),
        (dict(num_chains=0), "num_chains"),
        (dict(moves="hmc"), "moves"),
        (dict(moves=[("joint", 0.5), ("refine", 0.4)]), "moves"),
        (dict(moves=[("joint", 0.5), ("jump", 0.5)]), "moves"),
        (dict(moves=[("refine", 1.0)]), "refine"),
        (dict(moves="random_walk"), "rw_scale"),
        (dict(moves="random_walk", rw_scale=-1.0), "rw_scale"),
        (dict(moves="random_walk", rw_scale=torch.ones(3)), "rw_scale"),
        (dict(moves="random_walk", rw_scale="adapt"), "rw_scale"),
        (dict(exclusion=1.0), "exclusion must be an Exclusion or None, got float"),
        (dict(recapture=0.1), "recapture must be a Recapture or None, got float"),
    ],
)
def test_bad_settings_raise(kwargs, name):
    motion, sensor = ConstantVelocity(1.0, 1.0), LinearGaussian.position(1.0)
    with pytest.raises(ValueError, match=name):
        MCMCFilter(motion, sensor, 10, **{"num_chains": 2, **kwargs})


def test_step_rejects_existence_flags(gen):
    motion, sensor, zs, init, _, _ = _problem(gen, B=2, N=8)
    log_w = torch.full((2, 8), -math.log(8), dtype=DT)
    state = ParticleState(init[:, :8], log_w, torch.ones(2, 8, 2, dtype=torch.bool))
    with pytest.raises(ValueError, match="exists"):
        mcmc_step(state, zs[0], motion=motion, sensor=sensor, generator=gen)


def test_pick_moves_frequencies_and_seed():
    """One pick per iteration: the moves' frequencies match their probabilities within 4
    binomial standard errors, the same seed gives the same picks, a single move needs no draw."""
    from torchmcmcpf.filters.mcmc import pick_moves

    moves = (("joint", 0.75), ("refine", 0.25))
    n = 20000
    picks = pick_moves(moves, n, generator=torch.Generator().manual_seed(5))
    share = sum(p == "joint" for p in picks) / n
    assert abs(share - 0.75) <= 4 * math.sqrt(0.75 * 0.25 / n)
    assert picks == pick_moves(moves, n, generator=torch.Generator().manual_seed(5))
    g = torch.Generator().manual_seed(0)
    state = g.get_state()
    assert pick_moves((("joint", 1.0),), 3, generator=g) == ["joint"] * 3
    assert torch.equal(g.get_state(), state)


def test_mcmc_iteration_refuses_a_move_with_another_moves_noise(gen):
    """The picked move and its noise must agree: a ValueError names both."""
    from torchmcmcpf.filters.mcmc import draw_iteration_noise, mcmc_iteration
    from torchmcmcpf.kernels.chains import JointNoise, previous_cloud
    from torchmcmcpf.kernels.moves import init_chains
    from torchmcmcpf.models.existence import TargetDynamics

    motion, sensor, zs, init, _, _ = _problem(gen, B=2, N=8)
    cloud = previous_cloud(init[:, :8], torch.full((2, 8), -math.log(8), dtype=DT), None, motion=motion)
    template = init.new_empty((2, 4) + init.shape[2:])
    dynamics = TargetDynamics(motion)
    chain = init_chains(cloud, JointNoise.draw(template, dynamics, generator=gen), zs[0], dynamics=dynamics,
                        sensor=sensor)
    noise = draw_iteration_noise("joint", chain.x, dynamics, generator=gen)
    with pytest.raises(ValueError, match="move='refine' with JointNoise"):
        mcmc_iteration(chain, noise, move="refine", cloud=cloud, z=zs[0], dynamics=dynamics, sensor=sensor)
    with pytest.raises(ValueError, match="move must be one of"):
        draw_iteration_noise("hop", chain.x, dynamics, generator=gen)


def test_relocations_are_drawn_in_blocks_and_a_step_uses_them(gen, monkeypatch):
    """The MCMC-PF draws its step's relocation noise in blocks of iterations (the frame's
    peaks found once per block): one per iteration, each for the chains' slots (B, C, K),
    inside the data density's support; None without re-capture. A step with a block of one
    iteration equals, in law, one with a single block: both keep the tracks (same seed,
    different draws)."""
    from torchmcmcpf.models.existence import TargetDynamics
    from torchmcmcpf.models.multitarget import Recapture
    from torchmcmcpf.scenarios import ground_radar

    scn = ground_radar(3, 2, 2, generator=gen, snr_db=18.0)
    z = scn.measurements[0]
    dyn = TargetDynamics(scn.motion, None, Recapture(), scn.sensor)
    monkeypatch.setattr(mcmc_module, "RELOCATION_BLOCK", 2 * 4 * 3 * 2)  # two iterations a block
    drawn = list(mcmc_module.relocations(dyn, (2, 4, 3), 5, z, generator=gen, dtype=torch.float32,
                                         device=torch.device("cpu")))
    assert len(drawn) == 5
    for noise in drawn:
        assert noise.u.shape == noise.log_ratio.shape == (2, 4, 3) and noise.coords.shape == (2, 4, 3, 3)
        assert bool(torch.isfinite(noise.log_ratio).all())
    assert not torch.equal(drawn[0].coords, drawn[1].coords)  # each iteration its own draw
    plain = TargetDynamics(scn.motion, None, None, scn.sensor)
    assert list(mcmc_module.relocations(plain, (2, 4, 3), 3, z, generator=gen, dtype=torch.float32,
                                        device=torch.device("cpu"))) == [None] * 3
    errors = []
    for block in (2 * 10 * 3, 2**17):  # one iteration a block, every iteration in one
        monkeypatch.setattr(mcmc_module, "RELOCATION_BLOCK", block)
        filt = MCMCFilter(scn.motion, scn.sensor, 200, num_chains=10, burn_in=10)
        res = filt(scn.measurements, init=scn.initial_particles(200, generator=gen),
                   generator=torch.Generator().manual_seed(1))
        errors.append(float((res.mean[..., [0, 2]] - scn.truth[..., [0, 2]]).norm(dim=-1).max()))
    assert max(errors) < 15.0, errors  # metres: both keep every target (a cell is 10 m)


def _without_cache(sensor_class):
    """The same sensor class without the chains' cache (each slot update scored in full)."""
    class Uncached(sensor_class):
        def amplitude_cache(self, x, exists=None, z=None):
            return None
    return Uncached


@pytest.mark.parametrize("scene", ["points", "radar"])
def test_refinement_sweep_cache_is_a_speed_choice(scene, monkeypatch):
    """The refinement sweep reads each slot's ratio from a cache made once per sweep (point
    intensities; radar amplitudes) and advances it for the accepted updates: in float64 the
    MCMC-PF takes the same decisions with and without it (the ratios agree to ~1e-12), so
    its particles are the same; the paper-004 mixture with births and deaths (points) and 3
    crossing radar targets with the default exclusion and re-capture."""
    if scene == "points":
        from torchmcmcpf.models.sensors.points import PoissonClutterPoints
        from torchmcmcpf.scenarios.septier import septier

        scn = septier(2, 4, generator=torch.Generator().manual_seed(3))
        s = scn.sensor
        sensors = (s.to(DT), _without_cache(PoissonClutterPoints)(s.clutter_rate, s.detection_rate, s.area.tolist(),
                                                                  R=s.R).to(DT))
        motion, existence = scn.motion.to(DT), scn.existence.to(DT)
        z = type(scn.measurements)(scn.measurements.z.to(DT), scn.measurements.mask)
        x0 = torch.zeros(2, 40, scn.alive.shape[-1], 4, dtype=DT)
    else:
        from torchmcmcpf.models.sensors.radar import RangeDopplerBearingTBD

        deg = math.pi / 180
        limits = ((2740, 2850), (-8, 8), (-5 * deg, 4 * deg))
        sensors = (RangeDopplerBearingTBD.uniform(*limits).to(DT),
                   _without_cache(RangeDopplerBearingTBD).uniform(*limits).to(DT))
        motion, existence = ConstantVelocity(1.0, 1.0, amplitude_q=0.01).to(DT), None
        g = torch.Generator().manual_seed(5)
        r = torch.tensor([[2790.0, 2800.0, 2830.0], [2770.0, 2775.0, 2820.0]], dtype=DT)
        bearing = torch.tensor([[0.2, 0.6, -2.0], [1.0, 1.5, -3.0]], dtype=DT) * deg
        xt = torch.stack([r * torch.cos(bearing), torch.full_like(r, 2.0), r * torch.sin(bearing),
                          torch.full_like(r, -1.0), torch.full_like(r, 5.0)], -1)  # (B, K = 3, 5)
        frames = []
        for _ in range(3):
            xt = motion.propagate(xt, torch.zeros(xt.shape[:-1] + (motion.noise_dim,), dtype=DT))
            frames.append(sensors[0].simulate(xt, generator=g))
        z = torch.stack(frames)
        x0 = xt[:, None] + torch.tensor([4.0, 1.0, 4.0, 1.0, 0.3], dtype=DT) * torch.randn(2, 40, 3, 5, generator=g,
                                                                                             dtype=DT)
    assert sensors[0].amplitude_cache(x0[:, :2], None, z[0] if torch.is_tensor(z) else type(z)(z.z[0], z.mask[0])) \
        is not None
    assert sensors[1].amplitude_cache(x0[:, :2]) is None
    monkeypatch.setattr(type(sensors[0]), "sweep_cache", True)  # the radar's too (off by default: a speed choice)
    results = [MCMCFilter(motion, s, 40, num_chains=8, burn_in=6, moves="mixture", existence=existence)(
        z, init=x0, generator=torch.Generator().manual_seed(6)) for s in sensors]
    # NaN where a step picked no refinement, in both
    torch.testing.assert_close(results[0].info.extras["acceptance_refine"], results[1].info.extras["acceptance_refine"],
                               rtol=0, atol=0, equal_nan=True)
    assert float(results[0].info.extras["acceptance_refine"].nan_to_num().max()) > 0  # refinements accepted
    assert torch.equal(results[0].state.x, results[1].state.x)
