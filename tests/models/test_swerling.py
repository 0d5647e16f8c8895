"""AzimuthRangeSwerlingTBD: Swerling-I power per azimuth-range cell (Ling 2016, paper 002 eqs. 3-9)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from torchmcmcpf.models.sensors.swerling import POWER, AzimuthRangeSwerlingTBD

DEG = math.pi / 180


def small_sensor(**kw):
    """14 x 12 cells (1 deg x 10 m) around azimuth 0, range 600 m."""
    return AzimuthRangeSwerlingTBD.uniform((-7 * DEG, 6 * DEG), (540, 650), **kw)


def states(r, a_deg, v, power, dtype=torch.float64):
    """``[x, vx, y, vy, P]`` at range ``r``, azimuth ``a_deg``, velocity ``(v, v)``."""
    r, a, v, p = (torch.as_tensor(t, dtype=dtype) for t in (r, a_deg, v, power))
    a = a * DEG
    return torch.stack([r * torch.cos(a), v, r * torch.sin(a), v, p], -1)


def near(xt, n, g, pos=4.0, vel=1.0):
    """``(B, K, 5) -> (B, n, K, 5)``: positions and velocities jittered, power kept."""
    sd = torch.tensor([pos, vel, pos, vel, 0.0], dtype=xt.dtype)
    return xt[:, None] + sd * torch.randn(xt.shape[0], n, *xt.shape[1:], generator=g, dtype=xt.dtype)


# ----------------------------------------------------------------------------- the cell model
def test_cell_log_ratio_matches_exponential_densities():
    """Eqs. 7-8: z ~ Exp(mean sigma^2 + A) against Exp(mean sigma^2)."""
    s2 = 1.7
    sens = small_sensor(noise_power=s2)
    A = torch.tensor([0.0, 0.01, 0.5, 2.0, 10.0, 300.0], dtype=torch.float64)[:, None]
    z = torch.tensor([0.0, 1e-3, 0.7, 3.0, 25.0, 400.0], dtype=torch.float64)[None, :]
    got = sens.cell_log_ratio(A, sens.prepare_frame(z))
    ref = stats.expon.logpdf(z.numpy(), scale=s2 + A.numpy()) - stats.expon.logpdf(z.numpy(), scale=s2)
    np.testing.assert_allclose(got.numpy(), ref, rtol=1e-12, atol=1e-12)
    assert torch.equal(got[0], torch.zeros(6, dtype=torch.float64))  # A = 0 -> exactly 0


def test_cell_log_ratio_outside_support_is_minus_inf_with_finite_gradient():
    sens = small_sensor(noise_power=2.0)
    A = torch.tensor([-2.0, -3.0, -1.0, 1.0], dtype=torch.float64, requires_grad=True)
    out = sens.cell_log_ratio(A, torch.full((4,), 0.5, dtype=torch.float64))
    assert torch.isneginf(out[:2]).all() and torch.isfinite(out[2:]).all()
    (grad,) = torch.autograd.grad(out[2:].sum(), A)
    assert torch.isfinite(grad).all() and (grad[:2] == 0).all()


def test_snr_convention():
    sens = small_sensor(noise_power=2.0)
    # SNR = P / sigma^2: 0 dB is P = sigma^2, 10 dB is 10 sigma^2
    assert sens.power_from_snr(0.0) == pytest.approx(2.0)
    assert sens.power_from_snr(10.0) == pytest.approx(20.0)
    snr = torch.tensor([-3.0, 4.5, 14.0], dtype=torch.float64)
    torch.testing.assert_close(sens.snr_db_from_power(sens.power_from_snr(snr)), snr)
    assert sens.snr_db_from_power(sens.power_from_snr(7.0)) == pytest.approx(7.0)


def test_point_spread_is_eq5_with_d_equal_sqrt2_width():
    """h = exp(-(r_c - r)^2 / d_r^2 - (a_c - a)^2 / d_a^2), d = sqrt(2) w, times P."""
    sens = small_sensor(range_width=8.0, azimuth_width=1.5 * DEG)
    xt = states([[603.0]], [[0.7]], [[1.0]], [[3.0]])
    A = sens.signal_grid(xt)[0]  # (Na, Nr)
    a_c, r_c = sens.azimuth_bins[:, None], sens.range_bins[None, :]
    d_r, d_a = math.sqrt(2) * 8.0, math.sqrt(2) * 1.5 * DEG
    ref = 3.0 * torch.exp(-((r_c - 603.0) ** 2) / d_r**2 - (a_c - 0.7 * DEG) ** 2 / d_a**2)
    torch.testing.assert_close(A, ref, rtol=1e-12, atol=1e-14)


# ----------------------------------------------------------------------------- shapes
@pytest.mark.parametrize("method", ["window", "grid"])
@pytest.mark.parametrize("sample_dims", [(), (4,), (3, 2)])
def test_shapes_with_0_1_2_sample_dims(method, sample_dims):
    sens = small_sensor(method=method)
    g = torch.Generator().manual_seed(1)
    xt = states([[580, 610]] * 2, [[-2, 3]] * 2, [[1, -1]] * 2, [[5, 8]] * 2)
    z = sens.simulate(xt, generator=g)
    assert z.shape == (2,) + sens.frame_shape == (2, 14, 12)
    x = xt.reshape(2, *(1,) * len(sample_dims), 2, 5).expand(2, *sample_dims, 2, 5)
    out = sens.log_likelihood(x, z)
    assert out.shape == (2, *sample_dims) and out.dtype == torch.float64
    ref = sens.log_likelihood(xt, z)
    torch.testing.assert_close(out, ref.reshape(2, *(1,) * len(sample_dims)).expand_as(out), rtol=1e-12, atol=1e-12)
    x32 = x.float()
    assert sens.log_likelihood(x32, z.float()).dtype == torch.float32


def test_grid_path_is_sum_of_cell_log_ratios():
    """The whole-grid reference is eq. 9 in log form: sum over cells of log p(z|A) - log p(z|0)
    computed here from scipy's exponential densities and signal_grid."""
    sens = small_sensor(method="grid")
    g = torch.Generator().manual_seed(2)
    xt = states([[580, 600, 620]], [[-2, -1.5, 3]], [[1, 1, -1]], [[5, 6, 4]])
    z = sens.simulate(xt, generator=g)
    A = sens.signal_grid(xt)[0].numpy()
    ref = (stats.expon.logpdf(z[0].numpy(), scale=1.0 + A) - stats.expon.logpdf(z[0].numpy(), scale=1.0)).sum()
    assert sens.log_likelihood(xt, z).item() == pytest.approx(ref, rel=1e-12)


# ----------------------------------------------------------------------------- window vs grid
def test_window_matches_grid_on_ling_scenario():
    """Stated tolerance of the default window (4 cells, widths = cell sizes): over particles
    near the targets, max |d - mean(d)| <= 2e-3 * std(grid) per run, d = window - grid (the
    study in the AzimuthRangeSwerlingTBD docstring measured <= 6e-4). Targets 2 and 3 are
    20 m apart, so their boxes overlap (cells counted once)."""
    from torchmcmcpf.scenarios.ling import ling

    g = torch.Generator().manual_seed(3)
    scn = ling(torch.tensor([14.0, 8.0]), 2, generator=g, num_steps=5, dtype=torch.float64)
    sens = scn.sensor
    assert sens.window == 4
    x = near(scn.truth[-1], 150, g)
    z = scn.measurements[-1]
    win, grid = sens.log_likelihood_window(x, z), sens.log_likelihood_grid(x, z)
    d = win - grid
    assert ((d - d.mean(1, keepdim=True)).abs().amax(1) <= 2e-3 * grid.std(1)).all()


def test_window_covering_grid_equals_grid():
    sens = small_sensor(window=14)
    g = torch.Generator().manual_seed(4)
    xt = states([[580, 590, 620]], [[-2, -1.5, 3]], [[1, 1, -1]], [[5, 6, 4]])
    z = sens.simulate(xt, generator=g)
    x = near(xt, 20, g, pos=15.0)
    exists = torch.rand(1, 20, 3, generator=g) < 0.7
    torch.testing.assert_close(sens.log_likelihood_window(x, z, exists), sens.log_likelihood_grid(x, z, exists),
                               rtol=1e-12, atol=1e-10)


def test_log_likelihood_slot_changes_equal_window_differences():
    """Two axes (one merged box factor): slot_changes(ref, x, z)[..., k] equals
    window(ref with slot k = x_k) - window(ref) to round-off, with overlapping reference
    boxes (targets 20 m apart) and candidates near and far from their slot."""
    sens = small_sensor()
    g = torch.Generator().manual_seed(5)
    ref = states([[580, 600, 620]], [[-2, -1.5, 3]], [[1, 1, -1]], [[5, 6, 4]])
    z = sens.simulate(ref, generator=g)
    x = torch.cat([near(ref, 10, g), near(ref, 10, g, pos=30.0)], 1)  # (1, 20, 3, 5)
    out = sens.log_likelihood_slot_changes(ref, x, z)
    assert out.shape == (1, 20, 3)
    base = sens.log_likelihood_window(ref, z)[:, None]
    for k in range(3):
        moved = ref[:, None].expand_as(x).clone()
        moved[..., k, :] = x[..., k, :]
        torch.testing.assert_close(out[..., k], sens.log_likelihood_window(moved, z) - base, rtol=1e-10, atol=1e-9)
    assert out.abs().min() > 1e-3


def test_cached_delta_equals_delta():
    """Two axes: the amplitude cache's one-slot change equals log_likelihood_delta (and the
    cache summed with the cell log-ratios the windowed likelihood), with a slot per chain."""
    sens = small_sensor()
    g = torch.Generator().manual_seed(6)
    xt = states([[580, 600, 620]], [[-2, -1.5, 3]], [[1, 1, -1]], [[5, 6, 4]])
    z = sens.simulate(xt, generator=g)
    y = near(xt, 20, g)
    cache = sens.amplitude_cache(y)
    whole = sens.cell_log_ratio(cache.reshape(1, 20, *sens.frame_shape), sens.prepare_frame(z)[:, None])
    torch.testing.assert_close(whole.flatten(2).sum(-1), sens.log_likelihood_window(y, z), rtol=1e-10, atol=1e-9)
    slot = torch.randint(3, (1, 20), generator=g)
    x_n = near(xt, 20, g, pos=15.0)[:, :, 1]
    delta, _, _ = sens.log_likelihood_delta_cached(cache, y, x_n, slot, z)
    torch.testing.assert_close(delta, sens.log_likelihood_delta(y, x_n, slot, z), rtol=1e-10, atol=1e-9)
    assert delta.abs().min() > 1e-3


# ----------------------------------------------------------------------------- gradients
@pytest.mark.parametrize("method", ["window", "grid"])
def test_gradcheck(method):
    sens = small_sensor(window=1, method=method, memory_budget=20_000)
    g = torch.Generator().manual_seed(5)
    xt = states([[583, 607]], [[-1.3, 2.2]], [[1, -1]], [[4, 6]])
    z = sens.simulate(xt, generator=g)
    # offsets of a fraction of a cell, away from the cell boundaries where boxes jump
    x = xt[:, None] + torch.tensor([[[1.0, 0.4, 2.0, -0.3, 0.2]], [[-2.0, 0.1, 1.0, 0.2, -0.3]]], dtype=torch.float64)
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v: sens.log_likelihood(v, z), (x,))


# ----------------------------------------------------------------------------- simulate
def test_simulate_noise_only_moments():
    """No target: cells are Exp(sigma^2): mean sigma^2 and variance sigma^4. Over n cells the
    sample mean has sd sigma^2 / sqrt(n) and the sample variance sd sqrt(mu4 - sigma^8) /
    sqrt(n) = sqrt(8) sigma^4 / sqrt(n) (mu4 = 9 sigma^8); allow 4 sd (false alarm 6e-5 each)."""
    s2 = 1.6
    sens = small_sensor(noise_power=s2)
    g = torch.Generator().manual_seed(6)
    xt = states([[600.0]] * 300, [[0.0]] * 300, [[1.0]] * 300, [[5.0]] * 300)
    z = sens.simulate(xt, generator=g, exists=torch.zeros(300, 1, dtype=torch.bool))
    n = z.numel()
    assert abs(z.mean().item() - s2) <= 4 * s2 / math.sqrt(n)
    assert abs(z.var().item() - s2**2) <= 4 * math.sqrt(8) * s2**2 / math.sqrt(n)


def test_simulate_target_cell_moments():
    """At a cell of noise-free power A the draw is Exp(sigma^2 + A): mean m = sigma^2 + A and
    variance m^2; the mean of 3000 runs has sd m / sqrt(3000), the variance
    sqrt(8) m^2 / sqrt(3000); 4 sd."""
    sens = small_sensor(noise_power=1.0)
    runs = 3000
    g = torch.Generator().manual_seed(7)
    xt = states([[603.0]] * runs, [[0.4]] * runs, [[1.0]] * runs, [[6.0]] * runs)
    z = sens.simulate(xt, generator=g)
    A = sens.signal_grid(xt[:1])[0]
    cell = np.unravel_index(int(A.argmax()), A.shape)
    m = 1.0 + float(A[cell])
    zc = z[(slice(None),) + cell]
    assert abs(zc.mean().item() - m) <= 4 * m / math.sqrt(runs)
    assert abs(zc.var().item() - m * m) <= 4 * math.sqrt(8) * m * m / math.sqrt(runs)


def test_simulate_same_seed_same_frame():
    sens = small_sensor()
    xt = states([[580, 610]], [[-2, 3]], [[1, -1]], [[5, 8]])
    a = sens.simulate(xt, generator=torch.Generator().manual_seed(8))
    b = sens.simulate(xt, generator=torch.Generator().manual_seed(8))
    c = sens.simulate(xt, generator=torch.Generator().manual_seed(9))
    assert torch.equal(a, b) and not torch.equal(a, c) and (a >= 0).all() and torch.isfinite(a).all()


# ----------------------------------------------------------------------------- bad input
def test_bad_input_raises_value_error():
    sens = small_sensor()
    g = torch.Generator().manual_seed(10)
    xt = states([[580, 610]], [[-2, 3]], [[1, -1]], [[5, 8]])
    neg = xt.clone()
    neg[0, 1, POWER] = -1.0
    with pytest.raises(ValueError, match=r"x\[\.\.\., 4\] \(target power P\) has negative value"):
        sens.simulate(neg, generator=g)
    nan = xt.clone()
    nan[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="x contains 1 NaN/inf"):
        sens.simulate(nan, generator=g)
    with pytest.raises(ValueError, match=r"x has shape \(1, 2, 4\), expected \(\*, \*, 5\)"):
        sens.simulate(xt[..., :4], generator=g)
    with pytest.raises(ValueError, match="generator must be a torch.Generator"):
        sens.simulate(xt, generator=None)
    z = sens.simulate(xt, generator=g)
    with pytest.raises(ValueError, match=r"z has shape \(2, 14, 12\), expected \(1, 14, 12\)"):
        sens.log_likelihood(xt, torch.cat([z, z]))
    with pytest.raises(ValueError, match=r"x has shape \(1, 2, 4\), expected \(B, \*S, K, 5\)"):
        sens.log_likelihood(xt[..., :4], z)
    with pytest.raises(ValueError, match="z contains 1 NaN/inf"):
        sens.validate(z.clone().index_put_((torch.tensor([0]),) * 3, torch.tensor(float("nan"), dtype=z.dtype)))
    with pytest.raises(ValueError, match=r"z has negative value\(s\)"):
        sens.validate(-z)
    with pytest.raises(ValueError, match="noise_power must be > 0"):
        small_sensor(noise_power=-1.0)
    with pytest.raises(ValueError, match="noise_power must be > 0"):
        small_sensor(noise_power=float("nan"))
    with pytest.raises(ValueError, match="range_width must be > 0"):
        small_sensor(range_width=0.0)
    with pytest.raises(ValueError, match="azimuth_limits must be finite"):
        AzimuthRangeSwerlingTBD.uniform((1.0, -1.0), (500, 600))
    with pytest.raises(ValueError, match="range_cell must be > 0"):
        AzimuthRangeSwerlingTBD.uniform((-0.1, 0.1), (500, 600), range_cell=-10.0)


def test_uniform_grid_and_buffers():
    sens = small_sensor()
    assert sens.frame_shape == (14, 12) and sens.widths == pytest.approx((DEG, 10.0))
    assert {"azimuth_bins", "range_bins"} <= set(sens.state_dict())
    torch.testing.assert_close(sens.range_bins, 540.0 + 10.0 * torch.arange(12, dtype=torch.float64))
