"""The septier-groups study (paper 004 Figs. 4-6) in quick mode, into a temporary folder; its
reference filter and ceiling; its command-line errors (issue 25)."""

import json

import pytest
import torch

from torchmcmcpf.__main__ import main
from torchmcmcpf.experiments import discover
from torchmcmcpf.experiments import septier_groups as study
from torchmcmcpf.experiments._options import RunOptions


def test_study_quick_writes_figures_metrics_and_headline(tmp_path):
    assert discover()["septier-groups"] is study.STUDY
    out = study.STUDY.run(study.STUDY.settings(quick=True, beyond=True), RunOptions(out=tmp_path))
    for name in ("tracks.png", "structures.png", "existence.png", "ospa.png"):
        assert (tmp_path / name).stat().st_size > 0
    saved = json.loads((tmp_path / "metrics.json").read_text())
    steps = out["config"]["steps"]
    assert len(saved["expected_count_per_step"]) == steps and len(saved["structure_prob_per_step"][0]) == 15
    assert len(saved["merged_structure_first_above_half"]) == out["config"]["runs"]
    assert all(0.0 <= v <= 100.0 for v in saved["ospa_per_step"])
    assert set(saved["beyond"]) >= {"marginalised", "sampled_velocities_and_leaders", "C_chains", "one_chain"}
    assert len(saved["reference"]["expected_count_per_step"]) == steps
    ceiling = saved["ceiling"]
    assert abs(ceiling["stationary"] - 3.670) < 1e-3 and abs(ceiling["stationary_17db"] - 3.825) < 1e-3
    text = study.STUDY.summary(out)
    assert "| group MCMC-PF (ours) |" in text and "| reference (bootstrap PF per target) |" in text
    assert "| ceiling (pixel known) | 3.31 |" in text  # step 5 from an inactive start, four targets


def test_reference_finds_the_targets():
    """The per-target bootstrap filter on 2 runs: the expected count rises to the ceiling's
    neighbourhood within 12 steps and its estimates sit on the targets."""
    from torchmcmcpf.scenarios.group_merge import group_merge

    g = torch.Generator().manual_seed(3)
    scn = group_merge(2, generator=g, num_steps=12)
    ref = study.reference_filter(scn, 12, 20_000, generator=g)
    assert ref["exists_prob"].shape == (12, 2, 4) and ref["mean"].shape == (12, 2, 4, 2)
    ceiling = study.bayes_limit(scn, 12)
    count = ref["expected_count"].mean(1)
    assert float(count[0]) < 1.0 and abs(float(count[-3:].mean()) - ceiling["stationary"]) < 0.5
    found = ref["exists_prob"][-3:] > 0.5
    err = (ref["mean"][-3:] - scn.positions[9:12]).norm(dim=-1)[found]
    assert found.float().mean() > 0.7 and float(err.median()) < 30.0  # on the targets (a pixel is 50 m)


def test_first_step_above():
    p = torch.tensor([[0.1, 0.9], [0.6, 0.2], [0.7, 0.8]])
    assert study.first_step_above(p, 0.5) == [2, 1]
    assert study.first_step_above(p, 0.5, start=1) == [2, 3]
    assert study.first_step_above(p, 0.95) == [None, None]


@pytest.mark.parametrize("argv,words", [
    (["--particles", "101"], ("--particles", "101", "--chains 10")),  # issue 25: silently dropped to 1 chain
    (["--burn-in", "-5"], ("--burn-in", "-5")),  # issue 25: a traceback
    (["--lag", "2", "--p-past", "0.6", "--xi", "0.6"], ("--xi", "p_past")),
    (["--p-window-birth", "1.5"], ("--p-window-birth", "probability")),
    (["--p-past", "0.2", "--xi", "0.6", "--p-window-birth", "0.3"], ("--xi", "p_window_birth")),
])
def test_bad_arguments_are_one_line_errors(capsys, tmp_path, argv, words):
    with pytest.raises(SystemExit) as exc:
        main(["reproduce", "septier-groups", "--quick", "--out", str(tmp_path / "o"), *argv])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "error:" in line]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert all(w in lines[0] for w in words), lines[0]
