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
from collections.abc import Callable
from typing import Any, NamedTuple

import torch

from .. import _native, runtime
from ..typing import Tensor

__all__ = ["applies", "commit", "segment", "Moves"]


def applies(*tensors: Tensor | None) -> bool:
    """Whether :func:`commit` serves an iteration on these tensors: float32 CPU tensors (or
    None), the first where a C loop serves (:func:`torchmcmcpf._native.applies`: no gradient,
    no ``torch.func`` transform, the loops built; the others are the same chains' and
    proposals'), outside ``torch.compile``'s tracing (Inductor compiles the tensor path).
    """
    first = tensors[0]
    return (first is not None and _native.applies(first) and not runtime.compiling()
            and all(t is None or (t.dtype is torch.float32 and t.device.type == "cpu") for t in tensors))


def _row_widths(fields: list[tuple[Tensor, Tensor]], rows: int, new_rows: int) -> list[int]:
    """Each ``(field, new rows)`` pair's row in bytes (``rows`` rows a field, ``new_rows`` new
    ones): the loops copy rows as bytes, so a ValueError unless the new rows have the field's
    dtype and row shape.
    """
    width = [f.element_size() * (f.numel() // rows) for f, _ in fields]
    if any(f.dtype != r.dtype or r.element_size() * (r.numel() // new_rows) != w for (f, r), w in zip(fields, width)):
        raise ValueError("each field's rows must have its dtype and row shape, got "
                         f"{[(f.dtype, tuple(f.shape), r.dtype, tuple(r.shape)) for f, r in fields]}")
    return width


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
    width = _row_widths(fields, n * k, n * m)
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


class Moves(NamedTuple):
    """One kind of move of a segment (:func:`segment`): ``L`` iterations of ``(B, C)`` chains
    moving ``M`` slots each.

    Attributes
    ----------
    u : (L, B, C) float32, the MH uniforms; valid : (L, B, C) bool or None; slot : (L, B, C, M)
        int64.
    rows : per chain field of :func:`segment`, the moved slots' new rows ``(L, B, C, M, ...)``
        (the field's dtype).
    coords : (L, B, C, M, r) or None, their resolution coordinates (the exclusion term);
        log_r : (L, B, C, M) or None, their ratios at the move's ``epsilon``.
    conv : (3,) float32 or None: the chains' cached ratios converted to the move's ``epsilon``
        by kind (the float32 values of :func:`~torchmcmcpf.models.multitarget.log_q_ratio` of
        kinds 0, 1, 2), else read as they are.
    """

    u: Tensor
    valid: Tensor | None
    slot: Tensor
    rows: list[Tensor]
    coords: Tensor | None
    log_r: Tensor | None
    conv: Tensor | None


def segment(log_lik: Tensor, fields: list[Tensor], at: dict[str, int], cache: Tensor, loop: _native.RowsLoop,
            scale: float, log_phi_floor: float, single: Moves, pairs: Moves | None, at_pairs: tuple[int, ...],
            record: int, recorded: list[bool], source_term: Callable[[list[Tensor], int], Tensor | None]
            ) -> tuple[Tensor, list[Tensor], list[Tensor | None], Tensor, Tensor]:
    """The ``L`` iterations of a segment of ``(B, C)`` chains in C calls: each run of one-slot
    iterations (``single``) between the two-slot ones (``pairs``, at positions ``at_pairs``)
    in one call, each two-slot iteration in one after its source term; in each, the change
    by the sensor's entry ``loop`` (:meth:`~.SensorModel.delta_rows_loop`), then
    :func:`commit`'s arithmetic, chain by chain (the chains are independent: split over the
    threads once), on buffers made once for the segment: the same bits as ``L`` calls of the
    two.

    Parameters
    ----------
    log_lik : (B, C) float32; fields : the chain fields ``(B, C, K, ...)`` the moves write
        (:func:`commit`'s), ``at`` the positions of ``"terms"`` (the move terms ``(B, C, K,
        4)`` ``loop`` reads) and, where the moves read them, ``"coords"``, ``"log_r"``,
        ``"kind"``.
    cache : (B, C, G) float32 contiguous, advanced in place; scale, log_phi_floor: as
        :func:`commit`.
    single : :class:`Moves` of one slot, leading ``L`` (its rows at ``at_pairs`` unread);
        pairs : :class:`Moves` of two slots, leading ``len(at_pairs)``, or None.
    record : the first iteration whose chains are recorded; recorded : per field, whether.
    source_term : ``source_term(own, i) -> (B, C) float32 or None``, the ``i``-th two-slot
        move's source term from the chains' current fields ``own``.

    Returns
    -------
    log_lik : (B, C); the fields after the ``L`` iterations (new tensors); the recorded fields'
        traces ``(L - record, B, C, K, ...)`` (None where not recorded); the log-likelihood's
        ``(L - record, B, C)``; the acceptances per chain ``(B, C)`` float32.
    """
    length = single.u.shape[0]
    n, k = log_lik.numel(), fields[0].shape[2]
    width = _row_widths(list(zip(fields, single.rows)), n * k, n * length * single.slot.shape[-1])
    if pairs is not None:
        _row_widths(list(zip(fields, pairs.rows)), n * k, n * pairs.u.shape[0] * pairs.slot.shape[-1])
    own = [f.clone(memory_format=torch.contiguous_format) for f in fields]  # written in place
    ll = log_lik.clone(memory_format=torch.contiguous_format)
    rec = max(length - record, 0)
    traces = [torch.empty((rec,) + f.shape, dtype=f.dtype) if keep else None for f, keep in zip(own, recorded)]
    ll_trace = torch.empty((rec,) + ll.shape, dtype=ll.dtype)
    count = torch.zeros(ll.shape, dtype=torch.float32)
    rv = 2 * (1 if pairs is None else 2) * loop.cells  # the cells a chain's move changes, at most
    delta, accepted = torch.empty(n, dtype=torch.float32), torch.empty(n, dtype=torch.uint8)
    cells, change = torch.empty((n, rv), dtype=torch.int64), torch.empty((n, rv), dtype=torch.float32)
    r_old = torch.empty((n, 2), dtype=torch.float32)
    # log u as mh_accept takes it, one ATen call an iteration (its loops round by position)
    u_single = single.u.contiguous()
    u_pairs = None if pairs is None else pairs.u.contiguous()
    where_pair = dict(zip(at_pairs, range(len(at_pairs))))
    log_u = torch.stack([torch.log(u_pairs[where_pair[t]] if t in where_pair and u_pairs is not None else u_single[t])
                         for t in range(length)])
    lib: Any = _native.library()
    threads, ctx = torch.get_num_threads(), ctypes.addressof(loop.context)
    inv2s2, xmin = 1.0 / (2.0 * scale**2), math.exp(log_phi_floor)
    own_ptrs = [t.data_ptr() for t in own]
    terms_at, coords_at, log_r_at, kind_at = at["terms"], at.get("coords"), at.get("log_r"), at.get("kind")
    r = 0 if coords_at is None else own[coords_at].shape[-1]
    widths = (ctypes.c_int64 * len(own))(*width)

    def flat(moves: Moves) -> tuple:
        """The moves' tensors, contiguous, and each one's bytes an iteration."""
        tensors = [moves.valid.contiguous().view(torch.uint8) if moves.valid is not None else None,
                   moves.slot.contiguous(), None if moves.coords is None else moves.coords.contiguous(),
                   None if moves.log_r is None else moves.log_r.contiguous()] + [t.contiguous() for t in moves.rows]
        return tensors, [None if t is None else math.prod(t.shape[1:]) * t.element_size() for t in tensors]

    single_flat = flat(single)
    pairs_flat = None if pairs is None else flat(pairs)

    def call(moves: Moves, flats: tuple, first: int, start: int, steps: int, src: Tensor | None) -> None:
        """``steps`` iterations of ``moves`` from its iteration ``first``: the segment's
        iterations ``start ..``.
        """
        tensors, step = flats

        def ptr(i: int) -> int | None:
            t = tensors[i]
            return None if t is None else t.data_ptr() + first * step[i]

        row_ptrs = [ptr(4 + f) for f in range(len(own))]
        local = max(record - start, 0)  # the first recorded of this call's iterations
        base = max(start, record) - record  # its row in the traces
        trace_ptrs = [0 if t is None else t.data_ptr() + base * math.prod(t.shape[1:]) * t.element_size()
                      for t in traces]
        ptrs = (ctypes.c_void_p * (3 * len(own)))(*own_ptrs, *row_ptrs, *trace_ptrs)
        size = ctypes.sizeof(ctypes.c_void_p) * len(own)
        m = moves.slot.shape[-1]
        code = lib.exchange_segment(
            n, threads, steps, k, m, ll.data_ptr(), log_u.data_ptr() + start * n * 4, ptr(0), ptr(1),
            None if src is None else src.data_ptr(), None if coords_at is None else own_ptrs[coords_at], ptr(2), r,
            inv2s2, xmin, None if log_r_at is None else own_ptrs[log_r_at], ptr(3),
            None if kind_at is None or moves.conv is None else own_ptrs[kind_at],
            None if moves.conv is None else moves.conv.data_ptr(), r_old.data_ptr(), len(own), ptrs,
            ctypes.addressof(ptrs) + size, widths, own_ptrs[terms_at], row_ptrs[terms_at], cache.data_ptr(),
            loop.fn, ctx, 2 * m * loop.cells, delta.data_ptr(), cells.data_ptr(), change.data_ptr(),
            accepted.data_ptr(), min(local, steps), ctypes.addressof(ptrs) + 2 * size,
            ll_trace.data_ptr() + base * n * 4, count.data_ptr())
        if code:
            raise ValueError(f"the exchange segment's C loop got {len(own)} fields, M = {m} moved, {r} resolution "
                             "coordinates or a conversion without kinds, above its limits (16, 4, 4)")

    t = 0
    while t < length:
        if t in where_pair and pairs is not None and pairs_flat is not None:
            i = where_pair[t]
            src = source_term(own, i)
            call(pairs, pairs_flat, i, t, 1, None if src is None else src.to(torch.float32).contiguous())
            t += 1
            continue
        end = min([p for p in at_pairs if p > t], default=length)
        call(single, single_flat, t, t, end - t, None)
        t = end
    return ll, own, traces, ll_trace, count
