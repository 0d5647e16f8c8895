import math

import pytest
import torch
from torch.utils._pytree import tree_map

from torchmcmcpf import ConstantVelocity, LinearGaussian, SIRFilter


def _problem(gen, B=3, K=2, T=6, N=200, dtype=torch.float64):
    motion = ConstantVelocity(1.0, 0.5).to(dtype)
    sensor = LinearGaussian.position(2.0).to(dtype)
    x = torch.randn(B, K, 4, generator=gen, dtype=dtype) * 20
    xs, zs = [], []
    for _ in range(T):
        x = motion.sample(x, generator=gen)
        xs.append(x)
        zs.append(sensor.simulate(x, generator=gen))
    init = torch.stack(xs)[0].unsqueeze(1) + torch.randn(B, N, K, 4, generator=gen, dtype=dtype)
    return motion, sensor, torch.stack(xs), torch.stack(zs), init


def test_forward_shapes_and_info(gen):
    motion, sensor, xs, zs, init = _problem(gen)
    res = SIRFilter(motion, sensor, 200)(zs, init=init, generator=gen)
    T, B, K, D = xs.shape
    assert res.mean.shape == (T, B, K, D) and res.mean.dtype == torch.float64
    assert res.state.x.shape == (B, 200, K, D)
    assert res.info.ess.shape == (T, B) and res.info.log_evidence.shape == (T, B)
    assert res.log_evidence.shape == (B,) and torch.isfinite(res.log_evidence).all()
    assert torch.allclose(torch.logsumexp(res.state.log_w, -1), torch.zeros(B, dtype=torch.float64))


def test_same_seed_same_result(gen):
    motion, sensor, xs, zs, init = _problem(gen)
    filt = SIRFilter(motion, sensor, 200)
    a = filt(zs, init=init, generator=torch.Generator().manual_seed(5))
    b = filt(zs, init=init, generator=torch.Generator().manual_seed(5))
    assert torch.equal(a.mean, b.mean) and torch.equal(a.state.x, b.state.x)
    c = filt(zs, init=init, generator=torch.Generator().manual_seed(6))
    assert not torch.equal(a.mean, c.mean)


def test_step_equals_forward(gen):
    motion, sensor, xs, zs, init = _problem(gen, T=3)
    filt = SIRFilter(motion, sensor, 200)
    res = filt(zs, init=init, generator=torch.Generator().manual_seed(1))
    g = torch.Generator().manual_seed(1)
    state = filt.init(init)
    for t in range(3):
        state, _ = filt.step(state, zs[t], generator=g)
    assert torch.equal(state.x, res.state.x)


def test_no_nan_when_every_weight_underflows(gen):
    # Measurements 1e5 m away from every particle: all likelihoods underflow in linear
    # space (log-lik ~ -1e9). The filter must stay finite and keep uniform-ish weights.
    motion, sensor, xs, zs, init = _problem(gen, T=2, dtype=torch.float32)
    far = zs + 1e5
    res = SIRFilter(motion, sensor, 200)(far, init=init.float(), generator=gen)
    assert torch.isfinite(res.mean).all() and torch.isfinite(res.state.log_w).all()
    assert torch.isfinite(res.info.ess).all() and (res.info.ess >= 1).all()


def test_no_resampling_keeps_weights_accumulating(gen):
    motion, sensor, xs, zs, init = _problem(gen, T=2)
    filt = SIRFilter(motion, sensor, 200, ess_threshold=0.0)
    state = filt.init(init)
    s1, _ = filt.step(state, zs[0], generator=gen)
    s2, _ = filt.step(s1, zs[1], generator=gen)
    # Without resampling, x_k is the propagation of the same particle index: the weights
    # multiply, so the ESS can only have been reduced by two updates (not reset).
    assert not torch.allclose(s2.log_w, torch.full_like(s2.log_w, -math.log(200)))


def test_bad_input(gen):
    motion, sensor, xs, zs, init = _problem(gen)
    filt = SIRFilter(motion, sensor, 200)
    with pytest.raises(ValueError, match="num_particles"):
        SIRFilter(motion, sensor, 0)
    with pytest.raises(ValueError, match="resample_method"):
        SIRFilter(motion, sensor, 10, resample_method="nope")
    with pytest.raises(ValueError, match=r"\(3, 100, 2, 4\), expected \(B, N, K, D\) = \(\*, 200, \*, 4\)"):
        filt(zs, init=init[:, :100], generator=gen)
    with pytest.raises(ValueError, match="init contains"):
        filt(zs, init=init.clone().index_fill_(1, torch.tensor([0]), float("nan")), generator=gen)
    with pytest.raises(ValueError, match=r"measurements has shape \(6, 2, 2, 2\), expected \(T, B, \*grid\) with B"):
        filt(zs[:, :2], init=init, generator=gen)
    bad = zs.clone()
    bad[3, 0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match=r"measurements\[3\] contains 1 NaN/inf"):
        filt(bad, init=init, generator=gen)
    with pytest.raises(ValueError, match="generator"):
        filt(zs, init=init, generator=0)
    with pytest.raises(ValueError, match="motion must be a MotionModel"):
        SIRFilter("cv", sensor, 10)


@pytest.mark.slow
def test_posterior_matches_exact_kalman_filter():
    # Single target, linear-Gaussian model: the SIR posterior mean must converge to the
    # Kalman mean. B runs filter the SAME measurement sequence with independent particles,
    # so e_b = (SIR mean)_b - (Kalman mean) are iid draws of the SIR error.
    # (1) Consistency: the mean of e over runs is within 5 standard errors sd(e)/sqrt(B) of
    #     zero (the O(1/N) bias of SIR is far below the standard error ~ 1/sqrt(N B)).
    # (2) Rate: sd(e) shrinks as 1/sqrt(N): sd(N=500) / sd(N=2000) ~ 2. The log of one sd
    #     estimated from B runs has standard error ~ 1/sqrt(2B), so a log-ratio has
    #     ~ 1/sqrt(B) = 0.1; the geometric mean over the T*D entries is at least as precise.
    #     We allow 4 of those: ratio in [2 e^-0.4, 2 e^0.4].
    # (3) Posterior variance: the weighted particle variance, averaged over runs, matches the
    #     Kalman variance within 5% (its relative MC error is ~ sqrt(2 / (ESS B)) < 1%).
    gen = torch.Generator().manual_seed(11)
    dt = torch.float64
    motion = ConstantVelocity(1.0, 0.5).to(dt)
    sensor = LinearGaussian.position(3.0).to(dt)
    T, B = 10, 100
    m0 = torch.tensor([0.0, 1.0, 0.0, -0.5], dtype=dt)
    P0 = torch.diag(torch.tensor([25.0, 1.0, 25.0, 1.0], dtype=dt))
    x = m0 + torch.linalg.cholesky(P0) @ torch.randn(4, generator=gen, dtype=dt)
    zs = []
    for _ in range(T):
        x = motion.sample(x[None, None], generator=gen)[0, 0]
        zs.append(sensor.simulate(x[None, None], generator=gen)[0])
    z = torch.stack(zs)  # (T, 1, 2)
    from _kalman import kalman_filter

    km, kP = kalman_filter(motion.F, motion.Q, sensor.H, sensor.R, m0, P0, z[:, 0])
    P = torch.diagonal(kP, dim1=-2, dim2=-1)  # (T, D)
    sds = {}
    for N in (500, 2000):
        init = m0 + torch.randn(B, N, 1, 4, generator=gen, dtype=dt) @ torch.linalg.cholesky(P0).mT
        res = SIRFilter(motion, sensor, N)(z.unsqueeze(1).expand(T, B, 1, 2), init=init, generator=gen)
        err = res.mean[:, :, 0] - km.unsqueeze(1)  # (T, B, D)
        sds[N] = err.std(dim=1)
        assert torch.all(err.mean(dim=1).abs() <= 5 * sds[N] / B**0.5)
    ratio = torch.exp(torch.log(sds[500] / sds[2000]).mean())
    assert 2 * math.exp(-0.4) <= ratio <= 2 * math.exp(0.4), ratio
    w = torch.softmax(res.state.log_w, -1)
    var = torch.einsum("bn,bnd->bd", w, (res.state.x[:, :, 0] - res.mean[-1, :, 0, None]) ** 2)
    assert torch.allclose(var.mean(0), P[-1], rtol=0.05)


def _point_problem(sensor_kind, b, n, dtype):
    """A short sequence for the point sensors: LinearGaussian (one point per target, known
    association) or PoissonClutterPoints (clutter, missed and repeated detections, masks).
    """
    from torchmcmcpf.models import PoissonClutterPoints
    from torchmcmcpf.models.sensors.association import PointFrame

    g = torch.Generator().manual_seed(11)
    motion = ConstantVelocity(1.0, 0.1).to(dtype)
    x = torch.tensor([[10.0, 1.0, 20.0, 0.5], [60.0, -1.0, 50.0, 0.0]], dtype=dtype).expand(b, 2, 4)
    if sensor_kind == "linear":
        sensor = LinearGaussian.position(1.0).to(dtype)
    else:
        sensor = PoissonClutterPoints(5.0, 2.0, ((0, 100), (0, 100)), noise_std=1.0).to(dtype)
    frames = []
    for _ in range(4):
        x = motion.sample(x, generator=g)
        frames.append(sensor.simulate(x, generator=g))
    if sensor_kind == "linear":
        z = torch.stack(frames)
    else:  # pad every frame to the largest number of points
        m = max(f.z.shape[1] for f in frames)
        z = PointFrame(torch.stack([torch.nn.functional.pad(f.z, (0, 0, 0, m - f.z.shape[1])) for f in frames]),
                       torch.stack([torch.nn.functional.pad(f.mask, (0, m - f.mask.shape[1])) for f in frames]))
    init = x.unsqueeze(1) + torch.randn(b, n, 2, 4, generator=g, dtype=dtype)
    return motion, sensor, z, init


@pytest.mark.compile
@pytest.mark.parametrize("sensor_kind", ["linear", "clutter"])
@pytest.mark.parametrize("ess_threshold", [1.0, 0.5])
def test_compiled_point_sir_equals_eager_bit_for_bit(sensor_kind, ess_threshold):
    # float32 at sizes whose vector loops have tails (N = 1001), a few runs: the compiled
    # kernel (gather, motion, likelihood, resampling) gives eager's bits, through forward
    # and through step (issue 26)
    motion, sensor, z, init = _point_problem(sensor_kind, 3, 1001, torch.float32)
    results = []
    for compiled in (False, True):
        filt = SIRFilter(motion, sensor, 1001, ess_threshold=ess_threshold, compile_step=compiled)
        res = filt(z, init=init, generator=torch.Generator().manual_seed(5))
        state, info = filt.step(res.state, tree_map(lambda a: a[0], z), generator=torch.Generator().manual_seed(6))
        results.append((res, state, info))
    (a, sa, ia), (b, sb, ib) = results
    for u, v in ((a.mean, b.mean), (a.state.x, b.state.x), (a.state.log_w, b.state.log_w),
                 (a.info.ess, b.info.ess), (a.log_evidence, b.log_evidence), (sa.x, sb.x), (sa.log_w, sb.log_w),
                 (ia.log_evidence, ib.log_evidence)):
        assert torch.equal(u, v)
    assert bool(torch.isfinite(a.log_evidence).all())


@pytest.mark.compile
def test_compiled_filter_under_inference_mode_compiles_its_step_once():
    # the initial cloud made outside torch.inference_mode() (normal tensors), the steps run
    # inside it (they return inference tensors): Dynamo guards on that kind of its inputs, so
    # without the filter copying the first state in the step compiled again at the second
    # step (17 s cold on the Table II SIR step); the results are those of an initial cloud
    # made inside
    from torch._dynamo.utils import counters

    motion, sensor, z, init = _point_problem("linear", 2, 301, torch.float32)
    filt = SIRFilter(motion, sensor, 301, compile_step=True)
    before = counters["stats"]["unique_graphs"]
    with torch.inference_mode():
        res = filt(z, init=init, generator=torch.Generator().manual_seed(5))
        state, _ = filt.step(filt.init(init), tree_map(lambda a: a[0], z), generator=torch.Generator().manual_seed(6))
        state, _ = filt.step(state, tree_map(lambda a: a[1], z), generator=torch.Generator().manual_seed(7))
        inside = filt(z, init=init.clone(), generator=torch.Generator().manual_seed(5))
    assert counters["stats"]["unique_graphs"] - before == 1
    assert not init.is_inference() and res.state.x.is_inference()
    assert torch.equal(res.mean, inside.mean) and torch.equal(res.state.x, inside.state.x)
