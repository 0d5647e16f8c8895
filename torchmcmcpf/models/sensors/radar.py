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
from typing import Any

import torch

from ... import runtime
from ..._native.select import where
from ..._validation import check_generator, check_positive, check_shape
from ...typing import RHO, VX, VY, Tensor, X, Y
from .grid import SeparableGridSensor, lattice, native, polar

__all__ = ["RangeDopplerBearingTBD", "log_i0", "log_i0_approx"]


#: Abramowitz and Stegun 9.8.1: ``I0(u) = sum_i P_SMALL[i] (u / 3.75)^(2 i)`` for ``|u| <= 3.75``
#: (relative error < 1.6e-7).
_P_SMALL = (1.0, 3.5156229, 3.0899424, 1.2067492, 0.2659732, 0.0360768, 0.0045813)
#: Abramowitz and Stegun 9.8.2: ``sqrt(u) exp(-u) I0(u) = sum_i P_LARGE[i] (3.75 / u)^i`` for
#: ``u >= 3.75`` (absolute error < 1.9e-7 on a value >= 0.39).
_P_LARGE = (0.39894228, 0.01328592, 0.00225319, -0.00157565, 0.00916281, -0.02057706, 0.02635537,
            -0.01647633, 0.00392377)


def _horner(t: Tensor, coefficients: tuple[float, ...], own: bool) -> Tensor:
    """``sum_i c_i t^i`` by Horner's rule; ``own``: the running value (a fresh tensor) is
    updated in place (the same operations, the same bits).
    """
    p = t * coefficients[-1] + coefficients[-2]
    for c in reversed(coefficients[:-2]):
        p = p.mul_(t).add_(c) if own else p * t + c
    return p


def log_i0_approx(u: Tensor) -> Tensor:
    """``log I0(u)`` from the polynomials of Abramowitz and Stegun 9.8.1-9.8.2, branch-free.

    ``log P_small((u/3.75)^2)`` for ``|u| < 3.75``, ``|u| - log(|u|)/2 + log P_large(3.75/|u|)``
    above (both branches computed, one kept by ``torch.where``). Absolute error below 5e-7
    for every ``u`` (measured against ``i0e`` in float64: 4.7e-7; tested), gradient
    ``I1/I0`` to 1e-6 (tested), exactly 0 with zero slope at ``u = 0``. Only elementwise
    arithmetic, ``log`` and ``where``: ``torch.compile`` fuses it into one loop (about 10x
    faster than ``torch.special.i0e`` on the CPU); eager it is faster than ``i0e`` only on
    cache-sized tensors (measured in benchmarks/bench_likelihood.py), and without autograd
    its temporaries are updated in place (:func:`~torchmcmcpf.runtime.in_place`) and, on a
    CPU, the large branch is evaluated at its own arguments only
    (:func:`~torchmcmcpf.runtime.host_reads`): the same bits.
    """
    own = runtime.in_place(u)
    a = u.abs()
    small = a < 3.75
    t = torch.clamp(a, max=3.75)
    t = t.mul_(1.0 / 3.75).square_() if own else torch.square(t * (1.0 / 3.75))
    p_small = _horner(t, _P_SMALL, own)
    if own and runtime.host_reads(u) and p_small.is_contiguous():  # the large branch on its arguments only
        at = (~small).view(-1).nonzero().squeeze(-1)  # (12 % of a radar move's cells)
        big = a.view(-1)[at]  # >= 3.75 or NaN, where the clamp below is the identity
        out = p_small.log_()  # + 0.0 where small: the same bits
        out.view(-1)[at] = _horner(torch.reciprocal(big).mul_(3.75), _P_LARGE, own).log_().add_(
            big.sub_(torch.log(big).mul_(0.5)))
        return out
    big = torch.clamp(a, min=3.75)
    del a  # temporaries are dropped as soon as possible: the whole-grid path budgets memory
    r = torch.reciprocal(big, out=t) if own else torch.reciprocal(big)
    del t
    p = where(small, p_small, _horner(r.mul_(3.75) if own else r * 3.75, _P_LARGE, own))  # 3.75 / |u|
    del p_small, r
    tail = big.sub_(torch.log(big).mul_(0.5)) if own else big - 0.5 * torch.log(big)
    del big
    return (p.log_() if own else torch.log(p)) + where(small, 0.0, tail)


#: Largest float32 tensor for which eager :func:`log_i0` with autograd uses
#: :func:`log_i0_approx` (above it ``i0e``, whose graph holds two tensors where the
#: polynomial's holds about ten).
_APPROX_MAX_EAGER = 2**20

#: Elements per block, at most, of eager :func:`log_i0` without autograd on tensors of more
#: than ``2 * _APPROX_BLOCK`` elements (1 MB in float32): the polynomial's two dozen passes
#: stay in the cache. On the crossing's arguments (7.5 % of them >= 3.75; one thread, AMD
#: EPYC, 2026-12-07), ns an element for ``i0e`` / the polynomial in one call / in blocks:
#: 19.1 / 3.4 / 3.4 at 1.6e5 elements, 19.0 / 4.8 / 3.7 at 3.2e6, 26.5 / 11.6 / 5.1 at 1.7e7
#: (benchmarks/bench_likelihood.py, ``log-i0-*``, on uniform arguments in [0, 60]).
_APPROX_BLOCK = 2**18


def log_i0(u: Tensor) -> Tensor:
    """``log I0(u)``: exact in float64; :func:`log_i0_approx` (error < 5e-7) for lower
    precisions: under ``torch.compile`` one fused loop; eager without autograd block by block
    of :data:`_APPROX_BLOCK` elements (each block's passes in the cache: the MCMC filters'
    per-chain evaluations, the SIR's boxes, at any size); eager with autograd on tensors of at
    most :data:`_APPROX_MAX_EAGER` elements, ``i0e`` above (fewer saved tensors).

    The exact form is ``log(i0e(|u|)) + |u|``, stable for any ``u``; the ``|u|`` makes the
    gradient ``I1(u) / I0(u)`` exact everywhere, including ``u = 0`` where ``i0e`` itself has
    a kink (its autograd derivative there would give 1, not 0). Float64 (tests, gradcheck)
    always uses it. The approximation's error is far below the float32 round-off of a
    log-likelihood summed over hundreds of cells, so which form a float32 call uses does
    not matter numerically. Blocks are of memory, not of samples: the values are those of
    one :func:`log_i0_approx` call on the whole tensor, bit for bit.
    """
    n, fused, own = u.numel(), runtime.fused_elementwise(), runtime.in_place(u)
    if u.dtype == torch.float64 or not (fused or own or n <= _APPROX_MAX_EAGER):  # exact
        a = u.abs()
        return torch.log(torch.special.i0e(a)) + a
    if fused or not own or n <= 2 * _APPROX_BLOCK:
        return log_i0_approx(u)
    flat = u.reshape(-1)
    out = torch.empty_like(flat)
    blocks = math.ceil(n / _APPROX_BLOCK)
    size = 64 * math.ceil(n / blocks / 64)  # even blocks of whole cache lines
    for first in range(0, n, size):  # blocks of memory (cache tiling), not of samples
        out[first:first + size] = log_i0_approx(flat[first:first + size])
    return out.reshape(u.shape)


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
        (``2 * window + 1`` cells per axis), to which each target's point spread is truncated
        there (see :class:`~torchmcmcpf.models.sensors.grid.SeparableGridSensor`). Default 3,
        chosen by measuring the windowed against the whole-grid log-likelihood on the Table I
        scenario (widths = cell sizes, r0 ~ U[2700, 2900] m, b0 ~ U[-6, 6] deg, speed ~
        U[0, 15] m/s, SNR ~ U[9, 20] dB; K = 1, 3 and 10 targets; 1000 particles per run
        around the truth with spreads 5 m, 1 m/s and 10 % in amplitude; frames simulated from
        the truth; 6 runs each). Largest centred error ``max |d - mean(d)| / std(grid)`` over
        particles, ``d = window - grid``, and total variation between the two normalised
        weight vectors:

        ======  ===  =====================  ================
        window  K    centred error / std    TV of weights
        ======  ===  =====================  ================
        2       1    0.02 - 0.06            4e-3 - 7e-3
        2       3    0.06 - 0.15            3e-3 - 0.06
        3       1    2e-5 - 4e-5            1e-5 - 2e-5
        3       3    2e-3 - 3e-3            1e-4 - 9e-4
        3       10   2.5e-3 - 3e-3          up to 2.5e-3
        4       3    1e-5 - 7e-5            up to 8e-6
        4       10   4e-5 - 7e-5            up to 4e-5
        ======  ===  =====================  ================

        With one target the error is that of dropping the cells outside the box; with
        several, the truncated tails of neighbours inside each other's boxes add the rest
        (before the spread was truncated, window 3 measured 4e-5 for K = 3 too: the price of
        the local :meth:`log_likelihood_delta`). Stated tolerance for the default
        (tests/models/test_radar.py): ``max |d - mean(d)| <= 5e-3 * std(grid)`` over
        particles near the targets (3.5e-3 measured there, two overlapping 20 and 15 dB
        targets); ``window = 4`` brings it to 1e-4 at about twice the cost.
    method, memory_budget : evaluation path, memory; see :class:`~torchmcmcpf.models.sensors.grid.SeparableGridSensor`.

    Example
    -------
    >>> import math
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> sensor = tp.RangeDopplerBearingTBD.uniform((2700.0, 2900.0), (-10.0, 10.0), (-0.1, 0.1),
    ...                                            bearing_cell=math.pi / 180, noise_std=1.0)
    >>> sensor.frame_shape                             # (Nr, Nd, Nb) cells of 10 m, 2 m/s, 1 deg
    (21, 11, 12)
    >>> x = torch.tensor([[[2800.0, -5.0, 0.0, 0.0, sensor.amplitude_from_snr(15.0)]]])   # (B, K, D)
    >>> z = sensor.simulate(x, generator=torch.Generator().manual_seed(0))
    >>> z.shape, sensor.log_likelihood(x.unsqueeze(1), z).shape   # (B, Nr, Nd, Nb), (B, N)
    (torch.Size([1, 21, 11, 12]), torch.Size([1, 1]))
    """

    dim = 5
    #: ``sigma``
    noise_std: float

    def __init__(self, range_bins: Tensor, doppler_bins: Tensor, bearing_bins: Tensor, *, noise_std: float = 1.0,
                 range_width: float | None = None, doppler_width: float | None = None,
                 bearing_width: float | None = None, window: int = 3, method: str = "window",
                 memory_budget: int | None = None):
        super().__init__({"range_bins": (range_bins, range_width), "doppler_bins": (doppler_bins, doppler_width),
                          "bearing_bins": (bearing_bins, bearing_width)},
                         window=window, method=method, memory_budget=memory_budget)
        self.noise_std = check_positive(noise_std, "noise_std")
        native.available()  # the C loop built (once per machine) or found now, not inside a compiled step

    @classmethod
    def uniform(cls, range_limits: tuple[float, float], doppler_limits: tuple[float, float],
                bearing_limits: tuple[float, float], *, range_cell: float = 10.0, doppler_cell: float = 2.0,
                bearing_cell: float = math.pi / 180, **kw: Any) -> RangeDopplerBearingTBD:
        """Uniform grid: each ``(first, last)`` gives the first cell centre and an upper limit
        of an axis (:func:`~torchmcmcpf.models.sensors.grid.lattice`), with cells of 10 m, 2 m/s
        and 1 deg by default (Table I); other keywords go to the constructor.
        """
        return cls(lattice(range_limits, range_cell, "range"), lattice(doppler_limits, doppler_cell, "doppler"),
                   lattice(bearing_limits, bearing_cell, "bearing"), **kw)

    # ------------------------------------------------------------------ model pieces
    def measurement_coords(self, x: Tensor) -> Tensor:
        """Eq. 21: ``(..., K, 5) -> (..., K, 3)`` as ``[r, d, b]`` (bearing ``atan2(y, x)``;
        a state at the radar itself maps to ``r = d = b = 0``, see :func:`grid.polar`).
        """
        r, b, ux, uy = polar(x[..., X], x[..., Y])
        d = ux * x[..., VX] + uy * x[..., VY]
        return torch.stack((r, d, b), dim=-1)

    def signal(self, x: Tensor) -> Tensor:
        """Amplitude ``rho``: ``(..., K, 5) -> (..., K)``."""
        return x[..., RHO]

    def prepare_frame(self, z: Tensor) -> Tensor:
        """``sqrt(z) / sigma^2``, so that :meth:`cell_log_ratio` is ``-A^2/(2 sigma^2) + log I0(A * zc)``."""
        return torch.sqrt(z) / self.noise_std**2

    def native_ratio(self) -> tuple[str, float]:
        """:meth:`cell_log_ratio` for the C loop of the windowed path
        (:mod:`~torchmcmcpf.models.sensors.grid.native`): ``("rician", 1 / (2 sigma^2))``.
        """
        return ("rician", 1.0 / (2.0 * self.noise_std**2))

    def cell_log_ratio(self, A: Tensor, zc: Tensor) -> Tensor:
        """Rician log ratio per cell: ``-A^2 / (2 sigma^2) + log I0(A sqrt(z) / sigma^2)``.

        Parameters
        ----------
        A : cell amplitudes; zc : ``prepare_frame(z)`` at the same cells (broadcastable).
        """
        return log_i0(A * zc) - A * A / (2.0 * self.noise_std**2)

    # ------------------------------------------------------------------ multitarget prior hooks
    def detection_statistic(self, z: Tensor) -> Tensor:
        """``z / (2 sigma^2)``: the power over the mean noise power, ``Exp(1)`` in a noise-only
        cell (the data-driven proposal's peaks, :meth:`SeparableGridSensor.sample_from_data`).
        """
        return z / (2.0 * self.noise_std**2)

    def detection_signal(self, stat: Tensor) -> Tensor:
        """``sqrt(stat)``: the envelope over ``sqrt(2) sigma``, where the amplitudes of a
        cell's targets add (eq. 19); inverse :meth:`detection_stat`.
        """
        return torch.sqrt(stat)

    def detection_stat(self, signal: Tensor) -> Tensor:
        """``signal^2`` (inverse of :meth:`detection_signal`)."""
        return signal * signal

    def place(self, x: Tensor, coords: Tensor) -> Tensor:
        """``x (*S, 5)`` moved to the measured coordinates ``coords (*S, 3) = [r, d, b]``
        (eq. 21 inverted): position ``r (cos b, sin b)``, radial velocity ``d`` along the new
        line of sight, the tangential velocity and the amplitude kept from ``x``.
        """
        _, _, ux, uy = polar(x[..., X], x[..., Y])
        tangential = ux * x[..., VY] - uy * x[..., VX]
        r, d, b = coords.unbind(-1)
        c, s = torch.cos(b), torch.sin(b)
        return torch.stack((r * c, d * c - tangential * s, r * s, d * s + tangential * c, x[..., RHO]), -1)

    # ------------------------------------------------------------------ SNR
    def amplitude_from_snr(self, snr_db: float | Tensor) -> float | Tensor:
        """``rho = sigma * sqrt(2 * 10^(snr_db / 10))``, inverse of ``SNR = rho^2 / (2 sigma^2)``."""
        if torch.is_tensor(snr_db):
            return self.noise_std * torch.sqrt(2.0 * 10.0 ** (snr_db / 10.0))
        return self.noise_std * math.sqrt(2.0 * 10.0 ** (snr_db / 10.0))

    def snr_db_from_amplitude(self, rho: float | Tensor) -> float | Tensor:
        """``10 log10(rho^2 / (2 sigma^2))`` (peak target power over mean noise power per cell)."""
        if torch.is_tensor(rho):
            return 10.0 * torch.log10(rho * rho / (2.0 * self.noise_std**2))
        return 10.0 * math.log10(rho * rho / (2.0 * self.noise_std**2))

    # ------------------------------------------------------------------ simulation
    def simulate(
        self, x: Tensor, *, generator: torch.Generator, exists: Tensor | None = None
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
        phi = 2.0 * math.pi * torch.rand((B,) + (1,) * self.n_axes, generator=generator, device=x.device, dtype=x.dtype)
        noise = self.noise_std * torch.randn((2, B) + self.frame_shape, generator=generator, device=x.device,
                                             dtype=x.dtype)
        return (A * torch.cos(phi) + noise[0]) ** 2 + (A * torch.sin(phi) + noise[1]) ** 2
