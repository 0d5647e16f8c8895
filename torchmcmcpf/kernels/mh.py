"""Batched Metropolis-Hastings accept/reject, branch-free and in log space.

Metropolis et al. (1953), Hastings (1970): a proposal ``x'`` drawn from ``q(. | x)`` is
accepted with probability ``min(1, alpha)``,

    ``log alpha = log pi(x') + log q(x | x') - log pi(x) - log q(x' | x)``

(paper 002 eq. 12; paper 004 eqs. 60 and 66). Every chain of every run decides at once:
the uniforms are drawn by the caller (eager code, from its explicit generator) and passed
in, and the decision is a comparison plus ``torch.where``, so both functions trace under
``torch.compile(fullgraph=True)`` (DESIGN.md, "Compile-friendly kernels").
"""

from __future__ import annotations

from typing import Any

import torch
from torch.utils._pytree import tree_map

from .._native.select import where
from ..typing import Tensor

__all__ = ["mh_accept", "mh_select"]


def mh_accept(log_alpha: Tensor, u: Tensor) -> Tensor:
    """Accept where ``log u < log alpha``, i.e. with probability ``min(1, alpha)``.

    Parameters
    ----------
    log_alpha : (B, C, ...)
        Log acceptance ratio of each chain (any shape; typically ``(B, C)``, or
        ``(B, C, K)`` for per-target updates). ``-inf`` (an impossible proposal) always
        rejects, ``+inf`` (a current state of zero target density) always accepts.
        **NaN rejects**: it arises from ``-inf - (-inf)`` when both the proposal and the
        current state have zero density, and keeping the current state is then the only
        safe choice.
    u : same shape as ``log_alpha``
        Uniforms in ``[0, 1)`` drawn by the caller.

    Returns
    -------
    accepted : bool, same shape as ``log_alpha``.
    """
    # log(0) = -inf < any finite log_alpha; every comparison with NaN is False.
    return torch.log(u) < log_alpha


def mh_select(accepted: Tensor, proposal: Any, current: Any) -> Any:
    """Branch-free ``accepted ? proposal : current`` over arbitrary trailing dims.

    Parameters
    ----------
    accepted : (B, C, ...) bool
        One flag per chain (or per chain and target).
    proposal, current : tensors ``(B, C, ..., *E)`` whose leading dims are those of
        ``accepted``, or matching pytrees of such tensors (e.g. a chain state NamedTuple
        with states ``(B, C, K, D)`` and cached log-likelihoods ``(B, C)``); ``None``
        leaves stay ``None``.

    Returns
    -------
    The selection, with the structure and shapes of ``current``.
    """

    def select(p: Tensor, c: Tensor) -> Tensor:
        flags = accepted.reshape(accepted.shape + (1,) * (c.dim() - accepted.dim()))
        return where(flags, p, c)

    if torch.is_tensor(current):
        return select(proposal, current)
    return tree_map(lambda p, c: None if c is None else select(p, c), proposal, current,
                    is_leaf=lambda t: t is None)
