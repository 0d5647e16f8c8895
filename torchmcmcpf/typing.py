"""Shape vocabulary used in every docstring of torchmcmcpf.

Particles, chains and targets are tensor dimensions; batch first, as in torch.

====  ================================================================================
name  meaning
====  ================================================================================
B     Monte Carlo runs: independent problems filtered side by side in one batch
N     particles (per run)
C     MCMC chains (per run)
K     target slots: the known number of targets, or N_max with existence flags
D     per-target state size; the layout is ``[x, vx, y, vy]`` (+ ``rho`` last for the
      amplitude-carrying radar models), SI units, angles in radians
T     time steps
S     kept MCMC samples per chain (a chain history is ``(S, B, C, K, D)``)
*G    the sensor grid: ``(Nr, Nd, Nb)`` range-doppler-bearing cells, ``(H, W)`` pixels
M     point measurements per frame (padded to a common M, with a ``(B, M)`` mask)
*S    any leading sample dims between B and K (``N`` for particles, ``C`` for chains)
====  ================================================================================

Conventions
-----------
- particle states ``(B, N, K, D)``, log-weights ``(B, N)``, existence ``(B, N, K)`` bool
- chain states ``(B, C, K, D)``
- a TBD frame ``(B, *G)``; a sequence of frames ``(T, B, *G)``
- point measurements ``(B, M, d)`` with ``mask (B, M)``
- models accept any leading dims ``(*S, K, D)`` and reduce only trailing ones.

Randomness only through an explicit keyword-only ``generator: torch.Generator``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch

Tensor = torch.Tensor
Generator = torch.Generator
#: A measurement for one time step: a tensor, or a tuple/NamedTuple of tensors that share
#: the batch dim (e.g. point measurements and their mask).
Measurement = Tensor | tuple[Any, ...]

# Indices into the per-target state ``[x, vx, y, vy, (rho)]``.
X, VX, Y, VY, RHO = 0, 1, 2, 3, 4
POSITION = (X, Y)



class PointFrame(NamedTuple):
    """One frame of unlabelled point measurements (a measurement type shared by the point
    sensors, the birth proposals and the scenarios).

    Attributes
    ----------
    z : (B, M, d) measurements, in no particular order.
    mask : (B, M) bool, True for a real measurement (rows with False are padding).

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.typing import PointFrame, split_points
    >>> z = torch.tensor([[[0.0, 1.0], [2.0, 3.0], [0.0, 0.0]],
    ...                   [[5.0, 5.0], [0.0, 0.0], [0.0, 0.0]]])   # (B, M, d) = (2, 3, 2)
    >>> frame = PointFrame(z, mask=torch.tensor([[True, True, False], [True, False, False]]))
    >>> frame.mask.sum(-1)                                  # real measurements per run
    tensor([2, 1])
    >>> points, mask = split_points(frame)                  # what the point sensors read
    >>> points[mask]
    tensor([[0., 1.],
            [2., 3.],
            [5., 5.]])
    """

    z: Tensor
    mask: Tensor


#: Point measurements: a tensor ``(B, M, d)``, or a :class:`PointFrame` / ``(z, mask)`` tuple.
PointMeasurement = Tensor | PointFrame | tuple[Any, ...]


def split_points(z: PointMeasurement) -> tuple[Tensor, Tensor | None]:
    """``(z (B, M, d), mask (B, M) or None)`` of a point measurement."""
    if isinstance(z, torch.Tensor):
        return z, None
    points, mask = z
    return points, mask


__all__ = ["Tensor", "Generator", "Measurement", "PointFrame", "PointMeasurement", "split_points", "X", "VX", "Y",
           "VY", "RHO", "POSITION"]
