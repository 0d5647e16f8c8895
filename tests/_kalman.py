"""Exact linear-Gaussian references for the statistical tests.

``kalman_filter``: the Kalman filter, batched over runs (and target slots, which are
independent in the tests' models). ``mixture_posterior``: the exact posterior of
``x_k`` (and of its ancestor) under a finite previous particle cloud and a linear-Gaussian
likelihood, the target of every MCMC move (paper 002 eq. 11).
"""

from __future__ import annotations

from typing import NamedTuple

import torch


def kalman_filter(F, Q, H, R, m0, P0, zs):
    """Kalman filter: predict with ``(F, Q)``, then update with each ``z_t``.

    The first measurement follows one prediction from ``(m0, P0)``, as in
    ``Filter.forward`` (particles at time 0, then propagate-and-weight for each frame).

    Parameters
    ----------
    F, Q : (D, D) transition and process noise; H : (d, D), R : (d, d) observation.
    m0 : (*B, D) initial means; P0 : (D, D) or (*B, D, D) initial covariances.
    zs : (T, *B, d) measurements.

    Returns
    -------
    means : (T, *B, D); covs : (T, *B, D, D), the filtering moments after each update.
    """
    m, P = m0, P0.expand(m0.shape + m0.shape[-1:])
    means, covs = [], []
    eye = torch.eye(F.shape[0], dtype=m0.dtype)
    for z in zs:
        m = m @ F.mT
        P = F @ P @ F.mT + Q
        S = H @ P @ H.mT + R
        G = torch.linalg.solve(S, H @ P).mT  # Kalman gain P H' S^-1, S symmetric
        m = m + ((z - m @ H.mT).unsqueeze(-2) @ G.mT).squeeze(-2)
        IKH = eye - G @ H
        P = IKH @ P @ IKH.mT + G @ R @ G.mT  # Joseph form
        means.append(m)
        covs.append(P)
    return torch.stack(means), torch.stack(covs)


class MixturePosterior(NamedTuple):
    """Exact moments of ``pi(x, a)`` (see :func:`mixture_posterior`); ``J = K * D``."""

    mean: torch.Tensor  # (B, J) posterior mean of vec(x)
    cov: torch.Tensor  # (B, J, J) posterior covariance of vec(x)
    ancestor_log_w: torch.Tensor  # (B, N) normalised log-posterior of the ancestor a
    prior_mean: torch.Tensor  # (B, J) mean of the prior mixture sum_a w_a p(x | x_a)
    component_prior_means: torch.Tensor  # (B, N, J) F x_a
    component_means: torch.Tensor  # (B, N, J) posterior mean of x given a
    component_cov: torch.Tensor  # (J, J) posterior covariance of x given a (same for all a)
    log_evidence: torch.Tensor  # (B,) log sum_a w_a N(z; H F x_a, H Q H' + R)
    log_lik_max: torch.Tensor  # () max_x log N(z; H x, R) = log N(0; 0, R) (z in range(H))


def mixture_posterior(prev, log_w, F, Q, H, R, z):
    """Exact posterior of ``pi(x, a) ∝ N(z; H vec(x), R) w_a prod_k N(x_k; F x_{a,k}, Q)``.

    Given ``a`` the model is linear-Gaussian, so ``x | a, z`` is Gaussian (a Kalman update of
    ``N(F x_a, Q)``) and ``a | z`` has weights ``w_a N(z; H F x_a, H Q H' + R)``.

    Parameters
    ----------
    prev : (B, N, K, D) previous particles; log_w : (B, N) their log-weights.
    F, Q : (D, D) per-target transition; H : (m, K*D) observation of the stacked state
        ``vec(x) = x.reshape(K*D)`` (row-major: slot, then component); R : (m, m).
    z : (B, m).

    Returns
    -------
    MixturePosterior.
    """
    B, N, K, D = prev.shape
    Fj = torch.block_diag(*[F] * K)
    Qj = torch.block_diag(*[Q] * K)
    mu = prev.reshape(B, N, K * D) @ Fj.mT  # (B, N, KD) component prior means
    S = H @ Qj @ H.mT + R
    G = torch.linalg.solve(S, H @ Qj).mT  # (KD, m) gain Qj H' S^-1
    resid = z.unsqueeze(1) - mu @ H.mT  # (B, N, m)
    means = mu + resid @ G.mT
    P = Qj - G @ S @ G.mT
    zero = torch.zeros(S.shape[0], dtype=S.dtype)
    lik = torch.distributions.MultivariateNormal(zero, S).log_prob(resid)
    log_w = torch.log_softmax(log_w, -1)
    log_evidence = torch.logsumexp(log_w + lik, -1)
    post_log_w = log_w + lik - log_evidence.unsqueeze(-1)
    w = post_log_w.exp()
    mean = torch.einsum("bn,bnj->bj", w, means)
    centred = means - mean.unsqueeze(1)
    cov = P + torch.einsum("bn,bni,bnj->bij", w, centred, centred)
    prior_mean = torch.einsum("bn,bnj->bj", log_w.exp(), mu)
    log_lik_max = torch.distributions.MultivariateNormal(zero, R).log_prob(zero)
    return MixturePosterior(mean, cov, post_log_w, prior_mean, mu, means, P, log_evidence, log_lik_max)


def rts_smoother(F, Q, means, covs):
    """Rauch-Tung-Striebel smoother over the filtering moments of :func:`kalman_filter`.

    Parameters
    ----------
    F, Q : (D, D); means : (T, *B, D); covs : (T, *B, D, D), the filtering moments.

    Returns
    -------
    (T, *B, D) the smoothed means ``E[x_t | z_0:T-1]``.
    """
    m_s, P_s = means[-1], covs[-1]
    out = [m_s]
    for m, P in zip(means[:-1].flip(0), covs[:-1].flip(0)):
        P_pred = F @ P @ F.mT + Q
        G = torch.linalg.solve(P_pred, F @ P).mT  # P F' P_pred^-1 (P_pred symmetric)
        m_s = m + ((m_s - m @ F.mT).unsqueeze(-2) @ G.mT).squeeze(-2)
        P_s = P + G @ (P_s - P_pred) @ G.mT
        out.append(m_s)
    return torch.stack(out[::-1])
