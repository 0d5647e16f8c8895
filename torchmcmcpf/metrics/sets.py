"""Distances between sets of targets: OSPA and GOSPA with their parts, and the cardinality error
(births and deaths, clutter).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import torch

from .._validation import (
    check_finite,
    check_positive,
    check_shape,
    check_tensor,
)
from ..typing import Tensor
from .assignment import optimal_assignment

if TYPE_CHECKING:  # the models import nothing from here; annotations only
    pass


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
