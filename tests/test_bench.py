"""``python -m torchmcmcpf bench --quick`` and the Stone Soup comparison's model.

The figures themselves are timings (benchmarks/README.md); these tests check that the
command writes its files and that both libraries filter the same model (their posterior
means agree with the exact Kalman filter)."""

import json
import math

import numpy as np
import pytest
import torch

from tests._kalman import kalman_filter
from torchmcmcpf import bench
from torchmcmcpf.__main__ import main
from torchmcmcpf.models.motion import cv_matrices


@pytest.fixture
def restore_threads():
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def test_bench_quick_writes_table_json_and_plot(tmp_path, capsys, restore_threads):
    out = tmp_path / "bench"
    assert main(["bench", "--quick", "--threads", "1", "--out", str(out)]) == 0
    result = json.loads((out / "bench.json").read_text())
    assert result["threads"] == 1 and result["quick"] and result["torch"] == torch.__version__
    assert result["device"] and result["device_type"] == "cpu"
    names = [f["name"] for f in result["figures"]]
    assert {"radar-sir", "mcmc-pf", "point-sir-B1", "stonesoup-B1", "stonesoup-B10"} <= set(names)
    assert any(n.startswith("ipmcmc-") and n.endswith("-B3") for n in names)
    for f in result["figures"]:
        assert f["seconds"] > 0 and math.isclose(f["per_run_s"], f["seconds"] / f["params"].get("B", 1))
        assert f["target_s"] is None  # the targets are for the full sizes only
    assert set(result["scaling"]) == {"N", "K", "B"}
    for lines in result["scaling"].values():
        for d in lines.values():
            assert len(d["values"]) == len(d["seconds"]) and all(t > 0 for t in d["seconds"])
    table = (out / "bench.md").read_text()
    assert "| radar-sir |" in table and "1 threads" in table
    assert (out / "bench_scaling.png").stat().st_size > 0
    assert "wrote" in capsys.readouterr().out


def test_bench_cuda_without_gpu_is_an_argument_error():
    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    with pytest.raises(SystemExit, match="--device"):
        main(["bench", "--quick", "--device", "cuda"])


@pytest.mark.parametrize("library", ["ours", "stonesoup"])
def test_point_sir_matches_kalman(library):
    # Same model in both libraries: after T steps the particle mean of every run is within
    # the Monte Carlo error of the exact Kalman mean. A resampled SIR mean has variance of
    # order P / N times an inflation from resampling over T steps (a few); we allow 6
    # standard errors with an inflation of 4.
    pytest.importorskip("stonesoup")
    N, B, T = 2000, 4, 5
    np.random.seed(0)  # Stone Soup draws from numpy's global generator
    step = (bench.point_sir_step(N, B, T, torch.device("cpu"), dtype=torch.float64) if library == "ours"
            else bench.stonesoup_step(N, B, T))
    for _ in range(T):
        state = step()
    if library == "ours":
        w = state.log_w.exp()
        mean = (w[..., None] * state.x[:, :, 0]).sum(1)  # (B, 4)
    else:
        mean = torch.tensor(np.stack([np.asarray(s.state_vector, dtype=float).mean(1) for s in state]))
    _, z = bench._point_track(B, T)
    F, Q = cv_matrices(bench.POINT_MODEL["dt"], bench.POINT_MODEL["q"], dtype=torch.float64)
    H = torch.zeros(2, 4, dtype=torch.float64)
    H[0, 0] = H[1, 2] = 1.0
    R = bench.POINT_MODEL["noise_std"] ** 2 * torch.eye(2, dtype=torch.float64)
    m0 = torch.tensor([0.0, 1.0, 0.0, 1.0], dtype=torch.float64).expand(B, 4)
    means, covs = kalman_filter(F, Q, H, R, m0, torch.eye(4, dtype=torch.float64), z)
    se = torch.sqrt(4.0 * torch.diagonal(covs[-1], dim1=-2, dim2=-1) / N)
    assert torch.all((mean - means[-1]).abs() <= 6 * se), (mean, means[-1], se)
