"""Independent-partition SIR filter (Orton and Fitzgerald; Kreucher et al.): exact against
per-target Kalman filters when the likelihood factorises over targets, through both
weighting paths (a separable sensor's per-target terms, and the one-slot likelihood change
at the reference that grid sensors use)."""

import math

import pytest
import torch

from torchmcmcpf import ConstantVelocity, LinearGaussian
from torchmcmcpf.filters import PartitionedSIRFilter, SIRFilter
from torchmcmcpf.models.base import SensorModel

DT = torch.float64


class JointLinearGaussian(LinearGaussian):
    """The same likelihood without declared per-target terms: the filter then weights each
    partition by ``log_likelihood_delta`` at the reference (the path grid sensors take)."""

    log_likelihood_per_target = SensorModel.log_likelihood_per_target

    def log_likelihood(self, x, z, exists=None):
        return LinearGaussian.log_likelihood_per_target(self, x, z, exists).sum(-1)


@pytest.mark.parametrize("sensor_cls", [LinearGaussian, JointLinearGaussian])
def test_two_targets_match_per_target_kalman_filters(sensor_cls):
    # Two targets, labelled position measurements: the posterior factorises over targets,
    # each partition is an exact SIR filter of its target, and the particle mean of each
    # target must agree with that target's Kalman mean. B runs filter the SAME data with
    # independent randomness: the mean error over runs within 5 standard errors of zero, and
    # the particle variance (averaged over runs) within 5% of the Kalman variance (relative
    # Monte Carlo error ~ sqrt(2 / (N B)) < 1%). N = 2000 keeps the O(1/N) bias of SIR, shared by
    # the runs (they filter the same data), well below the standard error sd / sqrt(B) (at
    # N = 500 and B = 100 it reached 6 standard errors on one coordinate, for SIR as well).
    from _kalman import kalman_filter

    gen = torch.Generator().manual_seed(3)
    motion = ConstantVelocity(1.0, 0.5).to(DT)
    sensor = sensor_cls(LinearGaussian.position(3.0).H, LinearGaussian.position(3.0).R).to(DT)
    assert sensor.separable == (sensor_cls is LinearGaussian)
    t_len, b, n, k = 10, 50, 2000, 2
    m0 = torch.tensor([[0.0, 1.0, 0.0, -0.5], [8.0, -1.0, 2.0, 0.5]], dtype=DT)  # (K, D)
    P0 = torch.diag(torch.tensor([25.0, 1.0, 25.0, 1.0], dtype=DT))
    x = m0 + torch.randn(k, 4, generator=gen, dtype=DT) @ torch.linalg.cholesky(P0).mT
    zs = []
    for _ in range(t_len):
        x = motion.sample(x[None], generator=gen)[0]
        zs.append(sensor.simulate(x[None], generator=gen)[0])
    z = torch.stack(zs)  # (T, K, 2)
    km, kP = kalman_filter(motion.F, motion.Q, sensor.H, sensor.R, m0, P0, z)  # (T, K, D), (T, K, D, D)
    init = m0 + torch.randn(b, n, k, 4, generator=gen, dtype=DT) @ torch.linalg.cholesky(P0).mT
    res = PartitionedSIRFilter(motion, sensor, n)(z.unsqueeze(1).expand(t_len, b, k, 2), init=init, generator=gen)
    err = res.mean - km.unsqueeze(1)  # (T, B, K, D)
    assert torch.all(err.mean(1).abs() <= 5 * err.std(1) / b**0.5)
    var = ((res.state.x - res.mean[-1].unsqueeze(1)) ** 2).mean(1)  # (B, K, D), equal weights
    torch.testing.assert_close(var.mean(0), torch.diagonal(kP[-1], dim1=-2, dim2=-1), rtol=0.05, atol=0.0)
    assert res.info.ess.shape == (t_len, b) and bool((res.info.extras["ess_min"] <= res.info.ess).all())


def test_partitions_beat_joint_weights_with_many_targets():
    # With K targets the joint SIR weight is a product of K per-target factors, so its ESS
    # collapses with K; the partitions keep each target's ESS. Ten independent targets,
    # same data, same N: the partitioned filter's mean partition ESS is several times the
    # joint filter's ESS, and its error against the exact per-target Kalman means is smaller.
    from _kalman import kalman_filter

    gen = torch.Generator().manual_seed(4)
    motion = ConstantVelocity(1.0, 0.5).to(DT)
    sensor = LinearGaussian.position(1.0).to(DT)
    t_len, b, n, k = 8, 20, 200, 10
    m0 = torch.zeros(k, 4, dtype=DT)
    m0[:, 0] = 30.0 * torch.arange(k, dtype=DT)
    P0 = torch.eye(4, dtype=DT)
    x = m0 + torch.randn(k, 4, generator=gen, dtype=DT)
    zs = []
    for _ in range(t_len):
        x = motion.sample(x[None], generator=gen)[0]
        zs.append(sensor.simulate(x[None], generator=gen)[0])
    z = torch.stack(zs).unsqueeze(1).expand(t_len, b, k, 2)
    km, _ = kalman_filter(motion.F, motion.Q, sensor.H, sensor.R, m0, P0, torch.stack(zs))
    init = m0 + torch.randn(b, n, k, 4, generator=gen, dtype=DT)
    part = PartitionedSIRFilter(motion, sensor, n)(z, init=init, generator=gen)
    joint = SIRFilter(motion, sensor, n)(z, init=init, generator=gen)
    assert float(part.info.ess.mean()) > 3 * float(joint.info.ess.mean())
    rmse = {name: (r.mean - km.unsqueeze(1)).square().mean().sqrt() for name, r in (("part", part), ("joint", joint))}
    assert rmse["part"] < rmse["joint"], rmse


def test_slot_changes_default_paths_agree():
    # The base class's two exact paths: a separable sensor's per-target differences and
    # the one-slot changes at the repeated reference equal the direct difference of two
    # log-likelihoods, slot by slot; a reference of the wrong shape is refused by name.
    gen = torch.Generator().manual_seed(5)
    sensor, joint = LinearGaussian.position(2.0).to(DT), JointLinearGaussian(
        LinearGaussian.position(2.0).H, LinearGaussian.position(2.0).R).to(DT)
    ref = torch.randn(2, 3, 4, generator=gen, dtype=DT)
    x = torch.randn(2, 5, 3, 4, generator=gen, dtype=DT)
    z = sensor.simulate(ref, generator=gen)
    out = sensor.log_likelihood_slot_changes(ref, x, z)
    torch.testing.assert_close(joint.log_likelihood_slot_changes(ref, x, z), out, rtol=1e-12, atol=1e-12)
    for k in range(3):
        moved = ref[:, None].expand_as(x).clone()
        moved[..., k, :] = x[..., k, :]
        direct = sensor.log_likelihood(moved, z) - sensor.log_likelihood(ref, z)[:, None]
        torch.testing.assert_close(out[..., k], direct)
    with pytest.raises(ValueError, match=r"ref has shape \(2, 2, 4\), expected \(2, 3, 4\)"):
        sensor.log_likelihood_slot_changes(ref[:, :2], x, z)


def test_existence_is_refused():
    from torchmcmcpf import BirthDeath

    area = ((0.0, 100.0), (0.0, 100.0))
    with pytest.raises(ValueError, match="existence must be None"):
        PartitionedSIRFilter(ConstantVelocity(1.0, 1.0), LinearGaussian.position(1.0), 10,
                             existence=BirthDeath(0.1, 0.1, area, velocity_std=1.0))


class SumLinearGaussian(LinearGaussian):
    """Two targets seen only through the sum of their positions, ``z = H (x_0 + x_1) + v``
    (row 0 of the frame; row 1 unused): the targets interact in every frame."""

    log_likelihood_per_target = SensorModel.log_likelihood_per_target

    def log_likelihood(self, x, z, exists=None):
        pair = x[..., :1, :] + x[..., 1:2, :]  # (B, *S, 1, D)
        return LinearGaussian.log_likelihood_per_target(self, pair, z[:, :1])[..., 0]


def test_reference_at_the_truth_is_each_targets_exact_filter():
    # The clairvoyant reference of the studies (clairvoyant_partitions): with the other target fixed at its true
    # state, partition k is the exact filter of target k given z - H x_other, here a Kalman
    # filter (the targets interact through the summed measurement, so the default reference,
    # the predicted mean, is only an approximation). Same tolerances as the first test.
    from _kalman import kalman_filter

    from torchmcmcpf.filters.partitioned import clairvoyant_partitions, partitioned_sir_step
    from torchmcmcpf.state import ParticleState

    gen = torch.Generator().manual_seed(6)
    motion = ConstantVelocity(1.0, 0.5).to(DT)
    base = LinearGaussian.position(2.0)
    sensor = SumLinearGaussian(base.H, base.R).to(DT)
    assert not sensor.separable
    t_len, b, n = 10, 50, 2000
    m0 = torch.tensor([[0.0, 1.0, 0.0, -0.5], [8.0, -1.0, 2.0, 0.5]], dtype=DT)  # (K, D)
    P0 = torch.diag(torch.tensor([25.0, 1.0, 25.0, 1.0], dtype=DT))
    x = m0 + torch.randn(2, 4, generator=gen, dtype=DT) @ torch.linalg.cholesky(P0).mT
    truth, zs = [], []
    for _ in range(t_len):
        x = motion.sample(x[None], generator=gen)[0]
        truth.append(x)
        zs.append(sensor.simulate(x.sum(0, keepdim=True).expand(2, 4)[None], generator=gen)[0])
    truth, z = torch.stack(truth), torch.stack(zs)  # (T, K, D), (T, K, 2)
    other = truth.flip(1) @ sensor.H.mT  # (T, K, 2): H x of the other target
    km, kP = kalman_filter(motion.F, motion.Q, sensor.H, sensor.R, m0, P0, z[:, :1] - other)  # per target
    init = m0 + torch.randn(b, n, 2, 4, generator=gen, dtype=DT) @ torch.linalg.cholesky(P0).mT
    x_last, means = clairvoyant_partitions(z[:, None].expand(t_len, b, 2, 2), truth[:, None].expand(t_len, b, 2, 4),
                                           init, motion=motion, sensor=sensor, generator=gen)
    err = means - km.unsqueeze(1)  # (T, B, K, D)
    assert torch.all(err.mean(1).abs() <= 5 * err.std(1) / b**0.5)
    var = ((x_last - means[-1].unsqueeze(1)) ** 2).mean(1)
    torch.testing.assert_close(var.mean(0), torch.diagonal(kP[-1], dim1=-2, dim2=-1), rtol=0.05, atol=0.0)
    state = ParticleState(x_last, torch.full((b, n), -math.log(n), dtype=DT))
    with pytest.raises(ValueError, match=r"reference has shape \(50, 1, 4\), expected"):
        partitioned_sir_step(state, z[0].expand(b, 2, 2), motion=motion, sensor=sensor, generator=gen,
                             reference=truth[0, :1].expand(b, 1, 4))


def test_recapture_draws_the_least_explained_partition_from_the_data():
    # One step from a known state on the line sensor of tests/_line.py (each slot measured
    # on its own, a data-driven density near the measurements): partition 0 is predicted at
    # 0 and measured at 5 (it explains least of the frame: the one partition that may
    # relocate), partition 1 predicted at 1.5 and measured at 1.3. Partition k's resampled
    # particles follow p(z_k | u) Phi(u - ref_l) pi_k(u), with pi_0 the heavy-tailed slot prior
    # (1 - delta) N(u; 0, Q) + delta p_0(u) and pi_1 its motion part (module docstring):
    # quadrature moments against the runs' means, 5 standard errors over the runs.
    from _line import DT as LDT
    from _line import LineSensor, Q, R, log_fov

    from torchmcmcpf.filters.partitioned import PartitionedSIRSettings, least_explained, partitioned_sir_step
    from torchmcmcpf.models.motion import LinearGaussianMotion
    from torchmcmcpf.models.multitarget import Exclusion, Recapture
    from torchmcmcpf.state import ParticleState

    gen = torch.Generator().manual_seed(3)
    motion, sensor = LinearGaussianMotion(torch.eye(1, dtype=LDT), Q * torch.eye(1, dtype=LDT)), LineSensor()
    b, n, delta = 40, 4000, 0.2
    ref = torch.tensor([[0.0], [1.5]], dtype=LDT)  # (K, D)
    z = torch.tensor([[5.0], [1.3]], dtype=LDT).expand(b, 2, 1)
    assert least_explained(sensor, ref.expand(b, 2, 1), z).tolist() == [[True, False]] * b
    exclusion, recapture = Exclusion(1.5), Recapture(p_jump=delta, p_propose=0.3)
    settings = PartitionedSIRSettings(exclusion=exclusion, recapture=recapture)
    state = ParticleState(ref.expand(b, n, 2, 1), torch.full((b, n), -math.log(n), dtype=LDT))
    new, _ = partitioned_sir_step(state, z, motion=motion, sensor=sensor, settings=settings, generator=gen)
    u = new.x[..., 0]  # (B, N, K)
    runs = torch.stack([u.mean(1), u.square().mean(1)], -1)  # (B, K, 2)
    mean, se = runs.mean(0), runs.std(0) / b**0.5

    grid = torch.arange(-14.0, 14.0, 0.005, dtype=LDT)

    def moments(log_density):
        w = torch.softmax(log_density, 0)
        return torch.stack([(w * grid).sum(), (w * grid.square()).sum()])

    def log_normal(x, m, v):
        return -0.5 * (x - m).square() / v

    base = [log_normal(grid, 5.0, R) + exclusion.log_phi((grid - 1.5).square()),
            log_normal(grid, 1.3, R) + exclusion.log_phi(grid.square())]
    motion_part = [math.log1p(-delta) + log_normal(grid, 0.0, Q) - 0.5 * math.log(2 * math.pi * Q),
                   math.log1p(-delta) + log_normal(grid, 1.5, Q) - 0.5 * math.log(2 * math.pi * Q)]
    heavy = torch.logaddexp(motion_part[0], math.log(delta) + log_fov(grid))
    exact = torch.stack([moments(base[0] + heavy), moments(base[1] + motion_part[1])])  # (K, 2)
    assert ((mean - exact).abs() <= 5 * se).all(), (mean, exact, se)
    # the check can fail: without the relocation component partition 0's moments are far off
    plain = moments(base[0] + motion_part[0])
    assert ((plain - exact[0]).abs() > 20 * se[0]).all()
    assert float((u[..., 0] > 3.5).double().mean()) > 0.2  # a real share relocated near its measurement
    # and partition 1 holds its motion part only: with the relocation component it would be off
    relocated_1 = moments(base[1] + torch.logaddexp(motion_part[1], math.log(delta) + log_fov(grid)))
    assert ((relocated_1 - exact[1]).abs() > 10 * se[1]).any()


def test_recapture_brings_a_coalesced_partition_back():
    # The crossing study's staged coalescence (docs/tracks.md): both partitions start on the
    # strong target, the weak one 150 m away uncovered. With re-capture a partition reaches it
    # within 20 steps in every run and the strong target keeps a slot within 20 m at the last
    # steps; without, no run reaches it (its motion proposal never gets there).
    from torchmcmcpf import metrics
    from torchmcmcpf.scenarios import crossing

    gen = torch.Generator().manual_seed(1)
    far = crossing(2, 20, 8, generator=gen, miss_distance=150.0, crossing_step=10)
    init = far.initial_particles(200, generator=gen)
    init[:, :, 1] = init[:, :, 0]
    weak = far.truth[:, :, 1:]
    found = {}
    for recapture in ("on", None):
        filt = PartitionedSIRFilter(far.motion, far.sensor, 200, **({} if recapture else {"recapture": None}))
        res = filt(far.measurements, init=init, generator=torch.Generator().manual_seed(2))
        cover = metrics.slot_coverage(res.mean, weak, radius=10.0)[..., 0] > 0  # (T, B)
        found[recapture] = int(cover.any(0).sum())
        if recapture:
            strong = metrics.slot_coverage(res.mean[-5:], far.truth[-5:, :, :1], radius=20.0)[..., 0] > 0
            assert bool(strong.all())
    assert found == {"on": 8, None: 0}


def test_compiled_recapture_step_equals_eager_on_the_radar():
    # compile_step=True compiles the body with the re-capture (its draws made eagerly and
    # passed in): the same bits as the eager step on a radar with a data-driven proposal
    from torchmcmcpf.scenarios import ground_radar

    scn = ground_radar(3, 3, 2, generator=torch.Generator().manual_seed(4))
    init = scn.initial_particles(64, generator=torch.Generator().manual_seed(5))
    out = []
    for compiled in (False, True):
        filt = PartitionedSIRFilter(scn.motion, scn.sensor, 64, compile_step=compiled)
        assert filt.settings.recapture is not None
        out.append(filt(scn.measurements, init=init, generator=torch.Generator().manual_seed(6)).mean)
    torch.testing.assert_close(out[1], out[0], rtol=0, atol=0)


@pytest.mark.parametrize("kwargs, message", [
    (dict(exclusion=1.0), "exclusion must be an Exclusion or None, got float"),
    (dict(recapture=0.1), "recapture must be a Recapture or None, got float"),
    (dict(resample_method="residual"), "resample_method must be one of"),
])
def test_bad_settings_raise(kwargs, message):
    with pytest.raises(ValueError, match=message):
        PartitionedSIRFilter(ConstantVelocity(1.0, 1.0), LinearGaussian.position(1.0), 10, **kwargs)


def test_recapture_is_off_for_a_sensor_without_a_data_driven_proposal():
    # labelled point measurements have no data-driven density: the settings say so
    filt = PartitionedSIRFilter(ConstantVelocity(1.0, 1.0), LinearGaussian.position(1.0), 10)
    assert filt.settings.recapture is None and filt.settings.exclusion is None
