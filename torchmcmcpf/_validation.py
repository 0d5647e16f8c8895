"""Input checks shared by every public entry point.

Each raises ``ValueError`` naming the argument, what was seen and what was expected. They
synchronise with the device (``.item()``), so they run once per public call in eager code,
never inside a step function's hot path.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from typing import Any, SupportsFloat

import torch
from torch.utils._pytree import tree_flatten

from .typing import Tensor


def _fmt(shape: Sequence[int | None]) -> str:
    return "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"


def check_tensor(value: object, name: str) -> Tensor:
    if not isinstance(value, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    return value


def check_shape(t: Tensor, name: str, expected: Sequence[int | None]) -> Tensor:
    """Check ``t.shape`` against ``expected`` (``None`` matches any size)."""
    check_tensor(t, name)
    ok = t.dim() == len(expected) and all(e is None or s == e for s, e in zip(t.shape, expected))
    if not ok:
        raise ValueError(f"{name} has shape {tuple(t.shape)}, expected {_fmt(expected)}")
    return t


def check_finite(t: Tensor, name: str) -> Tensor:
    check_tensor(t, name)
    if t.is_floating_point() and not bool(torch.isfinite(t).all()):
        bad = int((~torch.isfinite(t)).sum())
        raise ValueError(f"{name} contains {bad} NaN/inf value(s); expected finite values")
    return t


def check_nonnegative(t: Tensor, name: str) -> Tensor:
    if bool((t < 0).any()):
        raise ValueError(f"{name} has negative value(s) (min {float(t.min()):.4g}); expected >= 0")
    return t


def as_int(value: object) -> int | None:
    """``value`` as a Python ``int`` when it is integral, else ``None``: any
    :class:`numbers.Integral` (``int``, ``np.int64``, a 0-d integer tensor) and any real number
    with an integral value (``100.0``, ``np.float32(8)``); never a ``bool``.
    """
    if isinstance(value, bool) or getattr(value, "dtype", None) == torch.bool:
        return None
    if isinstance(value, torch.Tensor):
        if value.dim() != 0 or value.is_complex():
            return None
        value = value.item()
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        v = float(value)
        return int(v) if v.is_integer() else None
    return None


def check_positive_int(value: object, name: str, minimum: int = 1) -> int:
    """``value`` as an ``int >= minimum`` (see :func:`as_int` for what counts as an integer);
    a ``ValueError`` naming ``name`` otherwise.
    """
    v = as_int(value)
    if v is None or v < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return v


def check_positive(value: SupportsFloat | None, name: str, allow_zero: bool = False) -> float:
    if value is None:
        raise ValueError(f"{name} must be a number {'>= 0' if allow_zero else '> 0'}, got None")
    v = float(value)
    if not (v > 0 or (allow_zero and v == 0)) or v != v or v == float("inf"):
        raise ValueError(f"{name} must be {'>= 0' if allow_zero else '> 0'} and finite, got {value!r}")
    return v


def check_generator(generator: object, name: str = "generator") -> torch.Generator:
    if not isinstance(generator, torch.Generator):
        raise ValueError(
            f"{name} must be a torch.Generator (randomness is explicit in torchmcmcpf), "
            f"got {type(generator).__name__}"
        )
    return generator


def check_batch(t: Tensor, name: str, batch_size: int) -> Tensor:
    if t.dim() == 0 or t.shape[0] != batch_size:
        raise ValueError(
            f"{name} has batch size {t.shape[0] if t.dim() else 'none'} (shape {tuple(t.shape)}), "
            f"expected {batch_size} to match the particle state"
        )
    return t


def measurement_leaves(measurements: object, name: str) -> list[Tensor]:
    """The tensors of a measurement (a tensor, or a tuple / pytree of tensors); a
    ``ValueError`` naming ``name`` for anything else.
    """
    leaves = [measurements] if torch.is_tensor(measurements) else tree_flatten(measurements)[0]
    if not leaves or not all(torch.is_tensor(t) for t in leaves):
        raise ValueError(f"{name} must be a tensor or a tuple of tensors, got {type(measurements).__name__}")
    return leaves


def check_fields(name: str, rows: Sequence[tuple[str, Any, tuple[int | None, ...], torch.dtype | None]],
                 device: torch.device) -> None:
    """Check the fields of a carry: each row ``(field, value, shape, dtype)`` must be a tensor of
    that shape (None: any size), dtype (None: any) and ``device``; a ``ValueError`` naming
    ``{name}.{field}``, the shape (or dtype and device) seen and the one expected otherwise.
    The typed carries of the filter state use it (``filters/_carry.py``).
    """
    for field, t, shape, dtype in rows:
        if not torch.is_tensor(t):
            raise ValueError(f"{name}.{field} is {type(t).__name__}, expected a tensor of shape {shape} "
                             "(build the state with the filter's init)")
        check_shape(t, f"{name}.{field}", shape)
        if (dtype is not None and t.dtype != dtype) or t.device != device:
            raise ValueError(f"{name}.{field} is {t.dtype} on {t.device}, expected {dtype} on {device}")
