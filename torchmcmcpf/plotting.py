"""Matplotlib helpers: tracks, particle clouds, RMSE curves, cardinality, radar frames.

Every helper draws on a given ``ax`` (``f(ax, data, **kw)``) and returns what it created,
so figures compose freely. Tensors may live on any device (they are moved to the CPU);
numpy arrays are accepted too. matplotlib is imported only inside the functions that need
it, so ``import torchmcmcpf`` stays light.

Positions follow the state layout ``[x, vx, y, vy, ...]`` (x at index 0, y at index 2).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from .typing import X, Y

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.collections import QuadMesh

__all__ = ["plot_tracks", "plot_particles", "plot_rmse", "plot_cardinality", "plot_frame"]

ArrayLike = torch.Tensor | np.ndarray | Sequence[float]


def _np(a: ArrayLike) -> np.ndarray:
    if torch.is_tensor(a):
        return a.detach().cpu().double().numpy()
    return np.asarray(a, dtype=float)


def _tracks(data: ArrayLike, run: int, name: str) -> np.ndarray:
    a = _np(data)
    if a.ndim == 4:
        if not -a.shape[1] <= run < a.shape[1]:
            raise ValueError(f"run={run} is out of range for {name} with {a.shape[1]} runs")
        a = a[:, run]
    if a.ndim != 3 or a.shape[-1] <= Y:
        raise ValueError(f"{name} has shape {a.shape}, expected (T, K, D) or (T, B, K, D) with D >= 3")
    return a


def plot_tracks(
    ax: Axes,
    truth: ArrayLike,
    estimate: ArrayLike | None = None,
    *,
    run: int = 0,
    truth_style: dict | None = None,
    estimate_style: dict | None = None,
    mark_start: bool = True,
    legend: bool = True,
    truth_label: str = "truth",
    estimate_label: str = "estimate",
    match_colors: bool = True,
) -> dict:
    """True (and estimated) tracks in the x-y plane (paper 000 figs. 1, 4, 5), on equal axes.

    Parameters
    ----------
    ax : matplotlib Axes.
    truth : (T, K, D) or (T, B, K, D) states; with B, ``run`` picks the run.
    estimate : same layout, optional; drawn dashed in the colour of the true target it
        follows. NaN entries (e.g. absent targets) break the lines.
    run : Monte Carlo run to draw when a B dim is present.
    truth_style, estimate_style : extra keyword arguments of ``ax.plot``.
    mark_start : put a marker at the first position of each true track.
    legend : add a legend (one entry per kind).
    truth_label, estimate_label : legend entries (e.g. ``"IP-MCMC-PF, Np = 500"``).
    match_colors : colour each estimated slot like the true track it stays closest to (the
        whole-track optimal assignment of the mean distance over the frames where both are
        defined), so a label swap shows as a colour that follows its target; ``False``
        colours slot ``j`` like true slot ``j``.

    Returns
    -------
    dict with ``"truth"`` (K lines), ``"estimate"`` (K lines or []), ``"start"`` (markers)
    and ``"followed"`` (K ints: the true slot each estimate is coloured after, or []).
    """
    tr = _tracks(truth, run, "truth")
    k = tr.shape[1]
    colors = [f"C{j % 10}" for j in range(k)]
    out: dict[str, Any] = {"truth": [], "estimate": [], "start": [], "followed": []}
    for j in range(k):  # one artist per target: plotting, not computation
        (line,) = ax.plot(tr[:, j, X], tr[:, j, Y], "-", color=colors[j], lw=1.5,
                          label=truth_label if j == 0 else None, **(truth_style or {}))
        out["truth"].append(line)
    if mark_start:
        out["start"] = ax.scatter(tr[0, :, X], tr[0, :, Y], c=colors, marker="o", s=18, zorder=3)
    if estimate is not None:
        est = _tracks(estimate, run, "estimate")
        if est.shape[1] != k:
            raise ValueError(f"estimate has {est.shape[1]} targets, truth has {k}")
        followed = _followed(tr, est) if match_colors else list(range(k))
        out["followed"] = followed
        for j in range(k):
            (line,) = ax.plot(est[:, j, X], est[:, j, Y], "--", color=colors[followed[j]], lw=1.2,
                              label=estimate_label if j == 0 else None, **(estimate_style or {}))
            out["estimate"].append(line)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    if legend:  # neutral grey handles: the colours name targets, the line styles the kinds
        from matplotlib.lines import Line2D

        handles = [Line2D([], [], color="0.3", ls="-", lw=1.5, label=truth_label)]
        if out["estimate"]:
            handles.append(Line2D([], [], color="0.3", ls="--", lw=1.2, label=estimate_label))
        ax.legend(handles=handles, loc="best", fontsize="small")
    ax.set_aspect("equal", adjustable="datalim")  # metres on both axes: a crossing looks like one
    return out


def _followed(truth: np.ndarray, est: np.ndarray) -> list[int]:
    """For (T, K, D) truth and estimate: the true slot each estimated slot follows (optimal
    assignment of the mean x-y distance over the frames where both are finite).
    """
    from .metrics import optimal_assignment

    d = np.linalg.norm(est[:, :, None, [X, Y]] - truth[:, None, :, [X, Y]], axis=-1)  # (T, K est, K true)
    finite = np.isfinite(d)
    count = finite.sum(0)
    mean = np.where(finite, d, 0.0).sum(0) / np.maximum(count, 1)
    big = (np.nanmax(mean[count > 0]) if (count > 0).any() else 0.0) * 10 + 1.0
    cost = np.where(count > 0, mean, big)  # never seen together: assign last
    return optimal_assignment(torch.as_tensor(cost)).tolist()


def plot_particles(ax: Axes, particles: ArrayLike, *, weights: ArrayLike | None = None, size: float = 2.0,
                   alpha: float = 0.3, **kw: Any) -> list:
    """Scatter a particle cloud in the x-y plane, one colour per target slot (paper 000 fig. 2).

    Parameters
    ----------
    ax : matplotlib Axes.
    particles : (N, K, D).
    weights : (N,) normalised weights, optional; marker areas scale with ``N * w``.
    size, alpha : marker size and transparency; ``kw`` go to ``ax.scatter``.

    Returns
    -------
    list of K PathCollections.
    """
    p = _np(particles)
    if p.ndim != 3 or p.shape[-1] <= Y:
        raise ValueError(f"particles has shape {p.shape}, expected (N, K, D) with D >= 3")
    s: Any = size  # a float, or one area per particle (N,)
    if weights is not None:
        w = _np(weights)
        if w.shape != p.shape[:1]:
            raise ValueError(f"weights has shape {w.shape}, expected ({p.shape[0]},)")
        s = size * p.shape[0] * w
    return [ax.scatter(p[:, j, X], p[:, j, Y], s=s, alpha=alpha, color=f"C{j % 10}", linewidths=0, **kw)
            for j in range(p.shape[1])]


TIME_LABEL = "time [s]"


def plot_rmse(ax: Axes, rmse: ArrayLike | Mapping[str, ArrayLike], *, dt: float = 1.0,
              ylabel: str = "position RMSE [m]", xlabel: str = TIME_LABEL, **kw: Any) -> list:
    """RMSE over time (paper 000 figs. 3 and 6).

    Parameters
    ----------
    ax : matplotlib Axes.
    rmse : (T,) per-step RMSE, or a mapping name -> (T,) (one labelled line each).
    dt : time between steps [s]; the x axis is ``dt * (1..T)``.
    ylabel, xlabel : axis labels with units (any curve over time: RMSE, ESS, OSPA).
    kw : passed to every ``ax.plot``.

    Returns
    -------
    list of Line2D, one per curve.
    """
    curves = dict(rmse) if isinstance(rmse, Mapping) else {None: rmse}
    lines = []
    for name, values in curves.items():
        v = _np(values)
        if v.ndim != 1:
            raise ValueError(f"rmse{'' if name is None else f'[{name!r}]'} has shape {v.shape}, expected (T,)")
        (line,) = ax.plot(dt * np.arange(1, v.size + 1), v, label=name, **kw)
        lines.append(line)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if any(name is not None for name in curves):
        ax.legend(loc="best", fontsize="small")
    return lines


def plot_cardinality(ax: Axes, true_count: ArrayLike, est_count: ArrayLike | Mapping[str, ArrayLike], *,
                     dt: float = 1.0, est_label: str = "estimated", styles: Mapping[str, dict] | None = None) -> list:
    """True and estimated number of targets over time.

    Parameters
    ----------
    ax : matplotlib Axes.
    true_count : (T,) true number of targets.
    est_count : (T,) estimated number (e.g. the sum of existence probabilities), or a
        mapping label -> (T,) (one line per filter).
    dt : time between steps [s].
    est_label : legend entry of a single ``est_count``.
    styles : label -> keyword arguments of ``ax.plot`` for that curve (``color``, ``ls``,
        ...), optional: a study gives each tracker the colour it has in its other figures.

    Returns
    -------
    [true Line2D (steps), one estimated Line2D per curve].
    """
    tc = _np(true_count)
    curves = dict(est_count) if isinstance(est_count, Mapping) else {est_label: est_count}
    t = dt * np.arange(1, tc.size + 1)
    lines = []
    for i, (label, values) in enumerate(curves.items()):
        ec = _np(values)
        if tc.ndim != 1 or ec.shape != tc.shape:
            raise ValueError(f"true_count and est_count must both be (T,), got {tc.shape} and {ec.shape}")
        style = {"color": f"C{(i + 3) % 10}", "marker": "o", "ms": 3, **(styles or {}).get(label, {})}
        (line,) = ax.plot(t, ec, label=label, **style)
        lines.append(line)
    (true_line,) = ax.step(t, tc, where="mid", color="k", label="true")
    ax.set_xlabel(TIME_LABEL)
    ax.set_ylabel("number of targets")
    ax.legend(loc="best", fontsize="small")
    return [true_line, *lines]


def plot_frame(ax: Axes, frame: ArrayLike, *, range_bins: ArrayLike | None = None,
               bearing_bins: ArrayLike | None = None, degrees: bool = True, colorbar: bool = False,
               **kw: Any) -> QuadMesh:
    """Range-bearing image of one radar power frame, summed over doppler.

    Parameters
    ----------
    ax : matplotlib Axes.
    frame : (Nr, Nd, Nb) powers (e.g. ``scenario.measurements[t, b]``).
    range_bins : (Nr,) range cell centres [m], optional (cell indices otherwise).
    bearing_bins : (Nb,) bearing cell centres [rad], optional.
    degrees : label bearings in degrees.
    colorbar : add a colour bar.
    kw : passed to ``ax.pcolormesh``.

    Returns
    -------
    the QuadMesh; its array is the (Nr, Nb) doppler-summed image.
    """
    f = _np(frame)
    if f.ndim != 3:
        raise ValueError(f"frame has shape {f.shape}, expected (Nr, Nd, Nb)")
    image = f.sum(axis=1)  # (Nr, Nb)
    nr, nb = image.shape
    r = _np(range_bins) if range_bins is not None else np.arange(nr, dtype=float)
    b = _np(bearing_bins) if bearing_bins is not None else np.arange(nb, dtype=float)
    if r.shape != (nr,) or b.shape != (nb,):
        raise ValueError(f"range_bins {r.shape} and bearing_bins {b.shape} must be ({nr},) and ({nb},)")
    if degrees and bearing_bins is not None:
        b = b * 180.0 / math.pi
    mesh = ax.pcolormesh(b, r, image, shading="nearest", **kw)
    ax.set_xlabel("bearing [deg]" if degrees and bearing_bins is not None else "bearing cell")
    ax.set_ylabel("range [m]" if range_bins is not None else "range cell")
    if colorbar:
        ax.figure.colorbar(mesh, ax=ax, label="power (summed over doppler)")
    return mesh
