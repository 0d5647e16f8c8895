"""Particle marginal Metropolis-Hastings (PMMH) for static parameters.

Andrieu, Doucet and Holenstein (2010), "Particle Markov chain Monte Carlo methods", JRSS B
72(3), sec. 2.4.2 (refs. [7], [8] of paper 000). A random-walk MH chain on a static
parameter ``theta`` whose intractable likelihood ``p(z_{1:T} | theta)`` is replaced by the
unbiased SIR estimate ``hat p(z_{1:T} | theta) = prod_k hat p(z_k | z_{1:k-1}, theta)``
(``SIRFilter.forward(...).log_evidence``). The pair (theta, the random numbers of the
filter) is an exact MH chain on an extended space whose theta-marginal is
``p(theta | z_{1:T})`` (pseudo-marginal argument, Andrieu and Roberts 2009).

Batching: B independent problems (Monte Carlo runs) times C chains each. One PMMH
iteration runs a single SIR filter on ``B * C`` copies of the data at once, each copy with
its own parameter: the parameter enters the models as a ``(B * C,)`` tensor, e.g.
:class:`ProcessNoiseScale` (a linear-Gaussian motion whose process-noise covariance is
scaled per copy). ``build_models(theta (B*C, P)) -> (motion, sensor)`` is all a user writes.

What the PMMH row of Table II (paper 000) runs here
---------------------------------------------------
Paper 000 does not say how its PMMH produced filtering estimates. We run PMMH estimating the
process-noise level: ``theta = log q`` (the filters' acceleration noise level, true value
1 m^2 s^-3) with a N(0, 1) prior, a random-walk proposal, C chains per run; an iteration's
state part is the SIR filter's filtering means at every step under that iteration's
``theta`` (the Rao-Blackwellised version of the path PMMH samples). The reported track is
the average of those means over the post-burn-in PMMH iterations and chains: the filtering
estimate with the parameter integrated over its posterior. Its cost per time step is the
total PMMH time divided by T (see ``experiments/bocquel_table2.py``).
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple

import torch

from .._validation import check_generator, check_positive_int, check_shape
from ..kernels.mh import mh_accept, mh_select
from ..models.base import MotionModel, SensorModel
from ..models.motion import ProcessNoiseScale
from ..typing import Tensor
from .sir import SIRFilter

__all__ = ["pmmh", "PMMHResult", "sir_log_evidence", "ProcessNoiseScale"]


class PMMHResult(NamedTuple):
    """Output of :func:`pmmh`.

    Attributes
    ----------
    theta : (L, B, C, P) the chain of every run, one row per iteration.
    log_evidence : (L, B, C) the accepted log-evidence estimates.
    aux : pytree of ``(L, B, C, ...)`` tensors: the accepted auxiliary output of the
        evaluator (e.g. filter means), or ``None``.
    acceptance : (B, C) acceptance rate of every chain.
    """

    theta: Tensor
    log_evidence: Tensor
    aux: Any
    acceptance: Tensor


def sir_log_evidence(
    build_models: Callable[[Tensor], tuple[MotionModel, SensorModel]],
    measurements: Tensor,
    init: Callable[..., Tensor],
    num_particles: int,
    *,
    keep_means: bool = False,
) -> Callable[..., tuple[Tensor, Any]]:
    """The SIR estimate of ``log p(z_{1:T} | theta)``, batched over runs and chains.

    Parameters
    ----------
    build_models : ``theta (B*C, P) -> (motion, sensor)``, models whose parameters are
        batched over the ``B * C`` copies (e.g. :class:`ProcessNoiseScale`).
    measurements : (T, B, *G) the data of the B runs.
    init : ``init(M, *, generator) -> (M, N, K, D)`` initial particles of the copies, where
        copy ``m`` belongs to run ``m // C`` (run ``b``'s chains are ``b C .. b C + C - 1``).
    num_particles : N of the SIR filter.
    keep_means : also return the filter means ``(B, C, T, K, D)`` as auxiliary output.

    Returns
    -------
    ``evaluate(theta (B, C, P), *, generator) -> (log_evidence (B, C), aux)``.
    """
    check_positive_int(num_particles, "num_particles")

    def evaluate(theta: Tensor, *, generator: torch.Generator) -> tuple[Tensor, Any]:
        b, c, p = theta.shape
        motion, sensor = build_models(theta.reshape(b * c, p))
        filt = SIRFilter(motion, sensor, num_particles)
        z = measurements.repeat_interleave(c, dim=1)  # (T, B*C, *G)
        res = filt(z, init=init(b * c, generator=generator), generator=generator)
        aux = None
        if keep_means:
            t = res.mean.shape[0]
            aux = res.mean.reshape((t, b, c) + res.mean.shape[2:]).movedim(0, 2)
        return res.log_evidence.reshape(b, c), aux

    return evaluate


def pmmh(
    evaluate: Callable[..., tuple[Tensor, Any]],
    theta0: Tensor,
    *,
    log_prior: Callable[[Tensor], Tensor],
    proposal_std: Tensor | float,
    num_iterations: int,
    generator: torch.Generator,
) -> PMMHResult:
    """Particle marginal Metropolis-Hastings with a Gaussian random-walk proposal.

    Each iteration proposes ``theta' = theta + proposal_std * eps`` for every chain of every
    run, estimates ``log hat p(z | theta')`` with a fresh filter run (``evaluate``) and
    accepts with ``log alpha = log hat p(z|theta') + log p(theta') - log hat p(z|theta)
    - log p(theta)`` (Andrieu et al. 2010, eq. 13; the symmetric proposal cancels). The
    current estimate is *kept* on rejection, never recomputed: that is what makes the chain
    exact. A proposal outside the prior's support (``log_prior = -inf``) is rejected without
    evaluating the filter at it (the evaluator sees the current ``theta`` there instead).

    Parameters
    ----------
    evaluate : ``(theta (B, C, P), *, generator) -> (log_evidence (B, C), aux)``, e.g.
        :func:`sir_log_evidence`; ``aux`` a pytree of ``(B, C, ...)`` tensors or ``None``.
    theta0 : (B, C, P) starting points.
    log_prior : ``theta (B, C, P) -> (B, C)`` log prior density (``-inf`` off support).
    proposal_std : scalar or (P,) random-walk standard deviation.
    num_iterations : L >= 1 iterations (the starting point is not counted or stored).
    generator : the only source of randomness.

    Returns
    -------
    PMMHResult with ``theta (L, B, C, P)``, ``log_evidence (L, B, C)``, ``aux`` and the
    acceptance rates ``(B, C)``.
    """
    check_generator(generator)
    check_shape(theta0, "theta0", (None, None, None))
    check_positive_int(num_iterations, "num_iterations")
    std = torch.as_tensor(proposal_std, dtype=theta0.dtype, device=theta0.device)
    if not bool((std > 0).all()):
        raise ValueError(f"proposal_std must be > 0, got {proposal_std!r}")
    theta, lp = theta0, log_prior(theta0)
    if not bool(torch.isfinite(lp).all()):
        raise ValueError("theta0 has zero prior density for some chain (log_prior is not finite)")
    log_ev, aux = evaluate(theta, generator=generator)
    thetas, evs, auxs = [], [], []
    accepted_count = torch.zeros(theta.shape[:2], device=theta.device, dtype=theta.dtype)
    for _ in range(num_iterations):
        eps = torch.randn(theta.shape, generator=generator, device=theta.device, dtype=theta.dtype)
        u = torch.rand(theta.shape[:2], generator=generator, device=theta.device, dtype=theta.dtype)
        prop = theta + std * eps
        lp_prop = log_prior(prop)
        valid = torch.isfinite(lp_prop)
        ev_prop, aux_prop = evaluate(torch.where(valid.unsqueeze(-1), prop, theta), generator=generator)
        log_alpha = torch.where(valid, ev_prop + lp_prop - log_ev - lp, torch.full_like(lp, -math.inf))
        acc = mh_accept(log_alpha, u)
        theta, lp, log_ev, aux = mh_select(acc, (prop, lp_prop, ev_prop, aux_prop), (theta, lp, log_ev, aux))
        accepted_count += acc.to(accepted_count.dtype)
        thetas.append(theta)
        evs.append(log_ev)
        auxs.append(aux)
    stacked_aux = None if aux is None else torch.utils._pytree.tree_map(lambda *a: torch.stack(a), *auxs)
    return PMMHResult(torch.stack(thetas), torch.stack(evs), stacked_aux, accepted_count / num_iterations)
