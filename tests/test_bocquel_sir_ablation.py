"""The quick SIR ablation (bocquel-sir-ablation) runs end to end: every factor, both
readings of eq. 20 and both SNR conventions, one row each."""

import json
import math

import pytest
import torch

from torchmcmcpf.experiments import bocquel_sir_ablation as exp
from torchmcmcpf.experiments._options import RunOptions
from torchmcmcpf.scenarios.ground_radar import ground_radar


def test_quick_ablation_end_to_end(tmp_path):
    settings = exp.STUDY.settings(quick=True)
    payload = exp.STUDY.run(settings, RunOptions(out=tmp_path))
    saved = json.loads((tmp_path / "metrics.json").read_text())
    rows = saved["results"]
    assert len(rows) == len(exp.cells(settings)) == 2 + 1 + 1 + 3  # K, Np, spread, reading x SNR
    assert {(r["point_spread"], r["snr"]) for r in rows.values()} == {
        ("std", "half"), ("std", "full"), ("variance", "half"), ("variance", "full")}
    for r in rows.values():
        assert 0 <= r["rmse"] < 100 and 0 <= r["tlr"] <= 1 and 1 <= r["ess"] <= r["particles"]
    assert "variance" in (tmp_path / "ablation.md").read_text()
    assert (tmp_path / "ablation.png").stat().st_size > 10_000  # RMSE and ESS against the number of targets
    assert exp.STUDY.summary(payload).count("|") > 20


def test_point_spread_readings_and_snr_shift():
    g = torch.Generator().manual_seed(0)
    std = ground_radar(1, 2, 1, generator=g).sensor
    var = ground_radar(1, 2, 1, generator=g, point_spread="variance").sensor
    assert std.widths == pytest.approx((10.0, 2.0, math.pi / 180))
    assert var.widths == pytest.approx((math.sqrt(10.0), math.sqrt(2.0), math.sqrt(math.pi / 180)))
    assert var.method == "grid"  # the 7.6 deg bearing spread does not fit a window
    # SNR = rho^2 / sigma^2 at S dB is rho^2 / (2 sigma^2) at S - 3.01 dB
    rho = std.amplitude_from_snr(12.0 + exp.SNR_SHIFT["full"])
    assert rho**2 / std.noise_std**2 == pytest.approx(10 ** 1.2)
    with pytest.raises(ValueError, match="point_spread"):
        ground_radar(1, 2, 1, generator=g, point_spread="fwhm")
