"""The group-merge scenario (Septier et al. 2009, sec. 5) and its study's quick mode."""

from __future__ import annotations

import argparse
import json
import math

import pytest
import torch

from torchmcmcpf.models.group import group_structures
from torchmcmcpf.scenarios import group_merge


@pytest.fixture(scope="module")
def scn():
    return group_merge(6, generator=torch.Generator().manual_seed(3))


def test_shapes_and_structures(scn):
    t, b, k = 110, 6, 4
    assert scn.truth.shape == scn.leaders.shape == (t, b, k, 4)
    assert scn.exists.shape == scn.labels.shape == (t, b, k) and scn.exists.all()
    assert scn.frames.shape == (t, b, 100, 100) and scn.frames.dtype == torch.bool
    assert scn.merge_step == 45
    table = group_structures(4)
    assert (table[scn.structure[:45]] == torch.tensor([0, 0, 1, 1])).all()
    assert (table[scn.structure[45:]] == torch.tensor([0, 0, 0, 0])).all()
    assert torch.equal(table[scn.structure], scn.labels)
    # one track set for all runs (the paper's 40 observation sets of one scenario)
    assert torch.equal(scn.truth, scn.truth[:, :1].expand_as(scn.truth))
    assert not torch.equal(scn.frames[:, 0], scn.frames[:, 1])


def test_tracks_converge_merge_and_stay_in_the_scene(scn):
    pos = scn.positions[:, 0]  # (T, K, 2)
    assert ((pos >= 0) & (pos <= 5000)).all()
    centre_a, centre_b = pos[:, :2].mean(1), pos[:, 2:].mean(1)
    gap = (centre_a - centre_b).norm(dim=-1)
    assert gap[0] > 1000 and gap[45:].max() < 400  # far apart at first, together after the merge
    d = (pos.unsqueeze(1) - pos.unsqueeze(2)).norm(dim=-1) + 1e9 * torch.eye(4)
    assert d.min() > 50  # the repulsion keeps members about a pixel apart or more
    # merge rule (eq. 38) with noise-free leaders: the merged leader is the average, propagated
    v44 = scn.leaders[44, 0]
    avg = 0.5 * (v44[0] + v44[1])
    F = scn.motion.F_ll
    for axis in range(2):
        got = scn.leaders[45, 0, 0, [2 * axis, 2 * axis + 1]]
        torch.testing.assert_close(got, F @ avg[[2 * axis, 2 * axis + 1]], rtol=1e-12, atol=1e-9)


def test_detection_and_false_alarm_rates(scn):
    """Pooled over runs, steps and targets: P_d,1 = 0.7 in target pixels (none shared here),
    P_fa = 0.002 elsewhere, within 5 standard errors."""
    idx = scn.sensor.pixel_index(scn.truth, scn.exists)  # (T, B, K)
    t, b, k = idx.shape
    flat = scn.frames.reshape(t, b, -1)
    hits = torch.gather(flat, 2, idx).double()
    n = hits.numel()
    assert abs(float(hits.mean()) - 0.7) < 5 * math.sqrt(0.21 / n)
    on_target = torch.zeros_like(flat).scatter_(2, idx, True)
    fa = (flat & ~on_target).sum().double() / (~on_target).sum()
    m = float((~on_target).sum())
    assert abs(float(fa) - 0.002) < 5 * math.sqrt(0.002 * 0.998 / m)


def test_same_seed_same_scenario_and_options():
    a = group_merge(2, generator=torch.Generator().manual_seed(5), num_steps=20)
    b = group_merge(2, generator=torch.Generator().manual_seed(5), num_steps=20)
    assert torch.equal(a.truth, b.truth) and torch.equal(a.frames, b.frames)
    c = group_merge(2, generator=torch.Generator().manual_seed(5), num_steps=50, num_slots=6, same_tracks=False,
                    leader_noise=True)
    assert c.truth.shape == (50, 2, 6, 4) and not c.exists[..., 4:].any()
    assert (c.truth[..., 4:, :] == 0).all()
    assert not torch.equal(c.truth[:, 0], c.truth[:, 1])
    with pytest.raises(ValueError, match="num_slots"):
        group_merge(2, generator=torch.Generator(), num_slots=3)


def test_study_quick_writes_figure_and_metrics(tmp_path):
    from torchmcmcpf.experiments import group_merge_scenario as study
    from torchmcmcpf.experiments._options import RunOptions

    parser = argparse.ArgumentParser()
    study.STUDY.add_arguments(parser)  # the options derived from the settings: none given, quick values
    settings = study.STUDY.settings_from({**vars(parser.parse_args([])), "quick": True})
    assert (settings.runs, settings.slots) == (2, 4)
    out = study.STUDY.run(settings, RunOptions(out=tmp_path))
    assert (tmp_path / "tracks.png").stat().st_size > 0
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["snr_db"] == pytest.approx(12.15, abs=0.01)
    assert out["merge_step"] == 46


def test_generator_is_keyword_only():
    """DESIGN.md: every function that draws takes ``generator=`` by keyword."""
    with pytest.raises(TypeError):
        group_merge(2, torch.Generator().manual_seed(0))  # type: ignore[misc]
