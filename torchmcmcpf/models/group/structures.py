"""Group structures (paper 004 eqs. 19-23, Table 2): the ``Bell(K)`` partitions of ``K`` slots as
restricted-growth label strings, and the Markov prior on the structure given the positions.

Paper 004's model as a whole, its state layouts and notation: the docstring of :mod:`torchmcmcpf.models.group`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import torch
from torch import nn

from ..._native.select import where
from ..._validation import check_positive, check_positive_int
from ...resampling import cdf, inverse_cdf
from ...runtime import squared_norm
from ...typing import Tensor
from ..existence import _probability

__all__ = ["GroupStructurePrior", "group_structures", "structure_index", "bell_number", "canonical_labels",
           "gaussian_closeness"]


@functools.cache
def bell_number(n: int) -> int:
    """Number of partitions of ``n`` items (Bell numbers 1, 1, 2, 5, 15, 52, ...)."""
    check_positive_int(n, "n", minimum=0)
    row = [1]
    for _ in range(n):
        nxt = [row[-1]]
        for v in row:
            nxt.append(nxt[-1] + v)
        row = nxt
    return row[0]


def _rows(n: int) -> tuple[tuple[int, ...], ...]:
    rows: list[tuple[int, ...]] = [(0,)]
    for _ in range(n - 1):
        rows = [r + (j,) for r in rows for j in range(max(r) + 2)]
    return tuple(rows)


_structures = functools.cache(_rows)


def group_structures(n: int, *, device: torch.device | str | None = None) -> Tensor:
    """Every partition of ``n`` targets once, as canonical labels (paper 004, Table 2).

    A row is a restricted-growth string: target 0 is in group 0 and each target's label is
    at most one more than the largest label before it; group ``h`` of a row owns leader slot
    ``h``. Rows are in lexicographic order, so for ``n = 4`` they are the 15 columns of
    Table 2 (labels minus one).

    Parameters
    ----------
    n : number of targets ``N_max >= 1``.
    device : where the table is made (default the CPU).

    Returns
    -------
    (Bell(n), n) int64.
    """
    check_positive_int(n, "n")
    # under torch.compile the rows are built without the cache, whose wrapper Dynamo warns
    # about; they are the graph's constants either way
    rows = _rows(n) if torch.compiler.is_compiling() else _structures(n)
    return torch.tensor(rows, dtype=torch.int64, device=device)


def structure_index(labels: Tensor) -> Tensor:
    """Row of :func:`group_structures` that a labelling describes: ``(*S, K) -> (*S,)``.

    ``labels`` need not be canonical (any integers in ``[0, K)`` naming the groups); they
    are relabelled in order of first appearance first.
    """
    k = labels.shape[-1]
    table = group_structures(k, device=labels.device)
    canon = canonical_labels(labels)
    # encode in base K and look up (the table is sorted lexicographically, so its codes are)
    powers = k ** torch.arange(k - 1, -1, -1, device=labels.device)
    codes = (table * powers).sum(-1)
    return torch.searchsorted(codes, (canon * powers).sum(-1).contiguous())


def canonical_labels(labels: Tensor) -> Tensor:
    """Relabel groups in order of first appearance: ``(*S, K) -> (*S, K)`` int64."""
    k = labels.shape[-1]
    same = labels.unsqueeze(-1) == labels.unsqueeze(-2)  # (*S, K, K)
    idx = torch.arange(k, device=labels.device)
    first = where(same, idx, k).amin(-1)  # first member of each target's group
    is_first = first == idx  # (*S, K)
    rank = is_first.long().cumsum(-1) - 1  # rank of each first member
    return torch.gather(rank, -1, first)


def _same_group(labels: Tensor) -> Tensor:
    return labels.unsqueeze(-1) == labels.unsqueeze(-2)


def gaussian_closeness(scale: float, power: float = 2.0) -> Callable[[Tensor, Tensor], Tensor]:
    """``h(x_i, x_j) = exp(-(|x_i - x_j| / scale)^power / 2)``, a closeness in (0, 1] (eq. 23):
    the Gaussian for ``power = 2``, a generalised Gaussian (flatter near 0, sharper at
    ``|x_i - x_j| ~ scale``) for larger powers. ``h = e^{-1/2}`` at distance ``scale``.
    """
    s = check_positive(scale, "scale")
    p = check_positive(power, "power")

    def closeness(pi: Tensor, pj: Tensor) -> Tensor:
        d2 = squared_norm(pi - pj) / s**2
        return torch.exp(-0.5 * d2 if p == 2.0 else -0.5 * d2.pow(0.5 * p))

    return closeness


class GroupStructurePrior(nn.Module):
    """Group structure transition of eqs. 19-23.

    ``p(g_t | x_{p,t-1}, g_{t-1}, e_{t-1}) = P_NC delta(g_t - g_{t-1}) + (1 - P_NC) pi(g_t)``
    (eq. 19) with ``pi(h) propto prod_{(i,j) in Delta_h} q_ij prod_{(i,j) not in Delta_h}
    (1 - q_ij)`` (eqs. 21-22) over unordered pairs ``i < j``, ``Delta_h`` the pairs in one
    group of ``h``, and ``q_ij = P_Q`` if ``e_{t-1,i} = 0`` or ``e_{t-1,j} = 0``, else
    ``closeness(x_{p,t-1,i}, x_{p,t-1,j})`` (eq. 23; the paper writes ``e_t`` in eq. 23 but
    eq. 20 and Algorithm 1, which draws ``g_t`` before ``e_t``, condition on ``e_{t-1}``).
    ``q`` is clipped to ``[1e-12, 1 - 1e-12]`` so that no structure has probability exactly
    zero under ``pi`` (two pairs at distance 0 and a third far apart would otherwise leave
    no structure). Normalised over all ``Bell(K)`` structures in log space.

    Parameters
    ----------
    p_nc : ``P_NC`` in [0, 1], probability of no change (paper: 0.6).
    p_q : ``P_Q`` in (0, 1), pair score involving an inactive target (paper: 0.05).
    closeness : ``h(p_i (*S, 2), p_j (*S, 2)) -> (*S,)`` in [0, 1]; default
        :func:`gaussian_closeness` with ``scale`` (the paper gives no ``h``).
    scale, power : of the default closeness (default 300 m and 2: two targets 300 m apart are
        in one group with score ``e^{-1/2}``); the group-merge scenario sets them from its
        geometry (:func:`~torchmcmcpf.scenarios.group_merge.group_merge`).

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.models.group import GroupStructurePrior, group_structures
    >>> prior = GroupStructurePrior(p_nc=0.6, p_q=0.05)
    >>> group_structures(2)                                  # Bell(2) = 2 structures: together, apart
    tensor([[0, 0],
            [0, 1]])
    >>> pos = torch.tensor([[[0.0, 0.0], [20.0, 0.0]]], dtype=torch.float64)   # (S, K, 2): 20 m apart
    >>> prior.log_scores(pos, torch.tensor([[True, True]])).exp().round(decimals=3)
    tensor([[0.9980, 0.0020]], dtype=torch.float64)
    >>> prior.sample(torch.tensor([1]), pos, torch.tensor([[True, True]]), generator=torch.Generator()).shape
    torch.Size([1])
    """

    def __init__(self, p_nc: float, p_q: float, closeness: Callable[[Tensor, Tensor], Tensor] | None = None, *,
                 scale: float = 300.0, power: float = 2.0) -> None:
        super().__init__()
        self.p_nc = _probability(p_nc, "p_nc")
        self.p_q = _probability(p_q, "p_q")
        if not 0.0 < self.p_q < 1.0:
            raise ValueError(f"p_q must be in (0, 1), got {p_q!r}")
        self.closeness = gaussian_closeness(scale, power) if closeness is None else closeness

    def log_scores(self, pos: Tensor, exists: Tensor) -> Tensor:
        """``log pi(h | x_{p,t-1}, e_{t-1})`` for every structure ``h`` (eqs. 21-23).

        Parameters
        ----------
        pos : (*S, K, 2) positions at ``t - 1``; exists : (*S, K) bool at ``t - 1``.

        Returns
        -------
        (*S, Bell(K)), normalised: ``logsumexp(-1) == 0``.
        """
        k = pos.shape[-2]
        h = self.closeness(pos.unsqueeze(-2), pos.unsqueeze(-3))  # (*S, K, K)
        both = exists.unsqueeze(-1) & exists.unsqueeze(-2)
        q = where(both, h.to(pos.dtype), torch.full_like(h, self.p_q, dtype=pos.dtype))
        q = q.clamp(1e-12, 1 - 1e-12)
        same = _same_group(group_structures(k, device=pos.device)).to(pos.dtype)  # (G, K, K)
        upper = torch.triu(torch.ones(k, k, dtype=pos.dtype, device=pos.device), 1)
        lq, l1q = (q.log() * upper), (torch.log1p(-q) * upper)  # (*S, K, K)
        score = torch.einsum("...ij,gij->...g", lq - l1q, same) + l1q.sum((-1, -2)).unsqueeze(-1)
        return score - torch.logsumexp(score, -1, keepdim=True)

    def log_probs(self, structure_prev: Tensor, pos: Tensor, exists: Tensor) -> Tensor:
        """``log p(g_t = h | ...)`` for every ``h`` (eq. 19): ``(*S,), (*S, K, 2), (*S, K)
        -> (*S, Bell(K))``; ``structure_prev`` is the row index of ``g_{t-1}``.
        """
        log_pi = self.log_scores(pos, exists)
        stay = torch.nn.functional.one_hot(structure_prev, log_pi.shape[-1]).bool()
        log_nc = math.log(self.p_nc) if self.p_nc > 0 else -math.inf
        log_c = math.log1p(-self.p_nc) if self.p_nc < 1 else -math.inf
        dtype, dev = log_pi.dtype, log_pi.device
        return torch.logaddexp(log_c + log_pi,
                               where(stay, torch.tensor(log_nc, dtype=dtype, device=dev),
                                           torch.tensor(-math.inf, dtype=dtype, device=dev)))

    def log_prob(self, structure: Tensor, structure_prev: Tensor, pos: Tensor, exists: Tensor) -> Tensor:
        """``log p(g_t | x_{p,t-1}, g_{t-1}, e_{t-1})`` of row indices ``structure (*S,)``."""
        lp = self.log_probs(structure_prev, pos, exists)
        return torch.gather(lp, -1, structure.unsqueeze(-1)).squeeze(-1)

    def sample(self, structure_prev: Tensor, pos: Tensor, exists: Tensor, *,
               generator: torch.Generator) -> Tensor:
        """Draw row indices ``g_t (*S,)`` int64 from eq. 19 (inverse CDF, one uniform each)."""
        log_p = self.log_probs(structure_prev, pos, exists)
        u = torch.rand(log_p.shape[:-1] + (1,), generator=generator, device=log_p.device, dtype=torch.float64)
        return inverse_cdf(cdf(log_p), u).squeeze(-1)
