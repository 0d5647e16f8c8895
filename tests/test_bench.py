"""``python -m torchmcmcpf bench --quick`` and the Stone Soup comparison's model.

The figures themselves are timings (benchmarks/README.md); these tests check that the
command writes its files and that both libraries filter the same model (their posterior
means agree with the exact Kalman filter)."""

import argparse
import json
import math
import time
from pathlib import Path

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
    assert {"radar-sir", "mcmc-pf", "point-sir-B1", "point-sir-step-B1", "point-sir-kernel-B1", "stonesoup-B1",
            "stonesoup-B10", "particles-ours-B4", "particles-B4"} <= set(names)
    by_name = {f["name"]: f for f in result["figures"]}
    assert set(by_name["stonesoup-B1"]["check"]["configurations_s"]) == set(bench.STONESOUP_WEIGHTS)
    for name in ("particles-ours-B4", "particles-B4"):  # the correctness check of the comparison
        err = by_name[name]["check"]["log_evidence_error"]
        assert abs(err["median"]) < 2.0 and err["iqr"] >= 0, (name, err)
    assert any(n.startswith("ipmcmc-") and n.endswith("-B3") for n in names)
    # every radar figure stands next to its arithmetic floor: N K (2w + 1)^3 cell terms for the SIR step
    sir, floor = by_name["radar-sir"], by_name["radar-sir-floor"]
    assert floor["params"]["terms"] == sir["params"]["N"] * sir["params"]["K"] * 7**3 and "x the floor" in sir["note"]
    assert all(f"{n}-floor" in by_name for n in names if n.startswith("ipmcmc-") and not n.endswith("floor"))
    # the MCMC-PF's: N / C iterations per chain of the mixture kernel, in expectation 0.75 K boxes
    # (a joint draw) + 0.25 x 4 K (a refinement sweep: 2 boxes, 2 log ratios per slot)
    mc = by_name["mcmc-pf"]["params"]
    assert by_name["mcmc-pf-floor"]["params"]["terms"] == round(mc["N"] * mc["K"] * 7**3 * 1.75)
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


def test_bench_out_that_is_a_file_is_a_one_line_argument_error(tmp_path, capsys):
    readme = tmp_path / "README.md"
    readme.write_text("x")
    with pytest.raises(SystemExit) as exc:
        main(["bench", "--quick", "--out", str(readme)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "argument --out" in err and "existing file" in err and "Traceback" not in err


def test_bench_writes_under_results_by_default(tmp_path, monkeypatch):
    from torchmcmcpf.__main__ import _bench_parser

    parser = argparse.ArgumentParser()
    _bench_parser(parser.add_subparsers())
    args = parser.parse_args(["bench", "--quick"])
    assert args.out == Path("results") / "bench"  # results/ is ignored by git: the repository stays clean


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


def test_kalman_log_evidence_matches_the_reference_filter():
    # the bench's exact value, against the tests' Kalman filter (its predictive densities)
    B, T = 3, 6
    _, z = bench._point_track(B, T)
    F, Q = cv_matrices(bench.POINT_MODEL["dt"], bench.POINT_MODEL["q"], dtype=torch.float64)
    H = torch.zeros(2, 4, dtype=torch.float64)
    H[0, 0] = H[1, 2] = 1.0
    R = torch.eye(2, dtype=torch.float64)
    m, P = torch.tensor(bench.POINT_M0, dtype=torch.float64).expand(B, 4), torch.eye(4, dtype=torch.float64)
    total = torch.zeros(B, dtype=torch.float64)
    for t in range(T):
        mp, Pp = m @ F.mT, F @ P @ F.mT + Q
        pred = torch.distributions.MultivariateNormal(mp @ H.mT, H @ Pp @ H.mT + R)
        total += pred.log_prob(z[t])
        means, covs = kalman_filter(F, Q, H, R, m, P, z[t:t + 1])
        m, P = means[0], covs[0][0]
    torch.testing.assert_close(bench.kalman_log_evidence(z), total, rtol=0, atol=1e-10)


@pytest.mark.parametrize("library", ["ours", "particles"])
def test_log_evidence_against_kalman(library):
    # both filters of the particles comparison estimate log p(z_1:T) of the same model: over
    # B runs, the median error against the exact value is within a few standard errors of 0
    # (the estimate's sd at N = 1000, T = 10 is about 0.3; its bias -var/2 about -0.05)
    pytest.importorskip("particles")
    B, T, N = 40, 10, 1000
    exact = bench.kalman_log_evidence(bench._point_track(B, T)[1])
    if library == "ours":
        filt, z, x0 = bench.point_filter(N, B, T, torch.device("cpu"), torch.float64)
        log_z = filt(z, init=x0, generator=torch.Generator().manual_seed(4)).log_evidence
    else:
        log_z = bench.particles_runs(N, B, T)()
    err = log_z - exact
    se = 1.2533 * err.std() / math.sqrt(B)  # standard error of a median
    assert abs(float(err.median())) < 4 * float(se) + 0.1, (err.median(), se)


def test_time_interleaved_times_fast_calls_in_blocks_and_slow_ones_alone():
    """A call much shorter than ``block_s`` is timed over a block of consecutive calls (a lone
    call after the garbage collection runs cold); one longer than ``block_s`` alone.
    """
    calls = {"fast": 0, "slow": 0}

    def fast():
        calls["fast"] += 1

    def slow():
        calls["slow"] += 1
        time.sleep(0.03)

    times = bench.time_interleaved({"fast": fast, "slow": slow}, repeats=3, device=torch.device("cpu"),
                                   block_s=0.02, per_call=2)
    assert calls["slow"] == 1 + 1 + 3  # warm-up, the sizing call, one call a round
    assert calls["fast"] > 1 + 1 + 3 and (calls["fast"] - 2) % 3 == 0  # blocks of equal size, each round
    assert times["slow"] >= 0.03 / 2 and times["fast"] < times["slow"]
