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
from typing import TYPE_CHECKING, NamedTuple, cast

import torch
from torch.utils._pytree import tree_map

from ._validation import (
    check_finite,
    check_positive,
    check_positive_int,
    check_shape,
    check_tensor,
    measurement_leaves,
)
from .typing import VX, VY, Tensor, X, Y

if TYPE_CHECKING:  # the models import nothing from here; annotations only
    from .models.base import MotionModel, SensorModel
    from .models.multitarget import Exclusion

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
    "longest_run",
    "identity_switches",
    "cardinality_error",
    "pcrb_position_rmse",
    "MAPTrajectory",
    "map_trajectory",
]


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


# -- optimal assignment -----------------------------------------------------------------

#: Largest number of columns for which ``method="auto"`` solves exactly by dynamic
#: programming (``2^m`` subsets); above it the auction algorithm runs.
DP_MAX_COLUMNS = 8


def optimal_assignment(cost: Tensor, *, method: str = "auto", rtol: float = 1e-9) -> Tensor:
    """Minimum-cost assignment of rows to columns, batched over leading dims.

    ``perm[..., i]`` is the column assigned to row ``i``; the total
    ``sum_i cost[..., i, perm[..., i]]`` is minimal over all one-to-one assignments.

    Parameters
    ----------
    cost : (..., n, m) finite costs. Rectangular costs are allowed: with ``n <= m`` every
        row gets a distinct column; with ``n > m`` only ``m`` rows are assigned and the
        others get ``-1`` (solved on the transpose).
    method : ``"dp"`` exact dynamic programming over column subsets (``O(n m 2^m)`` per
        problem), ``"auction"`` (Bertsekas' auction with epsilon scaling), or ``"auto"``
        (``"dp"`` when ``min(n, m) <= 8``, else ``"auction"``).
    rtol : auction only: the total cost found is within ``rtol * (max cost - min cost)``
        of the minimum of each problem (see :func:`_auction`); the assignment is the
        exact optimum whenever the optimum is unique by more than that margin.

    Returns
    -------
    (..., n) int64 column indices (``-1`` for unassigned rows when ``n > m``).

    No Python loop runs over the batch: the dynamic programme loops over the n rows
    (stages), the auction over bidding rounds, each vectorised over every problem.
    Compare :func:`scipy.optimize.linear_sum_assignment`, which solves one problem.
    """
    check_tensor(cost, "cost")
    if cost.dim() < 2 or cost.shape[-1] == 0 or cost.shape[-2] == 0:
        raise ValueError(f"cost has shape {tuple(cost.shape)}, expected (..., n, m) with n, m >= 1")
    if not cost.is_floating_point():
        cost = cost.double()
    check_finite(cost, "cost")
    if method not in ("auto", "dp", "auction"):
        raise ValueError(f"method must be 'auto', 'dp' or 'auction', got {method!r}")
    n, m = cost.shape[-2:]
    if n > m:  # assign each column a row on the transpose, then invert
        rows = optimal_assignment(cost.mT, method=method, rtol=rtol)  # (..., m)
        perm = torch.full(cost.shape[:-1], -1, dtype=torch.long, device=cost.device)
        cols = torch.arange(m, device=cost.device).expand_as(rows)
        return perm.scatter(-1, rows, cols)
    if method == "auto":
        method = "dp" if m <= DP_MAX_COLUMNS else "auction"
    if method == "dp" and m > 16:
        raise ValueError(f"method='dp' needs 2^m subsets; cost has m = {m} > 16 columns, use 'auction'")
    batch = cost.shape[:-2]
    flat = cost.reshape((-1, n, m))
    if flat.shape[0] == 0:
        return torch.empty(batch + (n,), dtype=torch.long, device=cost.device)
    if method == "dp":
        perm = _assignment_dp(flat)
    else:
        check_positive(rtol, "rtol")
        if m > n:  # dummy rows of one constant cost absorb the spare columns: same optimum
            fill = flat.amin(dim=(1, 2), keepdim=True).expand(-1, m - n, m)
            flat = torch.cat([flat, fill], dim=1)
        perm = _auction(flat, rtol)[:, :n]
    return perm.reshape(batch + (n,))


def _assignment_dp(cost: Tensor) -> Tensor:
    """Exact assignment by dynamic programming over column subsets.

    ``V_i(S)`` = least cost of assigning rows ``0..i-1`` to the column set ``S`` with
    ``|S| = i``; ``V_{i+1}(S) = min_{j in S} V_i(S - {j}) + cost[i, j]``. The minimiser
    ``j`` is stored per stage and subset, and the assignment read back from the best final
    subset. ``cost (P, n, m)`` with ``n <= m`` -> ``(P, n)``.
    """
    p, n, m = cost.shape
    dev = cost.device
    masks = torch.arange(2**m, device=dev)  # (2^m,)
    bits = torch.arange(m, device=dev)
    has = (masks[:, None] >> bits) & 1 == 1  # (2^m, m): column j in subset S
    prev = masks[:, None] ^ (1 << bits)  # (2^m, m): S - {j}
    inf = torch.tensor(float("inf"), dtype=cost.dtype, device=dev)
    value = torch.full((p, 2**m), float("inf"), dtype=cost.dtype, device=dev)
    value[:, 0] = 0.0
    choices = []
    for i in range(n):  # stages: rows, each vectorised over problems and subsets
        cand = value[:, prev] + cost[:, i, None, :]  # (P, 2^m, m)
        cand = torch.where(has, cand, inf)
        value, choice = cand.min(dim=-1)
        choices.append(choice)
    subset = value.argmin(dim=-1)  # (P,) best final subset (only |S| = n are finite)
    perm = torch.empty((p, n), dtype=torch.long, device=dev)
    for i in reversed(range(n)):
        j = choices[i].gather(1, subset[:, None]).squeeze(1)
        perm[:, i] = j
        subset = subset ^ (1 << j)
    return perm


def _auction(cost: Tensor, rtol: float) -> Tensor:
    """Bertsekas' auction algorithm (Jacobi form: every unassigned row bids at once) with
    epsilon scaling, on square problems ``cost (P, n, n)`` -> ``(P, n)``.

    Rows are bidders maximising the benefit ``a_ij = -c_ij`` (scaled to [-1, 0] per
    problem) against column prices ``p_j``. Each unassigned row bids for its best column
    ``j* = argmax_j a_ij - p_j`` with increment ``v1 - v2 + eps`` (best minus second-best
    value); each column goes to its highest bidder (lowest row index on ties) and its
    previous owner is unassigned (Bertsekas 1988, "The auction algorithm: a distributed
    relaxation method for the assignment problem", Ann. Oper. Res. 14).

    Optimality within ``n * eps``: every assigned row keeps eps-complementary slackness,
    ``a_{i,j_i} - p_{j_i} >= max_k (a_ik - p_k) - eps`` (it held when the row won its column
    at the bid price, and later rounds only raise other prices). At termination all rows are
    assigned, so for the found assignment ``{j_i}`` and any other ``{k_i}``:
    ``sum_i a_{i,j_i} = sum_i (a_{i,j_i} - p_{j_i}) + sum_j p_j
    >= sum_i (a_{i,k_i} - p_{k_i} - eps) + sum_j p_j = sum_i a_{i,k_i} - n eps``.
    The Jacobi form (all unassigned rows bid at once, each column keeps the best bid)
    keeps the property and terminates like the sequential one (each winning bid raises a
    price by at least eps, and benefits are bounded).

    Epsilon scaling runs phases with ``eps = 1/8, 1/64, ...`` down to ``rtol / n``,
    keeping the prices between phases (the assignment restarts empty); the final phase
    leaves a total cost within ``n * (rtol / n) * (max c - min c) = rtol * (max c - min c)``
    of the minimum.
    Runs in float64.
    """
    p, n, _ = cost.shape
    dev = cost.device
    c = cost.double()
    lo = c.amin(dim=(1, 2), keepdim=True)
    span = (c.amax(dim=(1, 2), keepdim=True) - lo).clamp_min(torch.finfo(torch.float64).tiny)
    benefit = -(c - lo) / span  # (P, n, n) in [-1, 0]
    if n == 1:
        return torch.zeros((p, 1), dtype=torch.long, device=dev)
    prices = torch.zeros((p, n), dtype=torch.float64, device=dev)
    rows = torch.arange(n, device=dev).expand(p, n)
    neg_inf = torch.tensor(float("-inf"), dtype=torch.float64, device=dev)
    eps_final = rtol / n
    num_phases = max(1, math.ceil(math.log(0.125 / eps_final) / math.log(8.0)) + 1)
    for phase in range(num_phases):
        eps = max(0.125 / 8.0**phase, eps_final)
        row_col = torch.full((p, n), -1, dtype=torch.long, device=dev)  # column of each row
        col_row = torch.full((p, n), -1, dtype=torch.long, device=dev)  # row owning each column
        while True:  # bidding rounds (each vectorised over every problem and row)
            bidding = row_col < 0
            if not bool(bidding.any()):
                break
            values = benefit - prices[:, None, :]  # (P, n, n)
            top, arg = values.topk(2, dim=-1)
            target = arg[..., 0]  # (P, n)
            bid = prices.gather(1, target) + (top[..., 0] - top[..., 1]) + eps
            bid = torch.where(bidding, bid, neg_inf)
            best = torch.full((p, n), float("-inf"), dtype=torch.float64, device=dev)
            best = best.scatter_reduce(1, target, bid, "amax")
            candidate = bidding & (bid == best.gather(1, target))
            winner = torch.full((p, n), n, dtype=torch.long, device=dev)
            winner = winner.scatter_reduce(1, target, torch.where(candidate, rows, n), "amin")
            won = winner < n  # (P, n) columns that received a winning bid
            # unassign the previous owners (column n of the padded tensor is a sink)
            sink = torch.full((p, 1), -1, dtype=torch.long, device=dev)
            old = torch.where(won & (col_row >= 0), col_row, n)
            row_col = torch.cat([row_col, sink], 1).scatter(1, old, -1)[:, :n]
            new = torch.where(won, winner, n)
            cols = torch.arange(n, device=dev).expand(p, n)
            row_col = torch.cat([row_col, sink], 1).scatter(1, new, cols)[:, :n]
            col_row = torch.where(won, winner, col_row)
            prices = torch.where(won, best, prices)
    return row_col


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
    diff = _positions(truth)[:, :, :, None, :] - _positions(estimate)[:, :, None, :, :]
    cost = diff.square().sum(-1)  # (T, B, K, K): truth k vs estimate j
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


def _set_assignment(x: Tensor, y: Tensor, x_mask: Tensor | None, y_mask: Tensor | None, c: float, p: float,
                    miss: float, name: str) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The optimal assignment behind OSPA and GOSPA: minimum over assignments of
    ``sum min(d, c)^p`` plus ``miss`` per unassigned point.

    Both sets are padded to ``P = max(m, n)`` slots; the square cost is ``min(d, c)^p``
    between two real points, ``miss`` between a real point and a padding slot and 0
    between two padding slots. With ``miss >= c^p / 2`` an optimal assignment never pairs
    a real point with padding while a real point of the other set is left to padding (the
    two ``miss`` terms cost at least ``min(d, c)^p``), so the padded optimum is the
    optimum over assignments of the smaller set into the larger one plus ``miss`` times
    the cardinality difference.

    Returns ``(cost (..., P), close (..., P), |X| (...), |Y| (...))``: the cost of each
    row's assigned pair (its sum is the optimum) and whether the pair joins two real points
    closer than ``c`` (a localised pair; a real pair at ``d >= c`` costs ``c^p``, a missed
    and a false point at ``c^p / 2`` each).
    """
    check_tensor(x, f"{name} x")
    check_tensor(y, f"{name} y")
    if x.dim() < 2 or y.dim() != x.dim() or x.shape[-1] != y.shape[-1] or x.shape[:-2] != y.shape[:-2]:
        raise ValueError(f"{name}: x has shape {tuple(x.shape)} and y {tuple(y.shape)}, expected "
                         "(..., m, d) and (..., n, d) with the same leading dims and d")
    check_finite(x, f"{name} x")
    check_finite(y, f"{name} y")
    check_positive(c, "c")
    p = check_positive(p, "p")
    if p < 1:
        raise ValueError(f"p must be >= 1, got {p!r}")
    lead, m, n = x.shape[:-2], x.shape[-2], y.shape[-2]
    dtype = torch.promote_types(x.dtype, y.dtype)
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    x, y = x.to(dtype), y.to(dtype)
    xm = torch.ones(lead + (m,), dtype=torch.bool, device=x.device) if x_mask is None else x_mask
    ym = torch.ones(lead + (n,), dtype=torch.bool, device=x.device) if y_mask is None else y_mask
    check_shape(xm, "x_mask", tuple(x.shape[:-1]))
    check_shape(ym, "y_mask", tuple(y.shape[:-1]))
    xm, ym = xm.to(torch.bool), ym.to(torch.bool)
    size = max(m, n)
    if size == 0:
        zero = torch.zeros(lead, dtype=dtype, device=x.device)
        none = torch.zeros(lead + (0,), dtype=dtype, device=x.device)
        return none, none.bool(), zero, zero
    pad_x, pad_y = size - m, size - n
    x = torch.nn.functional.pad(x, (0, 0, 0, pad_x))
    y = torch.nn.functional.pad(y, (0, 0, 0, pad_y))
    xm = torch.nn.functional.pad(xm, (0, pad_x))
    ym = torch.nn.functional.pad(ym, (0, pad_y))
    dist = torch.linalg.vector_norm(x.unsqueeze(-2) - y.unsqueeze(-3), dim=-1)  # (..., P, P)
    both = xm.unsqueeze(-1) & ym.unsqueeze(-2)
    one = xm.unsqueeze(-1) ^ ym.unsqueeze(-2)
    cost = torch.where(both, dist.clamp(max=c).pow(p), torch.zeros_like(dist))
    cost = torch.where(one, torch.full_like(cost, miss), cost)
    perm = optimal_assignment(cost.detach()).unsqueeze(-1)
    close = (both & (dist < c)).gather(-1, perm).squeeze(-1)
    return cost.gather(-1, perm).squeeze(-1), close, xm.sum(-1).to(dtype), ym.sum(-1).to(dtype)


def _set_distance_sum(x: Tensor, y: Tensor, x_mask: Tensor | None, y_mask: Tensor | None, c: float, p: float,
                      miss: float, name: str) -> tuple[Tensor, Tensor, Tensor]:
    """``(optimal total (...), |X| (...), |Y| (...))`` of :func:`_set_assignment`."""
    cost, _, nx, ny = _set_assignment(x, y, x_mask, y_mask, c, p, miss, name)
    return cost.sum(-1), nx, ny


def ospa(x: Tensor, y: Tensor, *, c: float, p: float = 2.0, x_mask: Tensor | None = None,
         y_mask: Tensor | None = None) -> Tensor:
    """OSPA distance of order ``p`` with cut-off ``c`` (Schuhmacher, Vo and Vo 2008, eq. 3).

    For ``|X| = m <= n = |Y|``::

        d_p^c(X, Y) = ( (1/n) (min_pi sum_{i<=m} min(c, |x_i - y_pi(i)|)^p + c^p (n - m)) )^(1/p)

    (symmetric in X, Y); 0 when both sets are empty, ``c`` when exactly one is.

    Parameters
    ----------
    x : (..., m, d) points of the first set (e.g. estimated positions), padded.
    y : (..., n, d) points of the second set (e.g. true positions), padded.
    c : cut-off > 0 [m]; p : order >= 1.
    x_mask, y_mask : (..., m), (..., n) bool, True for a real point (default: all real).

    Returns
    -------
    (...) distances, batched over the leading dims (e.g. ``(T, B)``).
    """
    total, nx, ny = _set_distance_sum(x, y, x_mask, y_mask, c, float(p), float(c) ** float(p), "ospa")
    big = torch.maximum(nx, ny)
    return torch.where(big > 0, total / big.clamp(min=1), torch.zeros_like(total)).pow(1.0 / float(p))


class OSPAParts(NamedTuple):
    """OSPA and its two components (Schuhmacher, Vo and Vo 2008, sec. IV-B), each ``(...)``.

    ``total^p = localisation^p + cardinality^p`` with, for ``m <= n``,
    ``localisation = ((1/n) min_pi sum_i min(c, d_i)^p)^(1/p)`` and
    ``cardinality = (c^p (n - m) / n)^(1/p)``.

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.metrics import ospa_parts
    >>> estimates = torch.tensor([[0.0, 0.0], [10.0, 0.0]])  # (m, d): one of them false
    >>> truth = torch.tensor([[3.0, 4.0]])                   # (n, d): 5 m from the first
    >>> ospa_parts(estimates, truth, c=10.0, p=1)           # (5 + 10) / 2 = 5 / 2 + 10 / 2
    OSPAParts(total=tensor(7.5000), localisation=tensor(2.5000), cardinality=tensor(5.))
    """

    total: Tensor
    localisation: Tensor
    cardinality: Tensor


def ospa_parts(x: Tensor, y: Tensor, *, c: float, p: float = 2.0, x_mask: Tensor | None = None,
               y_mask: Tensor | None = None) -> OSPAParts:
    """:func:`ospa` split into its localisation and cardinality components
    (:class:`OSPAParts`); parameters as :func:`ospa`.
    """
    miss = float(c) ** float(p)
    total, nx, ny = _set_distance_sum(x, y, x_mask, y_mask, c, float(p), miss, "ospa")
    big = torch.maximum(nx, ny).clamp(min=1)
    card = miss * (nx - ny).abs()
    loc = (total - card).clamp(min=0.0)
    e = 1.0 / float(p)
    return OSPAParts((total / big).pow(e), (loc / big).pow(e), (card / big).pow(e))


def gospa(x: Tensor, y: Tensor, *, c: float, p: float = 2.0, x_mask: Tensor | None = None,
          y_mask: Tensor | None = None) -> Tensor:
    """GOSPA distance with ``alpha = 2`` (Rahmathullah, Garcia-Fernandez and Svensson 2017).

    Eq. 2, for ``|X| = m <= n = |Y|``::

        d_p^(c,2)(X, Y) = ( min_pi sum_{i<=m} min(c, |x_i - y_pi(i)|)^p + (c^p / 2) (n - m) )^(1/p),

    equivalently localisation error of the assigned pairs plus ``c^p / 2`` per missed or
    false target (pairs farther apart than ``c`` count as one of each). Not normalised by
    the cardinality: 0 for two empty sets, ``(n c^p / 2)^(1/p)`` against an empty set.

    Parameters and returns as :func:`ospa`.
    """
    miss = float(c) ** float(p) / 2.0
    total, _, _ = _set_distance_sum(x, y, x_mask, y_mask, c, float(p), miss, "gospa")
    return total.pow(1.0 / float(p))


class GOSPAParts(NamedTuple):
    """GOSPA (``alpha = 2``) and its parts (Rahmathullah, Garcia-Fernandez and Svensson 2017,
    eq. 3), each ``(...)``.

    ::

        total^p = localisation^p + (c^p / 2) (missed + false)

    Attributes
    ----------
    total : the GOSPA distance (:func:`gospa`) [m].
    localisation : ``(sum over the localised pairs of d^p)^(1/p)`` [m]: the pairs of the
        optimal assignment closer than ``c``.
    missed : number of true points not in a localised pair (float).
    false : number of estimated points not in a localised pair (float).

    Stone Soup's ``GOSPAMetric`` reports the same split in units of ``d^p``: its
    ``localisation`` is ``localisation^p`` here, its ``missed`` and ``false`` are
    ``c^p / 2`` times the counts here.

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.metrics import gospa_parts
    >>> estimates = torch.tensor([[0.0, 0.0], [10.0, 0.0]])  # x: one estimate too many
    >>> truth = torch.tensor([[3.0, 4.0]])                   # y: 5 m from the first
    >>> gospa_parts(estimates, truth, c=10.0, p=1)          # 5 + (10 / 2) * 1 false
    GOSPAParts(total=tensor(10.), localisation=tensor(5.), missed=tensor(0.), false=tensor(1.))
    """

    total: Tensor
    localisation: Tensor
    missed: Tensor
    false: Tensor


def gospa_parts(x: Tensor, y: Tensor, *, c: float, p: float = 2.0, x_mask: Tensor | None = None,
                y_mask: Tensor | None = None) -> GOSPAParts:
    """:func:`gospa` split into localisation error, missed and false points
    (:class:`GOSPAParts`); ``x`` are the estimates, ``y`` the truth. Parameters as
    :func:`ospa`.

    A pair of the optimal assignment at ``d >= c`` costs ``c^p``, as much as leaving both
    points unassigned, so it counts as one missed and one false point (paper eq. 3: the
    assignment sets ``gamma`` hold only pairs closer than ``c``).
    """
    e = 1.0 / float(p)
    cost, close, nx, ny = _set_assignment(x, y, x_mask, y_mask, c, float(p), float(c) ** float(p) / 2.0, "gospa")
    paired = close.sum(-1).to(cost.dtype)
    loc = torch.where(close, cost, torch.zeros_like(cost)).sum(-1)
    return GOSPAParts(cost.sum(-1).pow(e), loc.pow(e), ny - paired, nx - paired)


def cardinality_error(estimated_count: Tensor, true_count: Tensor) -> Tensor:
    """Absolute error of the number of targets, ``|n_hat - n|``, elementwise.

    Parameters
    ----------
    estimated_count : (...) estimated numbers (e.g. the expected number of targets, the
        sum of existence probabilities, or the number of reported slots).
    true_count : (...) true numbers, same shape.

    Returns
    -------
    (...) float.
    """
    check_tensor(estimated_count, "estimated_count")
    check_tensor(true_count, "true_count")
    if estimated_count.shape != true_count.shape:
        raise ValueError(f"estimated_count has shape {tuple(estimated_count.shape)}, expected "
                         f"{tuple(true_count.shape)} (the shape of true_count)")
    est = estimated_count if estimated_count.is_floating_point() else estimated_count.to(torch.get_default_dtype())
    return (est - true_count.to(est.dtype)).abs()


def pcrb_position_rmse(sensor: SensorModel, motion: MotionModel, x: Tensor, *, generator: torch.Generator,
                       num_frames: int = 200, iterations: int = 200) -> Tensor:
    """Floor of a filter's per-step position RMSE for each target alone: the steady-state
    posterior Cramer-Rao bound (Tichavsky, Muravchik and Nehorai 1998, eq. 21 for a linear
    Gaussian motion model) of the kinematic state ``[x, vx, y, vy]``.

    The one-frame Fisher information ``J_z = E[s s^T]`` of the sensor's exact likelihood at
    ``x`` is estimated by Monte Carlo: ``num_frames`` frames simulated from each target alone,
    ``s`` the autograd score of ``sensor.log_likelihood`` with respect to the kinematic
    components (the other components, such as a radar amplitude, are taken as known). The
    recursion ``J_k = (Q + F J_{k-1}^{-1} F^T)^{-1} + J_z`` with the motion model's ``F`` and
    ``Q`` (kinematic block) is run ``iterations`` times from ``J_z`` to its fixed point. The
    floor of target ``j``'s position RMSE is ``sqrt(P_xx + P_yy)`` with ``P = J^{-1}``: on
    trajectories drawn from the motion model, no filter does better on average in steady
    state, with every other target away and the known components known, so a scene's
    interactions and unknowns only add to it. It bounds the error averaged over such
    trajectories, not on one truth: a truth that moves with less noise than the model's ``Q``
    (a noise-free one, say) is tracked below it for as long as it keeps so (the soak study's
    clairvoyant reference, 10-20 % below), as are the first steps after a sharp start. On a
    linear-Gaussian position sensor it is the Kalman filter's steady-state error.

    Parameters
    ----------
    sensor : a sensor model whose ``log_likelihood`` is differentiable in the state.
    motion : a motion model with ``F`` and ``Q`` ``(D, D)`` (linear Gaussian, such as
        :class:`~torchmcmcpf.models.ConstantVelocity`).
    x : (B, J, D) target states at which the information is taken (a mid-run truth, say).
    generator : draws the frames.
    num_frames : M >= 2 frames per target (relative Monte Carlo error of ``J_z`` about
        ``sqrt(2 / M)``).
    iterations : >= 1 steps of the recursion.

    Returns
    -------
    (B, J) float64, the floor [m] of each target's per-step position RMSE.
    """
    check_tensor(x, "x")
    if x.dim() != 3 or x.shape[-1] < 4:
        raise ValueError(f"x has shape {tuple(x.shape)}, expected (B, J, D) with D >= 4")
    if not isinstance(num_frames, int) or num_frames < 2:
        raise ValueError(f"num_frames must be an int >= 2, got {num_frames!r}")
    if not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations must be an int >= 1, got {iterations!r}")
    if not (hasattr(motion, "F") and hasattr(motion, "Q")):
        raise ValueError(f"motion must be linear Gaussian with F and Q, got {type(motion).__name__}")
    kin = [X, VX, Y, VY]
    b, j, d = x.shape
    targets = x.detach().reshape(b * j, 1, d)
    frames = targets.repeat(num_frames, 1, 1)  # (M P, 1, D): frame m of target p at row m P + p
    z = sensor.simulate(frames, generator=generator)
    at = frames.unsqueeze(1).clone().requires_grad_(True)  # (M P, N = 1, K = 1, D)
    with torch.enable_grad():
        (score,) = torch.autograd.grad(sensor.log_likelihood(at, z).sum(), at)
    s = score[:, 0, 0, kin].to(torch.float64).reshape(num_frames, b * j, 4)
    info = torch.einsum("mpa,mpb->pab", s, s) / num_frames  # (P, 4, 4)
    F = cast(Tensor, motion.F).to(torch.float64)[kin][:, kin]
    Q = cast(Tensor, motion.Q).to(torch.float64)[kin][:, kin]
    bound = info + 1e-9 * torch.eye(4, dtype=info.dtype)  # a flat prior: J_z alone may be singular
    for _ in range(iterations):  # the recursion's steps, batched over the targets
        bound = torch.linalg.inv(Q + F @ torch.linalg.inv(bound) @ F.T) + info
    cov = torch.linalg.inv(bound)
    return (cov[:, 0, 0] + cov[:, 2, 2]).clamp(min=0).sqrt().reshape(b, j)


class MAPTrajectory(NamedTuple):
    """A local maximum of the posterior over a window of frames (:func:`map_trajectory`).

    Attributes
    ----------
    x : (T, B, K, D) the trajectory, every target's state at every frame.
    log_posterior : (B,) its log posterior density (up to the data's normalising constant):
        ``log_lik`` summed over the frames plus the motion, exclusion and prior terms.
    log_lik : (T, B) ``log p(z_t | x_t)`` per frame.
    grad_norm : (B,) the largest absolute component of the gradient there (0 at an exact
        stationary point; compare it with the scale of the states).

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.metrics import map_trajectory
    >>> motion, sensor = tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=0.1)
    >>> z = torch.tensor([[0.0, 0.0], [1.0, 0.5], [2.0, 1.0], [3.0, 1.5]], dtype=torch.float64)
    >>> fit = map_trajectory(sensor, motion, z.view(4, 1, 1, 2), torch.zeros(4, 1, 1, 4, dtype=torch.float64))
    >>> fit.x.shape, fit.log_lik.shape                      # (T, B, K, D), (T, B)
    (torch.Size([4, 1, 1, 4]), torch.Size([4, 1]))
    >>> fit.x[-1, 0, 0].round(decimals=2)                   # [x, vx, y, vy]: the velocity is recovered
    tensor([3.0000, 1.0000, 1.5000, 0.5000], dtype=torch.float64)
    >>> bool(fit.grad_norm < 1e-4)
    True
    """

    x: Tensor
    log_posterior: Tensor
    log_lik: Tensor
    grad_norm: Tensor


def map_trajectory(sensor: SensorModel, motion: MotionModel, z: object, start: Tensor, *,
                   prior_mean: Tensor | None = None, prior_cov: Tensor | None = None,
                   exclusion: Exclusion | None = None, max_iter: int = 1000) -> MAPTrajectory:
    """The trajectory that locally maximises the model's own posterior over a window of
    frames, found from ``start`` by L-BFGS on autograd gradients: what the model and the data
    say, without a particle approximation.

    The objective of each run is the log density of the whole window,
    ``sum_t log p(z_t | x_t) + sum_{t >= 1} sum_k log f(x_{t,k} | x_{t-1,k})`` plus, with an
    exclusion factor, ``sum_t log Phi(x_t)`` (the multitarget prior's interaction term of the
    filters that have it, :mod:`~torchmcmcpf.models.multitarget`; pass the filter's own to
    maximise its posterior) and, with a prior, ``sum_k log N(x_{0,k}; prior_mean_k,
    prior_cov)`` (without one the first frame's state is free: the window's start is not
    constrained by earlier frames). On a linear-Gaussian model it is the Kalman (RTS)
    smoother's mean (tested). On a nonlinear
    one it is the local maximum uphill from ``start``: started from a filter's estimate, a
    trajectory that stays where the filter is says the data and the model support the
    filter there (a mode of the posterior: a tracker may hold it); one that moves to the
    truth says the filter's estimate is no mode of its own posterior, so the gap between the
    estimate and the truth is the filter's (its particle approximation), not the model's
    (docs/tracks.md: the crossing's late gaps).

    Runs are independent; their objectives are summed and optimised together (the gradient
    separates), ``max_iter`` L-BFGS iterations with a strong-Wolfe line search in all, in the
    dtype of ``start`` (float64 advised). Frames, runs, targets and components are tensor
    dims (the ``T x B`` frames are scored as one batch of runs).

    Parameters
    ----------
    sensor : its ``log_likelihood`` must be differentiable in the state (every sensor of the
        library with a density is; existence flags are not used: every slot is a target).
    motion : a motion model with a density (``log_prob``).
    z : the window's measurements, any :class:`~torchmcmcpf.typing.Measurement` with a
        leading ``T`` dim (for grid sensors ``(T, B, *G)``).
    start : (T, B, K, D) the trajectory to start from (a filter's estimate ``result.mean``,
        or the truth).
    prior_mean : (B, K, D), optional: a Gaussian prior on the first frame's state, with
    prior_cov : (D, D) or (B, K, D, D), its covariance (both or neither).
    exclusion : an :class:`~torchmcmcpf.models.multitarget.Exclusion`, optional (counted only
        when the sensor declares its resolution, as in the filters).
    max_iter : >= 1.

    Returns
    -------
    :class:`MAPTrajectory`.
    """
    check_tensor(start, "start")
    if start.dim() != 4:
        raise ValueError(f"start has shape {tuple(start.shape)}, expected (T, B, K, D)")
    check_finite(start, "start")
    check_positive_int(max_iter, "max_iter")
    from .models.multitarget import check_exclusion, log_exclusion

    check_exclusion(exclusion)
    t_len, b, k, d = start.shape
    if (prior_mean is None) != (prior_cov is None):
        raise ValueError("prior_mean and prior_cov must be given together, got only "
                         f"{'prior_mean' if prior_cov is None else 'prior_cov'}")
    leaves = measurement_leaves(z, "z")
    if any(a.shape[:1] != (t_len,) for a in leaves):
        raise ValueError(f"z must be measurements with a leading T = {t_len} dim (start's), got leading dims "
                         f"{[tuple(a.shape[:1]) for a in leaves]}")
    dtype = start.dtype
    z = tree_map(lambda a: a.to(dtype) if torch.is_tensor(a) and a.is_floating_point() else a, z)
    prior = None
    if prior_mean is not None and prior_cov is not None:
        check_shape(prior_mean, "prior_mean", (b, k, d))
        if tuple(prior_cov.shape) not in ((d, d), (b, k, d, d)):
            raise ValueError(f"prior_cov has shape {tuple(prior_cov.shape)}, expected {(d, d)} or {(b, k, d, d)}")
        prior = torch.distributions.MultivariateNormal(prior_mean.to(dtype),
                                                       covariance_matrix=prior_cov.to(dtype))

    # the frames as runs of one batch: one likelihood call per evaluation, not one per frame
    frames = tree_map(lambda a: a.reshape((t_len * b,) + tuple(a.shape[2:])) if torch.is_tensor(a) else a, z)

    def terms(x: Tensor) -> tuple[Tensor, Tensor]:  # log_lik (T, B), log_posterior (B,)
        log_lik = sensor.log_likelihood(x.reshape(t_len * b, 1, k, d), frames)[:, 0].reshape(t_len, b)
        total = log_lik.sum(0)
        if t_len > 1:
            total = total + motion.log_prob(x[1:], x[:-1]).sum((0, -1))
        total = total + log_exclusion(exclusion, sensor, x).sum(0)  # zeros without one
        if prior is not None:
            total = total + prior.log_prob(x[0]).sum(-1)
        return log_lik, total

    with torch.no_grad():
        _, first = terms(start)
    if not bool(torch.isfinite(first).all()):
        raise ValueError(f"start has log posterior {first.tolist()} (not finite) in some run: start every run "
                         "where the likelihood and motion densities are finite (inside the sensor's grid)")
    x = start.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        opt = torch.optim.LBFGS([x], lr=1.0, max_iter=max_iter, tolerance_grad=1e-12, tolerance_change=1e-15,
                                history_size=50, line_search_fn="strong_wolfe")

        def closure() -> Tensor:
            opt.zero_grad()
            loss = -terms(x)[1].sum()
            loss.backward()
            return loss

        opt.step(closure)
        x_opt = x.detach()
        at = x_opt.clone().requires_grad_(True)
        log_lik, total = terms(at)
        (grad,) = torch.autograd.grad(total.sum(), at)
    return MAPTrajectory(x_opt, total.detach(), log_lik.detach(), grad.abs().amax((0, 2, 3)))
