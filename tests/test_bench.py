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
    # a stored run (hand-made, another machine): radar-sir at the quick sizes, 1 ns, so flagged slower
    stored = tmp_path / "stored.json"
    figures = [dict(name="radar-sir", seconds=1e-9, params=dict(N=200, K=2, B=1, compiled=False)),
               dict(name="gone-B7", seconds=1.0, params={})]
    stored.write_text(json.dumps(dict(schema=bench.SCHEMA, quick=True, figures=figures, threads=1,
                                      machine=dict(name="Another CPU (64 logical CPUs)"))))
    saved = tmp_path / "ref" / "reference.json"
    torch.set_num_threads(2)  # not the stored run's count: without --threads, --compare takes the stored one
    assert main(["bench", "--quick", "--out", str(out), "--compare", str(stored), "--save", str(saved)]) == 0
    result = json.loads((out / "bench.json").read_text())
    assert result["threads"] == 1 and result["quick"] and result["torch"] == torch.__version__
    assert result["device"] and result["device_type"] == "cpu"
    # the machine record, and each figure's kind and floor (a figure of the run)
    assert result["schema"] == bench.SCHEMA and result["machine"]["name"] == result["device"]
    assert {"cpu", "cores", "torch", "threads", "date", "device_type"} <= set(result["machine"])
    assert result["machine"]["threads"] == 1 and result["machine"]["cores"] >= 1
    kinds = {f["name"]: f["kind"] for f in result["figures"]}
    assert kinds["radar-sir"] == "ours" and kinds["radar-sir-floor"] == "floor" and kinds["stonesoup-B1"] == "peer"
    assert kinds["point-floor-B1"] == "floor" and kinds["particles-B4"] == "peer" and kinds["point-sir-B1"] == "ours"
    for f in result["figures"]:  # a floor, where named, is a figure of the run, of kind floor
        assert (f["floor"] is None) == (f["floor_s"] is None) and kinds.get(f["floor"], "floor") == "floor"
    floors = {f["name"]: f["floor"] for f in result["figures"]}
    assert floors["radar-sir"] == "radar-sir-floor" and floors["point-sir-step-B10"] == "point-floor-B10"
    # the comparison: in the result, in bench_compare.md, and last on stdout
    cmp = result["comparison"]
    assert cmp["source"] == str(stored) and cmp["slower"] == ["radar-sir"] and cmp["only_stored"] == ["gone-B7"]
    assert "mcmc-pf" in cmp["only_now"] and any("machines differ" in w for w in cmp["warnings"])
    printed = capsys.readouterr().out
    assert printed.startswith(f"--compare: 1 thread, as the stored run {stored} (--threads to change)")
    assert printed.rstrip().splitlines()[-1].startswith(f"vs {stored}: SLOWER: 1 of 1 figures of ours")
    assert "Another CPU (64 logical CPUs)" in printed and "**SLOWER**" in (out / "bench_compare.md").read_text()
    # the saved run is a stored run for a later --compare (without this run's comparison)
    again = bench.load_result(saved)
    assert "comparison" not in again and again["figures"] == result["figures"]
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
    assert "wrote" in printed and f"saved the run to {saved}" in printed


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


# -- the comparison with a stored run (issue 49 item 8): pure, on hand-made results -------------
def _result(figures, name="CPU A (2 logical CPUs)", **top):
    """A minimal bench result: ``figures`` as (name, seconds[, extra fields])."""
    figs = [dict(name=f[0], seconds=f[1], params=dict(N=5000, B=1), **(f[2] if len(f) > 2 else {})) for f in figures]
    return dict(schema=bench.SCHEMA, quick=False, figures=figs,
                machine=dict(name=name, cpu=name, cores=2, torch="2.13.0", threads=1, date="2026-12-04"), **top)


def _floored(floor_s):
    """The fields of a figure of ours with the floor radar-sir-floor (``floor_s``)."""
    return dict(kind="ours", floor="radar-sir-floor", floor_s=floor_s)


STORED = _result([("radar-sir", 0.100, _floored(0.010)), ("radar-sir-floor", 0.010, dict(kind="floor")),
                  ("mcmc-pf", 0.200), ("point-sir-B1", 0.002), ("stonesoup-B1", 0.004, dict(kind="peer")),
                  ("gone", 0.5)])


def test_compare_ratios_now_over_stored_and_flags_ours_only():
    now = _result([("radar-sir", 0.150, _floored(0.011)), ("radar-sir-floor", 0.011, dict(kind="floor")),
                   ("mcmc-pf", 0.205), ("point-sir-B1", 0.001), ("stonesoup-B1", 0.008, dict(kind="peer")),
                   ("new-figure", 0.3)])
    cmp = bench.compare(now, STORED, source="ref.json")
    rows = {r["name"]: r for r in cmp["rows"]}
    assert list(rows) == ["radar-sir", "radar-sir-floor", "mcmc-pf", "point-sir-B1", "stonesoup-B1"]
    assert rows["radar-sir"]["ratio"] == pytest.approx(1.5) and rows["radar-sir"]["flag"] == "slower"
    assert (rows["radar-sir"]["stored_s"], rows["radar-sir"]["now_s"]) == (0.100, 0.150)
    # its multiple of the floor: 15 / 13.6 = 1.5 / 1.1
    assert rows["radar-sir"]["floor_multiple_ratio"] == pytest.approx(1.5 / 1.1)
    assert rows["mcmc-pf"]["ratio"] == pytest.approx(1.025) and rows["mcmc-pf"]["flag"] == ""  # within 1.10
    assert rows["mcmc-pf"]["floor_multiple_ratio"] is None
    assert rows["point-sir-B1"]["flag"] == "faster"
    assert rows["stonesoup-B1"]["ratio"] == pytest.approx(2.0) and rows["stonesoup-B1"]["flag"] == ""  # a peer
    assert rows["radar-sir-floor"]["kind"] == "floor" and rows["radar-sir-floor"]["flag"] == ""
    assert cmp["slower"] == ["radar-sir"] and cmp["faster"] == ["point-sir-B1"]
    assert cmp["only_stored"] == ["gone"] and cmp["only_now"] == ["new-figure"]
    assert cmp["warnings"] == []  # the same machine, torch, threads and sizes; the floor within 1.10x
    assert json.loads(json.dumps(cmp)) == cmp  # kept in bench.json as it is
    # a higher threshold lets radar-sir pass
    assert bench.compare(now, STORED, threshold=1.6)["slower"] == []
    text = bench.comparison_markdown(cmp)
    assert "| radar-sir | ours | 100 | 150 | 1.500 | 1.364 | **SLOWER** |" in text
    assert "Only in the stored run: gone" in text and "Only in this run: new-figure" in text
    assert text.rstrip().splitlines()[-1] == ("vs ref.json: SLOWER: 1 of 3 figures of ours above 1.10x the stored "
                                              "run: radar-sir 1.50x; 1 faster below 0.91x")


def test_compare_without_slower_figures_says_so():
    cmp = bench.compare(STORED, STORED, source="ref.json")
    assert all(r["ratio"] == 1 and r["flag"] == "" for r in cmp["rows"]) and not cmp["only_now"] + cmp["only_stored"]
    assert bench.comparison_summary(cmp) == ("vs ref.json: no figure of ours above 1.10x the stored run (4 compared, "
                                             "median ratio 1.00)")


def test_compare_warns_when_the_machines_differ_naming_both():
    now = _result([("radar-sir", 0.1), ("mcmc-pf", 0.2)], name="CPU B (16 logical CPUs)")
    now["machine"].update(torch="2.14.0", threads=2)
    now["quick"] = True
    warnings = bench.compare(now, STORED)["warnings"]
    assert any("machines differ" in w and "CPU A (2 logical CPUs)" in w and "CPU B (16 logical CPUs)" in w
               for w in warnings), warnings
    assert any("torch versions differ: stored 2.13.0, now 2.14.0" in w for w in warnings)
    assert any("thread counts differ: stored 1, now 2" in w for w in warnings)
    assert any("sizes differ: stored at full sizes, now at --quick sizes" in w for w in warnings)
    text = bench.comparison_markdown(bench.compare(now, STORED))
    assert text.count("warning: ") == len(warnings) and "(4 warnings above)" in text


def test_compare_marks_changed_settings_instead_of_flagging_them():
    now = _result([("radar-sir", 0.5)])
    now["figures"][0]["params"] = dict(N=10000, B=1)
    row = bench.compare(now, STORED)["rows"][0]
    assert row["flag"] == "settings differ" and row["settings"] == {"N": [5000, 10000]}
    assert bench.compare(now, STORED)["slower"] == []
    assert "settings differ: N 5000 -> 10000" in bench.comparison_markdown(bench.compare(now, STORED))


def test_compare_warns_when_the_floors_moved():
    now = _result([("radar-sir", 0.130, _floored(0.013)), ("radar-sir-floor", 0.013, dict(kind="floor"))])
    cmp = bench.compare(now, STORED)
    assert cmp["slower"] == ["radar-sir"] and cmp["rows"][0]["floor_multiple_ratio"] == pytest.approx(1.0)
    assert any("floors themselves take 1.30x" in w and "busier or slower" in w for w in cmp["warnings"])


def test_a_stored_bench_json_of_before_the_machine_record_still_compares():
    # bench.json as written before issue 49: no schema, machine, kind or floor; kinds from the names
    legacy = dict(device="CPU A (2 logical CPUs)", device_type="cpu", torch="2.13.0", threads=1, quick=False,
                  figures=[dict(name=n, seconds=s, params={}) for n, s in
                           (("radar-sir", 0.1), ("radar-sir-floor", 0.01), ("point-floor-B1", 0.001),
                            ("stonesoup-B1", 0.002), ("particles-B100", 0.01), ("particles-ours-B100", 0.001))])
    checked = bench.check_result(legacy)
    assert checked["machine"] == dict(name="CPU A (2 logical CPUs)", device_type="cpu", torch="2.13.0", threads=1)
    assert [bench.figure_kind(f) for f in checked["figures"]] == ["ours", "floor", "floor", "peer", "peer", "ours"]
    assert bench.compare(legacy, legacy)["warnings"] == []


@pytest.mark.parametrize("content, message", [
    (None, "does not exist"),
    ("not json {", "is not JSON"),
    ("[1, 2]", "expected a JSON object with 'figures', got list"),
    ('{"device": "x"}', "expected a list 'figures', got none"),
    ('{"figures": []}', "holds no figures"),
    ('{"schema": "torchmcmcpf.bench/0", "figures": [{"name": "a", "seconds": 1}]}', "has schema"),
    ('{"figures": [{"seconds": 1}]}', "figures[0] has no 'name'"),
    ('{"figures": [{"name": "a", "seconds": -1}]}', "figure 'a' has seconds -1"),
    ('{"figures": [{"name": "a", "seconds": "1"}]}', "figure 'a' has seconds '1'"),
    ('{"figures": [{"name": "a", "seconds": 1}, {"name": "a", "seconds": 2}]}', "figure 'a' appears twice"),
    ('{"figures": [{"name": "a", "seconds": 1}], "machine": "x"}', "'machine' is str"),
])
def test_load_result_refuses_a_bad_file_naming_it(tmp_path, content, message):
    path = tmp_path / "stored.json"
    if content is not None:
        path.write_text(content)
    with pytest.raises(ValueError, match=r"stored\.json") as err:
        bench.load_result(path)
    assert message in str(err.value)


def test_compare_refuses_a_threshold_not_above_1():
    with pytest.raises(ValueError, match="threshold"):
        bench.compare(STORED, STORED, threshold=1.0)


@pytest.mark.parametrize("argv, message", [
    (["--compare", "{tmp}/missing.json"], "argument --compare: '{tmp}/missing.json' does not exist"),
    (["--compare", "{tmp}/bad.json"], "argument --compare: '{tmp}/bad.json' is not JSON"),
    (["--compare", "{tmp}/empty.json"], "argument --compare: '{tmp}/empty.json' holds no figures"),
    (["--threshold", "1.2"], "argument --threshold: needs --compare"),
    (["--compare", "{tmp}/empty.json", "--threshold", "1"], "argument --threshold: '1' is not a ratio above 1"),
    (["--save", "{tmp}"], "argument --save: '{tmp}' is a directory"),
    (["--save"], "argument --save: a --quick run is no reference"),
])
def test_bench_compare_and_save_errors_are_one_line_before_any_timing(tmp_path, capsys, monkeypatch, argv, message):
    (tmp_path / "bad.json").write_text("{")
    (tmp_path / "empty.json").write_text('{"figures": []}')
    monkeypatch.setattr(bench, "run", lambda *a, **k: pytest.fail("the bench ran"))
    with pytest.raises(SystemExit) as exc:
        main(["bench", "--quick", "--out", str(tmp_path / "out"), *(a.format(tmp=tmp_path) for a in argv)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert message.format(tmp=tmp_path) in err and "Traceback" not in err
    assert [line for line in err.splitlines() if "error:" in line] == [err.splitlines()[-1]]


def test_the_stored_reference_lives_in_benchmarks_by_device():
    assert bench.reference_path("cpu").parts[-2:] == ("benchmarks", "reference-cpu.json")
    assert bench.reference_path("cuda").name == "reference-cuda.json"
    assert bench.reference_path().parent == Path(__file__).resolve().parent.parent / "benchmarks"


def test_bench_compare_without_file_reads_the_reference_of_the_device(tmp_path, capsys, monkeypatch):
    asked = []
    monkeypatch.setattr(bench, "reference_path", lambda device: asked.append(device) or tmp_path / "ref.json")
    monkeypatch.setattr(bench, "run", lambda *a, **k: pytest.fail("the bench ran"))
    with pytest.raises(SystemExit):
        main(["bench", "--quick", "--out", str(tmp_path / "out"), "--compare"])
    assert asked == ["cpu"]
    assert f"argument --compare: '{tmp_path / 'ref.json'}' does not exist" in capsys.readouterr().err
