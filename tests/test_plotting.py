import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from torchmcmcpf.plotting import (  # noqa: E402
    plot_cardinality,
    plot_frame,
    plot_particles,
    plot_rmse,
    plot_tracks,
)


@pytest.fixture
def ax():
    fig, ax = plt.subplots()
    yield ax
    plt.close(fig)


def test_plot_tracks_draws_the_given_run(ax, gen):
    truth = torch.randn(6, 3, 2, 5, generator=gen)  # (T, B, K, D)
    est = truth + 0.1
    out = plot_tracks(ax, truth, est, run=1)
    assert len(out["truth"]) == 2 and len(out["estimate"]) == 2
    for k in range(2):
        np.testing.assert_allclose(out["truth"][k].get_xdata(), truth[:, 1, k, 0].numpy(), rtol=1e-6)
        np.testing.assert_allclose(out["truth"][k].get_ydata(), truth[:, 1, k, 2].numpy(), rtol=1e-6)
        np.testing.assert_allclose(out["estimate"][k].get_ydata(), est[:, 1, k, 2].numpy(), rtol=1e-6)
    np.testing.assert_allclose(out["start"].get_offsets(), truth[0, 1][:, [0, 2]].numpy(), rtol=1e-6)
    assert ax.get_aspect() == 1.0  # equal axes: metres are metres both ways (issue 52)


def test_plot_tracks_without_batch_dim(ax):
    truth = np.arange(24, dtype=float).reshape(3, 2, 4)  # (T, K, D)
    out = plot_tracks(ax, truth, legend=False)
    assert out["estimate"] == []
    np.testing.assert_array_equal(out["truth"][1].get_xdata(), truth[:, 1, 0])
    with pytest.raises(ValueError, match="run"):
        plot_tracks(ax, truth[:, None], run=2)
    with pytest.raises(ValueError, match="truth"):
        plot_tracks(ax, truth[0])


def test_plot_particles(ax, gen):
    p = torch.randn(50, 3, 4, generator=gen)
    out = plot_particles(ax, p)
    assert len(out) == 3
    np.testing.assert_allclose(out[2].get_offsets(), p[:, 2][:, [0, 2]].numpy(), rtol=1e-6)
    w = torch.softmax(torch.randn(50, generator=gen), 0)
    out = plot_particles(ax, p, weights=w, size=4.0)
    np.testing.assert_allclose(out[0].get_sizes(), 4.0 * 50 * w.numpy(), rtol=1e-5)
    with pytest.raises(ValueError, match="weights"):
        plot_particles(ax, p, weights=w[:10])


def test_plot_rmse_single_and_dict(ax):
    lines = plot_rmse(ax, torch.tensor([3.0, 2.0, 1.0]), dt=2.0)
    np.testing.assert_array_equal(lines[0].get_xdata(), [2.0, 4.0, 6.0])
    np.testing.assert_array_equal(lines[0].get_ydata(), [3.0, 2.0, 1.0])
    lines = plot_rmse(ax, {"SIR": [1.0, 2.0], "IP-MCMC": np.array([0.5, 0.4])})
    assert [line.get_label() for line in lines] == ["SIR", "IP-MCMC"]
    np.testing.assert_array_equal(lines[1].get_ydata(), [0.5, 0.4])
    with pytest.raises(ValueError, match="rmse"):
        plot_rmse(ax, torch.zeros(2, 2))


def test_plot_cardinality(ax):
    true_line, est_line = plot_cardinality(ax, [1, 2, 2], torch.tensor([0.9, 1.8, 2.1]))
    np.testing.assert_array_equal(true_line.get_ydata(), [1, 2, 2])
    np.testing.assert_allclose(est_line.get_ydata(), [0.9, 1.8, 2.1], rtol=1e-6)
    with pytest.raises(ValueError, match="est_count"):
        plot_cardinality(ax, [1, 2], [1.0])


def test_plot_frame_sums_over_doppler(ax, gen):
    frame = torch.rand(5, 4, 3, generator=gen, dtype=torch.float64)
    mesh = plot_frame(ax, frame, range_bins=torch.arange(5) * 10.0,
                      bearing_bins=torch.zeros(3) + torch.arange(3) * 0.01, colorbar=True)
    np.testing.assert_allclose(np.asarray(mesh.get_array()).reshape(5, 3), frame.sum(1).numpy())
    assert ax.get_xlabel() == "bearing [deg]"
    with pytest.raises(ValueError, match="frame"):
        plot_frame(ax, frame[0])


def test_estimate_colour_follows_the_truth_it_tracks(ax):
    t = np.arange(5.0)
    truth = np.zeros((5, 2, 4))
    truth[:, 0, 0], truth[:, 1, 0], truth[:, 1, 2] = t, t, 100.0  # two parallel tracks 100 m apart
    est = truth[:, ::-1].copy()  # slot 0 follows target 1 and vice versa
    est[2:, 0] = np.nan  # gaps (absent targets) are ignored
    out = plot_tracks(ax, truth, est, estimate_label="IP-MCMC-PF, Np = 50")
    assert out["followed"] == [1, 0]
    assert out["estimate"][0].get_color() == out["truth"][1].get_color()
    assert out["estimate"][1].get_color() == out["truth"][0].get_color()
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["truth", "IP-MCMC-PF, Np = 50"]
    plain = plot_tracks(ax, truth, est, match_colors=False, legend=False)
    assert plain["estimate"][0].get_color() == plain["truth"][0].get_color()


def test_plot_cardinality_draws_every_filter(ax):
    lines = plot_cardinality(ax, [1, 2, 2], {"SIR PF, Np = 10": [1.0, 1.5, 2.0], "IP-MCMC-PF, Np = 10": [1, 2, 2]})
    assert [line.get_label() for line in lines] == ["true", "SIR PF, Np = 10", "IP-MCMC-PF, Np = 10"]
    assert ax.get_xlabel() == "time [s]"


def _overlap(a, b) -> bool:
    return not (a.x1 <= b.x0 or b.x1 <= a.x0 or a.y1 <= b.y0 or b.y1 <= a.y0)


def test_demo_figure_titles_do_not_overlap(tmp_path):
    import argparse

    from torchmcmcpf.__main__ import demo_figure
    from torchmcmcpf.metrics import position_rmse
    from torchmcmcpf.scenarios import ground_radar
    from torchmcmcpf.state import FilterResult

    g = torch.Generator().manual_seed(0)
    scn = ground_radar(10, 4, 1, generator=g)
    result = FilterResult(mean=scn.truth + 1.0, state=None, info=None, log_evidence=torch.zeros(1))
    args = argparse.Namespace(filter="ipmcmc", particles=1000, runs=1, steps=4, targets=10)
    fig = demo_figure(scn, result, position_rmse(result.mean, scn.truth), args)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    boxes = [ax.title.get_window_extent(renderer) for ax in fig.axes]
    boxes.append(fig._suptitle.get_window_extent(renderer))
    assert not any(_overlap(a, b) for i, a in enumerate(boxes) for b in boxes[i + 1:])
    for ax in fig.axes:  # titles stay above their own axes, inside the figure
        assert 0 <= ax.title.get_window_extent(renderer).x0 and ax.title.get_window_extent(renderer).x1 <= fig.bbox.x1
    labels = [t.get_text() for ax in fig.axes for t in ax.get_legend().get_texts()]
    assert "IP-MCMC-PF, Np = 1000" in labels
    plt.close(fig)


# Every study's figures, captured before they are saved: labels, units, "quick", Np legends.
STUDIES = {
    "bocquel-table2": dict(runs=None, steps=2, particles=None, max_extensions=None, pmmh_candidates=None),
    "ling-rmse-vs-snr": dict(runs=1, snr=None, steps=2, burn_in=4, thinning=1, particles=None, moves=None),
    "maroulas-hmc": dict(runs=1, steps=3, hmc_steps=2),
    "septier-birth-death": dict(runs=2, steps=4, particles=40, burn_in=2),
}
UNITLESS = ("number of targets",)  # counts


@pytest.fixture(scope="module")
def study_figures(tmp_path_factory):
    import sys

    from torchmcmcpf import experiments
    from torchmcmcpf.experiments._options import RunOptions

    found = experiments.discover()
    figures = {}
    mp = pytest.MonkeyPatch()
    for name, extra in STUDIES.items():
        study = found[name]
        module = sys.modules[type(study).__module__]
        original = module.save_figure

        def capture(fig, out, filename, *, quick=False, _name=name, _orig=original):
            fig.canvas.draw()
            figures[(_name, filename)] = {
                "quick": quick,
                "texts": [t.get_text() for t in fig.texts] + ([fig._suptitle.get_text()] if fig._suptitle else []),
                "axes": [dict(title=ax.get_title(), xlabel=ax.get_xlabel(), ylabel=ax.get_ylabel(),
                              legend=[t.get_text() for t in ax.get_legend().get_texts()] if ax.get_legend() else [])
                         for ax in fig.axes if ax.get_label() != "<colorbar>"],
            }
            return _orig(fig, out, filename, quick=quick)

        mp.setattr(module, "save_figure", capture)
        payload = study.run(study.settings(quick=True, **extra), RunOptions(out=tmp_path_factory.mktemp(name)))
        figures[(name, "summary")] = study.summary(payload)
    mp.undo()
    return figures


def test_study_figures_are_labelled(study_figures):
    summaries = {k: v for k, v in study_figures.items() if k[1] == "summary"}
    assert len(summaries) == 4 and all(v.count("|") > 8 for v in summaries.values())  # headline tables
    figures = {k: v for k, v in study_figures.items() if k[1] != "summary"}
    assert len(figures) == 3 + 2 + 6 + 3
    for (study, filename), fig in figures.items():
        where = f"{study}/{filename}"
        assert fig["quick"], where  # quick-mode figures are stamped (test_save_figure_stamps_quick_mode)
        for ax in fig["axes"]:
            for label in (ax["xlabel"], ax["ylabel"]):
                assert label, where
                assert "[" in label or label in UNITLESS, (where, label)  # units on every axis
            if ax["xlabel"].startswith("time"):
                assert ax["xlabel"] == "time [s]", where  # one time label (RMSE, ESS, OSPA, counts)
            filters = [t for t in ax["legend"] if t not in ("truth", "true", "observations") and "resolution" not in t
                           and not t.startswith("Stone Soup")]  # Stone Soup's trackers have no particles
            assert all("Np = " in t for t in filters), (where, ax["legend"])


def test_every_filter_is_shown_and_titles_are_consistent(study_figures):
    names = ("SIR PF", "MCMC-PF", "IP-MCMC-PF")
    tracks = study_figures[("septier-birth-death", "tracks.png")]["axes"]
    assert [ax["title"].split(" (")[0] for ax in tracks] == list(names)
    card = study_figures[("septier-birth-death", "cardinality.png")]["axes"][0]["legend"]
    assert all(any(t.startswith(n + ",") for t in card) for n in names)
    ling = study_figures[("ling-rmse-vs-snr", "rmse_vs_snr.png")]["axes"][0]["title"]
    assert "burn-in" in ling and "B=" not in ling  # B is the number of runs elsewhere
    rmse = study_figures[("maroulas-hmc", "rmse_linear.png")]["axes"][0]["xlabel"]
    ess = study_figures[("maroulas-hmc", "ess_linear.png")]["axes"][0]["xlabel"]
    assert rmse == ess


def test_save_figure_stamps_quick_mode(tmp_path, monkeypatch):
    from torchmcmcpf.experiments._figures import save_figure

    seen = {}
    monkeypatch.setattr(plt, "close", lambda fig: seen.setdefault("texts", [t.get_text() for t in fig.texts]))
    fig, _ = plt.subplots()
    assert save_figure(fig, tmp_path / "sub", "a.png", quick=True).stat().st_size > 0
    assert any("quick" in t for t in seen["texts"])
    monkeypatch.undo()
    plt.close(fig)


def test_plot_cardinality_takes_each_curve_style(ax):
    """A study gives each tracker its colour in every figure (issue 52)."""
    lines = plot_cardinality(ax, [1, 2], {"a": [1.0, 2.0], "b": [1.0, 1.0]}, styles={"b": {"color": "C7", "ls": "--"}})
    assert lines[2].get_color() == "C7" and lines[2].get_linestyle() == "--"
    assert lines[1].get_color() == "C3"  # the default cycle where no style is given
