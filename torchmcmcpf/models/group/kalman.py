"""Pairwise Kalman marginalisation of the velocities and leaders (paper 004 eqs. 42-58): one
Kalman filter per particle, conditioned on its positions.

Paper 004's model as a whole, its state layouts and notation: the docstring of :mod:`torchmcmcpf.models.group`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch

from ..._validation import check_positive_int
from ...typing import Tensor
from .existence import GroupExistence
from .motion import LOG_2PI, AffineTransition, _masked_cholesky

__all__ = ["KalmanStats", "GroupPrediction", "pairwise_kalman_init", "pairwise_kalman_predict",
           "pairwise_kalman_update", "pairwise_kalman_sample"]


class KalmanStats(NamedTuple):
    """``p(w_{t-1} | x_{p,0:t-1}, ...) = N(mean, cov)`` per axis, ``w = [velocities (K),
    leader positions (K), leader velocities (K)]``.

    Attributes
    ----------
    mean : (*S, 2, 3K) one row per axis.
    cov : (*S, 3K, 3K) shared by both axes.

    Example
    -------
    >>> from torchmcmcpf.models.group import GroupExistence, pairwise_kalman_init
    >>> existence = GroupExistence(0.2, 0.05, ((0.0, 1000.0), (0.0, 1000.0)))
    >>> stats = pairwise_kalman_init((5,), 2, existence=existence)   # 5 samples, K = 2: all inactive
    >>> stats.mean.shape, stats.cov.shape                   # w = [velocities, leader pos, leader vel]
    (torch.Size([5, 2, 6]), torch.Size([5, 6, 6]))
    >>> float(stats.cov.abs().max())                        # nothing uncertain yet
    0.0
    """

    mean: Tensor
    cov: Tensor


class GroupPrediction(NamedTuple):
    """Joint Gaussian of ``(x_{p,t}, w_t)`` given the past positions (eqs. 47, 51-52).

    Attributes
    ----------
    mean : (*S, 2, 4K) per axis ``[positions, w]``, without the independent newborns'
        positions' contribution to the new leaders.
    cov : (*S, 4K, 4K).
    transition : the AffineTransition it came from (``observed``, ``free_birth``,
        ``born_gain``).

    Example
    -------
    One step of the pairwise Kalman filter (eqs. 47-58):

    >>> import torch
    >>> from torchmcmcpf.models.group import GroupExistence, VirtualLeaderMotion
    >>> motion = VirtualLeaderMotion(alpha=0.0006, beta=0.05, gamma1=0.001, gamma2=0.001, sigma_x=0.2,
    ...                              sigma_g=0.5, dt=5.0)          # paper 004 Table 1
    >>> existence = GroupExistence(0.2, 0.05, ((0.0, 1000.0), (0.0, 1000.0)))
    >>> x = torch.tensor([[[100.0, 1.0, 100.0, 0.0], [120.0, 1.0, 100.0, 0.0]]], dtype=torch.float64)
    >>> v = torch.tensor([[[110.0, 1.0, 100.0, 0.0], [0.0, 0.0, 0.0, 0.0]]], dtype=torch.float64)
    >>> labels, alive = torch.tensor([[0, 0]]), torch.tensor([[True, True]])   # (S, K): one group of two
    >>> from torchmcmcpf.models.group import pairwise_kalman_init, pairwise_kalman_predict, pairwise_kalman_update
    >>> tr = motion.transition(x[..., 0::2], labels, labels, alive, alive, existence=existence)
    >>> pred = pairwise_kalman_predict(pairwise_kalman_init((1,), 2, existence=existence), x[..., 0::2], tr)
    >>> pred.position_mean.shape, pred.position_cov.shape   # (S, K, 2), (S, K, K) per axis
    (torch.Size([1, 2, 2]), torch.Size([1, 2, 2]))
    >>> log_pred, stats = pairwise_kalman_update(pred, x[..., 0::2])   # condition on positions at t
    >>> log_pred.shape, stats.mean.shape
    (torch.Size([1]), torch.Size([1, 2, 6]))
    """

    mean: Tensor
    cov: Tensor
    transition: AffineTransition

    @property
    def position_mean(self) -> Tensor:
        """(*S, K, 2) predictive mean of the positions (``x~_t`` of eq. 51 on ``Upsilon~``)."""
        k = self.mean.shape[-1] // 4
        return self.mean[..., :k].transpose(-1, -2)

    @property
    def position_cov(self) -> Tensor:
        """(*S, K, K) predictive covariance of the positions, per axis (``L_t`` of eq. 52)."""
        k = self.mean.shape[-1] // 4
        return self.cov[..., :k, :k]


def pairwise_kalman_init(batch_shape: Sequence[int], num_slots: int, *, existence: GroupExistence,
                         dtype: torch.dtype = torch.float64,
                         device: torch.device | str | None = None) -> KalmanStats:
    """Statistics of an all-inactive configuration: velocities at ``x_death``'s, leaders at
    ``v_death``, zero covariance: ``-> mean (*batch, 2, 3K), cov (*batch, 3K, 3K)``.
    """
    k = check_positive_int(num_slots, "num_slots")
    xd, vd = existence.x_death.to(dtype=dtype, device=device), existence.v_death.to(dtype=dtype, device=device)
    row = torch.stack([torch.cat([xd[1 + a].expand(k), vd[a].expand(k), vd[1 + a].expand(k)])
                       for a in (0, 2)])  # (2, 3K)
    mean = row.expand(tuple(batch_shape) + (2, 3 * k)).clone()
    return KalmanStats(mean, torch.zeros(tuple(batch_shape) + (3 * k, 3 * k), dtype=dtype, device=device))


def pairwise_kalman_predict(stats: KalmanStats, pos_prev: Tensor, tr: AffineTransition) -> GroupPrediction:
    """Predict ``(x_{p,t}, w_t)`` jointly from ``N(w_{t-1}; mean, cov)`` and the known
    ``x_{p,t-1}`` through ``s_t = Psi s_{t-1} + r + b`` (eq. 47):
    ``mean = Psi [x_{p,t-1}; w_mean] + r``, ``cov = Psi_{.w} cov Psi_{.w}^T + Q``. Its
    position block is ``(x~_t, L_t)`` of eqs. 51-52.

    Parameters
    ----------
    stats : KalmanStats at ``t - 1``; pos_prev : (*S, K, 2);
    tr : :meth:`VirtualLeaderMotion.transition` (built with ``pos_born=None``).

    Returns
    -------
    GroupPrediction.
    """
    k = pos_prev.shape[-2]
    s_prev = torch.cat([pos_prev.transpose(-1, -2), stats.mean], -1)  # (*S, 2, 4K)
    mean = s_prev @ tr.Psi.transpose(-1, -2) + tr.r
    Pw = tr.Psi[..., :, k:]  # (*S, 4K, 3K)
    cov = Pw @ stats.cov @ Pw.transpose(-1, -2) + tr.Q  # symmetric up to rounding; the update re-symmetrises
    return GroupPrediction(mean, cov, tr)


def pairwise_kalman_update(pred: GroupPrediction, pos: Tensor) -> tuple[Tensor, KalmanStats]:
    """Condition the prediction on the positions ``x_{p,t}`` (eqs. 53-58).

    ``log N(x_{p,t}; x~_t, L_t)`` over the observed positions (survivors and group births,
    eq. 58; both axes), and ``w_t | x_{p,0:t}`` by Gaussian conditioning,
    ``mean_w + S_wp S_pp^{-1} (x_p - x~)``, ``S_ww - S_wp S_pp^{-1} S_pw``: this is the
    pairwise Kalman filter of eqs. 51-57 written as predict-then-condition (eqs. 54-57
    compose the conditioning of ``w_{t-1}`` on ``x_{p,t}`` with the step to ``w_t``). The
    independent newborns' positions enter the new leaders' means through ``born_gain``;
    their ``p_0`` density is not included (:meth:`GroupExistence.log_p0_position`).

    Parameters
    ----------
    pred : GroupPrediction; pos : (*S, K, 2) positions at ``t`` (dead slots ignored).

    Returns
    -------
    log_pred : (*S,) ``log p(x_{p,t,Upsilon~} | x_{p,0:t-1}, e_{0:t}, g_{0:t})``.
    stats : KalmanStats at ``t``.
    """
    tr = pred.transition
    k = pos.shape[-2]
    obs = tr.observed.to(pos.dtype)  # (*S, K)
    posT = pos.transpose(-1, -2)  # (*S, 2, K)
    mean = pred.mean + (tr.born_gain @ (posT * tr.free_birth.to(pos.dtype).unsqueeze(-2)).transpose(-1, -2)
                        ).transpose(-1, -2)
    innov = (posT - mean[..., :k]) * obs.unsqueeze(-2)  # (*S, 2, K)
    S = pred.cov[..., :k, :k] * obs.unsqueeze(-1) * obs.unsqueeze(-2) + torch.diag_embed(1.0 - obs)
    L = torch.linalg.cholesky(S)
    y = torch.linalg.solve_triangular(L, innov.transpose(-1, -2), upper=False)  # (*S, K, 2)
    logdet = 2 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
    log_pred = -0.5 * y.square().sum((-1, -2)) - logdet - obs.sum(-1) * LOG_2PI
    Swp = pred.cov[..., k:, :k] * obs.unsqueeze(-2)  # (*S, 3K, K)
    G = torch.linalg.solve_triangular(L, Swp.transpose(-1, -2), upper=False)  # L^{-1} S_pw (*S, K, 3K)
    w_mean = mean[..., k:] + y.transpose(-1, -2) @ G  # (*S, 2, 3K)
    w_cov = pred.cov[..., k:, k:] - G.transpose(-1, -2) @ G
    return log_pred, KalmanStats(w_mean, 0.5 * (w_cov + w_cov.transpose(-1, -2)))


def pairwise_kalman_sample(pred: GroupPrediction, *, generator: torch.Generator | None = None,
                           eps: Tensor | None = None) -> Tensor:
    """Draw the observed positions from their predictive ``N(x~_t, L_t)`` (eq. 58, the
    position part of the proposal of eq. 63); the other slots are returned as zeros (fill
    them with ``p_0`` / ``q_0`` births and ``x_death``).

    Parameters
    ----------
    pred : GroupPrediction.
    generator : source of the standard normals; or pass them as
    eps : (*S, K, 2) pre-drawn standard normals (compiled kernels, DESIGN.md).

    Returns
    -------
    (*S, K, 2).
    """
    obs = pred.transition.observed
    k = obs.shape[-1]
    mean = pred.mean[..., :k].transpose(-1, -2)  # (*S, K, 2)
    if eps is None:
        if generator is None:
            raise ValueError("pairwise_kalman_sample needs a generator or eps")
        eps = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
    L = _masked_cholesky(pred.cov[..., :k, :k], obs)
    return (mean + L @ eps) * obs.to(mean.dtype).unsqueeze(-1)
