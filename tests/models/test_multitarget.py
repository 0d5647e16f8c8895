"""The multitarget prior's terms (models/multitarget.py) and the sensor hooks they use."""

import itertools
import math

import pytest
import torch

import torchmcmcpf as tp
from torchmcmcpf.filters.base import active_prior
from torchmcmcpf.filters.ipmcmc import IPMCMCSettings
from torchmcmcpf.models.multitarget import (
    FIXED,
    LOG_PHI_FLOOR,
    MOTION,
    RELOCATED,
    Exclusion,
    Recapture,
    RelocationNoise,
    exclusion_against,
    log_q_component,
    relocate,
)
from torchmcmcpf.models.sensors.points import PoissonClutterPoints
from torchmcmcpf.scenarios import crossing, ground_radar, septier

DT = torch.float64


def test_exclusion_factor_values_and_one_slot_change(gen):
    ex = Exclusion(scale=1.0)
    # phi(d) = 1 - exp(-d^2 / 2): one cell 0.39, two 0.86, three 0.99; coincident slots floored
    d2 = torch.tensor([1.0, 4.0, 9.0, 0.0], dtype=DT)
    torch.testing.assert_close(ex.log_phi(d2)[:3], torch.log(1 - torch.exp(-d2[:3] / 2)))
    assert float(ex.log_phi(d2)[3]) == LOG_PHI_FLOOR
    u = torch.randn(5, 7, 4, 3, generator=gen, dtype=DT)  # (*S, K, r)
    alive = torch.rand(5, 7, 4, generator=gen) < 0.7
    # log Phi is the sum over live pairs i < j
    k = 4
    brute = torch.zeros(5, 7, dtype=DT)
    for i in range(k):
        for j in range(i + 1, k):
            both = alive[..., i] & alive[..., j]
            term = ex.log_phi((u[..., i, :] - u[..., j, :]).square().sum(-1))
            brute = brute + torch.where(both, term, 0.0)
    torch.testing.assert_close(ex.log_factor(u, alive), brute)
    # a one-slot move pays exactly the change of log Phi (K - 1 factors)
    n = torch.randint(k, (5, 7), generator=gen)
    u_n = torch.randn(5, 7, 3, generator=gen, dtype=DT)
    alive_n = torch.rand(5, 7, generator=gen) < 0.5
    here = torch.arange(k) == n.unsqueeze(-1)
    u2 = torch.where(here.unsqueeze(-1), u_n.unsqueeze(-2), u)
    a2 = torch.where(here, alive_n.unsqueeze(-1), alive)
    want = ex.log_factor(u2, a2) - ex.log_factor(u, alive)
    torch.testing.assert_close(ex.log_change(u, u_n, n, alive, alive_n), want)
    # gradients are finite, also for coincident slots (floored)
    v = torch.zeros(1, 2, 3, dtype=DT, requires_grad=True)
    ex.log_factor(v).sum().backward()
    assert bool(torch.isfinite(v.grad).all())
    with pytest.raises(ValueError, match="scale"):
        Exclusion(scale=0.0)


def test_exclusion_against_a_reference(gen):
    sensor = PoissonClutterPoints(1.0, 1.0, ((0, 100), (0, 100)), noise_std=2.0)
    x = torch.randn(2, 5, 3, 4, generator=gen, dtype=DT) * 3
    ref = torch.randn(2, 3, 4, generator=gen, dtype=DT) * 3
    got = exclusion_against(Exclusion(), sensor, x, ref)  # (B, N, K)
    u, ur = sensor.resolution_coords(x), sensor.resolution_coords(ref)
    for k in range(3):
        want = sum(Exclusion().log_phi((u[:, :, k] - ur[:, None, j]).square().sum(-1)) for j in range(3) if j != k)
        torch.testing.assert_close(got[..., k], want)


def test_recapture_settings_and_ratios():
    r = Recapture(p_jump=0.01, p_propose=0.2)
    for bad in (dict(p_jump=0.0), dict(p_jump=1.0), dict(p_propose=0.0), dict(pair_every=-1),
                dict(pair_distance=0.0), dict(p_propose_pair=1.5), dict(p_same_source=1.0),
                dict(p_same_source=-0.1)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            Recapture(**bad)
    kind = torch.tensor([FIXED, MOTION, RELOCATED], dtype=torch.int8)
    torch.testing.assert_close(log_q_component(kind, 0.2),
                               torch.tensor([0.0, math.log(0.8), math.log(0.2)], dtype=DT))
    # relocate: r = (1 - delta) / (1 - eps) for a slot from its prediction, delta p0 / (eps g)
    # for a relocated one, 0 (log) for one that did not survive
    x = torch.zeros(3, 4, dtype=DT)
    noise = RelocationNoise(torch.tensor([0.5, 0.1, 0.1], dtype=DT), torch.ones(3, 2, dtype=DT),
                            torch.tensor([-1.0, -2.0, -3.0], dtype=DT))
    sensor = PoissonClutterPoints(1.0, 1.0, ((0, 100), (0, 100)), noise_std=2.0)
    y, log_r, kinds = relocate(x, torch.tensor([True, True, False]), noise, r, sensor)
    assert kinds.tolist() == [MOTION, RELOCATED, FIXED]
    torch.testing.assert_close(log_r, torch.tensor([math.log(0.99 / 0.8), math.log(0.01 / 0.2) - 2.0, 0.0], dtype=DT))
    assert y[1, 0] == 1.0 and y[1, 2] == 1.0 and y[0].abs().sum() == 0 and y[2].abs().sum() == 0


def _density_check(sensor, z, centre, gen, n=200_000):
    """E_g[p0 / g] = 1 and E_g[u p0 / g] = the field of view's centre: the returned log_ratio is
    log p0 - log g of the density the draws come from (p0 / g <= 1 / p_u bounds the weights).
    """
    coords, log_ratio = sensor.sample_from_data(z, (z[0].shape[0] if isinstance(z, tuple) else z.shape[0], n),
                                                generator=gen, dtype=DT)
    w = log_ratio.exp()
    assert float(w.max()) <= 1.0 / sensor.uniform_weight + 1e-6
    se = w.std() / math.sqrt(n)
    assert abs(float(w.mean()) - 1.0) < 5 * float(se.max())
    mean = (w.unsqueeze(-1) * coords).mean(1)  # (B, r)
    se_m = (w.unsqueeze(-1) * coords).std(1) / math.sqrt(n)
    assert bool(((mean - centre).abs() <= 5 * se_m).all()), (mean, centre)


def test_radar_data_driven_density_is_what_it_draws(gen):
    scn = ground_radar(3, 2, 2, generator=gen, dtype=DT, snr_db=20.0)  # every target detected
    sensor = scn.sensor
    assert sensor.resolved and sensor.data_driven
    z = scn.measurements[0]
    lo = torch.tensor([o - c / 2 for o, c in zip(sensor.origins, sensor.cell_sizes)], dtype=DT)
    hi = torch.tensor([o + (n - 0.5) * c for o, c, n in zip(sensor.origins, sensor.cell_sizes, sensor.frame_shape)],
                      dtype=DT)
    _density_check(sensor, z, (lo + hi) / 2, gen)
    # the peaks are the (strong) targets: one detection within a cell of each
    centres, mask = sensor.detections(z)
    truth = sensor.measurement_coords(scn.truth[0])  # (B, K, 3)
    cells = torch.tensor(sensor.cell_sizes, dtype=DT)
    d = ((centres.unsqueeze(1) - truth.unsqueeze(2)) / cells).abs().amax(-1)  # (B, K, P)
    d = torch.where(mask.unsqueeze(1), d, torch.full_like(d, float("inf")))
    assert bool((d.amin(-1) < 1.0).all())
    # place is eq. 21 inverted: a state placed at its own coordinates is unchanged
    x = scn.truth[0]
    torch.testing.assert_close(sensor.place(x, sensor.measurement_coords(x)), x)


def test_detections_are_the_centroids_of_each_peaks_neighbourhood(gen):
    """A peak's centre is the centroid of the statistic above the noise mean over its 3^n
    neighbourhood (cells beyond the grid weigh nothing), checked cell by cell against a
    Python loop, with peaks in a corner and on an edge of the grid; padding is masked."""
    sensor = ground_radar(2, 2, 1, generator=gen, dtype=DT).sensor
    shape = sensor.frame_shape
    stat = torch.rand((2,) + shape, generator=gen, dtype=DT) * 2.0  # noise: below the threshold
    planted = [(0, (0, 0, 0)), (0, (5, shape[1] - 1, 7)), (1, (shape[0] - 1, 3, shape[2] - 1)), (1, (9, 9, 9))]
    for b, cell in planted:
        stat[(b,) + cell] = 30.0 + 10 * torch.rand((), generator=gen, dtype=DT)
    z = stat * sensor.detection_statistic(torch.ones((1,) + shape, dtype=DT)).reciprocal()  # the frame giving stat
    torch.testing.assert_close(sensor.detection_statistic(z), stat)
    centres, mask = sensor.detections(z)
    assert mask.sum(-1).tolist() == [2, 2]
    for b, cell in planted:
        num, den = torch.zeros(3, dtype=DT), torch.zeros((), dtype=DT)
        for off in itertools.product((-1, 0, 1), repeat=3):
            c = [i + o for i, o in zip(cell, off)]
            if all(0 <= i < n for i, n in zip(c, shape)):
                w = (stat[(b,) + tuple(c)] - 1.0).clamp(min=0.0)
                num += w * torch.tensor([o + d * i for o, d, i in zip(sensor.origins, sensor.cell_sizes, c)], dtype=DT)
                den += w
        got = centres[b][mask[b]]
        assert bool(((got - num / den).abs().amax(-1) < 1e-9).any()), (cell, got, num / den)


@pytest.mark.parametrize("make", ["radar", "swerling"])
def test_detections_find_a_weak_target_on_a_strong_ones_shoulder(gen, make):
    """CLEAN: a weak target two cells beside one four times stronger (its signal a shoulder of
    the strong one's spread, not a local maximum, so a local-maximum detector misses it) is
    found once the strong one's fitted spread is taken off, each within half a cell; every
    detection lies within one and a half cells of a target (the remainder of a fitted spread
    may give a second detection beside a strong target, never one far from it; the radar's
    give none). Noise-free frames built from the sensor's own spread, in the domain where its
    targets add (amplitude for the radar, power for Swerling).
    """
    from torchmcmcpf.models.base import neighbourhood
    from torchmcmcpf.scenarios import ling

    sensor = ground_radar(2, 2, 1, generator=gen, dtype=DT).sensor if make == "radar" else \
        ling(1, 2, generator=gen, dtype=DT).sensor
    shape, n = sensor.frame_shape, len(sensor.frame_shape)
    width = torch.tensor([w / c for w, c in zip(sensor.widths, sensor.cell_sizes)], dtype=DT)
    grid = torch.stack(torch.meshgrid(*[torch.arange(m, dtype=DT) for m in shape], indexing="ij"), -1)
    strong = torch.tensor([m // 2 + 0.3 for m in shape], dtype=DT)
    weak = strong.clone()
    weak[0] += 2.0
    weak[-1] -= 0.4

    def frame(targets):
        s = sum(a * torch.exp(-0.5 * ((grid - c) / width).square().sum(-1)) for a, c in targets)
        return sensor.detection_stat(s).unsqueeze(0)  # the statistic of a noise-free frame

    one = sensor.detection_signal(torch.tensor(60.0, dtype=DT))
    both = frame([(4 * one, strong), (one, weak)])
    cell = tuple(int(round(float(v))) for v in weak)
    assert float(both[(0,) + cell]) < float(neighbourhood(both, "max", n)[(0,) + cell])  # no local maximum
    ones = sensor.detection_statistic(torch.ones((1,) + shape, dtype=DT))
    origin, size = torch.tensor(sensor.origins, dtype=DT), torch.tensor(sensor.cell_sizes, dtype=DT)
    for targets in ([(4 * one, strong), (one, weak)], [(4 * one, strong)]):
        centres, mask = sensor.detections(frame(targets) / ones)
        got = (centres[0][mask[0]] - origin) / size  # in cells
        assert int(sensor.peaks(frame(targets) / ones).sum()) == int(mask.sum())  # one cell per detection
        for _, c in targets:
            assert float((got - c).abs().amax(-1).min()) < 0.5, (got, c)
        near = torch.stack([(got - c).abs().amax(-1) for _, c in targets]).amin(0)
        assert bool((near < 1.5).all()), got
        if make == "radar":
            assert got.shape[0] == len(targets), got


@pytest.mark.parametrize("shape", [(2, 7), (2, 5, 1), (3, 9, 4, 6), (1, 2, 1, 4)])
@pytest.mark.parametrize("radius", [1, 2])
def test_neighbourhood_is_atens_pooling_one_axis_at_a_time(gen, shape, radius):
    """``models.base.neighbourhood`` (the grid sensors' peaks and centroids, the group
    filter's pixels near a detection): the max equals ATen's max pooling exactly, the mean its
    average pooling (zero padding counted) to round-off, on grids with axes of 1 to 9 cells
    (padded first: ATen refuses axes shorter than the window) and over the last axes only;
    bad arguments are refused by name.
    """
    import torch.nn.functional as F

    from torchmcmcpf.models.base import neighbourhood

    t = torch.rand(shape, generator=gen, dtype=DT)
    n = len(shape) - 1
    width = [radius] * (2 * n)  # the padding neighbourhood assumes, for every pooled axis
    padded = {r: F.pad(t, width, value=v) for r, v in (("max", float("-inf")), ("mean", 0.0))}
    pools = {1: (F.max_pool1d, F.avg_pool1d), 2: (F.max_pool2d, F.avg_pool2d), 3: (F.max_pool3d, F.avg_pool3d)}[n]
    size = 2 * radius + 1
    assert torch.equal(neighbourhood(t, "max", n, radius),
                       pools[0](padded["max"].unsqueeze(1), size, stride=1).squeeze(1))
    torch.testing.assert_close(neighbourhood(t, "mean", n, radius),
                               pools[1](padded["mean"].unsqueeze(1), size, stride=1).squeeze(1),
                               rtol=1e-12, atol=1e-14)
    if n >= 2:  # the leading axes are not pooled
        last = neighbourhood(t, "max", 1, radius)
        assert torch.equal(last, F.max_pool1d(F.pad(t, [radius, radius], value=float("-inf")).flatten(0, -2)
                                              .unsqueeze(1), size, stride=1).reshape(t.shape))
    with pytest.raises(ValueError, match="reduce must be"):
        neighbourhood(t, "sum", n)
    with pytest.raises(ValueError, match="axes="):
        neighbourhood(t, "max", t.dim() + 1)
    with pytest.raises(ValueError, match="radius=0"):
        neighbourhood(t, "max", n, 0)


def test_point_data_driven_density_is_what_it_draws(gen):
    scn = septier(2, 3, generator=gen)
    sensor = scn.sensor
    z = type(scn.measurements)(*(f[1] for f in scn.measurements))
    _density_check(sensor, z, torch.tensor([2500.0, 2500.0], dtype=DT), gen)
    x = scn.truth[1]
    moved = sensor.place(x, torch.full(x.shape[:-1] + (2,), 7.0, dtype=DT))
    assert bool((moved[..., [0, 2]] == 7.0).all()) and torch.equal(moved[..., [1, 3]], x[..., [1, 3]])


def test_terms_are_off_where_the_sensor_cannot_support_them():
    lg = tp.LinearGaussian.position(1.0)
    assert not lg.resolved and not lg.data_driven  # labelled measurements: no exclusion, no re-capture
    settings = active_prior(IPMCMCSettings(), lg)
    assert settings.exclusion is None and settings.recapture is None
    filt = tp.IPMCMCFilter(tp.ConstantVelocity(1.0, 1.0), lg, 100, num_chains=10)
    assert filt.settings.exclusion is None and filt.settings.recapture is None
    scn = crossing(2, 2, 1, generator=torch.Generator().manual_seed(0))
    filt = tp.IPMCMCFilter(scn.motion, scn.sensor, 100, num_chains=10)
    assert filt.settings.exclusion == Exclusion() and filt.settings.recapture == Recapture()
    plain = tp.IPMCMCFilter(scn.motion, scn.sensor, 100, num_chains=10, exclusion=None, recapture=None)
    assert plain.settings.exclusion is None and plain.settings.recapture is None
    # re-capture needs the labelled prior: off with the random walk or HMC
    mcmc = tp.MCMCFilter(scn.motion, scn.sensor, 100, moves="random_walk", rw_scale=1.0)
    assert mcmc.settings.recapture is None and mcmc.settings.exclusion == Exclusion()


def test_radar_data_draws_score_only_where_asked(gen):
    """``sample_from_data(scored=)`` (what :class:`RelocationNoise` asks for the draws a
    proposal can read): the same draws, the same ratio where scored, 0 elsewhere."""
    scn = ground_radar(3, 2, 2, generator=gen, dtype=DT, snr_db=20.0)
    sensor, z = scn.sensor, scn.measurements[0]
    scored = torch.rand(2, 50, 3, generator=gen) < 0.2
    full = sensor.sample_from_data(z, (2, 50, 3), generator=torch.Generator().manual_seed(1), dtype=DT)
    part = sensor.sample_from_data(z, (2, 50, 3), generator=torch.Generator().manual_seed(1), dtype=DT, scored=scored)
    assert torch.equal(full[0], part[0])
    assert torch.equal(part[1], torch.where(scored, full[1], 0.0))
    noise = RelocationNoise.draw((2, 50, 3), sensor, z, generator=torch.Generator().manual_seed(2), dtype=DT,
                                 device="cpu", p_propose=0.1)
    assert torch.equal(noise.log_ratio == 0, noise.u >= 0.1)


@pytest.mark.parametrize("scene", ["radar", "points"])
def test_packed_relocations_draw_where_read(scene, gen):
    """``RelocationNoise.draw(packed=True)`` (the MCMC-PF's): coordinates drawn only where the
    uniform picks the relocation, each run's packed in order into one block that the sensor
    draws densely after the uniforms; 0 and ratio 0 elsewhere, which :func:`relocate` never
    reads (NaN there changes nothing)."""
    if scene == "radar":
        scn = ground_radar(3, 2, 2, generator=gen, dtype=DT, snr_db=20.0)
        z = scn.measurements[0]
    else:
        scn = septier(2, 3, generator=gen)
        z = type(scn.measurements)(*(f[1] for f in scn.measurements))
    sensor, shape, p = scn.sensor, (2, 60, 3), 0.1
    noise = RelocationNoise.draw(shape, sensor, z, generator=torch.Generator().manual_seed(2), dtype=DT,
                                 device="cpu", p_propose=p, packed=True)
    g = torch.Generator().manual_seed(2)
    u = torch.rand(shape, generator=g, dtype=DT)
    assert torch.equal(noise.u, u)
    flags = u < p
    counts = flags.flatten(1).sum(-1)
    assert counts.min() > 0 and counts[0] != counts[1]
    block, ratio = sensor.sample_from_data(z, (2, int(counts.max())), generator=g, dtype=DT)
    for r in range(2):
        assert torch.equal(noise.coords[r][flags[r]], block[r, :int(counts[r])])
        assert torch.equal(noise.log_ratio[r][flags[r]], ratio[r, :int(counts[r])])
    assert bool((noise.coords[~flags] == 0).all()) and bool((noise.log_ratio[~flags] == 0).all())
    x = scn.truth[0][:, :1].unsqueeze(1).expand(2, 60, 3, -1).to(DT)  # one slot state per run, copied
    unread = noise._replace(coords=torch.where(flags.unsqueeze(-1), noise.coords, math.nan),
                            log_ratio=torch.where(flags, noise.log_ratio, math.nan))
    ref, got = relocate(x, None, noise, Recapture(), sensor), relocate(x, None, unread, Recapture(), sensor)
    assert all(torch.equal(a, b) for a, b in zip(ref, got))
    assert bool((ref[2] == 2).any())  # some slots relocated


@pytest.mark.parametrize("r", [1, 2, 3])
def test_pairwise_squared_distances_equal_the_broadcast_form(r):
    """Coordinate by coordinate, the same values as the squared norm of the broadcast
    differences (the exclusion factors' bits are those of the form they replace)."""
    from torchmcmcpf.runtime import pairwise_squared_distances, squared_norm

    g = torch.Generator().manual_seed(r)
    a = torch.randn(3, 7, 4, r, generator=g, dtype=torch.float64) * 50
    b = torch.randn(3, 7, 5, r, generator=g, dtype=torch.float64) * 50
    want = squared_norm(a.unsqueeze(-2) - b.unsqueeze(-3))  # (3, 7, 4, 5)
    assert torch.equal(pairwise_squared_distances(a, b), want)
    assert torch.equal(pairwise_squared_distances(b, a), want.transpose(-1, -2))
    with pytest.raises(ValueError, match="at least one coordinate"):
        pairwise_squared_distances(a[..., :0], b[..., :0])


def test_log_q_ratio_is_the_difference_of_the_components():
    """``log_q_ratio(kind, a, b)``, the conversion of a cached ``log r`` between two moves'
    ``epsilon``, is ``log_q_component(kind, a) - log_q_component(kind, b)`` to the bit for every
    kind, float64, in the kind's shape."""
    from torchmcmcpf.models.multitarget import FIXED, MOTION, RELOCATED, log_q_component, log_q_ratio

    kind = torch.tensor([[FIXED, MOTION, RELOCATED], [RELOCATED, RELOCATED, MOTION]], dtype=torch.int8)
    for a, b in ((0.1, 0.3), (0.3, 0.1), (0.05, 0.05), (1e-3, 0.5)):
        got = log_q_ratio(kind, a, b)
        want = log_q_component(kind, a) - log_q_component(kind, b)
        assert got.dtype == torch.float64 and got.shape == kind.shape and torch.equal(got, want)
    assert log_q_ratio(kind, 0.1, 0.3)[0, 0] == 0 and log_q_ratio(kind, 0.1, 0.3)[0, 1] != 0
