"""Motion models.

- ``ConstantVelocity``: nearly constant velocity in 2-D with an optional random-walk target
  amplitude, Bocquel, Driessen and Bagchi (2012) eqs. 15-17 (paper 000).
- ``WhiteAccelerationMotion``: the rank-2 white-acceleration model of Maroulas and Stinis
  (2010) eqs. 11-13 (paper 003), whose noise the HMC move samples.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from .._validation import check_positive, check_shape
from ..typing import Tensor
from .base import MotionModel, linear_map

__all__ = ["ConstantVelocity", "LinearGaussianMotion", "WhiteAccelerationMotion", "ProcessNoiseScale"]


class LinearGaussianMotion(MotionModel):
    """``x_k = F x_{k-1} + v``, ``v ~ N(0, Q)``, per target slot.

    Parameters
    ----------
    F : (D, D) transition matrix.
    Q : (D, D) symmetric positive definite process noise covariance.

    Attributes ``F``, ``Q`` and ``L`` (lower Cholesky factor of Q) are buffers, so
    ``.to(device)`` moves them with the filter. Used directly for Kalman cross-checks.

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.models.motion import LinearGaussianMotion
    >>> motion = LinearGaussianMotion(F=torch.tensor([[0.9]]), Q=torch.tensor([[0.19]]))  # AR(1), D = 1
    >>> x = torch.ones(10000, 1, 1)                          # (N, K, D)
    >>> x_next = motion.sample(x, generator=torch.Generator().manual_seed(0))
    >>> x_next.shape, motion.log_prob(x_next, x).shape
    (torch.Size([10000, 1, 1]), torch.Size([10000, 1]))
    >>> round(x_next.mean().item(), 1), round(x_next.var().item(), 2)   # F x = 0.9, Q = 0.19
    (0.9, 0.19)
    """

    F: Tensor
    Q: Tensor
    L: Tensor

    def __init__(self, F: Tensor, Q: Tensor) -> None:
        super().__init__()
        F = torch.as_tensor(F, dtype=torch.get_default_dtype() if not torch.is_tensor(F) else F.dtype)
        Q = torch.as_tensor(Q, dtype=F.dtype)
        d = F.shape[-1]
        if F.shape != (d, d) or Q.shape != (d, d):
            raise ValueError(f"F and Q must be square (D, D); got F {tuple(F.shape)}, Q {tuple(Q.shape)}")
        try:
            L = torch.linalg.cholesky(Q)
        except RuntimeError as err:  # pragma: no cover - message path
            raise ValueError(f"Q must be symmetric positive definite: {err}") from err
        self.register_buffer("F", F)
        self.register_buffer("Q", Q)
        self.register_buffer("L", L)
        self.dim = d
        self.noise_dim = d
        # log-density constant: -0.5 * (D log 2pi + log det Q)
        self._log_norm = -0.5 * (d * math.log(2 * math.pi)) - float(torch.log(torch.diagonal(L)).sum())

    def mean(self, x: Tensor) -> Tensor:
        """``F x``: ``(*S, K, D) -> (*S, K, D)``."""
        return linear_map(x, self.F)

    def propagate(self, x: Tensor, eps: Tensor) -> Tensor:
        """``F x + L eps``: ``(*S, K, D), (*S, K, D) -> (*S, K, D)``."""
        return self.mean(x) + linear_map(eps, self.L)

    def log_prob(self, x_next: Tensor, x: Tensor) -> Tensor:
        """``log N(x_next; F x, Q)``: ``(*S, K, D), (*S, K, D) -> (*S, K)``."""
        r = (x_next - self.mean(x)).unsqueeze(-1)
        L = self.L.to(x.dtype).expand(r.shape[:-2] + self.L.shape)
        white = torch.linalg.solve_triangular(L, r, upper=False).squeeze(-1)
        return self._log_norm - 0.5 * white.square().sum(-1)


def cv_matrices(dt: float, q: float, amplitude_q: float | None = None,
                dtype: torch.dtype | None = None) -> tuple[Tensor, Tensor]:
    """F and Q of paper 000 eqs. 16-17 for ``[x, vx, y, vy(, rho)]``.

    ``F = diag(F1, F1(, 1))`` with ``F1 = [[1, T], [0, 1]]``;
    ``Q = diag(q G1, q G1(, a_rho T))`` with ``G1 = [[T^3/3, T^2/2], [T^2/2, T]]``.
    """
    dtype = dtype or torch.get_default_dtype()
    F1 = torch.tensor([[1.0, dt], [0.0, 1.0]], dtype=dtype)
    G1 = torch.tensor([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]], dtype=dtype)
    Fs, Qs = [F1, F1], [q * G1, q * G1]
    if amplitude_q is not None:
        Fs.append(torch.ones(1, 1, dtype=dtype))
        Qs.append(torch.full((1, 1), amplitude_q * dt, dtype=dtype))
    return torch.block_diag(*Fs), torch.block_diag(*Qs)


class ConstantVelocity(LinearGaussianMotion):
    """Nearly constant velocity in 2-D, paper 000 eqs. 15-17.

    State per target ``[x, vx, y, vy]`` (D = 4), or ``[x, vx, y, vy, rho]`` (D = 5) when
    ``amplitude_q`` is given; SI units.

    Parameters
    ----------
    dt : sampling time T [s].
    q : acceleration noise level ``a_x = a_y`` [m^2 s^-3] (the power spectral density of
        the white acceleration; paper 000 uses a 1 m/s^2 acceleration standard deviation,
        ``q = 1``).
    amplitude_q : random-walk level ``a_rho`` of the amplitude; ``None`` for no amplitude.

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> motion = tp.ConstantVelocity(dt=1.0, q=0.5)
    >>> x = torch.tensor([[0.0, 1.0, 0.0, 2.0]])       # (K, D) = [x, vx, y, vy]
    >>> x_next = motion.sample(x, generator=torch.Generator().manual_seed(0))
    >>> x_next.shape, motion.log_prob(x_next, x).shape
    (torch.Size([1, 4]), torch.Size([1]))
    >>> motion.F @ x[0]                                # the noise-free prediction
    tensor([1., 1., 2., 2.])
    """

    def __init__(self, dt: float = 1.0, q: float = 1.0, amplitude_q: float | None = None) -> None:
        check_positive(dt, "dt")
        check_positive(q, "q")
        if amplitude_q is not None:
            check_positive(amplitude_q, "amplitude_q")
        F, Q = cv_matrices(dt, q, amplitude_q)
        super().__init__(F, Q)
        self.dt, self.q, self.amplitude_q = float(dt), float(q), amplitude_q

    def extra_repr(self) -> str:
        """The constructor arguments, shown inside ``repr(module)``."""
        return f"dt={self.dt}, q={self.q}, amplitude_q={self.amplitude_q}"


class WhiteAccelerationMotion(MotionModel):
    """2-D nearly constant velocity with a piecewise constant white acceleration.

    Paper 003 eqs. 11-13: ``x_t = A x_{t-1} + B v_t``, state ``[x, vx, y, vy]``,
    ``A = diag(F1, F1)``, ``F1 = [[1, T], [0, 1]]``, ``B = [[T^2/2, 0], [T, 0], [0, T^2/2],
    [0, T]]``, ``v ~ N(0, diag(s_x^2, s_y^2))``. The noise is 2-D (``noise_dim = 2``), so
    the 4-D transition density is singular and ``log_prob`` is not defined; filters use
    ``propagate`` (the HMC move of paper 003 acts on its noise).

    Parameters
    ----------
    dt : T > 0 (paper: 1).
    sigma : ``(s_x, s_y)`` acceleration standard deviations, or one float for both
        (paper: 1).

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.models.motion import WhiteAccelerationMotion
    >>> motion = WhiteAccelerationMotion(dt=1.0, sigma=1.0)
    >>> x = torch.tensor([[0.0, 1.0, 0.0, 2.0]])             # (K, D) = [x, vx, y, vy]
    >>> motion.noise_dim                                     # one acceleration per axis
    2
    >>> motion.propagate(x, torch.tensor([[1.0, 0.0]]))      # a unit push along x: +T^2/2, +T
    tensor([[1.5000, 2.0000, 2.0000, 2.0000]])
    >>> motion.sample(x.expand(5, 1, 4), generator=torch.Generator()).shape
    torch.Size([5, 1, 4])
    """

    A: Tensor
    G: Tensor

    def __init__(self, dt: float = 1.0, sigma: float | Sequence[float] | Tensor = 1.0) -> None:
        super().__init__()
        check_positive(dt, "dt")
        s = torch.as_tensor(sigma, dtype=torch.get_default_dtype()).expand(2).clone()
        for i, v in enumerate(s.tolist()):
            check_positive(v, f"sigma[{i}]")
        f1 = torch.tensor([[1.0, dt], [0.0, 1.0]])
        g1 = torch.tensor([[dt**2 / 2], [dt]])
        self.register_buffer("A", torch.block_diag(f1, f1))
        self.register_buffer("G", torch.block_diag(g1 * s[0], g1 * s[1]))  # B sigma, (4, 2)
        self.dim, self.noise_dim, self.dt = 4, 2, float(dt)

    def mean(self, x: Tensor) -> Tensor:
        """``A x``: ``(*S, K, 4) -> (*S, K, 4)``."""
        return linear_map(x, self.A)

    def propagate(self, x: Tensor, eps: Tensor) -> Tensor:
        """``A x + B sigma eps``: ``(*S, K, 4), (*S, K, 2) -> (*S, K, 4)``."""
        return self.mean(x) + linear_map(eps, self.G)

    def log_prob(self, x_next: Tensor, x: Tensor) -> Tensor:
        """Not defined: the 4-D transition is driven by 2-D noise, so it has no density.

        Raises
        ------
        NotImplementedError
            Always; use :meth:`propagate` (or move the noise, as paper 003's HMC does).
        """
        raise NotImplementedError("the transition of paper 003 eq. 11 is rank 2 in 4-D: no density")

    def extra_repr(self) -> str:
        """The constructor arguments, shown inside ``repr(module)``."""
        return f"dt={self.dt}"


class ProcessNoiseScale(MotionModel):
    """A linear-Gaussian motion whose process noise is scaled per batch entry:
    ``x_k = F x_{k-1} + sqrt(scale_b) L v``, i.e. covariance ``scale_b Q`` for entry ``b``.

    With ``ConstantVelocity(dt, q=1)`` (no amplitude) as ``base``, ``scale = q`` gives the
    constant-velocity model with acceleration noise level ``q`` (eq. 17: ``Q`` is linear
    in ``q``).

    Parameters
    ----------
    base : LinearGaussianMotion (F, Q).
    scale : (M,) positive scales, one per leading (batch) entry of the states it moves.

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.models.motion import ProcessNoiseScale
    >>> motion = ProcessNoiseScale(tp.ConstantVelocity(dt=1.0, q=1.0), torch.tensor([1.0, 4.0]))
    >>> x = torch.zeros(2, 1, 4)                            # (M, K, D): entry 1 has q = 4
    >>> motion.log_prob(x, x)                               # 4 x the covariance in D = 4: - 2 log 4 lower
    tensor([[-1.1908],
            [-3.9634]])
    >>> motion.sample(x, generator=torch.Generator()).shape
    torch.Size([2, 1, 4])
    """

    scale: Tensor

    def __init__(self, base: LinearGaussianMotion, scale: Tensor) -> None:
        super().__init__()
        if not isinstance(base, LinearGaussianMotion):
            raise ValueError(f"base must be a LinearGaussianMotion, got {type(base).__name__}")
        check_shape(scale, "scale", (None,))
        self.base = base
        self.register_buffer("scale", scale)
        self.dim, self.noise_dim = base.dim, base.noise_dim

    def _s(self, x: Tensor) -> Tensor:
        return self.scale.to(x.dtype).reshape((-1,) + (1,) * (x.dim() - 1))

    def propagate(self, x: Tensor, eps: Tensor) -> Tensor:
        """``(M, *S, K, D), (M, *S, K, D) -> (M, *S, K, D)``."""
        return self.base.mean(x) + self._s(x).sqrt() * linear_map(eps, self.base.L)

    def log_prob(self, x_next: Tensor, x: Tensor) -> Tensor:
        """``log N(x_next; F x, scale Q)``: ``(M, *S, K, D) -> (M, *S, K)``."""
        s = self._s(x)
        white = (x_next - self.base.mean(x)) / s.sqrt()
        return self.base.log_prob(self.base.mean(x) + white, x) - 0.5 * self.dim * torch.log(s[..., 0])
