"""The noise of each group move (paper 004 Algorithms 1-2 and the fixed-lag moves), drawn eagerly
from the caller's generator and passed into the pure moves (DESIGN.md, "Compile-friendly kernels").

The maths, the moves' targets and acceptance ratios: the docstring of :mod:`torchmcmcpf.filters.group`.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch

from ..._validation import check_positive_int
from ...typing import Tensor

__all__ = ["GroupJointNoise", "GroupRefineNoise", "GroupPastNoise", "GroupWindowBirthNoise", "NOISES"]

#: the dims of each noise field after the chains' ``(B, C)`` ("K": the slots); every field is
#: ``U(0, 1)`` but the standard normals ``eps`` and ``step``
_FIELD_DIMS: dict[str, tuple[int | str, ...]] = {
    "mix": (), "j": (), "g": (), "u": (), "u_g": (), "slot": (), "e": ("K",), "u_x": ("K",), "b_sel": ("K",),
    "b_pix": ("K",), "eps": ("K", 2), "b_xy": ("K", 2), "step": (2, 2), "y_pix": (), "y_xy": (2,),
    "x_eps": ("L", 2)}
_NORMALS = ("eps", "step", "x_eps")


def _draw_fields(cls: Any, shape: tuple[int, int, int], generator: torch.Generator, dtype: torch.dtype,
                 device: torch.device | str | None, window: int = 1) -> Any:
    """One noise tuple of class ``cls`` for ``shape = (B, C, K)``, its fields drawn in
    declaration order with the dims of :data:`_FIELD_DIMS` (``"L"``: ``window``).
    """
    b, c, k = shape
    fields = []
    sizes = {"K": k, "L": window}
    for name in cls._fields:
        size = (b, c, *(sizes[d] if isinstance(d, str) else d for d in _FIELD_DIMS[name]))
        draw = torch.randn if name in _NORMALS else torch.rand
        fields.append(draw(size, generator=generator, dtype=dtype, device=device))
    return cls(*fields)


class GroupJointNoise(NamedTuple):
    """Uniforms and normals of one joint draw for chains ``(B, C)`` of ``K`` slots: ``mix``,
    ``j``, ``g``, ``u (B, C)``; ``e (B, C, K)``; ``eps (B, C, K, 2)``; the birth proposal's
    ``b_sel``, ``b_pix (B, C, K)`` and ``b_xy (B, C, K, 2)`` (eqs. 64-65).
    """

    mix: Tensor
    j: Tensor
    g: Tensor
    e: Tensor
    eps: Tensor
    u: Tensor
    b_sel: Tensor
    b_pix: Tensor
    b_xy: Tensor

    @classmethod
    def draw(cls, shape: tuple[int, int, int], *, generator: torch.Generator, dtype: torch.dtype = torch.float64,
             device: torch.device | str | None = None) -> GroupJointNoise:
        """Draw for ``shape = (B, C, K)``."""
        return _draw_fields(cls, shape, generator, dtype, device)


class GroupRefineNoise(NamedTuple):
    """Uniforms and normals of one refinement sweep for chains ``(B, C)`` of ``K`` slots:
    ``g``, ``u_g (B, C)``; ``e``, ``u_x (B, C, K)``; ``eps (B, C, K, 2)``; the birth uniforms.
    """

    g: Tensor
    u_g: Tensor
    e: Tensor
    eps: Tensor
    u_x: Tensor
    b_sel: Tensor
    b_pix: Tensor
    b_xy: Tensor

    @classmethod
    def draw(cls, shape: tuple[int, int, int], *, generator: torch.Generator, dtype: torch.dtype = torch.float64,
             device: torch.device | str | None = None) -> GroupRefineNoise:
        """Draw for ``shape = (B, C, K)``."""
        return _draw_fields(cls, shape, generator, dtype, device)


class GroupPastNoise(NamedTuple):
    """Noise of one past move for chains ``(B, C)``: ``slot`` uniforms (the slot moved),
    ``step (B, C, 2, 2)`` standard normals (shift, velocity step; per axis), ``u (B, C)``.
    """

    slot: Tensor
    step: Tensor
    u: Tensor

    @classmethod
    def draw(cls, shape: tuple[int, int, int], *, generator: torch.Generator, dtype: torch.dtype = torch.float64,
             device: torch.device | str | None = None) -> GroupPastNoise:
        """Draw for ``shape = (B, C, K)``."""
        return _draw_fields(cls, shape, generator, dtype, device)


class GroupWindowBirthNoise(NamedTuple):
    """Noise of one window birth/death move for chains ``(B, C)``: ``slot`` uniforms (the slot
    and the window step of the birth or death), ``y_pix (B, C)`` and ``y_xy (B, C, 2)``
    uniforms (the pixel of ``Z_s`` and the place in it), ``x_eps (B, C, L, 2)`` standard
    normals (the positions after ``s``; ``L = window``, the lag), ``u (B, C)``.
    """

    slot: Tensor
    y_pix: Tensor
    y_xy: Tensor
    x_eps: Tensor
    u: Tensor

    @classmethod
    def draw(cls, shape: tuple[int, int, int], *, generator: torch.Generator, dtype: torch.dtype = torch.float64,
             device: torch.device | str | None = None, window: int = 1) -> GroupWindowBirthNoise:
        """Draw for ``shape = (B, C, K)`` and a window of ``window`` steps."""
        return _draw_fields(cls, shape, generator, dtype, device, check_positive_int(window, "window"))


#: the noise type of each move of :meth:`~torchmcmcpf.filters.group.GroupMCMCSettings.moves`
NOISES: dict[str, Any] = {"joint": GroupJointNoise, "refine": GroupRefineNoise, "past": GroupPastNoise,
                          "birth": GroupWindowBirthNoise}
