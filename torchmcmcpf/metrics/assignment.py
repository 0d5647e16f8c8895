"""Optimal assignment of estimates to truths: exact by dynamic programming over subsets for a few
targets, by the auction algorithm beyond (the engine of the matched metrics and OSPA / GOSPA).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from .._validation import (
    check_finite,
    check_positive,
    check_tensor,
)
from ..typing import Tensor

#: Largest number of columns for which ``method="auto"`` solves exactly by dynamic
#: programming (``2^m`` subsets); above it the auction algorithm runs.
DP_MAX_COLUMNS = 8

if TYPE_CHECKING:  # the models import nothing from here; annotations only
    pass


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
