"""The two model roles: motion (transition density) and sensor (likelihood).

Models hold parameters (buffers), never filtering state. Every method accepts any leading
dims ``(*S, K, D)`` and reduces only trailing ones, so one model serves particles
``(B, N, K, D)`` and chains ``(B, C, K, D)`` alike.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import nn

from .._validation import check_batch, check_finite, check_shape
from ..typing import Tensor

__all__ = ["MotionModel", "SensorModel"]


class MotionModel(nn.Module):
    """Per-target Markov transition ``p(x_k | x_{k-1})``, applied to every slot alike.

    Subclasses implement :meth:`propagate` (deterministic given standard normal noise) and
    :meth:`log_prob`; :meth:`sample` draws the noise from the explicit generator. Splitting
    the draw from the map lets compiled kernels take pre-drawn noise (DESIGN.md) and lets
    HMC move the noise itself (Maroulas and Stinis 2010).

    Attributes
    ----------
    dim : int
        Per-target state size D.
    noise_dim : int
        Size of the standard normal noise one transition consumes per target.
    """

    dim: int
    noise_dim: int

    def propagate(self, x: Tensor, eps: Tensor) -> Tensor:
        """Map ``x (*S, K, D)`` and standard normal ``eps (*S, K, noise_dim)`` to ``x_next``."""
        raise NotImplementedError

    def log_prob(self, x_next: Tensor, x: Tensor) -> Tensor:
        """``log p(x_next | x)`` per target: ``(*S, K, D), (*S, K, D) -> (*S, K)``."""
        raise NotImplementedError

    def sample(self, x: Tensor, *, generator: torch.Generator) -> Tensor:
        """Draw ``x_next ~ p(. | x)``: ``(*S, K, D) -> (*S, K, D)``."""
        eps = torch.randn(
            x.shape[:-1] + (self.noise_dim,), generator=generator, device=x.device, dtype=x.dtype
        )
        return self.propagate(x, eps)


class SensorModel(nn.Module):
    """Measurement likelihood ``p(z_k | x_k)`` of a multitarget state.

    Subclasses implement :meth:`log_likelihood`, :meth:`simulate` and declare
    :attr:`frame_shape` (the trailing shape of one run's measurement, e.g. ``(Nr, Nd, Nb)``
    or ``(K, 2)``). :meth:`validate` then checks shape and values in eager code.
    """

    #: trailing shape of one run's measurement; ``None`` entries match any size
    frame_shape: tuple[Optional[int], ...] = ()

    def log_likelihood(self, x: Tensor, z: Tensor, exists: Optional[Tensor] = None) -> Tensor:
        """``log p(z | x)`` up to terms that do not depend on ``x``.

        Parameters
        ----------
        x : (B, *S, K, D) multitarget states.
        z : (B, *G) one frame per run.
        exists : (B, *S, K) bool, optional; absent slots contribute nothing.

        Returns
        -------
        (B, *S). Differentiable in ``x``.
        """
        raise NotImplementedError

    def simulate(
        self, x: Tensor, *, generator: torch.Generator, exists: Optional[Tensor] = None
    ) -> Tensor:
        """Draw one frame per run from the true states ``x (B, K, D)``: ``-> (B, *G)``."""
        raise NotImplementedError

    def validate(self, z: Tensor, batch_size: Optional[int] = None, name: str = "z") -> Tensor:
        """Check one frame ``z (B, *G)``: shape, batch size, finite values. Returns ``z``."""
        check_shape(z, name, (None,) + tuple(self.frame_shape))
        if batch_size is not None:
            check_batch(z, name, batch_size)
        return check_finite(z, name)
