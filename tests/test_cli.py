import json
import math
import sys
import textwrap

import pytest

from torchmcmcpf import experiments
from torchmcmcpf.__main__ import main


def test_demo_small_writes_metrics_and_figure(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--particles", "64", "--runs", "1", "--steps", "5", "--targets", "2",
                 "--out", out, "--no-progress"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    s = m["settings"]
    assert (s["particles"], s["runs"], s["steps"], s["targets"], s["seed"]) == (64, 1, 5, 2, 0)
    assert m["device"].startswith("cpu")
    assert len(m["rmse_per_step_m"]) == 5 and len(m["lost_runs"]) == 1
    # overall RMSE^2 is the mean of the per-step RMSE^2 (equal counts per step)
    ms = sum(v * v for v in m["rmse_per_step_m"]) / 5
    assert m["rmse_overall_m"] == pytest.approx(math.sqrt(ms), rel=1e-5)
    assert m["track_loss_rate"] in (0.0, 1.0) and m["seconds_per_step"] > 0
    assert (out / "tracks.png").stat().st_size > 1000
    printed = capsys.readouterr().out
    assert "position RMSE" in printed and "track loss rate" in printed


def test_demo_runs_ipmcmc(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--filter", "ipmcmc", "--particles", "40", "--runs", "1", "--steps", "2",
                 "--targets", "2", "--out", out, "--no-progress"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["filter"] == "IPMCMCFilter" and len(m["rmse_per_step_m"]) == 2
    assert "IPMCMCFilter" in capsys.readouterr().out


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
        from torchmcmcpf.experiments._common import write_metrics

        NAME = "fake-study"
        DESCRIPTION = "a throwaway study used by tests/test_cli.py"

        def add_arguments(parser):
            parser.add_argument("--level", type=int, default=1)

        def run(args):
            metrics = {"quick": args.quick, "level": args.level, "seed": args.seed,
                       "device_type": args.device.type, "progress": args.progress}
            write_metrics(args.out, metrics, args=args)
            return metrics
    '''))
    monkeypatch.setattr(experiments, "__path__", [*experiments.__path__, str(pkg)])
    yield "fake-study"
    sys.modules.pop("torchmcmcpf.experiments.fake_study", None)


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


def test_bench_points_to_pytest_benchmark(capsys):
    assert main(["bench"]) == 0
    assert "pytest benchmarks/ --benchmark-only" in capsys.readouterr().out
