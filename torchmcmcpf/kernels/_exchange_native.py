"""The exchange move's iteration after its likelihood change, in one C call
(``torchmcmcpf/_native/exchange.c``).

:func:`~torchmcmcpf.kernels.exchange.exchange_iteration` on tensors makes forty to a hundred
ATen calls an iteration after the sensor's change (the exclusion factors' change, the slots'
re-capture ratios, the MH test, one select per chain field, the cache's scatter-add), each
2-4 us of dispatch on tensors of a few hundred numbers: most of an eager iteration on the
radar scenes, whose likelihood change is one C call. :func:`commit` does the same arithmetic
in one call, operation by operation in the same float32 order (the exclusion's change by the
same C loop as :meth:`~torchmcmcpf.models.multitarget.Exclusion.log_change`, ``log u`` by
ATen as :func:`~torchmcmcpf.kernels.mh.mh_accept` takes it): the same chains, decisions and
cache to the bit (tests/kernels/test_exchange_caches.py). The fields are new tensors, as the
tensor path returns them (the chains a segment records are not written later); the cache
advances in place, as :meth:`~torchmcmcpf.models.base.SensorModel.update_amplitude_cache`
does. Eager CPU only (:func:`applies`).
"""

from __future__ import annotations

import ctypes
import math
from typing import Any

import torch

from .. import _native, runtime
from ..typing import Tensor

__all__ = ["applies", "commit"]


def applies(*tensors: Tensor | None) -> bool:
    """Whether :func:`commit` serves an iteration on these tensors: float32 CPU tensors (or
    None), the first where a C loop serves (:func:`torchmcmcpf._native.applies`: no gradient,
    no ``torch.func`` transform, the loops built; the others are the same chains' and
    proposals'), outside ``torch.compile``'s tracing (Inductor compiles the tensor path).
    """
    first = tensors[0]
    return (first is not None and _native.applies(first) and not runtime.compiling()
            and all(t is None or (t.dtype is torch.float32 and t.device.type == "cpu") for t in tensors))


def commit(log_lik: Tensor, delta: Tensor, u: Tensor, valid: Tensor | None, slot: Tensor, src_term: Tensor | None,
           coords: Tensor | None, coords_new: Tensor | None, scale: float, log_phi_floor: float,
           log_r: Tensor | None, r_new: Tensor | None, r_old: Tensor | None, fields: list[tuple[Tensor, Tensor]],
           cache: Tensor, cells: Tensor, change: Tensor) -> tuple[Tensor, Tensor, list[Tensor]]:
    """Exchange moves of ``M`` distinct slots of ``(B, C)`` chains decided and written in one
    call.

    Parameters
    ----------
    log_lik, delta, u : (B, C) float32: the chains' log-likelihood, the move's change, the
        MH uniforms; valid : (B, C) bool or None; slot : (B, C, M) int64, the moved slots.
    src_term : (B, C) float32 or None: the pair's source term of the move's prior ratio
        (:func:`~.exchange.pair_source_log_ratio`, new minus old).
    coords : (B, C, K, r) float32 or None (no exclusion term): the chains' resolution
        coordinates; coords_new : (B, C, M, r) the moved slots'; scale, log_phi_floor: the
        exclusion's width and ``log phi`` floor.
    log_r : (B, C, K) float32 or None (no re-capture): each slot's cached log ratio; r_new :
        (B, C, M) the moved slots'; r_old : (B, C, M) the moved slots' cached ratios converted
        to this move's ``epsilon``, or None (``M = 1``: read from ``log_r``).
    fields : ``(field (B, C, K, ...), rows (B, C, M, ...))`` pairs: each chain field and the
        moved slots' new rows (same dtype).
    cache : (B, C, G) float32, advanced in place; cells, change : (B, C, ...) the move's flat
        cells into ``cache`` and their change (:meth:`~.SensorModel.log_likelihood_delta_cached`).

    Returns
    -------
    log_lik : (B, C) the chains' new log-likelihood; accepted : (B, C) bool; the new fields
        (each moved slot's row the new one where accepted).
    """
    n, k, m = log_lik.numel(), fields[0][0].shape[2], slot.shape[-1]
    log_u = torch.log(u)  # mh_accept's log u, the same call
    log_lik, delta, log_u, slot, cells, change = (t.contiguous() for t in (log_lik, delta, log_u, slot, cells, change))
    valid, src_term, coords, coords_new, log_r, r_new, r_old = (
        None if t is None else t.contiguous() for t in (valid, src_term, coords, coords_new, log_r, r_new, r_old))
    nf = len(fields)
    # each field's row in bytes; its rows must have its dtype and as many elements (copied as bytes)
    width = [f.element_size() * (f.numel() // (n * k)) for f, _ in fields]
    if any(f.dtype != r.dtype or r.element_size() * (r.numel() // (n * m)) != w for (f, r), w in zip(fields, width)):
        raise ValueError("each field's rows must have its dtype and row shape, got "
                         f"{[(f.dtype, tuple(f.shape), r.dtype, tuple(r.shape)) for f, r in fields]}")
    srcs = [f.contiguous() for f, _ in fields]
    rows = [r.contiguous() for _, r in fields]
    dsts = [torch.empty_like(f) for f in srcs]
    ll_out = torch.empty_like(log_lik)
    accepted = torch.empty(log_lik.shape, dtype=torch.uint8)

    def at(t: Tensor | None) -> int | None:
        return None if t is None else t.data_ptr()

    # the fields' sources, outputs and rows in one array of pointers
    ptrs = (ctypes.c_void_p * (3 * nf))(*[t.data_ptr() for group in (srcs, dsts, rows) for t in group])
    step = ctypes.sizeof(ctypes.c_void_p) * nf
    lib: Any = _native.library()
    r = 0 if coords is None else coords.shape[-1]
    code = lib.exchange_commit(
        n, torch.get_num_threads(), k, m, at(log_lik), at(delta), at(log_u),
        None if valid is None else valid.view(torch.uint8).data_ptr(), at(slot), at(src_term), at(coords),
        at(coords_new), r, 1.0 / (2.0 * scale**2), math.exp(log_phi_floor), at(log_r), at(r_new), at(r_old), nf,
        ptrs, ctypes.addressof(ptrs) + step, ctypes.addressof(ptrs) + 2 * step, (ctypes.c_int64 * nf)(*width),
        cache.data_ptr(), at(cells), at(change), cells.numel() // n, ll_out.data_ptr(), accepted.data_ptr())
    if code:
        raise ValueError(f"the exchange's C loop got K = {k} slots, M = {m} moved or {r} resolution coordinates, "
                         "above its limits (1024, 4, 4)")
    return ll_out, accepted.view(torch.bool), dsts
