"""Point measurements in Poisson clutter, without data association.

Septier, Pang, Carmi and Godsill (paper 001, "Observation model"; after Gilholm et al.
2005): at every step the sensor returns an unordered set of ``M_k`` points in a
rectangular surveillance area of size ``V``:

- clutter: a Poisson process of rate ``L_C`` per frame, uniform over the area
  (``p_C(z) = 1 / V``);
- targets: every live target ``n`` (``e_n = 1``) yields ``Poisson(L_x)`` points
  ``z = H x_n + v``, ``v ~ N(0, R)``.

The superposition is a Poisson process of intensity ``lambda(z) = L_C / V + L_x sum_n e_n
N(z; H x_n, R)``, whose density, association-free (DESIGN.md), is

    log p(Z | x, e) = -(L_C + L_x sum_n e_n) + sum_m log(L_C / V + L_x sum_n e_n N(z_m; H x_n, R)).

:meth:`PoissonClutterPoints.log_likelihood` returns exactly this (the density of the set
with respect to the unit-rate Poisson process on the area, up to the constant ``V``), so a
filter's evidence is comparable across models.

Frames with different numbers of points are batched as a padded
:class:`~torchmcmcpf.models.sensors.association.PointFrame` ``(z (B, M, 2), mask (B, M))``;
padded rows (``mask`` False) contribute nothing. A sequence is the same NamedTuple with a
leading ``T``: ``z (T, B, M, 2)``, ``mask (T, B, M)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch

from ... import runtime
from ..._native import available
from ..._native.select import where
from ..._validation import check_batch, check_finite, check_positive, check_shape, check_tensor
from ...resampling import uniform_pick
from ...runtime import take_along
from ...typing import PointFrame, PointMeasurement, Tensor, X, Y, split_points
from ..base import SensorModel
from . import _points_native as native
from ._points_native import whiten as _whiten

__all__ = ["PoissonClutterPoints", "PointFrame", "as_area", "gauss_exponents", "log_near_points"]

AreaLike = Tensor | Sequence[Sequence[float]]


#: Below ``e^FLUSH`` (about ``1e-304``, a normal number) a float64 exponential is flushed to 0
#: (:func:`_exp_`). ATen's vectorised ``exp`` takes a slow path on arguments whose result is
#: subnormal or 0 (10x on ``-746 < t < -708``, 5x below, 3x on ``-inf``; AMD EPYC, one thread),
#: and the far (point, target) pairs and the inactive slots of a frame give them: 79 % of a
#: births/deaths joint draw's terms. Clamped to ``FLUSH`` first, every argument is in range.
#: A flushed term is below ``1e-304``: beside the clutter floor ``L_C / V`` of an intensity, or
#: the 1 of a shifted ``logsumexp``, it is below half an ulp.
FLUSH = -700.0
#: :data:`FLUSH` of the other floating dtypes: float32's slow path starts below ``-87.3`` (13x
#: on ``-200 < t < -88``; 2,000,000 numbers in 21.9 against 1.6 ms, AMD EPYC, one thread), and
#: ``e^-80`` (about ``1.8e-35``, a normal float32) is below half an ulp of any clutter floor
#: above ``1e-27`` and of a shifted ``logsumexp``'s 1
FLUSH_SINGLE = -80.0
#: dtype -> (its flush level, ATen's ``e^FLUSH`` in that dtype: what a clamped term gives)
_FLUSHES = {dt: (lo, float(torch.tensor(lo, dtype=dt).exp()))
            for dt, lo in ((torch.float64, FLUSH), (torch.float32, FLUSH_SINGLE), (torch.float16, FLUSH_SINGLE),
                           (torch.bfloat16, FLUSH_SINGLE))}


def flush_level(dtype: torch.dtype) -> tuple[float, float]:
    """``(FLUSH, e^FLUSH)`` for ``dtype``: :data:`FLUSH` for float64, :data:`FLUSH_SINGLE`
    for the other floating dtypes, with ATen's exponential of it in that dtype.
    """
    return _FLUSHES.get(dtype, _FLUSHES[torch.float32])


def _exp_(t: Tensor, *, fresh: bool = False) -> Tensor:
    """``exp(t)`` in place where it exceeds ``e^FLUSH`` (:data:`FLUSH`), exactly 0 elsewhere
    (``-inf`` included), NaN kept: clamp, ``exp``, then the clamped terms zeroed
    (``torch.threshold``, which keeps NaN). ``fresh``: on a new tensor, ``t`` untouched.
    No autograd (in place): :func:`_exp` is the same arithmetic, differentiable.
    """
    lo, e_lo = flush_level(t.dtype)
    t = t.clamp(min=lo) if fresh else t.clamp_(min=lo)
    return torch.threshold_(t.exp_(), e_lo, 0.0)


def _exp(t: Tensor) -> Tensor:
    """:func:`_exp_` out of place, differentiable (the same operations, the same bits)."""
    lo, e_lo = flush_level(t.dtype)
    return torch.threshold(t.clamp(min=lo).exp(), e_lo, 0.0)


def _rate(t: Tensor, in_place: bool) -> Tensor:
    """``exp(max(t, FLUSH))``: the exponentials an intensity adds to its clutter floor
    ``L_C / V > 0``, clamped (the fast path of ``exp``) and not zeroed, a clamped term being
    below half an ulp of that floor (:data:`FLUSH`): the intensities of :func:`_exp_`, one
    pass fewer. ``in_place``: ``t`` is a fresh tensor and may be overwritten (no autograd);
    else differentiable. NaN kept.
    """
    lo = flush_level(t.dtype)[0]
    return t.clamp_(min=lo).exp_() if in_place else t.clamp(min=lo).exp()


def _logsumexp_fast(x: Tensor, dim: int) -> Tensor:
    """``torch.logsumexp(x, dim)`` by ATen's steps (the maxima, infinite ones set to 0, ``exp``
    of the differences summed, ``log``, the maxima added back) with :func:`_exp_`: the terms
    below ``e^FLUSH`` of the maximum's 1 are dropped, so the same values (to half an ulp; in
    practice the same bits). No autograd (its in-place steps), ``x`` not modified.
    """
    maxes = x.amax(dim, keepdim=True)
    maxes.masked_fill_(maxes.abs() == math.inf, 0)
    return _exp_(x - maxes).sum(dim).log_().add_(maxes.squeeze(dim))


@torch.library.custom_op("torchmcmcpf::logsumexp", mutates_args=())
def _logsumexp(x: Tensor, dim: int) -> Tensor:
    """``torch.logsumexp(x, dim)``, opaque to ``torch.compile``: a compiled kernel calls the
    same ATen kernels as eager code, so its bits are eager's (Inductor's own ``exp`` differs
    from ATen's in the last bit, and a filter's ``compile_step=True`` must equal eager).
    """
    return _logsumexp_fast(x, dim)


@_logsumexp.register_fake
def _(x: Tensor, dim: int) -> Tensor:
    return x.sum(dim)


def _logsumexp_context(ctx, inputs, output):
    ctx.save_for_backward(inputs[0], output)
    ctx.dim = inputs[1]


def _logsumexp_backward(ctx, grad):
    x, out = ctx.saved_tensors
    # d/dx logsumexp = softmax; a slice of -inf values (out = -inf) gets no gradient, not NaN
    soft = torch.exp(x - where(torch.isneginf(out), 0.0, out).unsqueeze(ctx.dim))
    return grad.unsqueeze(ctx.dim) * soft, None


_logsumexp.register_autograd(_logsumexp_backward, setup_context=_logsumexp_context)


def _intensity_change_eager(rate_terms: Tensor, moved: int, cache: Tensor, mask: Tensor, in_place: bool = False
                            ) -> tuple[Tensor, Tensor]:
    """The arithmetic of :meth:`PoissonClutterPoints.log_likelihood_delta_cached` on flat rows:
    ``rate_terms (R, 2V, M)`` float64 the moved slots' ``log(L_x e N(z_m; H x, R))`` (old then
    new, ``-inf`` where the slot is inactive; ``V = moved``), ``cache (R, M)`` float64
    intensities, ``mask (R, M)`` bool -> ``(sum over valid points of log(lambda'_m / lambda_m)
    (R,), change lambda' - lambda (R, M))``, both float64. ``in_place``: ``rate_terms`` is a
    fresh tensor and may be overwritten (no autograd).
    """
    rate = _rate(rate_terms, in_place)
    # - sum of the old rates + sum of the new, j ascending, written out (2V = 2 or 4 terms):
    # an inactive slot's rate is e^FLUSH, below half an ulp of the cache it changes, so no sign
    # to multiply (the intensities of sum_j sign_j rate_j with sign -e_old, +e_new)
    if moved == 1:  # new - old: the value of -old + new, in one pass
        change = rate[:, 1] - rate[:, 0]
    else:
        change = -rate[:, 0]
        for j in range(1, rate.shape[1]):  # over the moved slots' old and new terms
            change = change.sub_(rate[:, j]) if j < moved else change.add_(rate[:, j])
    # log(lambda' / lambda) with lambda' = lambda + change, the cache's next value: ATen's
    # float64 log1p is not vectorised (2.3 against 0.34 ms for log on 380,000 numbers, one
    # thread), and the rounding of lambda + change costs at most an ulp of the ratio (about
    # 1e-16 absolute per point, against log1p's relative 1e-16)
    log_ratio = where(mask, torch.log((cache + change) / cache), 0.0)
    return (log_ratio @ torch.ones(log_ratio.shape[-1], 1, dtype=log_ratio.dtype, device=log_ratio.device)
            ).squeeze(-1), change


@torch.library.custom_op("torchmcmcpf::intensity_change", mutates_args=())
def _intensity_change(rate_terms: Tensor, moved: int, cache: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`_intensity_change_eager`, opaque to ``torch.compile`` (the same ATen kernels as
    eager code: Inductor's ``exp`` and ``log`` differ from ATen's in the last bit).
    """
    return _intensity_change_eager(rate_terms, moved, cache, mask)


@_intensity_change.register_fake
def _(rate_terms: Tensor, moved: int, cache: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    return cache.sum(-1), torch.empty_like(cache)


def _intensity_eager(terms: Tensor, clutter: float, in_place: bool = False) -> Tensor:
    """The Poisson intensity at every point, ``lambda_m = L_C / V + sum_k e_k exp(t_km)``:
    ``terms (..., K, M)`` the slots' ``t = log(L_x e_k N(z_m; H x_k, R))`` (float64, ``-inf``
    for an inactive slot: :meth:`PoissonClutterPoints.log_intensity_terms`), ``clutter`` ``L_C /
    V > 0`` -> ``(..., M)`` float64. ``in_place``: ``terms`` is a fresh tensor and may be
    overwritten (no autograd). A NaN state stays NaN.

    No shift by a maximum is needed: a term is at most ``L_x / (2 pi |R|^1/2)`` (no overflow)
    and ``lambda_m >= L_C / V > 0`` (no ``log 0``); the terms are clamped to ``e^FLUSH``
    (:func:`_rate`), below half an ulp of the clutter floor.
    """
    total = _rate(terms, in_place).sum(-2)
    return total.add_(clutter) if in_place else total + clutter


@torch.library.custom_op("torchmcmcpf::intensity", mutates_args=())
def _intensity(terms: Tensor, clutter: float) -> Tensor:
    """:func:`_intensity_eager`, opaque to ``torch.compile`` (the same ATen kernels as eager
    code, so ``compile_step=True`` gives eager's bits: Inductor's ``exp`` differs in the last bit).
    """
    return _intensity_eager(terms, clutter)


@_intensity.register_fake
def _(terms: Tensor, clutter: float) -> Tensor:
    return terms.new_empty(terms.shape[:-2] + terms.shape[-1:])


def _intensity_context(ctx, inputs, output):
    ctx.save_for_backward(inputs[0])


def _intensity_backward(ctx, grad):
    (terms,) = ctx.saved_tensors  # d lambda_m / d t_km = exp(t_km), 0 where clamped (and inactive)
    return grad.unsqueeze(-2) * _exp(terms), None


_intensity.register_autograd(_intensity_backward, setup_context=_intensity_context)


def as_area(area: AreaLike, name: str = "area") -> Tensor:
    """``((x_lo, x_hi), (y_lo, y_hi))`` -> a ``(2, 2)`` float64 tensor, checked (lo < hi)."""
    a = torch.as_tensor(area, dtype=torch.float64)
    if a.shape != (2, 2) or not bool(torch.isfinite(a).all()) or not bool((a[:, 1] > a[:, 0]).all()):
        raise ValueError(
            f"{name} must be ((x_lo, x_hi), (y_lo, y_hi)) with finite lo < hi, got {area!r}"
        )
    return a


def gauss_exponents(a: Tensor, b: Tensor, pts: Tensor, *, W: Tensor, diagonal: bool, centre: Tensor,
                    const: Tensor | float, mask: Tensor | None = None) -> Tensor:
    """``const - 0.5 |W (h - z_m)|^2`` for every position ``h = (a, b)`` and point ``z_m``: the
    exponent of a Gaussian at each (position, point) pair, as one batched matrix product.

    ``a, b`` : (B, *S) the positions' two coordinates (any strides); ``pts`` : (B, M, 2);
    ``W`` : (2, 2) whitening matrix (``R^{-1} = W^T W``), ``diagonal`` whether it is;
    ``centre`` : (2,) a point near the data (the area's centre), subtracted from both sides
    first; ``const`` : a float or ``(B, *S)`` (``-inf`` drops a position: an inactive slot);
    ``mask`` : (B, M) bool, optional: ``-inf`` at the points off it. Returns ``(B, *S, M)``
    float64, a fresh tensor, differentiable in ``a``, ``b``.

    With whitened, centred ``p = W (h - c)`` and ``w_m = W (z_m - c)``,

        ``const - 0.5 |p - w_m|^2 = [p, const - 0.5 |p|^2, 1] . [w_m, 1, -0.5 |w_m|^2]``,

    so every pair is one 4-term dot product of a row per position and a column per point
    (``torch.bmm``): one pass writing the ``(B, *S, M)`` result instead of two differences,
    two squares and three scalings, each a pass over it (a births/deaths joint draw's ``(B,
    C, K, M)`` exponents: 4.3 against 9.4 ms for the intensities at ``B = 10``, 1000 chains,
    one thread). Float64 whatever the dtype of the positions: the expansion cancels
    ``|p|^2`` against ``2 p . w_m``, to about ``1e-16 |p|^2`` (centred, ``|p|`` is at most
    the area's half-diagonal in noise units: relative errors of the Gaussians below ``1e-10``).
    """
    bsz, m = pts.shape[:2]
    lead = tuple(a.shape)
    p0, p1 = native.centred_axes(a, b, W, diagonal, centre)  # (B, *S) each
    w0, w1 = native.centred_axes(pts[..., 0], pts[..., 1], W, diagonal, centre)  # (B, M)
    w_half = -0.5 * (w0 * w0 + w1 * w1)
    if mask is not None:
        w_half = where(mask, w_half, -math.inf)
    rows = torch.stack([p0, p1, const - 0.5 * (p0 * p0 + p1 * p1), torch.ones_like(p0)], -1)  # (B, *S, 4)
    cols = torch.stack([w0, w1, torch.ones_like(w0), w_half], 1)  # (B, 4, M)
    out = torch.bmm(rows.reshape(bsz, -1, 4), cols)  # (B, prod(S), M)
    return out.reshape(lead + (m,))


def log_near_points(pos: Tensor, pts: Tensor, mask: Tensor | None, *, W: Tensor, p_uniform: float,
                    area: Tensor, diagonal: bool = False) -> Tensor:
    """``log g(pos)`` of the density "near one of the points, or anywhere".

        ``g(pos) = p_u U(pos; area) + (1 - p_u) (1 / M) sum_m N(pos; z_m, R)``,  ``R^{-1} = W^T W``

    over the ``M`` valid points of each run (``g = U`` for a run without points). The one
    helper behind the birth proposal of :class:`~torchmcmcpf.models.existence.BirthDeath`
    (paper 004 eqs. 64-65, point-measurement analogue) and the data-driven proposal of
    :meth:`PoissonClutterPoints.sample_from_data`.

    Parameters
    ----------
    pos : (B, *S, 2) positions; pts : (B, M, 2) points; mask : (B, M) bool or None (all valid).
    W : (2, 2) whitening matrix (``I / s`` for an isotropic spread ``s``); p_uniform : ``p_u``;
    area : (2, 2) ``((x_lo, x_hi), (y_lo, y_hi))``; diagonal : whether ``W`` is diagonal (the
    whitening then per axis, the same values).

    Returns
    -------
    (B, *S), dtype of ``pos`` (``-inf`` outside the area where no point is near).
    """
    b, m = pts.shape[:2]
    lead = (b,) + (1,) * (pos.dim() - 2)
    a = area.to(pos.dtype)
    log_volume = float(torch.log(area[:, 1] - area[:, 0]).sum())
    inside = ((pos >= a[:, 0]) & (pos <= a[:, 1])).all(-1)
    log_u = where(inside, -log_volume, -math.inf).to(pos.dtype)
    if mask is None:
        mask = torch.ones((b, m), dtype=torch.bool, device=pts.device)
    log_norm = float(torch.log(torch.abs(torch.det(W.to(torch.float64))))) - math.log(2 * math.pi)
    centre = area.to(torch.float64).mean(-1)
    n_valid = mask.sum(-1).to(pos.dtype).reshape(lead)
    if native.applies(pos) and m > 0:  # the C loop: one sum a position, no (B, *S, M) tensor
        q = native.centred(pos[..., 0], pos[..., 1], W, diagonal, centre).reshape(b, -1, 2)
        w = native.centred(pts[..., 0], pts[..., 1], W, diagonal, centre).transpose(1, 2)  # (B, 2, M)
        lse_near = native.near(q, w, mask.to(torch.uint8), log_norm).reshape(pos.shape[:-1]).to(pos.dtype)
    else:
        log_g = gauss_exponents(pos[..., 0], pos[..., 1], pts, W=W, diagonal=diagonal, centre=centre,
                                const=log_norm, mask=mask)  # (B, *S, M), -inf off the mask
        log_g = log_g.to(pos.dtype)
        lse = _logsumexp_fast if runtime.in_place(pos) else torch.logsumexp  # the same bits
        lse_near = lse(log_g, -1)
    log_near = lse_near - torch.log(n_valid.clamp(min=1))
    log_pi = math.log(p_uniform) if p_uniform > 0 else -math.inf
    log_pn = math.log1p(-p_uniform) if p_uniform < 1 else -math.inf
    log_q = torch.logaddexp(log_pi + log_u, log_pn + log_near)
    return where(n_valid > 0, log_q, log_u)


class PoissonClutterPoints(SensorModel[PointMeasurement]):
    """Association-free likelihood of point measurements in Poisson clutter (module docstring).

    Parameters
    ----------
    clutter_rate : ``L_C >= 0``, mean number of clutter points per frame.
    detection_rate : ``L_x >= 0``, mean number of points per live target and frame.
    area : ``((x_lo, x_hi), (y_lo, y_hi))`` [m]; clutter is uniform on it, ``V`` its size.
    noise_std : measurement noise standard deviation [m] (``R = noise_std^2 I``), or pass
        ``R``.
    R : (2, 2) symmetric positive definite noise covariance (instead of ``noise_std``).
    dim : per-target state size D (layout ``[x, vx, y, vy, ...]``; ``H`` picks x and y).

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> sensor = tp.PoissonClutterPoints(10.0, 2.0, ((0, 5000), (0, 5000)), noise_std=10.0)
    >>> x = torch.tensor([[[1000.0, 0.0, 2000.0, 0.0]]])   # (B, K, D)
    >>> alive = torch.ones(1, 1, dtype=torch.bool)        # (B, K)
    >>> frame = sensor.simulate(x, exists=alive, generator=torch.Generator().manual_seed(0))
    >>> frame.z.shape[-1], frame.mask.dtype              # points (B, M, 2) with a (B, M) mask
    (2, torch.bool)
    >>> sensor.log_likelihood(x.unsqueeze(1), frame, alive.unsqueeze(1)).shape   # (B, N)
    torch.Size([1, 1])
    """

    area: Tensor  #: (2, 2) buffer, ``((x_lo, x_hi), (y_lo, y_hi))``
    R: Tensor  #: (2, 2) buffer, the noise covariance
    W: Tensor  #: (2, 2) buffer, ``L^{-1}`` with ``R = L L^T`` (float64)
    centre: Tensor  #: (2,) buffer (not saved), the area's centre (:func:`gauss_exponents`)

    def __init__(
        self,
        clutter_rate: float,
        detection_rate: float,
        area: AreaLike,
        *,
        noise_std: float | None = None,
        R: Tensor | None = None,
        dim: int = 4,
    ):
        super().__init__()
        self.clutter_rate = check_positive(clutter_rate, "clutter_rate", allow_zero=True)
        self.detection_rate = check_positive(detection_rate, "detection_rate", allow_zero=True)
        if dim < 4:
            raise ValueError(f"dim must be >= 4 for the [x, vx, y, vy] layout, got {dim}")
        if (noise_std is None) == (R is None):
            raise ValueError("give exactly one of noise_std and R")
        if R is None:
            R = check_positive(noise_std, "noise_std") ** 2 * torch.eye(2, dtype=torch.float64)
        R = torch.as_tensor(R, dtype=torch.float64)
        if R.shape != (2, 2):
            raise ValueError(f"R has shape {tuple(R.shape)}, expected (2, 2)")
        try:
            L = torch.linalg.cholesky(R)
        except RuntimeError as err:
            raise ValueError(f"R must be symmetric positive definite: {err}") from err
        area_t = as_area(area)
        dtype = torch.get_default_dtype()
        self.register_buffer("area", area_t.to(dtype))
        self.register_buffer("R", R.to(dtype))
        # whitening precomputed (R = L L^T, W = L^{-1}; float64 like the grid sensors' bins,
        # computations follow the dtype of x): points and targets are whitened once per call,
        # not each of the K x M residuals, and no Cholesky per call
        self.register_buffer("W", torch.linalg.inv(L).tril())
        #: whether ``R`` (so ``W`` and ``L``) is diagonal: whitening and noise then per axis
        self.diagonal = bool((R == torch.diag(torch.diagonal(R))).all())
        self.volume = float((area_t[:, 1] - area_t[:, 0]).prod())
        #: (2,) float64, the area's centre: subtracted before the Gaussians' exponents are
        #: expanded into products (:func:`gauss_exponents`), which keeps their round-off small
        self.register_buffer("centre", area_t.mean(-1), persistent=False)
        self.dim = dim
        self.meas_dim = 2
        self.frame_shape = (None, 2)
        self._log_norm = -math.log(2 * math.pi) - float(torch.log(torch.diagonal(L)).sum())
        available()  # the C loops built (once per machine) or found now, not inside a compiled step

    # -- likelihood ---------------------------------------------------------------------
    def log_intensity_terms(self, x: Tensor, z: Tensor, exists: Tensor | None = None) -> Tensor:
        """``log(L_x N(z_m; H x_n, R))`` for every slot and point: ``(B, *S, K, D), (B, M, 2)
        -> (B, *S, K, M)`` float64, a fresh tensor (:func:`gauss_exponents`); with ``exists (B,
        *S, K)`` bool, ``-inf`` for the inactive slots (their terms then vanish from
        :meth:`intensity` without a pass over them).
        """
        log_rate = math.log(self.detection_rate) if self.detection_rate > 0 else -math.inf
        const: Tensor | float = log_rate + self._log_norm
        if exists is not None:  # float64: the default dtype of a where between two floats may be float32
            const = where(exists, torch.tensor(const, dtype=torch.float64, device=exists.device), -math.inf)
        return gauss_exponents(x[..., X], x[..., Y], z, W=self.W, diagonal=self.diagonal, centre=self.centre,
                               const=const)

    def _native_positions(self, a: Tensor, b: Tensor) -> Tensor:
        """Whitened, centred positions for the C loops: ``a, b (...)`` -> ``(..., 2)`` float64."""
        return native.centred(a, b, self.W, self.diagonal, self.centre)

    def _native_points(self, pts: Tensor) -> Tensor:
        """The frame's points for the C loops: ``(B, M, 2)`` -> whitened, centred, by axis ``(B, 2, M)``."""
        return self._native_positions(pts[..., 0], pts[..., 1]).transpose(1, 2)

    def _native_consts(self, exists: Tensor | None, shape: tuple[int, ...], device: torch.device) -> Tensor:
        """Each slot's ``log(L_x / (2 pi |R|^1/2))``, ``-inf`` where inactive: ``(..., K)`` float64."""
        log_rate = math.log(self.detection_rate) if self.detection_rate > 0 else -math.inf
        const = torch.tensor(log_rate + self._log_norm, dtype=torch.float64, device=device)
        return const.expand(shape) if exists is None else where(exists, const, -math.inf)

    def intensity(self, x: Tensor, z: Tensor, exists: Tensor | None = None) -> Tensor:
        """The Poisson intensity at every point (module docstring; :func:`_intensity_eager`):
        ``lambda_m = L_C / V + L_x sum_n e_n N(z_m; H x_n, R)``, ``(B, *S, K, D), (B, M, 2),
        (B, *S, K) -> (B, *S, M)`` float64; needs ``L_C > 0``. Differentiable in ``x``.
        """
        clutter = self.clutter_rate / self.volume
        if native.applies(x):  # the C loop: no (B, *S, K, M) tensor
            lead, k = tuple(x.shape[:-2]), x.shape[-2]
            rows = (lead[0], math.prod(lead[1:]), k)  # explicit: K = 0 or M = 0 too
            lam = native.intensity(self._native_positions(x[..., X], x[..., Y]).reshape(rows + (2,)),
                                   self._native_consts(exists, lead + (k,), x.device).reshape(rows),
                                   self._native_points(z), clutter)
            return lam.reshape(lead + (z.shape[1],))
        terms = self.log_intensity_terms(x, z, exists)  # an inactive slot's terms are -inf: rate 0
        if runtime.generated_reductions():  # compiled: eager's kernels, eager's bits
            return _intensity(terms, clutter)
        return _intensity_eager(terms, clutter, in_place=runtime.in_place(x))

    def log_likelihood(self, x: Tensor, z: PointMeasurement, exists: Tensor | None = None) -> Tensor:
        """``-(L_C + L_x sum_n e_n) + sum_m log(L_C / V + L_x sum_n e_n N(z_m; H x_n, R))``
        (paper 001, DESIGN.md), summed over the valid points only.

        Parameters
        ----------
        x : (B, *S, K, D) multitarget states.
        z : ``PointFrame(z (B, M, 2), mask (B, M))`` or a tensor ``(B, M, 2)`` (all valid).
        exists : (B, *S, K) bool, optional (all slots live when absent).

        Returns
        -------
        (B, *S). Differentiable in ``x``; a frame with ``M = 0`` gives ``-(L_C + L_x n)``.
        With clutter (``L_C > 0``) the log of :meth:`intensity`, the chains' cache
        (:meth:`amplitude_cache`; float64 whatever the dtype of ``x``); without it a
        ``logsumexp`` over the slots.
        """
        pts, mask = split_points(z)
        if self.clutter_rate > 0:
            return self.log_likelihood_of_cache(self.intensity(x, pts, exists), x, z, exists, fresh=True)
        terms = self.log_intensity_terms(x, pts)  # (B, *S, K, M)
        if exists is not None:
            terms = where(exists.unsqueeze(-1), terms, torch.full_like(terms, -math.inf))
        # compiled: through the opaque op, so that a compiled kernel gives eager's bits
        lse = _logsumexp if runtime.generated_reductions() else torch.logsumexp
        return self._sum_over_points(lse(terms, -2), mask, x, exists)  # (B, *S, M) summed

    def log_likelihood_of_cache(self, cache: Tensor, x: Tensor, z: PointMeasurement,
                                exists: Tensor | None = None, *, fresh: bool = False) -> Tensor:
        """:meth:`log_likelihood` from the intensities ``cache (B, *S, M)`` of ``x`` (:meth:`amplitude_cache`;
        ``cache`` is not changed unless ``fresh``: a temporary the logs may overwrite): the
        same arithmetic after the intensity, the same bits.
        """
        mask = split_points(z)[1]
        if native.applies(x):  # the C loop: one vectorised log a point, summed where valid
            lead, m = tuple(cache.shape[:-1]), cache.shape[-1]
            valid = torch.ones((lead[0], m), dtype=torch.uint8) if mask is None else mask.to(torch.uint8)
            total = native.log_sum(cache.reshape(lead[0], math.prod(lead[1:]), m), valid).reshape(lead)
            return self._minus_count(total, x, exists)
        logs = cache.log_() if fresh and runtime.in_place(x) else cache.log()
        return self._sum_over_points(logs, mask, x, exists)

    def _sum_over_points(self, per_point: Tensor, mask: Tensor | None, x: Tensor, exists: Tensor | None) -> Tensor:
        """``sum_m log lambda_m`` over the valid points minus the expected count ``L_C + L_x
        n``: ``per_point (B, *S, M)`` the logs, ``mask (B, M)`` or None -> ``(B, *S)``.
        """
        if mask is not None:
            m = mask.reshape(mask.shape[:1] + (1,) * (x.dim() - 3) + mask.shape[1:])
            per_point = where(m, per_point, torch.zeros_like(per_point))
        # The sum over the points as a product with a column of ones: eager and compiled code
        # then make the same BLAS call, so ``compile_step=True`` gives eager's bits (Inductor's
        # own inner reduction adds the M terms in another order: last-bit differences).
        ones = torch.ones(per_point.shape[-1], 1, dtype=per_point.dtype, device=per_point.device)
        total = (per_point.flatten(0, -2) @ ones).reshape(per_point.shape[:-1])  # flatten: M = 0 too
        return self._minus_count(total, x, exists)

    def _minus_count(self, total: Tensor, x: Tensor, exists: Tensor | None) -> Tensor:
        """``total (B, *S)`` (the sum over the points) minus the expected count ``L_C + L_x n``,
        in the dtype of ``x``.
        """
        if exists is not None:
            n_live = exists.to(x.dtype).sum(-1)
        else:
            n_live = torch.full(x.shape[:-2], float(x.shape[-2]), dtype=x.dtype, device=x.device)
        return total.to(x.dtype) - (self.clutter_rate + self.detection_rate * n_live)

    def trim_frame(self, z: PointMeasurement) -> PointMeasurement:
        """``PointFrame(z[:, :W], mask[:, :W])`` with ``W`` one past the last point valid in any
        run, at least 1 (one host read): a sequence's frames are padded to its widest (``M =
        45`` on the births/deaths scene, 33 valid at most in a step's batch on average), and
        every term of a step is a ``(..., M)`` tensor. ``z`` itself without a mask or without
        padding to drop.
        """
        pts, mask = split_points(z)
        if mask is None or mask.shape[-1] <= 1:
            return z
        cols = torch.arange(1, mask.shape[-1] + 1, device=mask.device)
        width = max(1, int(where(mask.any(0), cols, 0).max()))
        if width == mask.shape[-1]:
            return z
        return PointFrame(pts[:, :width].contiguous(), mask[:, :width].contiguous())

    # -- the chain cache: each sample's intensity at every point ----------------------------
    sweep_cache = True  # M numbers per sample: cheap beside the K M terms a slot update saves

    def amplitude_cache(self, x: Tensor, exists: Tensor | None = None, z: PointMeasurement | None = None
                        ) -> Tensor | None:
        """Each sample's Poisson intensity at every point of the frame ``z`` (:meth:`intensity`).

            ``lambda_m = L_C / V + L_x sum_n e_n N(z_m; H x_n, R)``   ``(B, *S, M)``, float64,

        is kept beside MCMC chains so that a move of one slot (or of ``M`` slots) pays for that
        slot's ``M`` terms only (:meth:`log_likelihood_delta_cached`), not for the other
        targets' (DESIGN.md, "Every move pays for what it changes"). Float64 whatever the
        state's dtype: a move subtracts the old slot's terms from the sum, and a target's
        term is up to ``1e4`` times the clutter floor at its points. ``None`` without clutter
        (``L_C = 0``: an intensity can then be 0, whose log-ratio the cache cannot carry).

        Parameters
        ----------
        x : (B, *S, K, D); exists : (B, *S, K) bool, optional; z : the frame (required).
        """
        if z is None:
            raise ValueError("z is required: the point sensor's cache holds the intensity at the frame's points")
        if self.clutter_rate <= 0:
            return None
        return self.intensity(x, split_points(z)[0], exists)

    def log_likelihood_delta_cached(self, cache: Tensor, x: Tensor, x_n: Tensor, n: Tensor, z: PointMeasurement,
                                    exists: Tensor | None = None, exists_n: Tensor | None = None
                                    ) -> tuple[Tensor, None, Tensor]:
        """:meth:`log_likelihood_delta` from the samples' intensities (:meth:`amplitude_cache`).

        With ``lambda'_m = lambda_m - L_x sum_{moved j} (e_j N(z_m; H x_j, R) - e'_j N(z_m; H
        x'_j, R))``,

            ``delta = sum_m log(lambda'_m / lambda_m) - L_x sum_{moved j} (e'_j - e_j)``

        (paper 001's association-free likelihood, DESIGN.md): ``2 M_moved`` terms per point
        instead of ``K``. Equal to :meth:`log_likelihood_delta` to round-off (tested).

        Parameters
        ----------
        cache : (B, *S, M) float64, the intensities of ``x`` (kept current by
            :meth:`update_amplitude_cache`).
        x : (B, *S, K, D); x_n : (B, *S, D) the new state of slot ``n``, or (B, *S, V, D)
            those of ``V`` distinct slots; n : int64 broadcastable to (B, *S) (or (B, *S, V));
        z : the frame; exists : (B, *S, K) bool, optional; exists_n : (B, *S) (or (B, *S, V))
            bool, optional: the moved slots' new flags.

        Returns
        -------
        delta : (B, *S) in the dtype of ``x``; cells : ``None`` (the change covers every entry of
        the cache, in order: :meth:`update_amplitude_cache`); change : (B, *S, M) float64,
        ``lambda' - lambda``.
        """
        pts, mask = split_points(z)
        lead, m = tuple(x.shape[:-2]), pts.shape[1]
        if tuple(cache.shape) != lead + (m,):
            raise ValueError(f"cache has shape {tuple(cache.shape)}, expected {lead + (m,)}")
        many = x_n.dim() == x.dim()
        xn = x_n if many else x_n.unsqueeze(-2)  # (B, *S, V, D)
        slot = n.to(device=x.device, dtype=torch.int64)
        slot = (slot if many else slot.unsqueeze(-1)).expand(xn.shape[:-1])
        x_old = take_along(x, slot.unsqueeze(-1), -2)
        e_old = torch.ones_like(slot, dtype=torch.bool) if exists is None else take_along(exists, slot, -1)
        e_new = e_old if exists_n is None else (exists_n if many else exists_n.unsqueeze(-1)).expand(slot.shape)
        valid = torch.ones(pts.shape[:2], dtype=torch.bool, device=x.device) if mask is None else mask
        born = (e_new.to(x.dtype) - e_old.to(x.dtype)).sum(-1)
        if native.applies(x):  # the C loop: the moved slots' terms, a log where an intensity changes
            both, flags = torch.cat([x_old, xn], -2), torch.cat([e_old, e_new], -1)  # (B, *S, 2V, D), (B, *S, 2V)
            rows = (lead[0], math.prod(lead[1:]), flags.shape[-1])
            log_ratio, change = native.delta(self._native_positions(both[..., X], both[..., Y]).reshape(rows + (2,)),
                                             self._native_consts(flags, flags.shape, x.device).reshape(rows),
                                             self._native_points(pts), valid.to(torch.uint8),
                                             cache.reshape(rows[:2] + (m,)))
            return log_ratio.reshape(lead).to(x.dtype) - self.detection_rate * born, None, change.reshape(cache.shape)
        # (B, *S, 2V, M), an inactive slot's terms -inf
        terms = self.log_intensity_terms(torch.cat([x_old, xn], -2), pts, torch.cat([e_old, e_new], -1))
        valid = valid.reshape((valid.shape[0],) + (1,) * (len(lead) - 1) + (m,)).expand(lead + (m,))
        flat = (terms.reshape(-1, *terms.shape[-2:]), xn.shape[-2], cache.reshape(-1, m), valid.reshape(-1, m))
        log_ratio, change = _intensity_change(*flat) if runtime.generated_reductions() else \
            _intensity_change_eager(*flat, in_place=runtime.in_place(x))
        delta = log_ratio.reshape(lead).to(x.dtype) - self.detection_rate * born
        return delta, None, change.reshape(cache.shape)

    # -- the multitarget prior's hooks --------------------------------------------------
    #: weight of the uniform part of the data-driven density (:meth:`sample_from_data`)
    uniform_weight: float = 0.05

    def resolution_coords(self, x: Tensor) -> Tensor:
        """The whitened position ``L^-1 H x`` (one unit is one noise standard deviation):
        ``(*S, K, D) -> (*S, K, 2)``.
        """
        return _whiten(torch.stack([x[..., X], x[..., Y]], -1), self.W.to(x.dtype), self.diagonal)

    def place(self, x: Tensor, coords: Tensor) -> Tensor:
        """``x (*S, D)`` with its position set to ``coords (*S, 2)``, the velocity kept."""
        return torch.cat([coords[..., :1], x[..., 1:2], coords[..., 1:2], x[..., 3:]], -1)

    def sample_from_data(self, z: PointMeasurement, shape: tuple[int, ...], *, generator: torch.Generator,
                         dtype: torch.dtype = torch.float32, scored: Tensor | None = None, found: Any = None
                         ) -> tuple[Tensor, Tensor]:
        """Positions from ``g(pos | z) = p_u U(area) + (1 - p_u) (1/M) sum_m N(pos; z_m, R)``
        (:func:`log_near_points`; ``p_u`` = :attr:`uniform_weight`): a valid point drawn
        uniformly and a position scattered around it by the measurement noise, or a uniform
        position. With ``p_0`` uniform over the area, ``log_ratio = log p_0 - log g``.

        Parameters
        ----------
        z : ``PointFrame(z (B, M, 2), mask (B, M))``; shape : ``(B, *S)``.
        scored : (B, *S) bool, optional: the draws whose ``log_ratio`` a move can read
            (:class:`~torchmcmcpf.models.multitarget.RelocationNoise`); ``g`` (a sum over the
            ``M`` points) is evaluated there only and ``log_ratio`` is 0 elsewhere. The draws
            themselves do not depend on it.
        found : ignored: the points are the data, nothing to prepare
            (:meth:`~torchmcmcpf.models.base.SensorModel.frame_detections` is None).

        Returns
        -------
        coords : (B, *S, 2); log_ratio : (B, *S).
        """
        pts, mask = split_points(z)
        b, m = pts.shape[:2]
        if not shape or shape[0] != b:
            raise ValueError(f"shape {tuple(shape)} must start with the batch size of z, {b}")
        dev = pts.device
        p = math.prod(shape[1:])
        a = self.area.to(dtype)
        pos = a[:, 0] + (a[:, 1] - a[:, 0]) * torch.rand((b, p, 2), generator=generator, device=dev, dtype=dtype)
        u_pick = torch.rand((b, p, 2), generator=generator, device=dev, dtype=dtype)
        eps = torch.randn((b, p, 2), generator=generator, device=dev, dtype=dtype)
        if mask is None:
            mask = torch.ones((b, m), dtype=torch.bool, device=dev)
        if m > 0:
            idx = uniform_pick(mask, u_pick[..., 0])  # (B, P)
            centre = take_along(pts.to(dtype), idx.unsqueeze(-1), dim=1)
            L = torch.linalg.cholesky(self.R.to(torch.float64)).to(dtype)
            near = centre + _whiten(eps, L, self.diagonal)  # eps @ L^T
            use = (u_pick[..., 1] >= self.uniform_weight) & mask.any(-1, keepdim=True)
            pos = where(use.unsqueeze(-1), near, pos)
        a = self.area.to(dtype)
        inside = ((pos >= a[:, 0]) & (pos <= a[:, 1])).all(-1)
        if scored is None:
            log_q = log_near_points(pos, pts, mask, W=self.W, p_uniform=self.uniform_weight, area=self.area,
                                    diagonal=self.diagonal)
            log_ratio = where(inside, -math.log(self.volume) - log_q, -math.inf)  # p_0 = 0 off the area
        else:  # only the draws a move can read (eager: the noise is drawn outside compiled code)
            rows, cols = scored.reshape(b, p).nonzero(as_tuple=True)
            log_ratio = torch.zeros((b, p), dtype=dtype, device=dev)
            if rows.numel():
                log_q = log_near_points(pos[rows, cols].unsqueeze(1), pts[rows], mask[rows], W=self.W,
                                        p_uniform=self.uniform_weight, area=self.area,
                                        diagonal=self.diagonal).squeeze(1)
                log_ratio.index_put_((rows, cols), where(inside[rows, cols], -math.log(self.volume) - log_q,
                                                               -math.inf))
        return pos.reshape(tuple(shape) + (2,)), log_ratio.reshape(tuple(shape))

    # -- simulation ---------------------------------------------------------------------
    def simulate(
        self, x: Tensor, *, generator: torch.Generator, exists: Tensor | None = None
    ) -> PointFrame:
        """Draw one frame per run: ``Poisson(L_C)`` clutter points uniform on the area and
        ``Poisson(L_x)`` noisy positions of every live target, in random order.

        Parameters
        ----------
        x : (B, K, D) true states; exists : (B, K) bool, optional (all live).

        Returns
        -------
        PointFrame ``(z (B, M, 2), mask (B, M))`` with ``M`` the largest number of points
        over the runs; padded rows are zero and masked out.
        """
        b, k = x.shape[:2]
        dev, dt = x.device, x.dtype
        if exists is None:
            exists = torch.ones((b, k), dtype=torch.bool, device=dev)
        n_clutter = torch.poisson(torch.full((b,), self.clutter_rate, dtype=torch.float64, device=dev),
                                  generator=generator).long()
        rate = where(exists, self.detection_rate, 0.0).to(torch.float64)
        n_target = torch.poisson(rate, generator=generator).long()  # (B, K)
        c_max, t_max = int(n_clutter.max()), int(n_target.max()) if k else 0
        lo, hi = self.area[:, 0].to(dt), self.area[:, 1].to(dt)
        clutter = lo + (hi - lo) * torch.rand((b, c_max, 2), generator=generator, device=dev, dtype=dt)
        clutter_mask = torch.arange(c_max, device=dev) < n_clutter[:, None]
        noise = torch.randn((b, k, t_max, 2), generator=generator, device=dev, dtype=dt) \
            @ torch.linalg.cholesky(self.R.to(dt)).mT
        pos = torch.stack([x[..., X], x[..., Y]], -1)
        target = (pos.unsqueeze(-2) + noise).reshape(b, k * t_max, 2)
        target_mask = (torch.arange(t_max, device=dev) < n_target[..., None]).reshape(b, k * t_max)
        pts = torch.cat([clutter, target], 1)
        mask = torch.cat([clutter_mask, target_mask], 1)
        # valid points first, in a uniformly random order
        key = torch.rand(mask.shape, generator=generator, device=dev, dtype=torch.float64)
        order = torch.argsort(where(mask, key, key + 2.0), dim=-1)
        m = int(mask.sum(-1).max()) if b else 0
        order = order[:, :m]
        pts = take_along(pts, order.unsqueeze(-1), dim=1)
        mask = take_along(mask, order, dim=1)
        return PointFrame(where(mask.unsqueeze(-1), pts, torch.zeros_like(pts)), mask)

    # -- input checks -------------------------------------------------------------------
    def validate(self, z: PointMeasurement, batch_size: int | None = None, name: str = "z") -> PointMeasurement:
        """Check a frame: points ``(B, M, 2)`` finite (padding included), ``mask (B, M)``
        bool of the same ``B, M``. Returns ``z``.
        """
        if not torch.is_tensor(z) and not (isinstance(z, tuple) and len(z) == 2):
            raise ValueError(f"{name} must be a PointFrame (z, mask) or a tensor (B, M, 2), got "
                             f"{type(z).__name__}")
        pts, mask = split_points(z)
        check_shape(pts, name if mask is None else f"{name}.z", (None, None, 2))
        if batch_size is not None:
            check_batch(pts, f"{name}.z", batch_size)
        check_finite(pts, f"{name}.z")
        if mask is not None:
            check_tensor(mask, f"{name}.mask")
            check_shape(mask, f"{name}.mask", tuple(pts.shape[:2]))
            if mask.dtype != torch.bool:
                raise ValueError(f"{name}.mask has dtype {mask.dtype}, expected torch.bool")
        return z

    def extra_repr(self) -> str:
        """The constructor arguments, shown inside ``repr(module)``."""
        return (f"clutter_rate={self.clutter_rate}, detection_rate={self.detection_rate}, "
                f"volume={self.volume:g}")
