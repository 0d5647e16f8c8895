"""Azimuth-range power TBD sensor with Swerling-I targets, Ling (2016) (paper 002, eqs. 3-9).

Each frame holds the reflected power ``z^{m,n}`` of every azimuth x range cell (eqs. 3-4):

    ``z^{m,n} = sum_j P_j h^{m,n}(x_j) + w^{m,n}``

with exponential noise ``w`` of mean ``sigma^2`` (the paper's ``S_w^2``), the target powers
``P_j`` and the point spread of eq. 5 evaluated at the target's range and azimuth (eq. 6),
``r = sqrt(x^2 + y^2)``, ``a = atan2(y, x)``. With Swerling-I (fluctuating) targets a cell
is exponential with mean ``sigma^2 + A``, ``A = sum_j P_j h_j`` (eq. 7; eq. 8 for ``A = 0``),
and cells are independent (eq. 9). Per cell

    ``log p(z | A) - log p(z | 0) = -log(1 + A / sigma^2) + z A / (sigma^2 (sigma^2 + A))``

(0 at ``A = 0``), and the sensor's log-likelihood is its sum over cells (DESIGN.md,
"Likelihoods worth writing down"); the whole-grid and windowed evaluations come from
:class:`~torchmcmcpf.models.sensors.grid.SeparableGridSensor`.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from ..._native.select import where
from ..._validation import check_finite, check_generator, check_nonnegative, check_positive, check_shape
from ...typing import RHO, VX, VY, Tensor, X, Y
from .grid import SeparableGridSensor, lattice, polar

__all__ = ["AzimuthRangeSwerlingTBD", "POWER"]

#: Index of the target power ``P`` in the per-target state ``[x, vx, y, vy, P]`` (the slot
#: the radar models use for the amplitude ``rho``).
POWER = RHO


class AzimuthRangeSwerlingTBD(SeparableGridSensor):
    """Reflected power per azimuth-range cell, Swerling-I targets (paper 002, eqs. 3-9).

    Target state per slot ``[x, vx, y, vy, P]`` (D = 5): position [m] and velocity [m/s] as
    in paper 002 eq. 1, and the target power ``P >= 0`` last (the paper's ``P_k^j``, eq. 3;
    the same slot as the radar's amplitude ``rho``, index :data:`POWER`). Paper 002 treats
    ``P`` as known and filters the 4-D kinematic state; keeping ``P`` in the state lets one
    model serve runs with different powers in one batch and lets a motion model with an
    amplitude random walk estimate it (:func:`~torchmcmcpf.scenarios.ling.ling` keeps it
    essentially fixed at the truth, as the paper does). Sensor at the origin, azimuth
    ``a = atan2(y, x)`` [rad] (eq. 6). Frames are ``(B, Na, Nr)`` powers: azimuth first, as
    ``z^{m,n}``, ``m = 1..N_a``, ``n = 1..N_r`` in the paper.

    Point spread (eq. 5). The paper writes ``h = exp(-(r_c - r)^2 / d_r^2 - (a_c - a)^2 /
    d_a^2)``; we use the base's standard-deviation form ``exp(-(r_c - r)^2 / (2 w_r^2) -
    (a_c - a)^2 / (2 w_a^2))``, i.e. ``d = sqrt(2) w``. The paper gives no values; the
    widths default to the cell size of each axis.

    Likelihood. A cell is exponential with mean ``sigma^2 + A`` (eq. 7), ``A = sum_j P_j h_j``;
    :meth:`cell_log_ratio` is its log ratio against noise only (eq. 8). A cell mean
    ``sigma^2 + A <= 0`` (possible only with negative powers) has zero density: the cell's
    log ratio is ``-inf``, which MCMC rejects.

    SNR convention: ``SNR = P / sigma^2``, the mean target power at the peak of its point
    spread over the mean noise power of one cell (paper 002 gives no formula; this is the
    usual one for power measurements); see :meth:`power_from_snr`.

    Parameters
    ----------
    azimuth_bins, range_bins : (Na,), (Nr,)
        Cell centres [rad], [m]; increasing, uniformly spaced (checked). Buffers.
    noise_power : float
        ``sigma^2`` (paper: ``S_w^2``), the mean of the exponential noise of one cell.
    azimuth_width, range_width : float, optional
        Point-spread standard deviations ``w_a`` [rad], ``w_r`` [m]; default the cell size.
    window : int
        Half-width in cells of the box per target in :meth:`log_likelihood_window`
        (``2 * window + 1`` cells per axis). Default 4 (``9 x 9`` cells), one more than the
        radar's: a Swerling cell's log ratio is first order in ``A`` (``~ a (z / sigma^2 - 1)``
        for small ``a``) where the Rician one is second order, so the cells left out weigh
        more. Measured on the paper-002 scenario (widths = cell sizes; frame 5; 2 runs per
        SNR; 150 particles per run around the truth with spreads 4 m and 1 m/s): largest
        centred error ``max |d - mean(d)| / std(grid)`` over particles, ``d = window - grid``,
        and total variation between the two normalised weight vectors:

        ======  ==============  =====================  ==============
        window  SNR [dB]        centred error / std    TV of weights
        ======  ==============  =====================  ==============
        2       4 / 8 / 14      0.3 / 0.8 / 1.6        0.07 / 0.10 / 0.39
        3       4 / 8 / 14      0.01 / 0.03 / 0.04     0.004 / 0.006 / 0.024
        4       4 / 8 / 14      2e-4 / 4e-4 / 6e-4     5e-5 / 1e-4 / 3e-4
        ======  ==============  =====================  ==============

        Stated tolerance for the default (tests/models/test_swerling.py):
        ``max |d - mean(d)| <= 2e-3 * std(grid)`` over particles near the targets.
    method, memory_budget : evaluation path, memory; see :class:`~torchmcmcpf.models.sensors.grid.SeparableGridSensor`.

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> sensor = tp.AzimuthRangeSwerlingTBD.uniform((-0.1, 0.1), (900.0, 1100.0), azimuth_cell=torch.pi / 180,
    ...                                             noise_power=1.0)
    >>> sensor.frame_shape                             # (Na, Nr) cells of 1 deg, 10 m
    (12, 21)
    >>> x = torch.tensor([[[1000.0, 0.0, 0.0, 0.0, sensor.power_from_snr(10.0)]]])   # (B, K, D)
    >>> z = sensor.simulate(x, generator=torch.Generator().manual_seed(0))
    >>> z.shape, sensor.log_likelihood(x.unsqueeze(1), z).shape
    (torch.Size([1, 12, 21]), torch.Size([1, 1]))
    """

    dim = 5
    #: ``sigma^2``
    noise_power: float

    def __init__(self, azimuth_bins: Tensor, range_bins: Tensor, *, noise_power: float = 1.0,
                 azimuth_width: float | None = None, range_width: float | None = None, window: int = 4,
                 method: str = "window", memory_budget: int | None = None):
        super().__init__({"azimuth_bins": (azimuth_bins, azimuth_width), "range_bins": (range_bins, range_width)},
                         window=window, method=method, memory_budget=memory_budget)
        self.noise_power = check_positive(noise_power, "noise_power")

    @classmethod
    def uniform(cls, azimuth_limits: tuple[float, float], range_limits: tuple[float, float], *,
                azimuth_cell: float = math.pi / 180, range_cell: float = 10.0, **kw: Any) -> AzimuthRangeSwerlingTBD:
        """Uniform grid: each ``(first, last)`` gives the first cell centre and an upper limit
        of an axis (:func:`~torchmcmcpf.models.sensors.grid.lattice`), with cells of 1 deg and
        10 m by default; other keywords go to the constructor.
        """
        return cls(lattice(azimuth_limits, azimuth_cell, "azimuth"), lattice(range_limits, range_cell, "range"), **kw)

    # ------------------------------------------------------------------ model pieces
    def measurement_coords(self, x: Tensor) -> Tensor:
        """Eq. 6: ``(..., K, 5) -> (..., K, 2)`` as ``[a, r]``, ``a = atan2(y, x)``."""
        r, a, _, _ = polar(x[..., X], x[..., Y])
        return torch.stack((a, r), dim=-1)

    def signal(self, x: Tensor) -> Tensor:
        """Target power ``P``: ``(..., K, 5) -> (..., K)``."""
        return x[..., POWER]

    def prepare_frame(self, z: Tensor) -> Tensor:
        """``z / sigma^2``, so that :meth:`cell_log_ratio` works with ``a = A / sigma^2``."""
        return z / self.noise_power

    def cell_log_ratio(self, A: Tensor, zc: Tensor) -> Tensor:
        """Swerling-I log ratio per cell (eqs. 7-8).

        With ``a = A / sigma^2``:

        ``log p(z | A) - log p(z | 0) = -log(1 + a) + (z / sigma^2) a / (1 + a)``

        Parameters
        ----------
        A : cell powers ``sum_j P_j h_j``; zc : ``prepare_frame(z) = z / sigma^2`` at the
            same cells (broadcastable).

        Returns
        -------
        The broadcast shape; exactly 0 where ``A = 0``, ``-inf`` where ``1 + a <= 0``.
        """
        a = A / self.noise_power
        valid = a > -1.0
        a = where(valid, a, torch.zeros_like(a))  # keeps the gradient finite off the support
        out = zc * (a / (1.0 + a)) - torch.log1p(a)
        return where(valid, out, torch.full_like(out, -math.inf))

    # ------------------------------------------------------------------ multitarget prior hooks
    def detection_statistic(self, z: Tensor) -> Tensor:
        """``z / sigma^2``, ``Exp(1)`` in a noise-only cell (eq. 8)."""
        return z / self.noise_power

    def place(self, x: Tensor, coords: Tensor) -> Tensor:
        """``x (*S, 5)`` moved to ``coords (*S, 2) = [a, r]``: position ``r (cos a, sin a)``,
        velocity and power kept.
        """
        a, r = coords.unbind(-1)
        return torch.stack((r * torch.cos(a), x[..., VX], r * torch.sin(a), x[..., VY], x[..., POWER]), -1)

    # ------------------------------------------------------------------ SNR
    def power_from_snr(self, snr_db: float | Tensor) -> float | Tensor:
        """``P = sigma^2 * 10^(snr_db / 10)``, inverse of ``SNR = P / sigma^2``."""
        return self.noise_power * 10.0 ** (snr_db / 10.0)

    def snr_db_from_power(self, power: float | Tensor) -> float | Tensor:
        """``10 log10(P / sigma^2)``."""
        if torch.is_tensor(power):
            return 10.0 * torch.log10(power / self.noise_power)
        return 10.0 * math.log10(power / self.noise_power)

    # ------------------------------------------------------------------ simulation
    def simulate(
        self, x: Tensor, *, generator: torch.Generator, exists: Tensor | None = None
    ) -> Tensor:
        """Draw one power frame per run (eqs. 3-8).

        Every cell is exponential with mean ``sigma^2 + A``, drawn by inversion,
        ``z = -(sigma^2 + A) log(1 - U)`` with ``U ~ U[0, 1)`` from ``generator``
        (``log(1 - U)`` is finite for every ``U`` that ``torch.rand`` returns).

        Parameters
        ----------
        x : (B, K, 5) true states, finite, powers ``P >= 0``; exists : (B, K) bool, optional.
        generator : torch.Generator (keyword-only).

        Returns
        -------
        (B, Na, Nr) powers, dtype of ``x``.
        """
        check_generator(generator)
        check_shape(x, "x", (None, None, self.dim))
        check_finite(x, "x")
        check_nonnegative(x[..., POWER], "x[..., 4] (target power P)")
        if exists is not None:
            check_shape(exists, "exists", tuple(x.shape[:-1]))
        mean = self.noise_power + self.signal_grid(x, exists)
        u = torch.rand(mean.shape, generator=generator, device=x.device, dtype=x.dtype)
        return -mean * torch.log1p(-u)
