"""Tracking metrics, batched over Monte Carlo runs and time: position RMSE, track loss,
optimal assignment and track-to-truth matching.

Conventions: estimates and truths are ``(T, B, K, D)`` with the state layout
``[x, vx, y, vy, ...]`` (positions at indices 0 and 2, :mod:`torchmcmcpf.typing`).
Every function takes and returns torch tensors and keeps the input's device.

Which labelling the RMSE uses
-----------------------------
A filter for a known number of targets returns one estimate per target *slot*; with
``match=False`` slot ``k`` is compared with true target ``k`` (the labels the filter was
initialised with). With ``match=True`` the estimates of each run are first relabelled by
:func:`match_tracks` on the *whole-track* cost (sum over time of squared position error),
so the labels are fixed per run: a track swap in the middle of a run still costs error,
as it does for a user who follows track labels. ``match_tracks(..., per_step=True)``
relabels every frame independently (the label-free error of an OSPA-like metric).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from .._validation import check_positive, check_shape, check_tensor
from ..runtime import pairwise_squared_distances, take_along
from ..typing import RHO, Tensor, X, Y

__all__ = [
    "RMSE",
    "position_rmse",
    "position_error",
    "track_loss",
    "track_loss_rate",
    "optimal_assignment",
    "match_tracks",
    "ospa",
    "ospa_parts",
    "OSPAParts",
    "gospa",
    "gospa_parts",
    "GOSPAParts",
    "slot_coverage",
    "amplitude_swapped",
    "longest_run",
    "identity_switches",
    "cardinality_error",
    "pcrb_position_rmse",
    "MAPTrajectory",
    "map_trajectory",
]

from .assignment import optimal_assignment  # noqa: E402  (after __all__: the split modules)
from .bounds import MAPTrajectory, map_trajectory, pcrb_position_rmse  # noqa: E402
from .sets import (  # noqa: E402
    GOSPAParts,
    OSPAParts,
    cardinality_error,
    gospa,
    gospa_parts,
    ospa,
    ospa_parts,
)


class RMSE(NamedTuple):
    """Position root-mean-square error (Ling 2012, paper 002 eq. 16).

    Attributes
    ----------
    per_step : (T,)
        ``sqrt(mean over runs and targets of the squared position error at step t)``.
    per_run : (B,)
        ``sqrt(mean over time and targets)`` for each Monte Carlo run.
    overall : ()
        ``sqrt(mean over runs, time and targets)``: eq. 16 itself.

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.metrics import position_rmse
    >>> truth = torch.zeros(3, 2, 1, 4)                      # (T, B, K, D)
    >>> estimate = truth.clone()
    >>> estimate[..., 0], estimate[..., 2] = 3.0, 4.0        # every estimate 5 m off
    >>> position_rmse(estimate, truth)
    RMSE(per_step=tensor([5., 5., 5.]), per_run=tensor([5., 5.]), overall=tensor(5.))
    """

    per_step: Tensor
    per_run: Tensor
    overall: Tensor


def _check_tracks(estimate: Tensor, truth: Tensor) -> None:
    check_tensor(truth, "truth")
    if truth.dim() != 4 or truth.shape[-1] < 3:
        raise ValueError(f"truth has shape {tuple(truth.shape)}, expected (T, B, K, D) with D >= 3")
    check_shape(estimate, "estimate", tuple(truth.shape))


def _positions(x: Tensor) -> Tensor:
    return x[..., [X, Y]]


def position_error(estimate: Tensor, truth: Tensor) -> Tensor:
    """Euclidean position error of every slot: ``(T, B, K, D), (T, B, K, D) -> (T, B, K)``."""
    _check_tracks(estimate, truth)
    return torch.linalg.vector_norm(_positions(estimate) - _positions(truth), dim=-1)


def position_rmse(estimate: Tensor, truth: Tensor, *, match: bool | str = False) -> RMSE:
    """Position RMSE over runs, time and targets (Ling 2012, paper 002 eq. 16).

    ``RMSE = sqrt( 1/(I E K) sum_i sum_k sum_j (x - x_hat)^2 + (y - y_hat)^2 )``

    with I runs, K frames, E targets. ``per_step`` keeps the time index (the curves of
    paper 000 figs. 3 and 6), ``per_run`` the run index.

    Parameters
    ----------
    estimate, truth : (T, B, K, D) with positions at indices 0 (x) and 2 (y).
    match : relabel the estimates of each run to the truth first (:func:`match_tracks`):
        ``True`` or ``"track"`` with one whole-track assignment per run (a label swap costs
        error), ``"step"`` with one assignment per step (the per-step assignment RMSE of long
        runs: a label swap costs nothing, a lost target still does).

    Returns
    -------
    RMSE with ``per_step (T,)``, ``per_run (B,)``, ``overall ()``.
    """
    if match not in (False, True, "track", "step"):
        raise ValueError(f"match must be False, True, 'track' or 'step', got {match!r}")
    if match:
        estimate, _ = match_tracks(estimate, truth, per_step=match == "step")
    se = position_error(estimate, truth).square()  # (T, B, K)
    return RMSE(
        per_step=se.mean(dim=(1, 2)).sqrt(),
        per_run=se.mean(dim=(0, 2)).sqrt(),
        overall=se.mean().sqrt(),
    )


def track_loss(estimate: Tensor, truth: Tensor, *, threshold: float = 20.0, match: bool = False
               ) -> Tensor:
    """Which runs lost track: Bocquel et al. (2012), paper 000 sec. VI (Table II): a run is
    lost when its maximum position error, over time and targets, exceeds ``threshold``.

    Parameters
    ----------
    estimate, truth : (T, B, K, D).
    threshold : [m], 20 m in paper 000.
    match : relabel estimates first (:func:`match_tracks`, whole-track assignment).

    Returns
    -------
    (B,) bool. A NaN error counts as lost.
    """
    check_positive(threshold, "threshold")
    if match:
        estimate, _ = match_tracks(estimate, truth)
    err = position_error(estimate, truth)
    worst = err.amax(dim=(0, 2))
    return ~(worst <= threshold)


def track_loss_rate(estimate: Tensor, truth: Tensor, *, threshold: float = 20.0,
                    match: bool = False) -> Tensor:
    """Track loss rate (TLR), paper 000 sec. VI: the fraction of runs that lost track
    (:func:`track_loss`). Returns a scalar tensor in [0, 1].
    """
    return track_loss(estimate, truth, threshold=threshold, match=match).float().mean()


def match_tracks(estimate: Tensor, truth: Tensor, *, per_step: bool = False
                 ) -> tuple[Tensor, Tensor]:
    """Relabel estimated tracks to the true targets by an optimal assignment.

    Parameters
    ----------
    estimate, truth : (T, B, K, D).
    per_step : ``False`` (default): one assignment per run on the whole-track cost
        ``C[b, k, j] = sum_t |p_truth[t, b, k] - p_est[t, b, j]|^2``, so labels are fixed
        within a run (what :func:`position_rmse` and :func:`track_loss` use with
        ``match=True``). ``True``: one assignment per run and step on the squared
        position error of that step.

    Returns
    -------
    matched : (T, B, K, D) with ``matched[t, b, k]`` the estimate assigned to true target k.
    perm : (B, K) (or (T, B, K) with ``per_step``): ``matched[t, b, k] =
        estimate[t, b, perm[b, k]]``.
    """
    _check_tracks(estimate, truth)
    cost = pairwise_squared_distances(_positions(truth), _positions(estimate))  # (T, B, K, K): truth k vs estimate j
    if not per_step:
        cost = cost.sum(0)  # (B, K, K)
    perm = optimal_assignment(cost)
    idx = perm if per_step else perm.expand(estimate.shape[:3])
    matched = estimate.gather(2, idx[..., None].expand(estimate.shape))
    return matched, perm


# -- long runs: coverage, identity switches ---------------------------------------------


def slot_coverage(estimate: Tensor, truth: Tensor, *, radius: float = 20.0, estimate_mask: Tensor | None = None,
                  truth_mask: Tensor | None = None) -> Tensor:
    """How many estimated slots lie within ``radius`` of each true target, per step.

    ``0`` marks an *uncovered* target (no slot within ``radius``: lost, whatever the labels),
    ``>= 2`` a target that two slots share (coalescence). A label swap changes neither.

    Parameters
    ----------
    estimate : (T, B, K, D) slot estimates; truth : (T, B, J, D) true states (positions at
        indices 0 and 2).
    radius : [m] > 0.
    estimate_mask : (T, B, K) bool, optional: the slots reported (e.g. existence > 0.5).
    truth_mask : (T, B, J) bool, optional: the targets present (absent ones count 0).

    Returns
    -------
    (T, B, J) int64.
    """
    check_tensor(estimate, "estimate")
    check_tensor(truth, "truth")
    if estimate.dim() != 4 or truth.dim() != 4 or estimate.shape[:2] != truth.shape[:2] or min(
            estimate.shape[-1], truth.shape[-1]) < 3:
        raise ValueError(f"estimate has shape {tuple(estimate.shape)} and truth {tuple(truth.shape)}, expected "
                         "(T, B, K, D) and (T, B, J, D) with the same T, B and D >= 3")
    check_positive(radius, "radius")
    d = torch.linalg.vector_norm(_positions(estimate).unsqueeze(-2) - _positions(truth).unsqueeze(-3), dim=-1)
    near = d < radius  # (T, B, K, J); NaN estimates are never near
    if estimate_mask is not None:
        check_shape(estimate_mask, "estimate_mask", tuple(estimate.shape[:3]))
        near = near & estimate_mask.to(torch.bool).unsqueeze(-1)
    count = near.sum(-2)
    if truth_mask is not None:
        check_shape(truth_mask, "truth_mask", tuple(truth.shape[:3]))
        count = torch.where(truth_mask.to(torch.bool), count, torch.zeros_like(count))
    return count


def amplitude_swapped(estimate: Tensor, truth: Tensor) -> Tensor:
    """Whether the slot with the largest estimated amplitude lies nearest (in position) a
    target other than the strongest one, per step: slots that left an unresolved crossing on
    each other's paths while each kept its own amplitude (the crossing study's late gaps,
    docs/tracks.md), whatever the labels.

    Parameters
    ----------
    estimate : (T, B, K, D) slot estimates; truth : (T, B, J, D) true states, ``D >= 5`` with
        the amplitude ``rho`` at index 4 (the radar's layout) and positions at 0 and 2.

    Returns
    -------
    (T, B) bool (False where an amplitude or position is NaN).

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.metrics import amplitude_swapped
    >>> truth = torch.tensor([[[[0.0, 0, 0, 0, 12.0], [100.0, 0, 0, 0, 6.0]]]])  # (T, B, J, D)
    >>> swapped = torch.tensor([[[[0.0, 0, 0, 0, 6.0], [100.0, 0, 0, 0, 12.0]]]])  # each on the other's target
    >>> amplitude_swapped(truth, truth), amplitude_swapped(swapped, truth)
    (tensor([[False]]), tensor([[True]]))
    """
    check_tensor(estimate, "estimate")
    check_tensor(truth, "truth")
    if estimate.dim() != 4 or truth.dim() != 4 or estimate.shape[:2] != truth.shape[:2] or min(
            estimate.shape[-1], truth.shape[-1]) <= RHO:
        raise ValueError(f"estimate has shape {tuple(estimate.shape)} and truth {tuple(truth.shape)}, expected "
                         f"(T, B, K, D) and (T, B, J, D) with the same T, B and D > {RHO} (an amplitude)")
    strongest = torch.nan_to_num(estimate[..., RHO], nan=-math.inf).argmax(-1, keepdim=True)  # (T, B, 1)
    at = _positions(take_along(estimate, strongest.unsqueeze(-1), -2))  # (T, B, 1, 2)
    d = torch.linalg.vector_norm(at - _positions(truth), dim=-1)  # (T, B, J)
    nearest = torch.nan_to_num(d, nan=math.inf).argmin(-1)
    known = d.isfinite().any(-1) & estimate[..., RHO].isfinite().any(-1)
    return known & (nearest != truth[..., RHO].argmax(-1))


def longest_run(flags: Tensor) -> Tensor:
    """Longest run of consecutive ``True`` along the first (time) dim: ``(T, ...) -> (...)``
    int64 (e.g. the longest stretch a target stays uncovered, ``slot_coverage(...) == 0``).
    """
    check_tensor(flags, "flags")
    if flags.dim() < 1:
        raise ValueError(f"flags has shape {tuple(flags.shape)}, expected (T, ...)")
    run = torch.zeros(flags.shape[1:], dtype=torch.int64, device=flags.device)
    best = torch.zeros_like(run)
    for f in flags.to(torch.bool):  # a loop over time only
        run = torch.where(f, run + 1, torch.zeros_like(run))
        best = torch.maximum(best, run)
    return best


def identity_switches(estimate: Tensor, truth: Tensor, *, gate: float = 20.0) -> Tensor:
    """Identity switches per run (the IDSW count of the CLEAR MOT metrics, Bernardin and
    Stiefelhagen 2008): at every step the slots are assigned to the true targets by an
    optimal assignment on the squared position error (:func:`match_tracks` per step), an
    assignment farther than ``gate`` does not count, and a true target whose assigned slot
    differs from the slot it had at its last counted step is one switch.

    Parameters
    ----------
    estimate, truth : (T, B, K, D) (the same K: every slot a target).
    gate : [m] > 0.

    Returns
    -------
    (B,) int64.
    """
    check_positive(gate, "gate")
    _check_tracks(estimate, truth)
    _, perm = match_tracks(estimate, truth, per_step=True)  # (T, B, K): slot of true target k
    matched = estimate.gather(2, perm[..., None].expand(estimate.shape))
    valid = position_error(matched, truth) < gate  # (T, B, K)
    last = torch.full(perm.shape[1:], -1, dtype=torch.int64, device=perm.device)
    switches = torch.zeros(perm.shape[1], dtype=torch.int64, device=perm.device)
    for p, v in zip(perm, valid):  # a loop over time only
        changed = v & (last >= 0) & (p != last)
        switches = switches + changed.sum(-1)
        last = torch.where(v, p, last)
    return switches


# -- set metrics: OSPA, GOSPA, cardinality ------------------------------------------------


