import math

import pytest
import torch

from torchmcmcpf import ConstantVelocity, LinearGaussian, ParticleState, SIRFilter
from torchmcmcpf.filters.sir import sir_step


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
    with pytest.raises(ValueError, match=r"init has shape \(3, 100, 2, 4\), expected \(\*, 200, \*, 4\)"):
        filt(zs, init=init[:, :100], generator=gen)
    with pytest.raises(ValueError, match="init contains"):
        filt(zs, init=init.clone().index_fill_(1, torch.tensor([0]), float("nan")), generator=gen)
    with pytest.raises(ValueError, match=r"measurements\[0\] has batch size 2"):
        filt(zs[:, :2], init=init, generator=gen)
    bad = zs.clone()
    bad[3, 0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match=r"measurements\[3\] contains 1 NaN/inf"):
        filt(bad, init=init, generator=gen)
    with pytest.raises(ValueError, match="generator"):
        filt(zs, init=init, generator=0)
    with pytest.raises(ValueError, match="motion must be a MotionModel"):
        SIRFilter("cv", sensor, 10)
