"""Paper-002 scenario (Ling 2016) and the quick ``ling-rmse-vs-snr`` reproduction."""

from __future__ import annotations

import argparse
import json
import math

import pytest
import torch

from torchmcmcpf.experiments import ling_rmse_vs_snr as exp
from torchmcmcpf.scenarios.ling import INITIAL_STATES, ling


def test_scenario_geometry_and_shapes():
    g = torch.Generator().manual_seed(0)
    scn = ling(torch.tensor([4.0, 10.0]), 2, generator=g)
    T, B, K = 35, 2, 3
    assert scn.truth.shape == (T, B, K, 5) and scn.initial.shape == (B, K, 5)
    assert scn.measurements.shape == (T, B) + scn.sensor.frame_shape
    assert scn.range_resolution == 10.0
    # noise-free constant velocity from INITIAL_STATES: truth[t] = F^(t+1) initial
    x0 = torch.tensor(INITIAL_STATES)
    t = torch.arange(1, T + 1, dtype=torch.float32)[:, None]
    torch.testing.assert_close(scn.truth[:, 1, :, 0], x0[:, 0] + t * x0[:, 1])
    torch.testing.assert_close(scn.truth[:, 1, :, 2], x0[:, 2] + t * x0[:, 3])
    pos = scn.truth[..., [0, 2]]
    d23 = (pos[:, :, 1] - pos[:, :, 2]).norm(dim=-1)
    d12 = (pos[:, :, 0] - pos[:, :, 1]).norm(dim=-1)
    assert torch.allclose(d23, torch.tensor(20.0), atol=1e-3)  # close and parallel
    assert d12.min() > 200  # target 1 well separated
    # SNR = P / sigma^2 per run, every target
    torch.testing.assert_close(scn.snr_db, torch.tensor([[4.0] * 3, [10.0] * 3]))
    torch.testing.assert_close(scn.truth[..., 4], scn.sensor.power_from_snr(scn.snr_db)[None].expand(T, B, K))
    # the grid covers every track with the margin
    u = scn.sensor.measurement_coords(scn.truth.double())
    for a in range(2):
        lo, hi = scn.sensor.bins(a)[0], scn.sensor.bins(a)[-1]
        assert (u[..., a] >= lo + 2.5 * scn.sensor.cell_sizes[a]).all()
        assert (u[..., a] <= hi - 2.5 * scn.sensor.cell_sizes[a]).all()


def test_scenario_frames_follow_the_snr():
    """The peak cell of target 1 at a frame is Exp(sigma^2 + P h_peak): over 400 runs its
    mean is within 4 sd (sd = mean / sqrt(400)) of that, and grows with the SNR."""
    g = torch.Generator().manual_seed(1)
    runs = 400
    scn = ling(torch.tensor([0.0, 10.0]).repeat_interleave(runs), 2 * runs, generator=g, num_steps=3,
               dtype=torch.float64)
    A = scn.sensor.signal_grid(scn.truth[2])  # (B, Na, Nr)
    peak = A[0].argmax()
    z = scn.measurements[2].flatten(1)[:, peak]
    for i in range(2):
        m = 1.0 + A[i * runs].flatten()[peak].item()
        assert abs(z[i * runs:(i + 1) * runs].mean().item() - m) <= 4 * m / math.sqrt(runs)


def test_scenario_initial_cloud_and_determinism():
    scn = ling(8.0, 3, generator=torch.Generator().manual_seed(2), num_steps=4)
    again = ling(8.0, 3, generator=torch.Generator().manual_seed(2), num_steps=4)
    assert torch.equal(scn.measurements, again.measurements)
    x = scn.initial_particles(4000, generator=torch.Generator().manual_seed(3))
    assert x.shape == (3, 4000, 3, 5)
    assert torch.equal(x[..., 4], scn.initial[:, None, :, 4].expand(3, 4000, 3))  # power known
    # positions: std 5 m; the sample std of 12000 normals is within 4 * 5 / sqrt(2 * 12000)
    err = (x - scn.initial[:, None])[..., [0, 2]]
    assert abs(err.std().item() - 5.0) <= 4 * 5.0 / math.sqrt(2 * err.numel())


def test_scenario_rejects_bad_arguments():
    g = torch.Generator().manual_seed(0)
    with pytest.raises(ValueError, match=r"snr_db has shape \(2,\), expected \(3,\)"):
        ling(torch.tensor([1.0, 2.0]), 3, generator=g)
    with pytest.raises(ValueError, match="snr_db must be a finite number"):
        ling(float("nan"), 1, generator=g)
    with pytest.raises(ValueError, match="batch_size must be an integer >= 1"):
        ling(5.0, 0, generator=g)
    with pytest.raises(ValueError, match="dt must be > 0"):
        ling(5.0, 1, generator=g, dt=0.0)


def test_quick_reproduction_end_to_end(tmp_path):
    from torchmcmcpf.experiments._options import RunOptions

    payload = exp.STUDY.run(exp.STUDY.settings(quick=True, steps=4), RunOptions(out=tmp_path))
    for f in ("metrics.json", "rmse_vs_snr.png", "tracks.png"):
        assert (tmp_path / f).stat().st_size > 0, f
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["range_resolution_m"] == 10.0 and saved["config"]["quick"]
    assert set(saved["results"]) == {"random_walk", "mixture"}
    for moves, r in saved["results"].items():
        assert [p["snr_db"] for p in r["per_snr"]] == [4.0, 10.0]
        for p in r["per_snr"]:
            # initialised on the truth: finite errors well inside the 51 x 19-cell grid
            assert 0 < p["rmse"] < 100 and p["rmse_matched"] <= p["rmse"] + 1e-6
            assert len(p["rmse_per_step"]) == 4 and len(p["rmse_per_target"]) == 3
            assert p["below_range_resolution"] == (p["rmse"] < 10.0)
            assert all(0 <= v <= 1 for v in p["acceptance"].values())
    assert payload["config"]["rw_scale"] == exp.RW_SCALE


def test_quick_study_is_deterministic():
    cfg = exp.STUDY.settings(quick=True, steps=2, moves=["random_walk"])
    a = exp.run_study(cfg, device=torch.device("cpu"), seed=5)
    b = exp.run_study(cfg, device=torch.device("cpu"), seed=5)
    assert torch.equal(a["estimates"]["random_walk"], b["estimates"]["random_walk"])


def test_settings_map_the_paper_and_validate():
    full = exp.settings(argparse.Namespace(quick=False))  # the notebook's entry point
    sizes = (full["burn_in"], full["thinning"], full["particles"], full["runs"], full["steps"])
    assert sizes == (500, 10, 100, 100, 35)
    with pytest.raises(ValueError, match="--burn-in must be >= 0"):
        exp.STUDY.settings(quick=True, burn_in=-1)
