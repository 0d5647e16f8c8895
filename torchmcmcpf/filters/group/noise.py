"""The noise of each group move (paper 004 Algorithms 1-2 and the fixed-lag moves), drawn eagerly
from the caller's generator (:func:`draw_noise`, one draw for every type) and passed into the
pure moves (DESIGN.md, "Compile-friendly kernels").

The maths, the moves' targets and acceptance ratios: the docstring of :mod:`torchmcmcpf.filters.group`.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch

from ..._validation import check_positive_int
from ...typing import Tensor

__all__ = ["GroupJointNoise", "GroupRefineNoise", "GroupPastNoise", "GroupWindowBirthNoise", "NOISES",
           "draw_noise"]

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


def draw_noise(cls: Any, shape: tuple[int, int, int], *, generator: torch.Generator,
               dtype: torch.dtype = torch.float64, device: torch.device | str | None = None, window: int = 1) -> Any:
    """One noise tuple of the type ``cls`` (any of :data:`NOISES`) for chains ``shape = (B,
    C, K)``, drawn from ``generator``: the one draw of every group move's noise (``window``:
    the steps ``L`` of :class:`GroupWindowBirthNoise`'s ``x_eps``, unused by the others).

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.filters.group import GroupWindowBirthNoise, draw_noise
    >>> noise = draw_noise(GroupWindowBirthNoise, (2, 4, 3), generator=torch.Generator().manual_seed(0), window=2)
    >>> noise.x_eps.shape               # (B, C, L, 2)
    torch.Size([2, 4, 2, 2])
    """
    return _draw_fields(cls, shape, generator, dtype, device, check_positive_int(window, "window"))


class GroupJointNoise(NamedTuple):
    """Uniforms and normals of one joint draw for chains ``(B, C)`` of ``K`` slots: ``mix``,
    ``j``, ``g``, ``u (B, C)``; ``e (B, C, K)``; ``eps (B, C, K, 2)``; the birth proposal's
    ``b_sel``, ``b_pix (B, C, K)`` and ``b_xy (B, C, K, 2)`` (eqs. 64-65).

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.filters.group import GroupJointNoise, draw_noise
    >>> noise = draw_noise(GroupJointNoise, (2, 4, 3), generator=torch.Generator().manual_seed(0))
    >>> noise.eps.shape, noise.u.shape      # (B, C, K, 2), (B, C)
    (torch.Size([2, 4, 3, 2]), torch.Size([2, 4]))
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



class GroupRefineNoise(NamedTuple):
    """Uniforms and normals of one refinement sweep for chains ``(B, C)`` of ``K`` slots:
    ``g``, ``u_g (B, C)``; ``e``, ``u_x (B, C, K)``; ``eps (B, C, K, 2)``; the birth uniforms.

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.filters.group import GroupRefineNoise, draw_noise
    >>> noise = draw_noise(GroupRefineNoise, (2, 4, 3), generator=torch.Generator().manual_seed(0))
    >>> noise.e.shape                       # (B, C, K)
    torch.Size([2, 4, 3])
    """

    g: Tensor
    u_g: Tensor
    e: Tensor
    eps: Tensor
    u_x: Tensor
    b_sel: Tensor
    b_pix: Tensor
    b_xy: Tensor



class GroupPastNoise(NamedTuple):
    """Noise of one past move for chains ``(B, C)``: ``slot`` uniforms (the slot moved),
    ``step (B, C, 2, 2)`` standard normals (shift, velocity step; per axis), ``u (B, C)``.

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.filters.group import GroupPastNoise, draw_noise
    >>> noise = draw_noise(GroupPastNoise, (2, 4, 3), generator=torch.Generator().manual_seed(0))
    >>> noise.step.shape                    # (B, C, 2, 2)
    torch.Size([2, 4, 2, 2])
    """

    slot: Tensor
    step: Tensor
    u: Tensor



class GroupWindowBirthNoise(NamedTuple):
    """Noise of one window birth/death move for chains ``(B, C)``: ``slot`` uniforms (the slot
    and the window step of the birth or death), ``y_pix (B, C)`` and ``y_xy (B, C, 2)``
    uniforms (the pixel of ``Z_s`` and the place in it), ``x_eps (B, C, L, 2)`` standard
    normals (the positions after ``s``; ``L = window``, the lag), ``u (B, C)``.

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.filters.group import GroupWindowBirthNoise, draw_noise
    >>> noise = draw_noise(GroupWindowBirthNoise, (2, 4, 3), generator=torch.Generator().manual_seed(0), window=2)
    >>> noise.x_eps.shape, noise.y_xy.shape  # (B, C, L, 2), (B, C, 2)
    (torch.Size([2, 4, 2, 2]), torch.Size([2, 4, 2]))
    """

    slot: Tensor
    y_pix: Tensor
    y_xy: Tensor
    x_eps: Tensor
    u: Tensor



#: the noise type of each move of :meth:`~torchmcmcpf.filters.group.GroupMCMCSettings.moves`
NOISES: dict[str, Any] = {"joint": GroupJointNoise, "refine": GroupRefineNoise, "past": GroupPastNoise,
                          "birth": GroupWindowBirthNoise}
