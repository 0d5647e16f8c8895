"""Selects: ``torch.where`` and the read-back of a packed block, one pass each on the CPU
(``torchmcmcpf/_native/select.c``).

ATen's CPU ``where`` runs a scalar loop per element whatever the layout: on one core of the
2-core host of benchmarks/README.md (2026-12-07) 1.3 ns an element for a contiguous
``(200000,)`` float32 select, 2.3 when the condition is broadcast over an inner dim (a
chain's accept flag over its ``(K, D)`` state: 460 us for ``(10, 5000, 4)``), against 0.08
for a copy. The MCMC moves of the births/deaths MCMC-PF make about 1,100 of them a step, a
quarter of its time. :func:`where` is ``torch.where`` with that loop in C for the layouts the
moves use: a condition over the leading dims (a row of ``w`` elements each) and operands
either whole or one row repeated (a fill value, ``x_death``); each row copied as ``(a & m) |
(b & ~m)`` on unsigned words of the element's size, so the same bits as ``torch.where``
(NaN, ``-0.0``), vectorised (0.14-0.35 ns an element). :func:`unpacked` reads a packed block
back (:func:`packed_places`) as one gather-and-select.

Both fall back to ATen (the same values) where the loop does not serve: another device, a
gradient to record, a ``torch.func`` transform, ``torch.compile`` tracing (Inductor fuses
its own selects), another broadcast, mixed dtypes, fewer than :data:`MIN_ELEMENTS`
elements, or the C loops not built (:func:`torchmcmcpf._native.available`, which the first
large select calls: it builds the loops once per machine).
"""

from __future__ import annotations

import math
from typing import Any

import torch

from .. import runtime
from . import available, library

__all__ = ["where", "packed_places", "unpacked", "MIN_ELEMENTS"]

Operand = torch.Tensor | bool | int | float

#: the fewest elements (of the condition or an operand) for which the loop's call (its
#: Python checks, 3-6 us) pays: ATen's where of 8,192 float32 elements takes 7-20 us on the
#: host above; a smaller call costs one size test (0.3 us) more than ATen's
MIN_ELEMENTS = 8192
#: elements below which the loop stays on the calling thread (a thread's start costs more)
_THREADED = 1 << 16


def _tensor(x: Operand, dtype: torch.dtype) -> torch.Tensor | None:
    """``x`` as a CPU tensor of ``dtype`` where ``torch.where`` would give ``dtype`` for it
    (a Python scalar of the same kind; a tensor of that dtype), else None.
    """
    if isinstance(x, torch.Tensor):
        return x if x.dtype == dtype and x.device.type == "cpu" else None
    if isinstance(x, bool):
        ok = dtype == torch.bool
    elif isinstance(x, int):
        ok = dtype != torch.bool and not dtype.is_complex
    elif isinstance(x, float):
        ok = dtype.is_floating_point
    else:
        return None
    return torch.tensor(x, dtype=dtype) if ok else None


def _rows(x: torch.Tensor, shape: tuple[int, ...], j: int, w: int) -> tuple[torch.Tensor, int] | None:
    """``x`` as the loop reads it for an output ``shape`` of rows over the dims before ``j``:
    one row repeated (row stride 0) where ``x`` does not vary over those dims (broadcast, or
    an ``expand``-ed view: ``x_death`` over every slot), else the whole operand contiguous
    (row stride ``w``); None for a broadcast within the rows' dims.
    """
    padded = (1,) * (len(shape) - x.dim()) + tuple(x.shape)
    if padded != shape and not all(s == 1 for s in padded[:j]):
        return None
    xe = x.expand(shape)
    if all(shape[i] == 1 or xe.stride(i) == 0 for i in range(j)):
        return xe[(0,) * j].contiguous(), 0
    return xe.contiguous(), w


def _loops(*tensors: torch.Tensor) -> Any:
    """The C library where its loops may serve a call on ``tensors`` (all on the CPU, no
    gradient to record, no ``torch.func`` transform), building it on the first such call;
    None elsewhere. The callers have asked :func:`~torchmcmcpf.runtime.compiling` first.
    """
    if runtime.in_function_transform() or any(t.device.type != "cpu" for t in tensors):
        return None
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return None
    return library() if available() else None


def _select(condition: torch.Tensor, input: Operand, other: Operand) -> torch.Tensor | None:
    """The C loop's ``torch.where(condition, input, other)``, or None where it does not serve
    (the small calls leave after one size test).
    """
    if runtime.compiling():  # first: a traced call reads nothing else (no guard on this module's state)
        return None
    big = condition.numel() >= MIN_ELEMENTS or (isinstance(input, torch.Tensor) and input.numel() >= MIN_ELEMENTS) \
        or (isinstance(other, torch.Tensor) and other.numel() >= MIN_ELEMENTS)
    t = input if isinstance(input, torch.Tensor) else other
    if not big or condition.dtype != torch.bool or not isinstance(t, torch.Tensor) \
            or t.element_size() not in (1, 2, 4, 8):
        return None
    a, b = _tensor(input, t.dtype), _tensor(other, t.dtype)
    if a is None or b is None:
        return None
    lib: Any = _loops(condition, a, b)
    if lib is None:
        return None
    shape = runtime.broadcast_or_none(tuple(condition.shape), tuple(a.shape), tuple(b.shape))
    n = 0 if shape is None else math.prod(shape)
    if shape is None or n == 0:
        return None
    c_shape = (1,) * (len(shape) - condition.dim()) + tuple(condition.shape)
    j = len(shape)
    while j > 0 and c_shape[j - 1] == 1:  # the condition's rows: its dims before j
        j -= 1
    if c_shape[:j] != shape[:j]:
        return None
    rows, w = math.prod(shape[:j]), math.prod(shape[j:])
    ra, rb = _rows(a, shape, j, w), _rows(b, shape, j, w)
    if ra is None or rb is None:
        return None
    c = condition.reshape(c_shape[:j]).contiguous()
    out = torch.empty(shape, dtype=t.dtype)
    lib.select_rows(rows, torch.get_num_threads() if n >= _THREADED else 1, w, t.element_size(), c.data_ptr(),
                    ra[0].data_ptr(), ra[1], rb[0].data_ptr(), rb[1], out.data_ptr())
    return out


def where(condition: torch.Tensor, input: Operand, other: Operand) -> torch.Tensor:
    """``torch.where(condition, input, other)``: the same values and bits, the same dtype and
    shape, by the C loop where it serves (module docstring), else by ATen.

    Parameters
    ----------
    condition : bool tensor, broadcastable against the operands.
    input, other : tensors, or Python scalars of the other's kind.

    Returns
    -------
    The select, shaped as the three broadcast together.
    """
    out = _select(condition, input, other)
    return torch.where(condition, input, other) if out is None else out


def packed_places(flags: torch.Tensor) -> tuple[int, torch.Tensor]:
    """Where each flagged entry of ``flags (B, P)`` bool lands when every run's flagged entries
    are packed, in order, to the front of a ``(B, W)`` block: ``W``, the most flagged entries
    in a run (one host read), and ``place (B, P)`` int64, the entry's column there (0 where not
    flagged). What is drawn ``(B, W, ...)`` for the flagged entries only is read back at their
    places by :func:`unpacked`; a run's columns past its own count are never read.

    Example
    -------
    >>> import torch
    >>> width, place = packed_places(torch.tensor([[False, True, True], [True, False, False]]))
    >>> width, place
    (2, tensor([[0, 0, 1],
            [0, 0, 0]]))
    """
    rank = flags.to(torch.int64).cumsum(-1)
    width = int(rank[:, -1].max()) if rank.numel() else 0
    return width, rank.sub_(1).clamp_(min=0)


def unpacked(block: torch.Tensor, place: torch.Tensor, flags: torch.Tensor,
             fill: torch.Tensor | float) -> torch.Tensor:
    """A packed ``block (B, W, *E)`` read back at the ``place (B, P)`` of each flagged entry of
    ``flags (B, P)`` (:func:`packed_places`), ``fill`` (broadcastable to ``(B, P, *E)``)
    elsewhere: ``-> (B, P, *E)``. One pass in C where :func:`where` would serve (a fill
    that is whole or one ``E`` row repeated), else a gather and a select.
    """
    b, p = flags.shape
    shape = (b, p) + tuple(block.shape[2:])
    fill_t = None if runtime.compiling() else _tensor(fill, block.dtype)  # traced: nothing else read
    big = math.prod(shape) >= MIN_ELEMENTS and block.element_size() in (1, 2, 4, 8)
    lib: Any = _loops(block, flags, fill_t) if big and fill_t is not None else None
    rows = None if lib is None or fill_t is None else _rows(fill_t, shape, 2, math.prod(shape[2:]))
    if rows is not None:
        out = torch.empty(shape, dtype=block.dtype)
        blk, f, pl = block.contiguous(), flags.contiguous(), place.contiguous()
        lib.unpack_rows(b * p, torch.get_num_threads() if out.numel() >= _THREADED else 1, p, block.shape[1],
                        math.prod(shape[2:]), block.element_size(), f.data_ptr(), pl.data_ptr(), blk.data_ptr(),
                        rows[0].data_ptr(), rows[1], out.data_ptr())
        return out
    index = place.reshape(place.shape + (1,) * (block.dim() - 2))
    return torch.where(flags.reshape(index.shape), runtime.take_along(block, index, 1), fill)
