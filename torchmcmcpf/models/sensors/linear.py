"""Linear-Gaussian point measurement with known association.

One measurement per target slot, ``z_k = H x_k + w``, ``w ~ N(0, R)``: Maroulas and Stinis
(2010) eq. 14 (paper 003) with the association given. Measurements are ``(B, K, d)``.
"""

from __future__ import annotations

import math

import torch

from ..._native.select import where
from ..._validation import check_positive
from ...runtime import squared_norm
from ...typing import Tensor
from ..base import SensorModel, linear_map

__all__ = ["LinearGaussian"]


class LinearGaussian(SensorModel[Tensor]):
    """``z_{k,j} = H x_{k,j} + w_j``, ``w_j ~ N(0, R)``, one measurement per target.

    The measurements are labelled (``z_j`` belongs to slot ``j``), so targets never merge:
    the sensor declares no ``resolution_coords`` and the filters apply no exclusion term to it
    (:mod:`torchmcmcpf.models.multitarget`); its posterior is the factorised Kalman one.

    ``log_likelihood`` returns the full Gaussian log density (constants included), so a
    filter's evidence is the true ``log p(z_{1:T})``, comparable across ``R``.

    Whitening is precomputed: with ``R = L L^T`` the buffers ``W = L^{-1}`` and ``WH = W H``
    give the whitened residual ``W z - WH x`` by two small matmuls per call (no triangular
    solve per call; the ``(B, K, d)`` measurements are whitened once per call, not once per
    particle).

    Parameters
    ----------
    H : (d, D) observation matrix.
    R : (d, d) symmetric positive definite noise covariance.

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> sensor = tp.LinearGaussian.position(noise_std=2.0)   # z = [x, y] + N(0, 4 I)
    >>> x = torch.zeros(3, 50, 1, 4)                   # (B, N, K, D)
    >>> z = sensor.simulate(torch.zeros(3, 1, 4), generator=torch.Generator().manual_seed(0))
    >>> z.shape, sensor.log_likelihood(x, z).shape     # (B, K, 2), (B, N)
    (torch.Size([3, 1, 2]), torch.Size([3, 50]))
    """

    H: Tensor  #: (d, D) buffer
    R: Tensor  #: (d, d) buffer
    L: Tensor  #: (d, d) buffer, lower Cholesky factor of ``R``
    W: Tensor  #: (d, d) buffer, ``L^{-1}``
    WH: Tensor  #: (d, D) buffer, ``W @ H``

    def __init__(self, H: Tensor, R: Tensor):
        super().__init__()
        H = torch.as_tensor(H, dtype=torch.get_default_dtype() if not torch.is_tensor(H) else H.dtype)
        R = torch.as_tensor(R, dtype=H.dtype)
        d = H.shape[0]
        if H.dim() != 2 or R.shape != (d, d):
            raise ValueError(f"H must be (d, D) and R (d, d); got H {tuple(H.shape)}, R {tuple(R.shape)}")
        try:
            L = torch.linalg.cholesky(R)
        except RuntimeError as err:
            raise ValueError(f"R must be symmetric positive definite: {err}") from err
        self.register_buffer("H", H)
        self.register_buffer("R", R)
        self.register_buffer("L", L)
        W = torch.linalg.solve_triangular(L, torch.eye(d, dtype=L.dtype), upper=False)  # L^{-1}
        self.register_buffer("W", W)
        self.register_buffer("WH", W @ H)
        self.meas_dim = d
        self.state_dim = H.shape[1]
        self.frame_shape = (None, d)
        self._log_norm = -0.5 * d * math.log(2 * math.pi) - float(torch.log(torch.diagonal(L)).sum())

    @classmethod
    def position(cls, noise_std: float, dim: int = 4) -> LinearGaussian:
        """Observe ``(x, y)`` of ``[x, vx, y, vy(, rho)]`` with isotropic noise ``noise_std`` [m]."""
        check_positive(noise_std, "noise_std")
        if dim < 4:
            raise ValueError(f"dim must be >= 4 for the [x, vx, y, vy] layout, got {dim}")
        H = torch.zeros(2, dim)
        H[0, 0] = 1.0
        H[1, 2] = 1.0
        return cls(H, noise_std**2 * torch.eye(2))

    def log_likelihood(self, x: Tensor, z: Tensor, exists: Tensor | None = None) -> Tensor:
        """Sum over slots of ``log N(z_j; H x_j, R)``.

        Parameters
        ----------
        x : (B, *S, K, D); z : (B, K, d); exists : (B, *S, K) bool, optional.

        Returns
        -------
        (B, *S).
        """
        per_target = self.log_likelihood_per_target(x, z, exists)
        return per_target[..., 0] if per_target.shape[-1] == 1 else per_target.sum(-1)  # one target: a view

    def log_likelihood_per_target(self, x: Tensor, z: Tensor, exists: Tensor | None = None) -> Tensor:
        """Per-slot terms ``log N(z_j; H x_j, R)`` of :meth:`log_likelihood` (targets do not
        interact: the per-target refinement of the MCMC filter caches them, see
        ``torchmcmcpf.kernels.moves``).

        Parameters
        ----------
        x : (B, *S, K, D); z : (B, K, d); exists : (B, *S, K) bool, optional (absent: 0).

        Returns
        -------
        (B, *S, K).
        """
        wz = z.to(x.dtype) @ self.W.to(x.dtype).mT  # (B, K, d): whitened once per call
        wz = wz.reshape(wz.shape[:1] + (1,) * (x.dim() - 3) + wz.shape[1:])
        white = wz - linear_map(x, self.WH)  # (B, *S, K, d) = L^{-1} (z - H x)
        per_target = self._log_norm - 0.5 * squared_norm(white)
        if exists is not None:
            per_target = where(exists, per_target, torch.zeros_like(per_target))
        return per_target

    def simulate(
        self, x: Tensor, *, generator: torch.Generator, exists: Tensor | None = None
    ) -> Tensor:
        """``x (B, K, D) -> z (B, K, d)``."""
        eps = torch.randn(x.shape[:-1] + (self.meas_dim,), generator=generator, device=x.device, dtype=x.dtype)
        return x @ self.H.to(x.dtype).mT + eps @ self.L.to(x.dtype).mT
