"""Range-doppler-bearing radar power TBD sensor, Bocquel, Driessen and Bagchi (2012) (paper 000).

Each frame holds the power ``z_{lmn} = |z_rho^{lmn}|^2`` of every range x doppler x bearing
cell (eq. 18), with complex envelope (eq. 19)

    ``z_rho^{lmn} = sum_j rho_j e^{i phi} h^{lmn}(x_j) + w^{lmn}``,  ``w ~ CN(0, 2 sigma^2)``

(real and imaginary parts independent ``N(0, sigma^2)``), the separable Gaussian point spread
of eq. 20 and the state-to-measurement map of eq. 21: ``r = sqrt(x^2 + y^2)``,
``d = (x vx + y vy) / r``, ``b = atan2(y, x)``.

Given the cell amplitude ``A = sum_j rho_j h_j`` and a phase ``phi`` common to all targets,
``z / sigma^2`` is non-central chi-square with 2 degrees of freedom and non-centrality
``A^2 / sigma^2`` (Rician envelope), so per cell

    ``log p(z | A) - log p(z | 0) = -A^2 / (2 sigma^2) + log I0(A sqrt(z) / sigma^2)``

with ``log I0(u) = log(i0e(u)) + u`` (stable for any ``u``). The sensor's log-likelihood is its
sum over cells (DESIGN.md "Likelihoods worth writing down").
"""

from __future__ import annotations

import math
from typing import Optional, Union

import torch

from ..._validation import check_generator, check_positive, check_shape
from ...typing import RHO, VX, VY, X, Y, Tensor
from .grid import SeparableGridSensor

__all__ = ["RangeDopplerBearingTBD", "log_i0"]


def log_i0(u: Tensor) -> Tensor:
    """``log I0(u)`` without overflow: ``log(i0e(|u|)) + |u|`` (I0 is even).

    The ``|u|`` makes the gradient ``I1(u) / I0(u)`` exact everywhere, including ``u = 0``
    where ``i0e`` itself has a kink (its autograd derivative there would give 1, not 0).
    """
    a = u.abs()
    return torch.log(torch.special.i0e(a)) + a


class RangeDopplerBearingTBD(SeparableGridSensor):
    """Radar power per range-doppler-bearing cell (paper 000, eqs. 18-21, Table I).

    Target state per slot ``[x, vx, y, vy, rho]`` (D = 5; ``rho`` the amplitude), radar at
    the origin, bearing ``b = atan2(y, x)`` in radians. Frames are ``(B, Nr, Nd, Nb)`` powers.

    Point spread (eq. 20). The paper writes ``exp(-(r_l - r)^2 / (2R) - ...)`` with ``R``,
    ``D``, ``B`` "related to the resolutions" and Table I gives them in metres, m/s and
    radians (range-quant size 10 m, doppler bin 2 m/s, beamwidth pi/180). We read them as
    standard deviations: ``h = exp(-(r_l - r)^2 / (2 wr^2) - (d_m - d)^2 / (2 wd^2)
    - (b_n - b)^2 / (2 wb^2))`` with widths ``wr, wd, wb`` defaulting to the cell size of the
    axis (so Table I is ``wr = 10 m``, ``wd = 2 m/s``, ``wb = pi/180``).

    SNR convention: ``SNR = rho^2 / (2 sigma^2)``, the peak target power over the mean
    noise power ``E|w|^2 = 2 sigma^2`` of one cell; see :meth:`amplitude_from_snr`.

    Parameters
    ----------
    range_bins, doppler_bins, bearing_bins : (Nr,), (Nd,), (Nb,)
        Cell centres [m], [m/s], [rad]; increasing, uniformly spaced (checked). Buffers.
    noise_std : float
        ``sigma``, the standard deviation of the real and of the imaginary noise part.
    range_width, doppler_width, bearing_width : float, optional
        Point-spread standard deviations; default the cell size of the axis.
    window : int
        Half-width in cells of the box per target in :meth:`log_likelihood_window`
        (``2 * window + 1`` cells per axis). Default 3, chosen by measuring the windowed
        against the whole-grid log-likelihood on the Table I scenario (widths = cell sizes,
        r0 ~ U[2700, 2900] m, b0 ~ U[-6, 6] deg, speed ~ U[0, 15] m/s, SNR ~ U[9, 20] dB;
        K = 1 and 3 targets; 1000-2000 particles per run around the truth with spreads 5 m,
        1 m/s and 10 % in amplitude; frames simulated from the truth). Largest centred error
        ``max |d - mean(d)| / std(grid)`` over particles, ``d = window - grid``, and total
        variation between the two normalised weight vectors:

        ======  =====================  ==============
        window  centred error / std    TV of weights
        ======  =====================  ==============
        1       1.4                    0.3 - 0.8
        2       0.03 - 0.08            0.01 - 0.11
        3       4e-5                   7e-5
        4       1e-8                   3e-8
        ======  =====================  ==============

        Stated tolerance for the default (tests/models/test_radar.py):
        ``max |d - mean(d)| <= 1e-3 * std(grid)`` over particles near the targets.
    method : {"window", "grid"}
        Which path :meth:`log_likelihood` uses.
    memory_budget : int
        Bytes of temporaries the whole-grid path may hold at once (default 1 GiB).
    """

    dim = 5

    def __init__(
        self,
        range_bins: Tensor,
        doppler_bins: Tensor,
        bearing_bins: Tensor,
        *,
        noise_std: float = 1.0,
        range_width: Optional[float] = None,
        doppler_width: Optional[float] = None,
        bearing_width: Optional[float] = None,
        window: int = 3,
        method: str = "window",
        memory_budget: int = 2**30,
    ):
        super().__init__(
            (range_bins, doppler_bins, bearing_bins),
            (range_width, doppler_width, bearing_width),
            names=("range", "doppler", "bearing"),
            window=window,
            method=method,
            memory_budget=memory_budget,
        )
        self.noise_std = check_positive(noise_std, "noise_std")

    @classmethod
    def uniform(
        cls,
        range_limits: tuple[float, float],
        doppler_limits: tuple[float, float],
        bearing_limits: tuple[float, float],
        *,
        range_cell: float = 10.0,
        doppler_cell: float = 2.0,
        bearing_cell: float = math.pi / 180,
        **kw,
    ) -> "RangeDopplerBearingTBD":
        """Uniform grid with Table I cell sizes (10 m, 2 m/s, 1 deg).

        Each ``*_limits = (first, last)`` gives the first cell centre and an upper limit:
        centres are ``first + i * cell`` for ``i = 0 .. floor((last - first) / cell)``
        (``last`` included when it lies on the lattice). Other keywords go to the constructor.
        """
        axes = []
        for limits, cell, name in (
            (range_limits, range_cell, "range"),
            (doppler_limits, doppler_cell, "doppler"),
            (bearing_limits, bearing_cell, "bearing"),
        ):
            check_positive(cell, f"{name}_cell")
            lo, hi = (float(v) for v in limits)
            if not (math.isfinite(lo) and math.isfinite(hi) and hi >= lo):
                raise ValueError(f"{name}_limits must be finite (first, last) with last >= first, got {limits!r}")
            n = int(math.floor((hi - lo) / cell + 1e-9)) + 1
            axes.append(lo + cell * torch.arange(n, dtype=torch.float64))
        return cls(*axes, **kw)

    # ------------------------------------------------------------------ model pieces
    def measurement_coords(self, x: Tensor) -> Tensor:
        """Eq. 21: ``(..., K, 5) -> (..., K, 3)`` as ``[r, d, b]`` (bearing ``atan2(y, x)``)."""
        px, py = x[..., X], x[..., Y]
        r = torch.sqrt(px * px + py * py)
        d = (px * x[..., VX] + py * x[..., VY]) / r
        return torch.stack((r, d, torch.atan2(py, px)), dim=-1)

    def signal(self, x: Tensor) -> Tensor:
        """Amplitude ``rho``: ``(..., K, 5) -> (..., K)``."""
        return x[..., RHO]

    def prepare_frame(self, z: Tensor) -> Tensor:
        """``sqrt(z) / sigma^2``, so that :meth:`cell_log_ratio` is ``-A^2/(2 sigma^2) + log I0(A * zc)``."""
        return torch.sqrt(z) / self.noise_std**2

    def cell_log_ratio(self, A: Tensor, zc: Tensor) -> Tensor:
        """Rician log ratio per cell: ``-A^2 / (2 sigma^2) + log I0(A sqrt(z) / sigma^2)``.

        Parameters
        ----------
        A : cell amplitudes; zc : ``prepare_frame(z)`` at the same cells (broadcastable).
        """
        return log_i0(A * zc) - A * A / (2.0 * self.noise_std**2)

    # ------------------------------------------------------------------ SNR
    def amplitude_from_snr(self, snr_db: Union[float, Tensor]) -> Union[float, Tensor]:
        """``rho = sigma * sqrt(2 * 10^(snr_db / 10))``, inverse of ``SNR = rho^2 / (2 sigma^2)``."""
        if torch.is_tensor(snr_db):
            return self.noise_std * torch.sqrt(2.0 * 10.0 ** (snr_db / 10.0))
        return self.noise_std * math.sqrt(2.0 * 10.0 ** (snr_db / 10.0))

    def snr_db_from_amplitude(self, rho: Union[float, Tensor]) -> Union[float, Tensor]:
        """``10 log10(rho^2 / (2 sigma^2))`` (peak target power over mean noise power per cell)."""
        if torch.is_tensor(rho):
            return 10.0 * torch.log10(rho * rho / (2.0 * self.noise_std**2))
        return 10.0 * math.log10(rho * rho / (2.0 * self.noise_std**2))

    # ------------------------------------------------------------------ simulation
    def simulate(
        self, x: Tensor, *, generator: torch.Generator, exists: Optional[Tensor] = None
    ) -> Tensor:
        """Draw one power frame per run, eqs. 18-19.

        ``z = (A cos phi + sigma e1)^2 + (A sin phi + sigma e2)^2`` with ``A`` the noise-free
        amplitude of every cell, ``phi ~ U(0, 2 pi)`` one per run, ``e1, e2 ~ N(0, 1)`` per cell.

        Parameters
        ----------
        x : (B, K, 5) true states; exists : (B, K) bool, optional.
        generator : torch.Generator (keyword-only).

        Returns
        -------
        (B, Nr, Nd, Nb) powers, dtype of ``x``.
        """
        check_generator(generator)
        check_shape(x, "x", (None, None, self.dim))
        if exists is not None:
            check_shape(exists, "exists", tuple(x.shape[:-1]))
        A = self.signal_grid(x, exists)
        B = x.shape[0]
        kw = dict(generator=generator, device=x.device, dtype=x.dtype)
        phi = 2.0 * math.pi * torch.rand((B,) + (1,) * self.n_axes, **kw)
        noise = self.noise_std * torch.randn((2, B) + self.frame_shape, **kw)
        return (A * torch.cos(phi) + noise[0]) ** 2 + (A * torch.sin(phi) + noise[1]) ** 2
