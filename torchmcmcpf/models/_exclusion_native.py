"""The exclusion factor and its change when one slot moves, as C loops (``torchmcmcpf/_native/exclusion.c``).

:meth:`~torchmcmcpf.models.multitarget.Exclusion.log_change` on tensors is about thirty ATen
calls (the moved slot's old and new positions against every slot, ``log phi``, the live
pairs' select, the sum): on the crossing's 250 chains each a few hundred numbers (79 us a
move, dispatch), on the births/deaths scene's 10,000 chains each a pass over ``(S, 2, K)``
tensors (1.5 ms a move). The loop works in float64, ``log phi`` as ``log(-expm1(-x))`` (series
below ``x = 1/2``, ``1 - e^-x`` above, the library's vectorised ``exp`` and ``log``), floored as
:data:`~torchmcmcpf.models.multitarget.LOG_PHI_FLOOR` floors it: the same value to round-off
(tested against the tensor path in float64); so does the whole factor of a state
(:meth:`~torchmcmcpf.models.multitarget.Exclusion.log_factor`, the joint draws' ``K (K - 1) /
2`` pairs). It gathers the live pairs of a block of samples, takes their ``log phi`` at once
(vectorised) and sums each sample's in order: the sums of one sample at a time to the bit
(tested), 1.5-2.3x faster than that on the births/deaths scene's chains, 1.5-2.3x on the
crossing's (``benchmarks/bench_exclusion.py``). It serves CPU
tensors without a gradient to record or a ``torch.func`` transform (:func:`torchmcmcpf._native.applies`).
"""

from __future__ import annotations

from typing import Any

import torch

from .. import runtime
from .._native import library
from ..typing import Tensor

__all__ = ["change", "factor", "log_phi"]


@runtime.custom_op("torchmcmcpf::exclusion_change")
def change(u: Tensor, u_n: Tensor, slot: Tensor, alive: Tensor | None, alive_n: Tensor | None, inv2s2: float,
           xmin: float) -> Tensor:
    """``u (n, K, r)``, ``u_n (n, r)`` float64, ``slot (n)`` int64, ``alive (n, K)`` and
    ``alive_n (n)`` uint8 or None, ``1 / (2 s^2)``, the floor of ``x`` -> ``(n,)`` float64: the
    sum over the live slots ``k != slot`` of ``e' log phi(|u_n - u_k|^2) - e log phi(|u_slot -
    u_k|^2)``.
    """
    n, k, r = u.shape
    u, u_n, slot = u.contiguous(), u_n.contiguous(), slot.contiguous()
    alive = None if alive is None else alive.contiguous()
    alive_n = None if alive_n is None else alive_n.contiguous()
    out = torch.empty(n, dtype=torch.float64)
    lib: Any = library()
    lib.exclusion_change(n, torch.get_num_threads(), k, r, u.data_ptr(), u_n.data_ptr(), slot.data_ptr(),
                         None if alive is None else alive.data_ptr(), None if alive_n is None else alive_n.data_ptr(),
                         inv2s2, xmin, out.data_ptr())
    return out


@change.register_fake
def _(u: Tensor, u_n: Tensor, slot: Tensor, alive: Tensor | None, alive_n: Tensor | None, inv2s2: float,
      xmin: float) -> Tensor:
    return u.new_empty(u.shape[:1])


@runtime.custom_op("torchmcmcpf::exclusion_factor")
def factor(u: Tensor, alive: Tensor | None, inv2s2: float, xmin: float) -> Tensor:
    """``u (n, K, r)`` float64, ``alive (n, K)`` uint8 or None -> ``(n,)`` float64: the sum
    over the pairs ``k < l`` of live slots of ``log phi(|u_k - u_l|^2)``.
    """
    n, k, r = u.shape
    u = u.contiguous()
    alive = None if alive is None else alive.contiguous()
    out = torch.empty(n, dtype=torch.float64)
    lib: Any = library()
    lib.exclusion_factor(n, torch.get_num_threads(), k, r, u.data_ptr(), None if alive is None else alive.data_ptr(),
                         inv2s2, xmin, out.data_ptr())
    return out


@factor.register_fake
def _(u: Tensor, alive: Tensor | None, inv2s2: float, xmin: float) -> Tensor:
    return u.new_empty(u.shape[:1])


def log_phi(d2: Tensor, inv2s2: float, xmin: float) -> Tensor:
    """The loop's ``log phi`` on squared distances ``d2`` (float64 CPU; for its test)."""
    d2 = d2.contiguous()
    out = torch.empty_like(d2)
    library().exclusion_log_phi(d2.numel(), d2.data_ptr(), inv2s2, xmin, out.data_ptr())
    return out
