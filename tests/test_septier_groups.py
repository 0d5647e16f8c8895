"""The septier-groups study (paper 004 Figs. 4-6) in quick mode, into a temporary folder."""

import argparse
import json

import torch

from torchmcmcpf.experiments import discover
from torchmcmcpf.experiments import septier_groups as study


def test_study_quick_writes_figures_and_metrics(tmp_path):
    assert discover()[study.NAME] is study
    parser = argparse.ArgumentParser()
    study.add_arguments(parser)
    args = parser.parse_args(["--beyond"])
    args.quick, args.out, args.device, args.seed, args.progress = True, tmp_path, torch.device("cpu"), 0, False
    args.name = study.NAME
    out = study.run(args)
    for name in ("tracks.png", "structures.png", "existence.png", "ospa.png"):
        assert (tmp_path / name).stat().st_size > 0
    saved = json.loads((tmp_path / "metrics.json").read_text())
    steps = out["config"]["steps"]
    assert len(saved["expected_count_per_step"]) == steps and len(saved["structure_prob_per_step"][0]) == 15
    assert len(saved["merged_structure_first_above_half"]) == out["config"]["runs"]
    assert all(0.0 <= v <= 100.0 for v in saved["ospa_per_step"])
    assert set(saved["beyond"]) >= {"marginalised", "sampled_velocities_and_leaders", "C_chains", "one_chain"}


def test_first_step_above():
    p = torch.tensor([[0.1, 0.9], [0.6, 0.2], [0.7, 0.8]])
    assert study.first_step_above(p, 0.5) == [2, 1]
    assert study.first_step_above(p, 0.5, start=1) == [2, 3]
    assert study.first_step_above(p, 0.95) == [None, None]
