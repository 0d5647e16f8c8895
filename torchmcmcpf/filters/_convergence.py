"""The IP-MCMC-PF's convergence check (paper 000 Alg. 1, step 3): R-hat of eq. 13 over the
second half of the iterations run so far, on chains whose slots are relabelled to a common
reference (:mod:`torchmcmcpf.filters.ipmcmc`, "Convergence check", says what is computed and
why), and which component drives it.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .._native.select import where
from ..diagnostics import rhat
from ..runtime import take_along
from ..state import relabel_order
from ..typing import Tensor

__all__ = ["RhatReport", "window_start", "chains_relabelled", "rhat_report"]


class RhatReport(NamedTuple):
    """R-hat of paper 000 eq. 13 per state component and where it is largest.

    Attributes
    ----------
    max : (B,) the largest R-hat over the ``K * D`` components (the stopping rule's value).
    slot : (B,) int64, the target slot ``k`` of the component that gives ``max``.
    dim : (B,) int64, its state dimension ``d``.
    """

    max: Tensor
    slot: Tensor
    dim: Tensor


def window_start(total: int) -> int:
    """First iteration of the R-hat window among ``total`` (the second half, >= 2 states)."""
    return min(total // 2, total - 2)


def chains_relabelled(window: Tensor, rounds: int = 2) -> Tensor:
    """The chains' states ``window (W, B, C, K, D)`` with each state's slots permuted to the
    labels of a reference common to the run, so that R-hat compares targets, not slot labels
    (:mod:`torchmcmcpf.filters.ipmcmc`, "Convergence check").

    Stephens (2000): the reference is chain 0's last state, then the mean of the relabelled
    states (``rounds`` times); :func:`~torchmcmcpf.state.relabel_order` gives each state's
    permutation. It keeps a state's own labels unless the permutation lowers its
    squared-distance cost by more than ``(cutoff / 4)^2``, so chains that agree (the usual
    case with the factorised target) are left as they are, and every state is put in a
    canonical labelling that does not depend on its chain: R-hat of a label-invariant
    function of the state.
    """
    w, b, c, k, d = window.shape
    if k < 2:
        return window
    # a chain whose move was rejected repeats its state, and an equal state gets the equal
    # permutation: relabel each chain's distinct states only (a quarter of the window at the
    # usual acceptance), each against its run's reference, and carry the permutation forward
    changed = torch.ones((w, b, c), dtype=torch.bool, device=window.device)
    changed[1:] = (window[1:] != window[:-1]).flatten(-2).any(-1)
    at_w, at_b, at_c = changed.nonzero(as_tuple=True)  # one host read
    steps = torch.arange(w, device=window.device).reshape(w, 1, 1)
    last = where(changed, steps, 0).cummax(0).values  # (W, B, C): the state's last change
    runs, chains = torch.arange(b, device=window.device).reshape(1, b, 1), torch.arange(c, device=window.device)
    distinct = window[at_w, at_b, at_c].unsqueeze(1)  # (R, 1, K, D), each its own "run"
    reference = window[-1, :, 0]
    for _ in range(rounds):
        order = torch.empty((w, b, c, k), dtype=torch.int64, device=window.device)
        order[at_w, at_b, at_c] = relabel_order(distinct, reference[at_b]).squeeze(1)
        relabelled = take_along(window, order[last, runs, chains].unsqueeze(-1), 3)
        reference = relabelled.permute(1, 0, 2, 3, 4).reshape(b, w * c, k, d).mean(1)
    return relabelled


def rhat_report(ys: list, offset: int, method: str, exchangeable: bool) -> RhatReport:
    """R-hat over chains of the states ``ys`` (a list of ``(B, C, K, D)``, those after
    iterations ``offset, offset + 1, ...``) of the second half of the iterations run so far
    (:mod:`torchmcmcpf.filters.ipmcmc`, "Convergence check"), on relabelled chains where the slots are
    ``exchangeable`` (a resolved sensor: :attr:`~torchmcmcpf.models.base.SensorModel.resolved`;
    labelled measurements say which slot is which target).
    """
    window = torch.stack(ys[window_start(offset + len(ys)) - offset:])  # (W, B, C, K, D)
    if exchangeable:
        window = chains_relabelled(window)
    r = rhat(window, chain_dim=2, sample_dim=0, method=method)  # (B, K, D)
    flat = r.flatten(1)
    # NaN-safe argmax: inf/NaN first (a NaN R-hat can only come from a NaN state)
    score = where(torch.isnan(flat), torch.full_like(flat, float("inf")), flat)
    at = score.argmax(-1)
    return RhatReport(score.amax(-1), at // r.shape[-1], at % r.shape[-1])
