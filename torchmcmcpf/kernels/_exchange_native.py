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

__all__ = ["applies", "commit", "segment"]


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


def segment(log_lik: Tensor, u: Tensor, valid: Tensor | None, slot: Tensor, src_term: Tensor | None,
            coords: Tensor | None, coords_new: Tensor | None, scale: float, log_phi_floor: float,
            log_r: Tensor | None, r_new: Tensor | None, kind: Tensor | None, conv: Tensor | None,
            fields: list[tuple[Tensor, Tensor]], terms_at: int, cache: Tensor, loop: _native.RowsLoop, record: int,
            recorded: list[bool]) -> tuple[Tensor, list[Tensor], list[Tensor | None], Tensor, Tensor]:
    """``L`` exchange iterations of ``(B, C)`` chains moving ``M`` slots each in one call: each
    iteration's change by the sensor's entry ``loop`` (:meth:`~.SensorModel.delta_rows_loop`),
    then :func:`commit`'s arithmetic, chain by chain (the chains are independent: split over
    the threads once), the same bits as ``L`` calls of the two.

    Parameters
    ----------
    log_lik : (B, C) float32; u : (L, B, C) the MH uniforms; valid : (L, B, C) bool or None;
        slot : (L, B, C, M) int64; src_term : (L, B, C) float32 or None, the pair's source
        term (:func:`commit`'s).
    coords : (B, C, K, r) or None, coords_new : (L, B, C, M, r); scale, log_phi_floor: as
        :func:`commit`. log_r : (B, C, K) or None, r_new : (L, B, C, M) at the move's
        ``epsilon``.
    kind, conv : with ``M > 1`` and moves at another ``epsilon`` than the chains cache: the
        chains' kinds (B, C, K) int8 and the conversion by kind (3,) float32 (the float32
        values of :func:`~torchmcmcpf.models.multitarget.log_q_ratio` of kinds 0, 1, 2), else
        None. Both are fields too, where given.
    fields : ``(field (B, C, K, ...), rows (L, B, C, M, ...))`` pairs (:func:`commit`'s, each
        iteration's rows); ``fields[terms_at]`` the chains' move terms ``(B, C, K, 4)``, read by
        ``loop``. coords, log_r and kind, where given, are fields too.
    cache : (B, C, G) float32 contiguous, advanced in place.
    record : the first iteration whose chains are recorded; recorded : per field, whether.

    Returns
    -------
    log_lik : (B, C); the fields after the ``L`` iterations (new tensors); the recorded fields'
        traces ``(L - record, B, C, K, ...)`` (None where not recorded); the log-likelihood's
        ``(L - record, B, C)``; the acceptances per chain ``(B, C)`` float32.
    """
    L, m = u.shape[0], slot.shape[-1]
    n, k = log_lik.numel(), fields[0][0].shape[2]
    width = [f.element_size() * (f.numel() // (n * k)) for f, _ in fields]
    if any(f.dtype != r.dtype or r.element_size() * (r.numel() // (n * L * m)) != w
           for (f, r), w in zip(fields, width)):
        raise ValueError("each field's rows must have its dtype and row shape, got "
                         f"{[(f.dtype, tuple(f.shape), r.dtype, tuple(r.shape)) for f, r in fields]}")
    # log u as mh_accept takes it, one ATen call an iteration (its loops round by position)
    log_u = torch.stack([torch.log(t) for t in u.contiguous().unbind(0)])
    own = [f.clone(memory_format=torch.contiguous_format) for f, _ in fields]  # written in place
    rows = [r.contiguous() for _, r in fields]
    ll = log_lik.clone(memory_format=torch.contiguous_format)
    rec = max(L - record, 0)
    traces = [torch.empty((rec,) + f.shape, dtype=f.dtype) if keep else None for f, keep in zip(own, recorded)]
    ll_trace = torch.empty((rec,) + ll.shape, dtype=ll.dtype)
    count = torch.zeros(ll.shape, dtype=torch.float32)
    rv = 2 * m * loop.cells
    delta, accepted = torch.empty(n, dtype=torch.float32), torch.empty(n, dtype=torch.uint8)
    cells, change = torch.empty((n, rv), dtype=torch.int64), torch.empty((n, rv), dtype=torch.float32)
    r_old = torch.empty((n, m), dtype=torch.float32)
    slot, valid8 = slot.contiguous(), None if valid is None else valid.contiguous().view(torch.uint8)
    src_term, coords_new, r_new, conv = (None if t is None else t.contiguous() for t in (src_term, coords_new, r_new,
                                                                                          conv))
    mine: dict[int, Tensor] = {}  # the chains' own buffers of the fields the loop reads
    for (f, _), o in zip(fields, own):
        mine[id(f)] = o
    if any(t is not None and id(t) not in mine for t in (coords, log_r, kind)):
        raise ValueError("coords, log_r and kind must be among the fields where given")
    own_coords, own_log_r, own_kind = (None if t is None else mine[id(t)] for t in (coords, log_r, kind))
    ptrs = (ctypes.c_void_p * (3 * len(own)))(*[t.data_ptr() for t in own + rows],
                                                *[0 if t is None else t.data_ptr() for t in traces])
    step = ctypes.sizeof(ctypes.c_void_p) * len(own)

    def at(t: Tensor | None) -> int | None:
        return None if t is None else t.data_ptr()

    lib: Any = _native.library()
    r = 0 if coords is None else coords.shape[-1]
    code = lib.exchange_segment(
        n, torch.get_num_threads(), L, k, m, ll.data_ptr(), log_u.data_ptr(), at(valid8), slot.data_ptr(),
        at(src_term), at(own_coords), at(coords_new), r, 1.0 / (2.0 * scale**2), math.exp(log_phi_floor),
        at(own_log_r), at(r_new), at(own_kind), at(conv), r_old.data_ptr(), len(own), ptrs,
        ctypes.addressof(ptrs) + step, (ctypes.c_int64 * len(own))(*width), own[terms_at].data_ptr(),
        rows[terms_at].data_ptr(), cache.data_ptr(), loop.fn, ctypes.addressof(loop.context), rv, delta.data_ptr(),
        cells.data_ptr(), change.data_ptr(), accepted.data_ptr(), min(record, L), ctypes.addressof(ptrs) + 2 * step,
        ll_trace.data_ptr(), count.data_ptr())
    if code:
        raise ValueError(f"the exchange segment's C loop got {len(own)} fields, M = {m} moved, {r} resolution "
                         "coordinates or a conversion without kinds, above its limits (16, 4, 4)")
    return ll, own, traces, ll_trace, count
