"""The birth/death scenario of paper 001, its study, and the Stone Soup trackers it is
compared with (issue 27)."""

import json
import math

import numpy as np
import pytest
import torch

from torchmcmcpf.experiments import septier_birth_death
from torchmcmcpf.filters.sir import SIRFilter
from torchmcmcpf.interop import stonesoup_trackers as sst
from torchmcmcpf.models.sensors.points import PointFrame
from torchmcmcpf.scenarios.septier import septier


def test_scenario_shapes_and_conventions():
    scn = septier(200, 12, generator=torch.Generator().manual_seed(0))
    t, b, k = scn.alive.shape
    assert (t, b, k) == (12, 200, 5)
    assert scn.truth.shape == (12, 200, 5, 4) and scn.truth.dtype == torch.float64
    z, mask = scn.measurements
    assert z.shape[:3] == mask.shape and z.shape[:2] == (12, 200) and z.shape[-1] == 2
    # inactive slots hold x_death (zeros); live ones are finite
    assert torch.equal(scn.truth[~scn.alive], torch.zeros_like(scn.truth[~scn.alive]))
    # the chain starts stationary, so P(alive) = P_B / (P_B + P_D) = 1/2 at every step:
    # 12 * 200 * 5 flags, correlated in time; per step 1000 independent flags, se 0.016
    frac = scn.alive.double().mean((1, 2))
    assert bool(((frac - 0.5).abs() < 5 * math.sqrt(0.25 / 1000)).all())
    # points per frame: Poisson(L_C + L_x n) = 10 + 4 n; mean over all frames
    expected = 10 + 4 * scn.true_count.double()
    assert abs((mask.sum(-1) - expected).double().mean().item()) < 5 * math.sqrt(expected.mean().item() / (12 * 200))
    again = septier(200, 12, generator=torch.Generator().manual_seed(0))
    assert torch.equal(again.truth, scn.truth) and torch.equal(again.measurements.z, z)


def test_thirds_cover_the_run_in_order():
    assert septier_birth_death.thirds(60) == [range(0, 20), range(20, 40), range(40, 60)]
    for steps in (1, 2, 8, 25):
        parts = septier_birth_death.thirds(steps)
        assert len(parts) == 3 and [i for p in parts for i in p] == list(range(steps))


def test_filter_resumed_per_third_matches_one_call():
    # the study filters each third as a call resumed from the last state: the same numbers
    scn = septier(2, 9, generator=torch.Generator().manual_seed(3))
    filt = SIRFilter(scn.motion, scn.sensor, num_particles=50, existence=scn.existence)
    init = torch.zeros((2, 50, 5, 4), dtype=torch.float64)
    whole = filt(scn.measurements, init=init, generator=torch.Generator().manual_seed(1))
    gen, state, means = torch.Generator().manual_seed(1), init, []
    for part in septier_birth_death.thirds(9):
        res = filt(PointFrame(*(a[part.start:part.stop] for a in scn.measurements)), init=state, generator=gen)
        state = res.state
        means.append(res.mean)
    assert torch.equal(torch.cat(means), whole.mean)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_our_problem_in_the_study_dtype(dtype):
    """Our filters get the scene's models and frames in the study's dtype; the scene itself
    (what Stone Soup and the scores read) stays float64, its frames the same up to rounding.
    """
    scn = septier(2, 3, generator=torch.Generator().manual_seed(0))
    cfg = septier_birth_death.BirthDeathSettings(dtype=dtype, stonesoup=False)
    motion, sensor, existence, z = septier_birth_death.our_problem(scn, cfg, torch.device("cpu"))
    want = getattr(torch, dtype)
    assert z.z.dtype == want and torch.equal(z.mask, scn.measurements.mask)
    assert scn.measurements.z.dtype == torch.float64 and scn.truth.dtype == torch.float64
    torch.testing.assert_close(z.z.double(), scn.measurements.z, rtol=1e-6, atol=0.0)
    assert motion.F.dtype == want and sensor.R.dtype == want and existence.x_death.dtype == want
    x = existence.sample_birth((2, 5), generator=torch.Generator().manual_seed(1), dtype=want)
    assert sensor.log_likelihood(x[:, None], PointFrame(z.z[0], z.mask[0])).dtype == want


def test_set_scores_on_a_hand_made_step():
    # one step, one run: truths at (0, 0) and (500, 500); reported (3, 4) and (2000, 0)
    truth = torch.tensor([[[[0.0, 0, 0, 0], [500, 0, 500, 0], [0, 0, 0, 0]]]], dtype=torch.float64)
    alive = torch.tensor([[[True, True, False]]])
    est = torch.tensor([[[[3.0, 0, 4, 0], [2000, 0, 0, 0]]]], dtype=torch.float64)
    present = torch.tensor([[[True, True]]])
    s = septier_birth_death.set_scores(est, present, truth, alive)
    assert all(v.shape == (1, 1) for v in s.values())
    assert s["localisation"].item() == pytest.approx(5.0)
    assert (s["missed"].item(), s["false"].item(), s["reported"].item(), s["cardinality_error"].item()) == (
        1.0, 1.0, 2.0, 0.0)
    assert s["gospa"].item() == pytest.approx(math.sqrt(25 + 100**2))
    assert s["ospa"].item() == pytest.approx(math.sqrt((25 + 100**2) / 2))


def test_cluster_points_single_linkage():
    pts = np.array([[0.0, 0.0], [1000.0, 0.0], [20.0, 0.0], [40.0, 0.0], [1000.0, 24.0], [3000.0, 3000.0]])
    centres, counts = sst.cluster_points(pts, 25.0)
    # single linkage chains (0, 0), (20, 0), (40, 0) by 20 m steps although the ends are 40 m apart
    assert counts.tolist() == [3, 2, 1]
    assert np.allclose(centres, [[20.0, 0.0], [1000.0, 12.0], [3000.0, 3000.0]])
    centres, counts = sst.cluster_points(pts, 10.0)
    assert counts.tolist() == [1] * 6 and np.allclose(centres, pts)
    assert sst.cluster_points(np.zeros((0, 2)), 10.0)[0].shape == (0, 2)
    with pytest.raises(ValueError, match="points"):
        sst.cluster_points(np.zeros((3, 3)), 10.0)
    with pytest.raises(ValueError, match="distance"):
        sst.cluster_points(pts, 0.0)


def test_point_scene_reads_the_true_model():
    scn = septier(1, 2, generator=torch.Generator().manual_seed(0))
    scene = sst.PointScene.from_models(scn.motion, scn.sensor, scn.existence, 5)
    assert scene.p_detect == pytest.approx(1 - math.exp(-4))
    assert scene.clutter_density == pytest.approx(10 / 5000**2)
    assert scene.p_survival == pytest.approx(0.98) and scene.q == 1.0 and scene.dt == 1.0
    assert np.allclose(scene.R, 100 * np.eye(2))
    assert scene.birth_rate == pytest.approx(0.02 * 5 * 0.5)  # P_B times the expected dead slots
    mean, cov = scene.birth_mean_covar()
    assert np.allclose(mean, [2500, 0, 2500, 0]) and np.allclose(np.diag(cov), [5000**2 / 12, 25, 5000**2 / 12, 25])
    with pytest.raises(ValueError, match="ConstantVelocity"):
        sst.PointScene.from_models(scn.sensor, scn.sensor, scn.existence, 5)


def _one_target_frames(steps=12, seed=0):
    """One target from (1000, 2000) at (3, -2) m/s, 4 points per frame (10 m noise) and 3
    clutter points per frame far from it: z (T, 1, 7, 2)."""
    g = np.random.default_rng(seed)
    t = np.arange(steps)[:, None]
    pos = np.array([1000.0, 2000.0]) + t * np.array([3.0, -2.0])
    pts = pos[:, None, :] + 10 * g.standard_normal((steps, 4, 2))
    clutter = g.uniform(3000, 5000, (steps, 3, 2))
    z = torch.as_tensor(np.concatenate([pts, clutter], 1))[:, None]
    return PointFrame(z, torch.ones(z.shape[:3], dtype=torch.bool)), pos


@pytest.mark.parametrize("kind, settings", [
    ("gmphd", sst.GMPHDSettings(cluster=30.0)), ("gmphd", sst.GMPHDSettings(cluster=None, merge_threshold=16.0)),
    ("jpda", sst.JPDASettings(cluster=30.0)),
])
def test_stonesoup_trackers_follow_an_isolated_target(kind, settings):
    pytest.importorskip("stonesoup")
    frames, pos = _one_target_frames()
    scn = septier(1, 1, generator=torch.Generator().manual_seed(0))
    scene = sst.PointScene.from_models(scn.motion, scn.sensor, scn.existence, 5)
    run = sst.track_run(kind, settings, scene, frames, 0)
    assert len(run.estimates) == 12 and run.step_seconds.shape == (12,) and bool((run.step_seconds > 0).all())
    # from step 4 on: exactly the target, within 15 m (the centroid of 4 points has 5 m noise)
    for t in range(4, 12):
        est = run.estimates[t]
        assert est.shape == (1, 4), (t, est)
        assert np.hypot(est[0, 0] - pos[t, 0], est[0, 2] - pos[t, 1]) < 15.0
    with pytest.raises(ValueError, match="GMPHDSettings"):
        sst.track_run("gmphd", sst.JPDASettings(), scene, frames, 0)
    with pytest.raises(ValueError, match="kind"):
        sst.track_run("mht", settings, scene, frames, 0)


def test_tuning_grid_points_are_valid_settings():
    for name, grid in septier_birth_death.TUNE_GRIDS.items():
        points = septier_birth_death._grid(name, quick=False)
        assert len(points) == math.prod(len(v) for v in grid.values())
        kind, chosen = septier_birth_death.STONESOUP[name]
        assert all(type(p) is type(chosen) for p in points)
        # the settings the study runs are a point of the grid it was tuned on
        assert chosen in points, name
    assert 0 not in septier_birth_death.TUNE_SEEDS  # tuned on other seeds than the study's default


def test_experiment_quick(tmp_path):
    from torchmcmcpf.experiments._options import RunOptions

    study = septier_birth_death.STUDY
    payload = study.run(study.settings(quick=True, runs=2, steps=8, particles=100), RunOptions(out=tmp_path))
    for name in ("metrics.json", "tracks.png", "cardinality.png", "ospa.png"):
        assert (tmp_path / name).exists()
    stored = json.loads((tmp_path / "metrics.json").read_text())
    names = list(septier_birth_death.FILTERS)
    try:
        import stonesoup  # noqa: F401
        names += list(septier_birth_death.STONESOUP)
    except ImportError:
        pass
    assert list(stored["results"]) == names
    for name in names:
        res = stored["results"][name]
        assert len(res["ospa_per_step"]) == 8 and len(stored["true_count_per_step"]) == 8
        # OSPA lies in [0, c]; GOSPA^2 = localisation^2 + c^2 / 2 (missed + false) at every step and run
        assert all(0 <= v <= payload["cutoff"] + 1e-9 for v in res["ospa_per_step"])
        assert res["cardinality_error"] >= 0 and res["seconds_per_step"] > 0
        assert len(res["ospa_thirds"]) == 3 and len(res["seconds_per_step_thirds"]) == 3
        # the thirds (3, 2 and 3 steps) average to the whole
        assert np.dot(res["ospa_thirds"], [3, 2, 3]) / 8 == pytest.approx(res["ospa"])
    text = study.summary(payload)
    assert all(f"| {name} |" in text for name in names) and "per third" in text


def test_gospa_parts_hold_per_run_and_step(tmp_path):
    # the per-run scores of a shard satisfy the GOSPA decomposition exactly
    study = septier_birth_death.STUDY
    cfg = study.settings(quick=True, runs=1, steps=5, particles=50, stonesoup=False)
    per_run, seconds = study.run_shard(cfg, range(2), generator=torch.Generator().manual_seed(0),
                                       device=torch.device("cpu"))
    for name in septier_birth_death.FILTERS:
        g, loc = per_run[f"{name}|gospa"], per_run[f"{name}|localisation"]
        wrong = per_run[f"{name}|missed"] + per_run[f"{name}|false"]
        assert torch.allclose(g.square(), loc.square() + 100.0**2 / 2 * wrong)
        assert set(seconds) >= {f"{name}|{i}" for i in range(3)}
