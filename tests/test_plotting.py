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
    mesh = plot_frame(ax, frame, range_bins=torch.arange(5) * 10.0, bearing_bins=torch.zeros(3) + torch.arange(3) * 0.01,
                      colorbar=True)
    np.testing.assert_allclose(np.asarray(mesh.get_array()).reshape(5, 3), frame.sum(1).numpy())
    assert ax.get_xlabel() == "bearing [deg]"
    with pytest.raises(ValueError, match="frame"):
        plot_frame(ax, frame[0])
