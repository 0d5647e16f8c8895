"""The birth/death scenario of paper 001 and its experiment."""

import argparse
import json
import math

import torch

from torchmcmcpf.experiments import septier_birth_death
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


def test_experiment_quick(tmp_path):
    args = argparse.Namespace(name=septier_birth_death.NAME, quick=True, out=tmp_path, device=torch.device("cpu"),
                              seed=0, progress=False, runs=2, steps=8, particles=100)
    payload = septier_birth_death.run(args)
    for name in ("metrics.json", "tracks.png", "cardinality.png", "ospa.png"):
        assert (tmp_path / name).exists()
    stored = json.loads((tmp_path / "metrics.json").read_text())
    res = stored["results"]["SIR PF"]
    assert len(res["ospa_per_step"]) == 8 and len(stored["true_count_per_step"]) == 8
    # OSPA lies in [0, c]
    assert all(0 <= v <= payload["cutoff"] + 1e-9 for v in res["ospa_per_step"])
    assert res["cardinality_error"] >= 0
