"""The arguments every evaluation path of a grid sensor takes: shape checks (no device sync,
so the hot paths stay compile-friendly; values are checked once per frame by the sensor's
``validate``) and the flattening of the states into per-target coordinates and signals.
"""

from __future__ import annotations

import math

import torch

from ....typing import Tensor
from ._protocol import GridSensorLike

__all__ = ["check_inputs", "check_state", "check_move", "flat_inputs", "slots"]


def check_state(sensor: GridSensorLike, x: Tensor, exists: Tensor | None) -> None:
    """Shapes of a state ``x (B, *S, K, D)`` and its flags ``exists (B, *S, K)``."""
    if x.dim() < 3 or x.shape[-1] != sensor.dim:
        raise ValueError(f"x has shape {tuple(x.shape)}, expected (B, *S, K, {sensor.dim})")
    if exists is not None and tuple(exists.shape) != tuple(x.shape[:-1]):
        raise ValueError(f"exists has shape {tuple(exists.shape)}, expected {tuple(x.shape[:-1])}")


def check_inputs(sensor: GridSensorLike, x: Tensor, z: Tensor, exists: Tensor | None) -> None:
    """:func:`check_state` and the frame ``z (B, *G)`` against ``x``."""
    check_state(sensor, x, exists)
    if z.dim() != 1 + sensor.n_axes or tuple(z.shape[1:]) != sensor.frame_shape or z.shape[0] != x.shape[0]:
        raise ValueError(
            f"z has shape {tuple(z.shape)}, expected ({x.shape[0]}, "
            f"{', '.join(map(str, sensor.frame_shape))}) to match x {tuple(x.shape)}"
        )


def check_move(x: Tensor, x_n: Tensor, exists_n: Tensor | None) -> bool:
    """Shapes of a move against ``x (B, *S, K, D)``: of one slot, ``x_n (B, *S, D)`` and
    ``exists_n (B, *S)``; of ``M <= K`` slots, ``x_n (B, *S, M, D)`` and ``exists_n (B, *S, M)``.
    Returns whether it is a move of ``M`` slots (the second form).
    """
    lead, D = tuple(x.shape[:-2]), x.shape[-1]
    many = x_n.dim() == x.dim() and 1 <= x_n.shape[-2] <= x.shape[-2]
    moved = lead + ((x_n.shape[-2],) if many else ())
    if tuple(x_n.shape) != moved + (D,):
        raise ValueError(f"x_n has shape {tuple(x_n.shape)}, expected {lead + (D,)} (one slot) or "
                         f"{lead + ('M', D)} (M <= {x.shape[-2]} slots) to match x {tuple(x.shape)}")
    if exists_n is not None and tuple(exists_n.shape) != moved:
        raise ValueError(f"exists_n has shape {tuple(exists_n.shape)}, expected {moved}")
    return many


def flat_inputs(sensor: GridSensorLike, x: Tensor, exists: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """``x (B, *S, K, D) -> u (B, P, K, n), s (B, P, K), e (B, P, K)`` with ``P = prod(S)``;
    ``s`` already multiplied by the existence flags ``e`` (float, dtype of ``x``).
    """
    B, K = x.shape[0], x.shape[-2]
    x = x.reshape(B, -1, K, x.shape[-1])
    u = sensor.measurement_coords(x)
    e = torch.ones_like(x[..., 0]) if exists is None else exists.reshape(B, -1, K).to(x.dtype)
    return u, sensor.signal(x) * e, e


def slots(n: int | Tensor, x: Tensor) -> Tensor:
    """The moved slot of every sample, ``(B, P)`` int64, from ``n`` (a Python int, or a tensor
    broadcastable to ``(B, *S)``) and ``x (B, *S, K, D)``.
    """
    B = x.shape[0]
    if torch.is_tensor(n):
        return n.to(device=x.device, dtype=torch.int64).expand(x.shape[:-2]).reshape(B, -1)
    return torch.full((B, math.prod(x.shape[1:-2])), n, device=x.device, dtype=torch.int64)
