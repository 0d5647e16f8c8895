import math

import pytest
import torch

from torchmcmcpf.models.motion import ConstantVelocity
from torchmcmcpf.models.sensors.radar import RangeDopplerBearingTBD
from torchmcmcpf.scenarios import Scenario, ground_radar
from torchmcmcpf.scenarios.ground_radar import MARGIN_CELLS

T, B, K = 20, 8, 10


@pytest.fixture(scope="module")
def scen():
    # Table I defaults with T = 20 steps: 80 target draws, 160 frames.
    return ground_radar(K, T, B, generator=torch.Generator().manual_seed(7), dtype=torch.float64)


@pytest.fixture(scope="module")
def amplitude(scen):
    """Noise-free cell amplitudes A of every frame, (T, B, Nr, Nd, Nb)."""
    return scen.sensor.signal_grid(scen.truth.flatten(0, 1)).reshape(scen.measurements.shape)


def test_shapes_and_models(scen):
    assert isinstance(scen, Scenario)
    G = scen.sensor.frame_shape
    assert G == (87, 22, 32)  # the grid documented in the module docstring
    assert scen.truth.shape == (T, B, K, 5) and scen.measurements.shape == (T, B) + G
    assert scen.initial.shape == (B, K, 5) and scen.snr_db.shape == (B, K)
    assert (scen.num_steps, scen.batch_size, scen.num_targets) == (T, B, K)
    assert isinstance(scen.sensor, RangeDopplerBearingTBD) and isinstance(scen.motion, ConstantVelocity)
    assert scen.motion.q == 1.0 and scen.motion.dim == 5  # 1 m/s^2 acceleration std, amplitude kept
    assert scen.truth.dtype == scen.measurements.dtype == torch.float64
    assert tuple(scen.sensor.cell_sizes) == pytest.approx((10.0, 2.0, math.pi / 180))  # Table I


def test_initial_conditions_follow_table_1(scen):
    x0 = scen.initial
    r = torch.hypot(x0[..., 0], x0[..., 2])
    b = torch.rad2deg(torch.atan2(x0[..., 2], x0[..., 0]))
    v = torch.hypot(x0[..., 1], x0[..., 3])
    assert r.min() >= 2700 and r.max() <= 2900
    assert b.min() >= -6 and b.max() <= 6
    assert v.min() >= 0 and v.max() <= 15
    assert scen.snr_db.min() >= 9 and scen.snr_db.max() <= 20
    # Uniform laws: each sample mean is within 5 standard errors (width / sqrt(12 n)).
    n = B * K
    for values, lo, hi in ((r, 2700, 2900), (b, -6, 6), (v, 0, 15), (scen.snr_db, 9, 20)):
        assert abs(values.mean().item() - (lo + hi) / 2) <= 5 * (hi - lo) / math.sqrt(12 * n)
    # uniform heading: E[cos] = E[sin] = 0 with standard error 1 / sqrt(2 n)
    heading = torch.atan2(x0[..., 3], x0[..., 1])
    assert abs(torch.cos(heading).mean()) <= 5 / math.sqrt(2 * n)
    assert abs(torch.sin(heading).mean()) <= 5 / math.sqrt(2 * n)
    # amplitude <-> SNR (SNR = rho^2 / (2 sigma^2)), constant along the track
    snr = scen.sensor.snr_db_from_amplitude(scen.truth[..., 4])
    assert torch.allclose(snr, scen.snr_db.expand(T, B, K))


def test_truth_is_constant_velocity_from_the_step_before_frame_0(scen):
    F = scen.motion.F.double()
    for t in (0, 1, T - 1):
        expected = scen.initial @ torch.linalg.matrix_power(F, t + 1).T
        assert torch.allclose(scen.truth[t], expected)


def test_every_track_inside_the_grid_with_margin(scen):
    coords = scen.sensor.measurement_coords(scen.truth)  # (T, B, K, 3): range, doppler, bearing
    for a in range(3):
        bins, cell = scen.sensor.bins(a), scen.sensor.cell_sizes[a]
        assert coords[..., a].min() >= bins[0] + MARGIN_CELLS * cell - 1e-9
        assert coords[..., a].max() <= bins[-1] - MARGIN_CELLS * cell + 1e-9


def test_noise_power_away_from_targets(scen, amplitude):
    # Cells whose noise-free amplitude A < 1e-3 hold noise only (bias A^2 < 1e-6): their
    # power is exponential with mean 2 sigma^2 = 2 and standard deviation 2, so the mean of
    # n independent cells has standard error 2 / sqrt(n); allow 5 of them.
    noise = scen.measurements[amplitude < 1e-3]
    n = noise.numel()
    assert n > 0.9 * scen.measurements.numel()
    assert abs(noise.mean().item() - 2.0) <= 5 * 2.0 / math.sqrt(n)


def test_frames_contain_the_true_targets(scen, amplitude):
    # E[z | A] = A^2 + 2 sigma^2 and Var[z | A] = 4 sigma^2 A^2 + 4 sigma^4 per cell (Rician
    # power, sigma = 1). The least-squares slope of the excess power z - 2 on A^2,
    # beta = sum A^2 (z - 2) / sum A^4, is 1 with standard error
    # sqrt(sum A^4 (4 A^2 + 4)) / sum A^4; allow 5. Frames built from the truth one step
    # off (targets moved up to 15 m, 1.5 range widths) would give a much lower slope.
    z = scen.measurements
    A2 = amplitude**2
    beta = (A2 * (z - 2)).sum() / (A2**2).sum()
    se = torch.sqrt((A2**2 * (4 * A2 + 4)).sum()) / (A2**2).sum()
    assert abs(beta.item() - 1.0) <= 5 * se.item()
    A2_off = amplitude[:-1] ** 2
    beta_off = (A2_off * (z[1:] - 2)).sum() / (A2_off**2).sum()
    assert beta_off < beta - 10 * se


def test_initial_particles_cloud(scen, gen):
    # N draws per component: mean within 5 sigma / sqrt(N); standard deviation within
    # 5 sigma / sqrt(2 N) (normal sample std).
    N = 4000
    p = scen.initial_particles(N, generator=gen)
    assert p.shape == (B, N, K, 5) and p.dtype == torch.float64
    std = torch.tensor([5.0, 1.0, 5.0, 1.0, 0.0], dtype=torch.float64).expand(B, K, 5).clone()
    std[..., 4] = 0.1 * scen.initial[..., 4]
    assert torch.all((p.mean(1) - scen.initial).abs() <= 5 * std / math.sqrt(N))
    assert torch.all((p.std(1) - std).abs() <= 5 * std / math.sqrt(2 * N))
    exact = scen.initial_particles(3, generator=gen, spread=(0.0, 0.0, 0.0))
    assert torch.equal(exact, scen.initial[:, None].expand(B, 3, K, 5))


def test_same_seed_same_scenario():
    a = ground_radar(3, 4, 2, generator=torch.Generator().manual_seed(3))
    b = ground_radar(3, 4, 2, generator=torch.Generator().manual_seed(3))
    c = ground_radar(3, 4, 2, generator=torch.Generator().manual_seed(4))
    assert torch.equal(a.truth, b.truth) and torch.equal(a.measurements, b.measurements)
    assert not torch.equal(a.truth, c.truth)
    pa = a.initial_particles(10, generator=torch.Generator().manual_seed(0))
    pb = b.initial_particles(10, generator=torch.Generator().manual_seed(0))
    assert torch.equal(pa, pb)


def test_single_target_and_fixed_snr():
    s = ground_radar(1, 3, 2, generator=torch.Generator().manual_seed(0), snr_db=12.0)
    assert s.truth.shape == (3, 2, 1, 5)
    assert torch.allclose(s.snr_db, torch.full((2, 1), 12.0))


def test_bad_arguments():
    g = torch.Generator().manual_seed(0)
    with pytest.raises(ValueError, match="num_targets"):
        ground_radar(0, 3, generator=g)
    with pytest.raises(ValueError, match="num_steps"):
        ground_radar(2, 200, generator=g)  # 15 m/s * 200 s > 2700 m
    with pytest.raises(ValueError, match="generator"):
        ground_radar(2, 3, generator=None)
    with pytest.raises(ValueError, match="generator"):
        ground_radar(2, 3, generator=g, device="meta")
    with pytest.raises(ValueError, match="snr_db"):
        ground_radar(2, 3, generator=g, snr_db=(20.0, 9.0))
    s = ground_radar(1, 2, generator=g)
    with pytest.raises(ValueError, match="num_particles"):
        s.initial_particles(0, generator=g)
    with pytest.raises(ValueError, match="spread"):
        s.initial_particles(5, generator=g, spread=(1.0, -1.0, 0.1))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_scenario_matches_shapes():
    s = ground_radar(3, 4, 2, generator=torch.Generator("cuda").manual_seed(0), device="cuda")
    assert s.truth.is_cuda and s.measurements.is_cuda
    assert s.initial_particles(8, generator=torch.Generator("cuda").manual_seed(1)).is_cuda
