import argparse
import json
import math
import re
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from torchmcmcpf import experiments
from torchmcmcpf.__main__ import main
from torchmcmcpf.experiments import Study
from torchmcmcpf.experiments._options import RunOptions
from torchmcmcpf.experiments._shards import ShardError, run_shards, shard_generator

TESTS = Path(__file__).resolve().parent


def test_demo_small_writes_metrics_and_figure(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--particles", "64", "--chains", "8", "--burn-in", "10", "--runs", "1", "--steps", "5",
                 "--targets", "2", "--out", out, "--no-progress"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    s = m["settings"]
    assert m["filter"] == "IPMCMCFilter"  # the default is the flagship filter
    assert (s["particles"], s["runs"], s["steps"], s["targets"], s["seed"], s["chains"]) == (64, 1, 5, 2, 0, 8)
    assert m["device"].startswith("cpu")
    assert len(m["rmse_per_step_m"]) == 5 and len(m["lost_runs"]) == 1
    # overall RMSE^2 is the mean of the per-step RMSE^2 (equal counts per step)
    ms = sum(v * v for v in m["rmse_per_step_m"]) / 5
    assert m["rmse_overall_m"] == pytest.approx(math.sqrt(ms), rel=1e-5)
    assert m["track_loss_rate"] in (0.0, 1.0) and m["seconds_per_step"] > 0
    assert (out / "tracks.png").stat().st_size > 1000
    printed = capsys.readouterr().out
    assert "position RMSE" in printed and "track loss rate" in printed


def test_demo_runs_sir_baseline(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--filter", "sir", "--particles", "40", "--runs", "1", "--steps", "2",
                 "--targets", "2", "--out", out, "--no-progress"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["filter"] == "SIRFilter" and len(m["rmse_per_step_m"]) == 2
    assert "SIRFilter" in capsys.readouterr().out


def assert_one_line_error(capsys, argv, *words):
    """argv exits with status 2 and a single ``error:`` line holding every word (no traceback)."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "error:" in line]
    assert len(lines) == 1 and "Traceback" not in err, err
    for word in words:
        assert word in lines[0], (word, lines[0])


def test_demo_rejects_particles_not_divisible_by_chains(capsys):
    assert_one_line_error(capsys, ["demo", "--particles", "100", "--chains", "30"], "--particles", "--chains 30")
    assert_one_line_error(capsys, ["demo", "--particles", "50"], "--particles", "--chains 50", "at least 2")
    assert_one_line_error(capsys, ["demo", "--chains", "0"], "--chains")
    assert_one_line_error(capsys, ["demo", "--burn-in", "-1"], "--burn-in")
    assert_one_line_error(capsys, ["reproduce", "bocquel-table2", "--particles", "45"], "--particles", "chains")


def test_out_errors_and_replacement_note(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert_one_line_error(capsys, ["demo", "--out", afile], "--out", "existing file")
    assert_one_line_error(capsys, ["demo", "--out", afile / "sub"], "--out", "is a file")
    assert_one_line_error(capsys, ["reproduce", "bocquel-table2", "--out", afile], "--out", "existing file")
    out = tmp_path / "demo"
    argv = ["demo", "--filter", "sir", "--particles", "20", "--runs", "1", "--steps", "2", "--targets", "1",
            "--out", out, "--no-progress"]
    assert main(argv) == 0
    assert "replacing" not in capsys.readouterr().out
    assert main(argv) == 0
    assert "replacing metrics.json, tracks.png" in capsys.readouterr().out


def test_bad_arguments_name_the_argument(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--particles", "0"])
    assert exc.value.code == 2
    assert "--particles" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["demo", "--runs", "two"])
    assert "--runs" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["reproduce", "no-such-experiment"])
    assert "no-such-experiment" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["demo", "--filter", "kalman"])
    assert "--filter" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([])


@pytest.fixture
def fake_experiment(tmp_path, monkeypatch):
    """A throwaway experiment module dropped next to the real ones (discovery test)."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "fake_study.py").write_text(textwrap.dedent('''
        """A new study is one file: its settings, what it computes, its instance."""
        from dataclasses import dataclass

        from torchmcmcpf.experiments._study import Settings, Study, option


        @dataclass(frozen=True)
        class FakeSettings(Settings):
            level: int = option(1, 2, help="a level")


        class Fake(Study[FakeSettings]):
            name = "fake-study"
            description = "a throwaway study used by tests/test_cli.py"

            def compute(self, settings, options):
                return {"quick": settings.quick, "level": settings.level, "seed": options.seed,
                        "device_type": options.device.type, "progress": options.progress}


        STUDY = Fake()
    '''))
    monkeypatch.setattr(experiments, "__path__", [*experiments.__path__, str(pkg)])
    yield "fake-study"
    sys.modules.pop("torchmcmcpf.experiments.fake_study", None)


def test_reproduce_help_lists_the_common_options(capsys):
    assert main(["reproduce", "--help"]) == 0
    text = capsys.readouterr().out
    for option in ("--list", "--quick", "--out", "--device", "--seed", "--threads", "--no-progress",
                   "--shard-size", "--workers", "--ray-address"):
        assert option in text, option
    for name in experiments.discover():
        assert name in text


@pytest.mark.parametrize("name", ["bocquel-table2", "bocquel-sir-ablation", "ling-rmse-vs-snr", "maroulas-hmc",
                                  "septier-birth-death"])
def test_study_help_states_the_settings_that_run(name, capsys):
    """Every ``(default X, quick Y)`` in a study's --help is read from its settings' fields."""
    from dataclasses import fields

    study = experiments.discover()[name]
    with pytest.raises(SystemExit) as exc:
        main(["reproduce", name, "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())  # undo argparse's line wrapping
    assert ("--shard-size" in text) == study.sharded
    checked = 0
    for f in fields(study.settings_type):
        option = "--" + f.name.replace("_", "-")
        if f.metadata.get("cli", True) and "(default" not in f.metadata["help"] and not isinstance(f.default, bool):
            assert option in text, option
            expected = f"({study.defaults_text(f.name)})"
            assert expected in text, (option, expected)
            checked += 1
    assert checked >= 3
    assert re.search(r"quick \d", text)
    if study.sharded:
        assert "--shard-size SHARD_SIZE Monte Carlo runs per shard" in text
        assert f"({study.defaults_text('shard_size')})" in text


def test_settings_declare_quick_and_full_values_once():
    """Quick and full values come from one declaration; given values win; settings are frozen."""
    import dataclasses

    study = experiments.discover()["crossing"]
    full, quick = study.settings(), study.settings(quick=True)
    assert (full.runs, full.particles, full.quick) == (20, 500, False)
    assert (quick.runs, quick.particles, quick.quick) == (2, 100, True)
    assert study.settings(quick=True, runs=7, steps=None).runs == 7  # None: not given
    with pytest.raises(dataclasses.FrozenInstanceError):
        quick.runs = 3
    with pytest.raises(ValueError, match="--particles"):
        study.settings(particles=105)
    with pytest.raises(TypeError, match="no setting"):
        study.settings(walkers=3)


def test_reproduce_list_and_run(fake_experiment, tmp_path, capsys):
    assert main(["reproduce", "--list"]) == 0
    listed = capsys.readouterr().out
    assert "fake-study" in listed and "a throwaway study" in listed
    out = tmp_path / "res"
    assert main(["reproduce", "fake-study", "--quick", "--out", out, "--seed", "5", "--level", "3",
                 "--no-progress"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert (m["quick"], m["level"], m["seed"], m["device_type"], m["progress"]) == (True, 3, 5, "cpu", False)
    assert m["settings"]["name"] == "fake-study" and m["device"].startswith("cpu")
    p = m["provenance"]  # what traces the file to the run that made it
    assert p["command"].endswith("reproduce fake-study --quick --out " + str(out) + " --seed 5 --level 3 --no-progress")
    assert p["seed"] == 5 and p["threads"] >= 1 and p["wall_seconds"] > 0 and p["device"].startswith("cpu")
    assert p["versions"]["torch"] == torch.__version__ and p["versions"]["torchmcmcpf"]
    printed = capsys.readouterr().out
    assert "fake-study" in printed and "QUICK RUN" in printed and "not comparable" in printed  # issue 52


# ------------------------------------------------------------------ shards and Ray


def _toy_args(tmp_path, **kw):
    return RunOptions(**{"seed": 3, "out": tmp_path, **kw})


def _toy(**given):
    import _shard_study as toy

    return toy.STUDY, toy.STUDY.settings(**given)


def test_shard_streams_depend_on_shard_size_not_grouping(tmp_path):
    a = run_shards(*_toy(runs=5, shard_size=2), _toy_args(tmp_path / "a"))
    assert a.layout["num_shards"] == 3 and a.layout["shard_size"] == 2
    assert torch.equal(a.per_run["run"], torch.arange(5)) and a.per_run["draws"].shape == (5, 3)
    assert a.seconds == {"toy": 1.5}
    # shard i draws from the generator of (seed, i), whatever ran before it
    first = torch.rand(2, 3, generator=shard_generator("cpu", 3, 1))
    assert torch.equal(a.per_run["draws"][2:4], first)
    b = run_shards(*_toy(runs=5, shard_size=1), _toy_args(tmp_path / "b"))
    assert not torch.equal(a.per_run["draws"], b.per_run["draws"])  # a different layout is a different study
    assert len(list((tmp_path / "a" / "shards").glob("shard-*.pt"))) == 3


def test_interrupted_study_resumes_from_its_shards(tmp_path):
    with pytest.raises(ShardError, match=r"shard-toy: shard 2 \(runs 4\.\.4\) failed: FloatingPointError: run 4"):
        run_shards(*_toy(runs=5, shard_size=2, fail_run=4), _toy_args(tmp_path))
    # the two shards written before the failure are stored, but under other settings: rerun
    args = _toy_args(tmp_path)
    full = run_shards(*_toy(runs=5, shard_size=2), args)
    assert full.layout["resumed"] == 0
    again = run_shards(*_toy(runs=5, shard_size=2), args)
    assert again.layout["resumed"] == 3 and torch.equal(again.per_run["draws"], full.per_run["draws"])
    other_seed = run_shards(*_toy(runs=5, shard_size=2), _toy_args(tmp_path, seed=4))
    assert other_seed.layout["resumed"] == 0


@pytest.fixture(scope="module")
def ray_cluster():
    """One local Ray cluster of 2 CPUs for the tests below (no dashboard); run_shards joins
    it instead of starting its own. Workers import the package and tests/_shard_study.py."""
    ray = pytest.importorskip("ray")
    root = str(TESTS.parent)
    ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR", log_to_driver=False,
             runtime_env={"env_vars": {"PYTHONPATH": f"{root}:{TESTS}", "OMP_NUM_THREADS": "1"}})
    yield ray
    ray.shutdown()


def _strip_timings(obj):
    """metrics.json without what legitimately differs between two runs of one study: the
    provenance, the settings (--out, --workers) and every time in seconds."""
    if isinstance(obj, dict):
        return {k: _strip_timings(v) for k, v in obj.items()
                if k not in ("provenance", "settings") and "seconds" not in k}
    if isinstance(obj, list):
        return [_strip_timings(v) for v in obj]
    return obj


def test_ray_workers_write_the_same_metrics(ray_cluster, tmp_path, capsys):
    """Done-when of issue 14: reproduce bocquel-table2 --quick with and without --workers 2."""
    common = ["reproduce", "bocquel-table2", "--quick", "--no-progress", "--steps", "2"]
    assert main([*common, "--out", tmp_path / "here"]) == 0
    assert main([*common, "--out", tmp_path / "ray", "--workers", "2"]) == 0
    printed = capsys.readouterr().out
    assert "| IP-MCMC-PF |" in printed and "paper RMSE" in printed  # the headline table
    here = json.loads((tmp_path / "here" / "metrics.json").read_text())
    ray_ = json.loads((tmp_path / "ray" / "metrics.json").read_text())
    assert _strip_timings(here) == _strip_timings(ray_)
    layout = ray_["provenance"]["shards"]
    assert (layout["num_shards"], layout["shard_size"], layout["workers"]) == (2, 1, 2)
    assert here["provenance"]["shards"]["workers"] is None and ray_["provenance"]["versions"]["ray"]


def test_ray_failing_shard_names_the_shard(ray_cluster, tmp_path):
    args = _toy_args(tmp_path, workers=2)
    with pytest.raises(ShardError, match=r"shard 1 \(runs 2\.\.3\) failed: FloatingPointError"):
        run_shards(*_toy(runs=6, shard_size=2, fail_run=3), args)
    # shards that could never be placed (a GPU each, none in the cluster) fail at once, no hang
    with pytest.raises(ShardError, match="GPUs"):
        run_shards(*_toy(runs=2, shard_size=1), _toy_args(tmp_path / "gpu", workers=2,
                                                                device=torch.device("cuda")))
    here = run_shards(*_toy(runs=6, shard_size=2), _toy_args(tmp_path / "here"))
    there = run_shards(*_toy(runs=6, shard_size=2), _toy_args(tmp_path / "there", workers=2))
    assert torch.equal(here.per_run["draws"], there.per_run["draws"])


def test_without_workers_ray_is_not_imported(tmp_path):
    """A fresh interpreter: a study without --workers never imports Ray."""
    import subprocess

    code = ("import sys; from torchmcmcpf.__main__ import main; "
            f"main(['reproduce', 'bocquel-table2', '--quick', '--runs', '1', '--steps', '1', '--no-progress', "
            f"'--out', {str(tmp_path)!r}]); print('ray' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], cwd=TESTS.parent, capture_output=True, text=True,
                          timeout=300, env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "False"


# ------------------------------------------------------------------ the first hour (issue 25)


def test_study_argument_errors_are_one_line(capsys):
    assert_one_line_error(capsys, ["reproduce", "bocquel-table2", "--quick", "--max-extensions", "-1"],
                          "--max-extensions", ">= 0")
    assert_one_line_error(capsys, ["reproduce", "ling-rmse-vs-snr", "--quick", "--burn-in", "-2"], "--burn-in")


@pytest.fixture
def failing_experiment(tmp_path, monkeypatch):
    """A study whose run raises the errors a real one can: a ValueError from a model, a shard failure."""
    pkg = tmp_path / "pkg_fail"
    pkg.mkdir()
    (pkg / "failing_study.py").write_text(textwrap.dedent('''
        from dataclasses import dataclass

        from torchmcmcpf.experiments._shards import ShardError
        from torchmcmcpf.experiments._study import Settings, Study, option


        @dataclass(frozen=True)
        class FailingSettings(Settings):
            kind: str = option("value", help="how to fail")


        class Failing(Study[FailingSettings]):
            name = "failing-study"
            description = "a study that fails (tests/test_cli.py)"

            def compute(self, settings, options):
                if settings.kind == "value":
                    raise ValueError("num_chains=30 must divide num_particles=100")
                raise ShardError("failing-study: shard 2 (runs 2..2) failed: RuntimeError: out of memory\\nsecond line")


        STUDY = Failing()
    '''))
    monkeypatch.setattr(experiments, "__path__", [*experiments.__path__, str(pkg)])
    yield "failing-study"
    sys.modules.pop("torchmcmcpf.experiments.failing_study", None)


def test_run_errors_are_one_line_unless_asked_for_the_traceback(failing_experiment, tmp_path, capsys, monkeypatch):
    argv = ["reproduce", failing_experiment, "--out", tmp_path]
    assert_one_line_error(capsys, argv, "failing-study: error:", "num_chains=30", "TORCHMCMCPF_TRACEBACK=1")
    with pytest.raises(SystemExit) as exc:  # a shard that failed for another reason: one line, status 1
        main([*argv, "--kind", "shard"])
    err = capsys.readouterr().err
    assert exc.value.code == 1 and "Traceback" not in err
    assert [line for line in err.splitlines() if line] == [
        f"python -m torchmcmcpf reproduce {failing_experiment}: error: failing-study: shard 2 (runs 2..2) failed: "
        "RuntimeError: out of memory second line (TORCHMCMCPF_TRACEBACK=1 shows the traceback)"]
    monkeypatch.setenv("TORCHMCMCPF_TRACEBACK", "1")
    with pytest.raises(ValueError, match="num_chains=30"):
        main(argv)


def test_shard_options_only_where_the_study_runs_in_shards(capsys):
    sharded = [n for n, s in experiments.discover().items() if s.sharded]
    unsharded = [n for n, s in experiments.discover().items() if not s.sharded]
    assert {"maroulas-hmc", "septier-groups"} <= set(unsharded) and "bocquel-table2" in sharded
    assert main(["reproduce", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    common = text.split("options common to all studies:")[1].split("shards and Ray")[0]
    assert "--workers WORKERS" not in common and "--quick" in common
    assert f"shards and Ray (only {', '.join(sharded)}):" in text
    for name in unsharded:
        assert_one_line_error(capsys, ["reproduce", name, "--quick", "--workers", "2"], "--workers",
                              "does not run in shards", "bocquel-table2")
        assert_one_line_error(capsys, ["reproduce", name, "--shard-size=3"], "--shard-size")
        with pytest.raises(SystemExit):
            main(["reproduce", name, "--help"])
        assert "--workers" not in capsys.readouterr().out


def test_every_study_prints_a_headline_table(fake_experiment, tmp_path, capsys):
    """A study without its own summary prints its scalar results as a table (not a key dump)."""
    assert main(["reproduce", fake_experiment, "--out", tmp_path, "--level", "7", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "| quantity | value |" in printed and "| level | 7 |" in printed
    assert main(["reproduce", "group-merge-scenario", "--quick", "--out", tmp_path / "gm", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "| quantity | this run | paper |" in printed and "P_d,1: model / simulated" in printed
    missing = [n for n, s in experiments.discover().items()
               if type(s).summary is Study.summary and n != fake_experiment]
    assert missing == [], missing


def test_demo_quick_states_its_expected_duration(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--out", out, "--no-progress"]) == 0
    s = json.loads((out / "metrics.json").read_text())["settings"]
    assert (s["runs"], s["steps"], s["particles"], s["chains"], s["targets"]) == (1, 5, 500, 50, 10)
    assert "expected: about 0.4 s of filtering (0.08 s per step) on a quiet 2-core CPU" in capsys.readouterr().out
    # explicit sizes win over the preset; no time is promised for them
    assert main(["demo", "--quick", "--steps", "2", "--particles", "100", "--chains", "10", "--targets", "2",
                 "--out", out, "--no-progress"]) == 0
    assert json.loads((out / "metrics.json").read_text())["settings"]["steps"] == 2
    assert "expected:" not in capsys.readouterr().out


def test_demo_warns_when_the_cores_are_busy(monkeypatch):
    from torchmcmcpf import __main__ as cli

    args = argparse.Namespace(filter="ipmcmc", quick=False, threads=2, **cli.DEMO_DEFAULTS)
    monkeypatch.setattr(cli.os, "getloadavg", lambda: (9.0, 9.0, 9.0))
    monkeypatch.setattr(cli.os, "cpu_count", lambda: 2)
    note = cli.demo_expectation(args)
    assert "expected: about 3 s of filtering" in note and "load average 9.0 on 2 cores" in note
    assert "--threads 1 avoids most of it" in note
    args.threads = 1
    assert "--threads 1" not in cli.demo_expectation(args)
    monkeypatch.setattr(cli.os, "getloadavg", lambda: (0.5, 0.5, 0.5))
    assert "load average" not in cli.demo_expectation(args)
