"""Stone Soup tracks and ground truth from torchmcmcpf results and scenarios.

Stone Soup (``stonesoup``) is imported when a function here is called. Its state vectors
keep the library's layout ``[x, vx, y, vy(, rho)]`` (Stone Soup's own constant-velocity
ordering), so a position measure is ``Euclidean(mapping=(0, 2))``.

Time: frame ``t`` (0-based) is at ``start_time + t * dt``; ``start_time`` defaults to
:data:`EPOCH` (fixed, so exports are reproducible) and ``dt`` to the motion model's sampling
time recorded in ``result.meta`` (1 s when none is). Tracks and truth exported with the same
``start_time`` and ``dt`` share timestamps, which Stone Soup's metrics pair by equality.

Identities: the track of slot ``k`` has ``id == str(k)`` and the truth path of target ``k``
``id == str(k)``, so Stone Soup's ``TrackIDbased`` associator pairs slot ``k`` with target
``k``, the labelling of the library's metrics with ``match=False``. With births and deaths a
slot is exported only where it exists (existence probability above ``threshold``, or the
truth's alive flag); each later stretch of existence is a new track or path with id
``f"{k}.{i}"`` (``i = 1, 2, ...``): a slot that dies and is reborn holds a new target.

The exporters loop over slots and steps in Python to build Stone Soup objects: export, not
filtering (the tensors are moved to NumPy once).
"""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

import numpy as np
import torch

from .._validation import check_positive
from ._layout import Result, check_index, optional

__all__ = ["EPOCH", "tracks_to_stonesoup", "truth_to_stonesoup", "timestamps"]

#: default time of frame 0
EPOCH = datetime(2000, 1, 1)
KINDS = ("gaussian", "particle")


def timestamps(num_steps: int, *, start_time: datetime | None = None, dt: float = 1.0) -> list[datetime]:
    """The ``datetime`` of frames ``0 .. num_steps - 1``: ``start_time + t * dt`` seconds."""
    start = EPOCH if start_time is None else start_time
    if not isinstance(start, datetime):
        raise ValueError(f"start_time must be a datetime.datetime or None, got {type(start_time).__name__}")
    step = check_positive(dt, "dt")
    return [start + timedelta(seconds=t * step) for t in range(num_steps)]


def _stretches(present: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs ``[start, stop)`` of True in a ``(T,)`` bool array."""
    edges = np.diff(np.concatenate([[0], present.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def _track_id(slot: int, stretch: int) -> str:
    return str(slot) if stretch == 0 else f"{slot}.{stretch}"


def _dt(dt: float | None, meta_dt: Any) -> float:
    if dt is not None:
        return check_positive(dt, "dt")
    return 1.0 if meta_dt is None else float(meta_dt)


def tracks_to_stonesoup(result: Result, *, run: int = 0, kind: str = "gaussian",
                        start_time: datetime | None = None, dt: float | None = None,
                        threshold: float = 0.5) -> list:
    """Stone Soup ``Track`` s of one Monte Carlo run of a filter result.

    Parameters
    ----------
    result : a :class:`~torchmcmcpf.state.FilterResult` with ``mean (T, B, K, D)`` and, for
        ``kind="gaussian"``, ``cov (T, B, K, D, D)`` (every ``Filter.forward`` records it).
    run : which of the B runs.
    kind : ``"gaussian"``: ``GaussianState(mean, cov)`` per step (the posterior mean and
        covariance of the slot, given existence with births and deaths); ``"particle"``:
        ``ParticleState`` per step, the slot's particles (those where it exists) with their
        normalised log-weights, from ``result.history`` (``forward(..., history=True)``).
    start_time, dt : timestamps (module docstring).
    threshold : with births and deaths, a slot is exported at the steps where its existence
        probability ``result.exists_prob`` exceeds this (0.5: the marginal MAP existence of
        :func:`~torchmcmcpf.state.existence_estimate`).

    Returns
    -------
    list of ``Track``, ordered by slot then start, ids as in the module docstring;
    ``init_metadata`` holds ``run`` and ``slot``.
    """
    sst = optional("stonesoup.types.state", "stonesoup")
    track_mod = optional("stonesoup.types.track", "stonesoup")
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    if not 0.0 <= float(threshold) < 1.0:
        raise ValueError(f"threshold must be in [0, 1), got {threshold!r}")
    t_len, b, k, _ = result.mean.shape
    r = check_index(run, "run", b, f"B = {b} runs")
    times = timestamps(t_len, start_time=start_time, dt=_dt(dt, (result.meta or {}).get("dt")))
    mean = result.mean[:, r].detach().cpu().double().numpy()  # (T, K, D)
    if result.exists_prob is None:
        present = np.ones((t_len, k), dtype=bool)
    else:
        present = (result.exists_prob[:, r] > float(threshold)).cpu().numpy()
    if kind == "gaussian":
        if result.cov is None:
            raise ValueError("result.cov is None: kind='gaussian' needs the per-step covariance that Filter.forward "
                             "records; use kind='particle' with forward(..., history=True)")
        cov = result.cov[:, r].detach().cpu().double().numpy()  # (T, K, D, D)
    else:
        hist = result.history
        if hist is None:
            raise ValueError("result.history is None: kind='particle' needs every step's particles; run the filter "
                             "with forward(..., history=True)")
        x = hist.x[:, r].detach().cpu().double().numpy()  # (T, N, K, D)
        log_w = hist.log_w[:, r].detach().cpu().double()  # (T, N)
        alive = None if hist.exists is None else hist.exists[:, r].cpu()  # (T, N, K)
    tracks = []
    for slot in range(k):
        for i, (a, z) in enumerate(_stretches(present[:, slot])):
            states = []
            for t in range(a, z):
                if kind == "gaussian":
                    states.append(sst.GaussianState(sst.StateVector(mean[t, slot]), sst.CovarianceMatrix(cov[t, slot]),
                                                    timestamp=times[t]))
                    continue
                lw = log_w[t] if alive is None else torch.where(alive[t, :, slot], log_w[t],
                                                                torch.full_like(log_w[t], -np.inf))
                keep = torch.isfinite(lw).numpy()
                lw = (lw - torch.logsumexp(lw, 0)).numpy()[keep]
                states.append(sst.ParticleState(sst.StateVectors(x[t, keep, slot].T), log_weight=lw,
                                                timestamp=times[t]))
            tracks.append(track_mod.Track(states, id=_track_id(slot, i), init_metadata={"run": r, "slot": slot}))
    return tracks


def truth_to_stonesoup(truth: Any, *, run: int = 0, exists: torch.Tensor | None = None,
                       start_time: datetime | None = None, dt: float | None = None) -> list:
    """Stone Soup ``GroundTruthPath`` s of one run of a scenario's true tracks.

    Parameters
    ----------
    truth : a scenario (anything with ``truth (T, B, K, D)``, e.g.
        :func:`~torchmcmcpf.scenarios.ground_radar.ground_radar`,
        :func:`~torchmcmcpf.scenarios.septier.septier`,
        :func:`~torchmcmcpf.scenarios.group_merge.group_merge`; its ``alive`` or ``exists``
        flags and its ``dt`` or ``motion.dt`` are used when present), or the ``(T, B, K, D)``
        tensor itself.
    run : which of the B runs.
    exists : (T, B, K) bool, optional: true existence (overrides the scenario's); a target is
        exported where it exists, each stretch of existence a path (module docstring).
    start_time, dt : timestamps (module docstring); ``dt`` defaults to the scenario's.

    Returns
    -------
    list of ``GroundTruthPath`` of ``GroundTruthState`` s, ordered by target then start; each
    state's ``metadata`` holds ``run`` and ``slot``.
    """
    gt = optional("stonesoup.types.groundtruth", "stonesoup")
    sst = optional("stonesoup.types.state", "stonesoup")
    scenario = None if torch.is_tensor(truth) else truth
    tensor = truth if scenario is None else getattr(scenario, "truth", None)
    if not torch.is_tensor(tensor) or tensor.dim() != 4:
        raise ValueError(f"truth must be a (T, B, K, D) tensor or a scenario with one as .truth, got "
                         f"{getattr(tensor, 'shape', type(truth).__name__)}")
    if exists is None and scenario is not None:
        flags = [getattr(scenario, a, None) for a in ("alive", "exists")]
        exists = next((f for f in flags if torch.is_tensor(f)), None)
    t_len, b, k, _ = tensor.shape
    if exists is not None and tuple(exists.shape) != (t_len, b, k):
        raise ValueError(f"exists has shape {tuple(exists.shape)}, expected {(t_len, b, k)} (T, B, K) like truth")
    r = check_index(run, "run", b, f"B = {b} runs")
    scenario_dt = None if scenario is None else getattr(scenario, "dt", getattr(getattr(scenario, "motion", None),
                                                                               "dt", None))
    times = timestamps(t_len, start_time=start_time, dt=_dt(dt, scenario_dt))
    values = tensor[:, r].detach().cpu().double().numpy()
    present = np.ones((t_len, k), dtype=bool) if exists is None else exists[:, r].cpu().numpy().astype(bool)
    paths = []
    for slot in range(k):
        for i, (a, z) in enumerate(_stretches(present[:, slot])):
            states = [gt.GroundTruthState(sst.StateVector(values[t, slot]), timestamp=times[t],
                                          metadata={"run": r, "slot": slot}) for t in range(a, z)]
            paths.append(gt.GroundTruthPath(states, id=_track_id(slot, i)))
    return paths
