"""Point sensors with an unknown target-to-measurement association.

Maroulas and Stinis (2010, paper 003) sec. 2: every existing target yields exactly one
measurement, no clutter, no missed detection, but the order of the measurements says
nothing about which target produced which. Two measurement functions:

- :class:`AssociationPosition`: ``z_m = (x_k, y_k) + w_m``, ``w ~ N(0, diag(s_x^2, s_y^2))``
  (paper 003 eqs. 14, 16);
- :class:`AssociationBearingRange`: ``z_m = (atan2(y_k, x_k), hypot(x_k, y_k)) + w_m``,
  ``w ~ N(0, diag(s_theta^2, s_r^2))`` (eqs. 15, 17; the paper writes ``arctan(y/x)``, we
  use the four-quadrant ``atan2`` and wrap the bearing residual to ``(-pi, pi]``).

Likelihood (exact, beyond the paper): with ``L[k, m] = log g(z_m | x_k)`` for the n_a
existing slots and the n_v valid measurements (n_a <= n_v; a measurement left unassigned
contributes a constant), the association is uniform a priori, so

    log p(z | x) = logsumexp over injections pi of sum_k L[k, pi(k)] - log(n_v! / (n_v - n_a)!).

It is evaluated as a log-sum-exp over all P! permutations of a square ``(P, P)`` matrix,
``P = max(K, M) <= 6``, padded so that padding never changes the sum (see
:func:`padded_pair_log_likelihood`). Paper 003 instead searches for the best association
with a Metropolis walk over assignments ([15] of paper 003); :func:`metropolis_association`
is that search, batched over every particle of every run.

Measurements are ``(B, M, d)`` or a :class:`PointFrame` ``(z (B, M, d), mask (B, M))``.
"""

from __future__ import annotations

import itertools
import math

import torch

from ..._native.select import where
from ..._validation import (
    check_batch,
    check_finite,
    check_generator,
    check_positive,
    check_positive_int,
    check_shape,
)
from ...runtime import take_along
from ...typing import PointFrame, PointMeasurement, Tensor, X, Y, split_points
from ..base import SensorModel

__all__ = [
    "PointFrame",
    "shuffle",
    "AssociationSensor",
    "AssociationPosition",
    "AssociationBearingRange",
    "padded_pair_log_likelihood",
    "metropolis_association",
    "permutations",
    "MAX_EXACT_TARGETS",
]

#: largest P for which the exact sum over the P! permutations is evaluated (720 terms)
MAX_EXACT_TARGETS = 6

#: stand-in for -inf inside the Metropolis search, where ``inf - inf`` would give NaN
_IMPOSSIBLE = -1e30


_PERMS: dict[tuple[int, torch.device], Tensor] = {}


def permutations(p: int, device: torch.device | str | None = None) -> Tensor:
    """All ``p!`` permutations of ``range(p)`` as a ``(p!, p)`` int64 tensor (cached; made
    outside ``torch.inference_mode()`` even when first asked for there, so that a later
    call under autograd may index with it).
    """
    key = (p, torch.device(device or "cpu"))
    if key not in _PERMS:
        with torch.inference_mode(False):
            _PERMS[key] = torch.tensor(list(itertools.permutations(range(p))), dtype=torch.long,
                                       device=key[1]).reshape(-1, p)
    return _PERMS[key]


def padded_pair_log_likelihood(pair: Tensor, exists: Tensor | None, mask: Tensor | None
                               ) -> tuple[Tensor, Tensor]:
    """Pad the ``(K, M)`` pair log-likelihoods to a square ``(P, P)``, ``P = max(K, M)``.

    Entry ``[k, m]`` is ``L[k, m]`` for an existing slot and a valid measurement, ``-inf``
    for an existing slot and a padding row (impossible), and ``0`` for a missing (or
    padding) slot with any measurement: a valid measurement left to a missing slot is an
    unassigned measurement with a constant density. Each injection of existing slots into
    valid measurements is then counted ``(P - n_a)!`` times among the P! permutations.

    Parameters
    ----------
    pair : (B, *S, K, M) ``log g(z_m | x_k)``.
    exists : (B, *S, K) bool or None (all exist); mask : (B, M) bool or None (all valid).

    Returns
    -------
    square : (B, *S, P, P).
    log_count : (B, *S) ``log((P - n_a)! * n_v! / (n_v - n_a)!)``, to subtract from the
        log-sum-exp over permutations (``+inf`` where ``n_a > n_v``: impossible).
    """
    k, m = pair.shape[-2:]
    lead = pair.shape[:-2]
    p = max(k, m)
    dev = pair.device
    ex = torch.ones(lead + (k,), dtype=torch.bool, device=dev) if exists is None else exists
    mk = torch.ones(pair.shape[:1] + (m,), dtype=torch.bool, device=dev) if mask is None else mask
    ex = torch.cat([ex, ex.new_zeros(lead + (p - k,))], -1)  # (B, *S, P)
    mk = torch.cat([mk, mk.new_zeros(mk.shape[:1] + (p - m,))], -1)  # (B, P)
    mk = mk.reshape(mk.shape[:1] + (1,) * (len(lead) - 1) + (p,))  # (B, 1.., P)
    square = torch.nn.functional.pad(pair, (0, p - m, 0, p - k))
    both = ex.unsqueeze(-1) & mk.unsqueeze(-2)
    impossible = ex.unsqueeze(-1) & ~mk.unsqueeze(-2)
    square = where(both, square, torch.zeros_like(square))
    square = where(impossible, torch.full_like(square, -math.inf), square)
    n_a = ex.sum(-1).to(pair.dtype)
    n_v = mk.sum(-1).to(pair.dtype).expand_as(n_a)
    log_count = torch.lgamma(p - n_a + 1) + torch.lgamma(n_v + 1) - torch.lgamma((n_v - n_a).clamp(min=0) + 1)
    log_count = where(n_a > n_v, torch.full_like(log_count, math.inf), log_count)
    return square, log_count


def _score(square: Tensor, assignment: Tensor) -> Tensor:
    """``sum_k square[..., k, assignment[..., k]]``: (B, *S, P, P), (B, *S, P) -> (B, *S)."""
    return take_along(square, assignment.unsqueeze(-1), dim=-1).squeeze(-1).sum(-1)


def metropolis_association(
    square: Tensor,
    *,
    num_iters: int,
    generator: torch.Generator,
    init: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Metropolis walk over assignments, batched over every leading dim (paper 003 / [15]).

    State: a permutation ``a`` (slot k takes measurement ``a[k]``). Proposal: swap the
    measurements of two distinct slots drawn uniformly (symmetric); accept with
    probability ``min(1, exp(score(a') - score(a)))``, ``score(a) = sum_k square[k, a[k]]``.
    The chain targets the posterior of the association, ``softmax(score)`` over the P!
    permutations; paper 003 keeps the best one visited, returned as ``best``.

    Parameters
    ----------
    square : (*A, P, P) padded pair log-likelihoods (:func:`padded_pair_log_likelihood`).
    num_iters : proposals per chain, >= 1.
    generator : source of randomness.
    init : (*A, P) int64 starting permutation; default the identity.

    Returns
    -------
    best : (*A, P) int64, the highest-scoring assignment visited.
    last : (*A, P) int64, the chain's final state (a draw from the walk).
    best_score : (*A) its score (``-inf`` entries counted as -1e30).
    """
    check_positive_int(num_iters, "num_iters")
    check_generator(generator)
    p = square.shape[-1]
    lead = square.shape[:-2]
    s = torch.clamp(square, min=_IMPOSSIBLE)
    a = (torch.arange(p, device=square.device).expand(lead + (p,)).clone() if init is None else init.clone())
    score = _score(s, a)
    best, best_score = a.clone(), score.clone()
    if p < 2:
        return best, a, best_score
    for _ in range(num_iters):
        i = torch.randint(p, lead + (1,), generator=generator, device=square.device)
        j = (i + torch.randint(1, p, lead + (1,), generator=generator, device=square.device)) % p
        log_u = torch.log(torch.rand(lead, generator=generator, device=square.device, dtype=square.dtype))
        ai, aj = a.gather(-1, i), a.gather(-1, j)
        row_i = s.gather(-2, i.unsqueeze(-1).expand(lead + (1, p))).squeeze(-2)  # (*A, P)
        row_j = s.gather(-2, j.unsqueeze(-1).expand(lead + (1, p))).squeeze(-2)
        delta = (row_i.gather(-1, aj) + row_j.gather(-1, ai) - row_i.gather(-1, ai) - row_j.gather(-1, aj)).squeeze(-1)
        accept = log_u < delta
        swapped = a.scatter(-1, i, aj).scatter(-1, j, ai)
        a = where(accept.unsqueeze(-1), swapped, a)
        score = where(accept, score + delta, score)
        better = score > best_score
        best = where(better.unsqueeze(-1), a, best)
        best_score = where(better, score, best_score)
    return best, a, best_score


def shuffle(z: Tensor, exists: Tensor, *, generator: torch.Generator) -> PointFrame:
    """Forget the association: ``z (B, K, d)`` in slot order -> ``PointFrame`` with the
    measurements of existing slots first, in a uniformly random order per run, and the
    other rows zeroed and masked out. ``exists`` is ``(B, K)`` bool.
    """
    key = torch.rand(exists.shape, generator=generator, device=z.device, dtype=torch.float64)
    order = torch.argsort(where(exists, key, key + 2.0), dim=-1)
    zs = take_along(z, order.unsqueeze(-1), dim=-2)
    mask = take_along(exists, order, dim=-1)
    return PointFrame(where(mask.unsqueeze(-1), zs, torch.zeros_like(zs)), mask)


class AssociationSensor(SensorModel[PointMeasurement]):
    """Base of the point sensors with unknown association (see the module docstring).

    Subclasses define :meth:`measure` (the noiseless measurement of each slot), the noise
    standard deviations ``noise_std (d,)`` and :meth:`to_position` (measurement -> xy).

    Example
    -------
    Position in kilometres, with 10 m noise:

    >>> import torch
    >>> from torchmcmcpf.models.sensors.association import AssociationSensor
    >>> class Kilometres(AssociationSensor):
    ...     def __init__(self):
    ...         super().__init__(torch.tensor([0.01, 0.01]), dim=4)
    ...     def measure(self, x):
    ...         return x[..., [0, 2]] / 1000.0
    ...     def to_position(self, z):
    ...         return z * 1000.0
    >>> sensor = Kilometres()
    >>> truth = torch.tensor([[[1000.0, 0.0, 2000.0, 0.0]]])  # (B, K, D)
    >>> sensor.measure(truth)
    tensor([[[1., 2.]]])
    >>> sensor.log_likelihood(torch.zeros(1, 50, 1, 4), sensor.measure(truth)).shape   # (B, N)
    torch.Size([1, 50])
    """

    noise_std: Tensor  #: (d,) buffer, the noise standard deviation of each measurement component

    def __init__(self, noise_std: Tensor, dim: int):
        super().__init__()
        if dim < 4:
            raise ValueError(f"dim must be >= 4 for the [x, vx, y, vy] layout, got {dim}")
        self.register_buffer("noise_std", torch.as_tensor(noise_std, dtype=torch.get_default_dtype()))
        self.meas_dim = int(self.noise_std.shape[0])
        self.state_dim = dim
        self.frame_shape = (None, self.meas_dim)
        self._log_norm = float(-0.5 * self.meas_dim * math.log(2 * math.pi) - torch.log(self.noise_std).sum())

    # -- measurement function (subclasses) ----------------------------------------------
    def measure(self, x: Tensor) -> Tensor:
        """Noiseless measurement ``h(x)``: ``(*S, K, D) -> (*S, K, d)``."""
        raise NotImplementedError

    def residual(self, z: Tensor, h: Tensor) -> Tensor:
        """``z - h`` (angles wrapped by subclasses), broadcasting."""
        return z - h

    def to_position(self, z: Tensor) -> Tensor:
        """Measurement to an xy position: ``(..., d) -> (..., 2)``."""
        raise NotImplementedError

    def resolution_coords(self, x: Tensor) -> Tensor:
        """The noiseless measurement over its noise standard deviations: ``(*S, K, D) ->
        (*S, K, d)``.
        """
        return self.measure(x) / self.noise_std.to(x.dtype)

    # -- likelihoods ---------------------------------------------------------------------
    def pair_log_likelihood(self, x: Tensor, z: Tensor) -> Tensor:
        """``L[k, m] = log g(z_m | x_k)`` with all constants.

        Parameters
        ----------
        x : (B, *S, K, D); z : (B, M, d).

        Returns
        -------
        (B, *S, K, M). Differentiable in ``x``.
        """
        h = self.measure(x).unsqueeze(-2)  # (B, *S, K, 1, d)
        zb = z.reshape(z.shape[:1] + (1,) * (x.dim() - 2) + z.shape[1:])  # (B, 1.., 1, M, d)
        white = self.residual(zb, h) / self.noise_std.to(x.dtype)
        return self._log_norm - 0.5 * white.square().sum(-1)

    def log_likelihood(self, x: Tensor, z: PointMeasurement, exists: Tensor | None = None) -> Tensor:
        """Exact ``log p(z | x)``: the average over all associations (module docstring).

        Parameters
        ----------
        x : (B, *S, K, D); z : (B, M, d) or ``PointFrame(z, mask)``;
        exists : (B, *S, K) bool, optional.

        Returns
        -------
        (B, *S); ``-inf`` where more slots exist than there are measurements.
        """
        zz, mask = split_points(z)
        square, log_count = padded_pair_log_likelihood(self.pair_log_likelihood(x, zz), exists, mask)
        p = square.shape[-1]
        if p > MAX_EXACT_TARGETS:
            raise ValueError(
                f"exact association needs max(K, M) <= {MAX_EXACT_TARGETS}, got K={x.shape[-2]}, "
                f"M={zz.shape[-2]}; use metropolis_association"
            )
        perms = permutations(p, x.device)  # (P!, P)
        rows = torch.arange(p, device=x.device)
        per_perm = square[..., rows, perms].sum(-1)  # (B, *S, P!)
        return torch.logsumexp(per_perm, -1) - log_count

    def assigned_log_likelihood(self, x: Tensor, z: PointMeasurement, assignment: Tensor,
                                exists: Tensor | None = None) -> Tensor:
        """Per-slot ``log g(z_{a[k]} | x_k)`` for a given association (paper 003 eq. 9).

        Parameters
        ----------
        x : (B, *S, K, D); z : (B, M, d) or ``PointFrame``;
        assignment : (B, *S, P) int64 from :func:`metropolis_association`, ``P = max(K, M)``;
        exists : (B, *S, K) bool, optional.

        Returns
        -------
        (B, *S, K); 0 for a missing slot, ``-inf`` for an existing slot assigned padding.
        """
        zz, mask = split_points(z)
        square, _ = padded_pair_log_likelihood(self.pair_log_likelihood(x, zz), exists, mask)
        k = x.shape[-2]
        return take_along(square[..., :k, :], assignment[..., :k].unsqueeze(-1), dim=-1).squeeze(-1)

    # -- simulation and checks -----------------------------------------------------------
    def simulate(self, x: Tensor, *, generator: torch.Generator, exists: Tensor | None = None
                 ) -> PointFrame:
        """Measure every existing slot, then shuffle the measurements of each run.

        Parameters
        ----------
        x : (B, K, D); exists : (B, K) bool, optional.

        Returns
        -------
        ``PointFrame(z (B, K, d), mask (B, K))``: the valid rows first, in random order.
        """
        check_generator(generator)
        ex = torch.ones(x.shape[:-1], dtype=torch.bool, device=x.device) if exists is None else exists
        return shuffle(self.measure_noisy(x, generator=generator), ex, generator=generator)

    def measure_noisy(self, x: Tensor, *, generator: torch.Generator) -> Tensor:
        """``h(x) + w`` per slot, in slot order: ``(B, K, D) -> (B, K, d)``."""
        noise = torch.randn(x.shape[:-1] + (self.meas_dim,), generator=generator, device=x.device, dtype=x.dtype)
        return self.measure(x) + noise * self.noise_std.to(x.dtype)

    def validate(self, z: PointMeasurement, batch_size: int | None = None, name: str = "z") -> PointMeasurement:
        """Check a frame: points ``(B, M, d)`` finite (padding included), ``mask (B, M)`` bool
        if given, and ``B == batch_size`` if given. Returns ``z``.
        """
        zz, mask = split_points(z)
        check_shape(zz, name, (None, None, self.meas_dim))
        if batch_size is not None:
            check_batch(zz, name, batch_size)
        check_finite(zz, name)
        if mask is not None:
            check_shape(mask, f"{name}.mask", tuple(zz.shape[:2]))
            if mask.dtype != torch.bool:
                raise ValueError(f"{name}.mask has dtype {mask.dtype}, expected torch.bool")
        return z


class AssociationPosition(AssociationSensor):
    """Linear position measurement, unknown association (paper 003 eqs. 14, 16).

    Parameters
    ----------
    noise_std : float or (2,) ``(s_obs_x, s_obs_y)``; the paper uses 1.
    dim : per-target state size D (layout ``[x, vx, y, vy, ...]``).

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.models.sensors.association import AssociationPosition
    >>> sensor = AssociationPosition(noise_std=1.0)
    >>> truth = torch.tensor([[[0.0, 0.0, 0.0, 0.0], [10.0, 0.0, 0.0, 0.0]]])   # (B, K, D)
    >>> frame = sensor.simulate(truth, generator=torch.Generator().manual_seed(0))
    >>> frame.z.shape, frame.mask.tolist()               # a PointFrame, order shuffled
    (torch.Size([1, 2, 2]), [[True, True]])
    >>> z = torch.tensor([[[0.0, 0.0], [10.0, 0.0]]])
    >>> x = truth.unsqueeze(1)                            # (B, N, K, D) with N = 1
    >>> torch.equal(sensor.log_likelihood(x, z), sensor.log_likelihood(x, z.flip(1)))  # order says nothing
    True
    """

    def __init__(self, noise_std: float | Tensor = 1.0, dim: int = 4):
        std = torch.as_tensor(noise_std, dtype=torch.get_default_dtype()).expand(2).clone()
        for i, s in enumerate(std.tolist()):
            check_positive(s, f"noise_std[{i}]")
        super().__init__(std, dim)

    def measure(self, x: Tensor) -> Tensor:
        """Eq. 14 without noise: the position ``(x, y)``, ``(*S, K, D) -> (*S, K, 2)``."""
        return torch.stack([x[..., X], x[..., Y]], -1)

    def to_position(self, z: Tensor) -> Tensor:
        """The measurement is the position: identity, ``(..., 2) -> (..., 2)``."""
        return z


class AssociationBearingRange(AssociationSensor):
    """Bearing and range from the origin, unknown association (paper 003 eqs. 15, 17).

    Parameters
    ----------
    bearing_std : s_theta [rad]; the paper uses 1e-2.
    range_std : s_r [m]; the paper uses 1.
    dim : per-target state size D.

    Example
    -------
    >>> import math
    >>> import torch
    >>> from torchmcmcpf.models.sensors.association import AssociationBearingRange
    >>> sensor = AssociationBearingRange(bearing_std=1e-2, range_std=1.0)
    >>> sensor.measure(torch.tensor([[0.0, 0.0, 5.0, 0.0]]))    # (K, D) -> (K, 2): due north, 5 m
    tensor([[1.5708, 5.0000]])
    >>> sensor.to_position(torch.tensor([[math.pi / 2, 5.0]])).round(decimals=4).abs()
    tensor([[0., 5.]])
    >>> sensor.residual(torch.tensor([[3.1, 5.0]]), torch.tensor([[-3.1, 5.0]]))  # bearing wrapped
    tensor([[-0.0832,  0.0000]])
    """

    def __init__(self, bearing_std: float = 1e-2, range_std: float = 1.0, dim: int = 4):
        check_positive(bearing_std, "bearing_std")
        check_positive(range_std, "range_std")
        super().__init__(torch.tensor([bearing_std, range_std]), dim)

    def measure(self, x: Tensor) -> Tensor:
        """Eq. 15 without noise: ``[atan2(y, x), hypot(x, y)]``, ``(*S, K, D) -> (*S, K, 2)``."""
        return torch.stack([torch.atan2(x[..., Y], x[..., X]), torch.hypot(x[..., X], x[..., Y])], -1)

    def residual(self, z: Tensor, h: Tensor) -> Tensor:
        """``z - h`` with the bearing difference wrapped to ``[-pi, pi]`` (broadcasting; the
        wrap is constant in ``h``, so the gradient is that of ``z - h``).
        """
        d = z - h
        two_pi = 2 * math.pi
        wrap = torch.zeros_like(d)
        wrap[..., 0] = two_pi * torch.round(d[..., 0].detach() / two_pi)
        return d - wrap

    def to_position(self, z: Tensor) -> Tensor:
        """``(bearing, range) -> (r cos b, r sin b)``: ``(..., 2) -> (..., 2)``."""
        return torch.stack([z[..., 1] * torch.cos(z[..., 0]), z[..., 1] * torch.sin(z[..., 0])], -1)
