"""The exchange / mutation kernel of the IP-MCMC-PF (Bocquel et al. 2012, paper 000, Alg. 2,
eq. 12), with and without births and deaths; see :mod:`torchmcmcpf.filters.ipmcmc` for the
target it leaves invariant. Pure and branch-free: the noise is pre-drawn
(:func:`draw_exchange_noise`), so one iteration compiles with ``fullgraph=True``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath, BirthNoise, TargetDynamics
from ..resampling import cdf, inverse_cdf
from ..typing import Measurement, Tensor
from .mh import mh_accept, mh_select

__all__ = ["ExchangeNoise", "draw_exchange_noise", "exchange_iteration"]


class ExchangeNoise(NamedTuple):
    """Pre-drawn randomness of ``L`` exchange iterations (leading dim ``L``).

    Attributes
    ----------
    source : (L, B, C) int64, index of the previous particle each proposal starts from.
    slot : (L, B, C) int64, the target slot ``j`` each chain updates.
    eps : (L, B, C, noise_dim), standard normal process noise of the proposal.
    u : (L, B, C), uniforms of the accept/reject test.
    birth : :class:`~torchmcmcpf.kernels.moves.BirthNoise` with leading ``(L, B, C)``, the
        existence part of the proposals (only with an existence model).
    """

    source: Tensor
    slot: Tensor
    eps: Tensor
    u: Tensor
    birth: BirthNoise | None = None


def draw_exchange_noise(
    log_w: Tensor, num_iterations: int, num_chains: int, num_targets: int, noise_dim: int,
    *, generator: torch.Generator, dtype: torch.dtype, existence: BirthDeath | None = None,
    z: Measurement | None = None,
) -> ExchangeNoise:
    """Draw the randomness of ``L = num_iterations`` exchange iterations in four calls
    (and, with ``existence``, the birth noise: births near the points of the frame ``z``
    when ``existence`` draws them so).

    ``source`` indices are categorical draws from the previous weights ``log_w (B, N)`` by
    inversion of uniforms (float64 CDF + ``searchsorted``, no ``torch.multinomial``).
    """
    b, n = log_w.shape
    shape = (num_iterations, b, num_chains)
    dev = log_w.device
    u_src = torch.rand((b, num_iterations * num_chains), generator=generator, device=dev, dtype=torch.float64)
    source = inverse_cdf(cdf(log_w), u_src)
    source = source.reshape(b, num_iterations, num_chains).permute(1, 0, 2)
    slot = torch.randint(num_targets, shape, generator=generator, device=dev)
    eps = torch.randn(shape + (noise_dim,), generator=generator, device=dev, dtype=dtype)
    u = torch.rand(shape, generator=generator, device=dev, dtype=dtype)
    if existence is None:
        return ExchangeNoise(source, slot, eps, u)
    template = torch.empty((b, num_iterations, num_chains, existence.dim), device=dev, dtype=dtype)
    birth = BirthNoise.draw(template, existence, z, generator=generator)  # leading (B, L, C)
    birth = BirthNoise(birth.u.transpose(0, 1), birth.x.transpose(0, 1), birth.log_ratio.transpose(0, 1))
    return ExchangeNoise(source, slot, eps, u, birth)


def exchange_iteration(
    chain: tuple, x_prev: Tensor, exists_prev: Tensor | None, z: Measurement,
    source: Tensor, slot: Tensor, eps: Tensor, u: Tensor, birth: BirthNoise | None = None,
    cache: Tensor | None = None,
    *, motion: MotionModel, sensor: SensorModel, existence: BirthDeath | None = None,
) -> tuple[tuple, Tensor, tuple[Tensor, Tensor] | None]:
    """One exchange/mutation MH iteration of every chain (paper 000 Alg. 2, eq. 12), with or
    without births and deaths (one code path: the slot is propagated by
    :class:`~torchmcmcpf.models.existence.TargetDynamics`).

    Chain ``c`` of run ``b`` replaces slot ``j = slot[b, c]`` by slot ``j`` of previous
    particle ``source[b, c]`` propagated (motion; with ``existence`` the existence chain, a
    birth or ``x_death``) and accepts with ``log u < log p(z | y') - log p(z | y)`` (plus
    ``log r'_j - log r_j`` for births from ``q_0``, see :mod:`torchmcmcpf.filters.ipmcmc`).
    Exact MH for the factorised-prior posterior. Pure and branch-free (``torch.compile``
    friendly). The proposal is scored by the declared hook
    :meth:`SensorModel.log_likelihood_slot`: a sensor that overrides ``log_likelihood_delta``
    (e.g. :class:`~torchmcmcpf.models.sensors.grid.SeparableGridSensor`) gives the ratio from
    the cells near the old and new position of the slot only, carried as ``log_lik + delta``;
    any other sensor scores the whole proposal with ``log_likelihood``. With ``cache`` (the
    chains' :meth:`SensorModel.amplitude_cache`) the ratio is
    :meth:`SensorModel.log_likelihood_delta_cached` instead (the boxes' amplitudes read, not
    summed from the neighbours' spreads), and the cache's change is returned for the caller
    to apply to the accepted chains (:meth:`SensorModel.update_amplitude_cache`, eager and in
    place: the kernel stays pure).

    Parameters
    ----------
    chain : ``(y (B, C, K, D), log_lik (B, C), exists, log_birth)`` with
        ``log_lik = log p(z | y, exists)``; ``exists (B, C, K)`` bool and ``log_birth (B, C, K)`` (the cached
        ``log r_j``) with ``existence``, else ``None``.
    x_prev : (B, N, K, D), exists_prev : (B, N, K) or None: the previous particles.
    z : the frame; source, slot : (B, C) int64; eps : (B, C, noise_dim) standard normals;
    u : (B, C) uniforms; birth : :class:`BirthNoise` with leading ``(B, C)`` (with existence).
    cache : (B, C, G), optional: the amplitudes of the chains ``y`` (see above).
    motion, sensor, existence : the models.

    Returns
    -------
    chain : the new chain tuple; accepted : (B, C) bool; update : ``(cells, change)`` of
    :meth:`SensorModel.log_likelihood_delta_cached` with ``cache``, else ``None``.
    """
    y, log_lik, exists, log_birth = chain
    b, n, k, d = x_prev.shape
    at = source * k + slot  # (B, C)
    parent = torch.take_along_dim(x_prev.reshape(b, n * k, d), at.unsqueeze(-1), dim=1)  # (B, C, D)
    parent_e = None if exists_prev is None else torch.take_along_dim(exists_prev.reshape(b, n * k), at, dim=1)
    one = None if birth is None else BirthNoise(birth.u.unsqueeze(-1), birth.x.unsqueeze(-2),
                                                birth.log_ratio.unsqueeze(-1))
    moved, e_new, lb_new = TargetDynamics(motion, existence).propagate(
        parent.unsqueeze(-2), None if parent_e is None else parent_e.unsqueeze(-1), eps.unsqueeze(-2), one)
    here = torch.arange(k, device=y.device) == slot.unsqueeze(-1)  # (B, C, K)
    proposal = torch.where(here.unsqueeze(-1), moved, y)
    exists_n = None if e_new is None else e_new.squeeze(-1)
    update = None
    if cache is None:
        log_lik_prop = sensor.log_likelihood_slot(y, moved.squeeze(-2), slot, z, log_lik, exists=exists,
                                                  exists_n=exists_n)
    else:
        delta, cells, change = sensor.log_likelihood_delta_cached(cache, y, moved.squeeze(-2), slot, z,
                                                                   exists=exists, exists_n=exists_n)
        log_lik_prop, update = log_lik + delta, (cells, change)
    log_alpha = log_lik_prop - log_lik
    new: tuple[Tensor, Tensor, Tensor | None, Tensor | None]
    if existence is None:
        new = (proposal, log_lik_prop, None, None)
    else:
        if e_new is None or exists is None or log_birth is None:
            raise ValueError("with an existence model the chains need exists and log_birth (got None)")
        new = (proposal, log_lik_prop, torch.where(here, e_new, exists), torch.where(here, lb_new, log_birth))
        log_alpha = log_alpha + (lb_new.squeeze(-1) - torch.where(here, log_birth, 0.0).sum(-1))
    accepted = mh_accept(log_alpha, u)
    return mh_select(accepted, new, chain), accepted, update
