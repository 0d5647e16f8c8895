"""What the model allows: the posterior Cramer-Rao bound on the position RMSE and the maximum of
the model's own posterior over a window of frames (whose gap a late gap is).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple, cast

import torch
from torch.utils._pytree import tree_map

from .._validation import (
    check_finite,
    check_positive_int,
    check_shape,
    check_tensor,
    measurement_leaves,
)
from ..typing import VX, VY, Tensor, X, Y

if TYPE_CHECKING:  # the models import nothing from here; annotations only
    from ..models.base import MotionModel, SensorModel
    from ..models.multitarget import Exclusion


def pcrb_position_rmse(sensor: SensorModel, motion: MotionModel, x: Tensor, *, generator: torch.Generator,
                       num_frames: int = 200, iterations: int = 200) -> Tensor:
    """Floor of a filter's per-step position RMSE for each target alone: the steady-state
    posterior Cramer-Rao bound (Tichavsky, Muravchik and Nehorai 1998, eq. 21 for a linear
    Gaussian motion model) of the kinematic state ``[x, vx, y, vy]``.

    The one-frame Fisher information ``J_z = E[s s^T]`` of the sensor's exact likelihood at
    ``x`` is estimated by Monte Carlo: ``num_frames`` frames simulated from each target alone,
    ``s`` the autograd score of ``sensor.log_likelihood`` with respect to the kinematic
    components (the other components, such as a radar amplitude, are taken as known). The
    recursion ``J_k = (Q + F J_{k-1}^{-1} F^T)^{-1} + J_z`` with the motion model's ``F`` and
    ``Q`` (kinematic block) is run ``iterations`` times from ``J_z`` to its fixed point. The
    floor of target ``j``'s position RMSE is ``sqrt(P_xx + P_yy)`` with ``P = J^{-1}``: on
    trajectories drawn from the motion model, no filter does better on average in steady
    state, with every other target away and the known components known, so a scene's
    interactions and unknowns only add to it. It bounds the error averaged over such
    trajectories, not on one truth: a truth that moves with less noise than the model's ``Q``
    (a noise-free one, say) is tracked below it for as long as it keeps so (the soak study's
    clairvoyant reference, 10-20 % below), as are the first steps after a sharp start. On a
    linear-Gaussian position sensor it is the Kalman filter's steady-state error.

    Parameters
    ----------
    sensor : a sensor model whose ``log_likelihood`` is differentiable in the state.
    motion : a motion model with ``F`` and ``Q`` ``(D, D)`` (linear Gaussian, such as
        :class:`~torchmcmcpf.models.ConstantVelocity`).
    x : (B, J, D) target states at which the information is taken (a mid-run truth, say).
    generator : draws the frames.
    num_frames : M >= 2 frames per target (relative Monte Carlo error of ``J_z`` about
        ``sqrt(2 / M)``).
    iterations : >= 1 steps of the recursion.

    Returns
    -------
    (B, J) float64, the floor [m] of each target's per-step position RMSE.
    """
    check_tensor(x, "x")
    if x.dim() != 3 or x.shape[-1] < 4:
        raise ValueError(f"x has shape {tuple(x.shape)}, expected (B, J, D) with D >= 4")
    if not isinstance(num_frames, int) or num_frames < 2:
        raise ValueError(f"num_frames must be an int >= 2, got {num_frames!r}")
    if not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations must be an int >= 1, got {iterations!r}")
    if not (hasattr(motion, "F") and hasattr(motion, "Q")):
        raise ValueError(f"motion must be linear Gaussian with F and Q, got {type(motion).__name__}")
    kin = [X, VX, Y, VY]
    b, j, d = x.shape
    targets = x.detach().reshape(b * j, 1, d)
    frames = targets.repeat(num_frames, 1, 1)  # (M P, 1, D): frame m of target p at row m P + p
    z = sensor.simulate(frames, generator=generator)
    at = frames.unsqueeze(1).clone().requires_grad_(True)  # (M P, N = 1, K = 1, D)
    with torch.enable_grad():
        (score,) = torch.autograd.grad(sensor.log_likelihood(at, z).sum(), at)
    s = score[:, 0, 0, kin].to(torch.float64).reshape(num_frames, b * j, 4)
    info = torch.einsum("mpa,mpb->pab", s, s) / num_frames  # (P, 4, 4)
    F = cast(Tensor, motion.F).to(torch.float64)[kin][:, kin]
    Q = cast(Tensor, motion.Q).to(torch.float64)[kin][:, kin]
    bound = info + 1e-9 * torch.eye(4, dtype=info.dtype)  # a flat prior: J_z alone may be singular
    for _ in range(iterations):  # the recursion's steps, batched over the targets
        bound = torch.linalg.inv(Q + F @ torch.linalg.inv(bound) @ F.T) + info
    cov = torch.linalg.inv(bound)
    return (cov[:, 0, 0] + cov[:, 2, 2]).clamp(min=0).sqrt().reshape(b, j)


class MAPTrajectory(NamedTuple):
    """A local maximum of the posterior over a window of frames (:func:`map_trajectory`).

    Attributes
    ----------
    x : (T, B, K, D) the trajectory, every target's state at every frame.
    log_posterior : (B,) its log posterior density (up to the data's normalising constant):
        ``log_lik`` summed over the frames plus the motion, exclusion and prior terms.
    log_lik : (T, B) ``log p(z_t | x_t)`` per frame.
    grad_norm : (B,) the largest absolute component of the gradient there (0 at an exact
        stationary point; compare it with the scale of the states).

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.metrics import map_trajectory
    >>> motion, sensor = tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=0.1)
    >>> z = torch.tensor([[0.0, 0.0], [1.0, 0.5], [2.0, 1.0], [3.0, 1.5]], dtype=torch.float64)
    >>> fit = map_trajectory(sensor, motion, z.view(4, 1, 1, 2), torch.zeros(4, 1, 1, 4, dtype=torch.float64))
    >>> fit.x.shape, fit.log_lik.shape                      # (T, B, K, D), (T, B)
    (torch.Size([4, 1, 1, 4]), torch.Size([4, 1]))
    >>> fit.x[-1, 0, 0].round(decimals=2)                   # [x, vx, y, vy]: the velocity is recovered
    tensor([3.0000, 1.0000, 1.5000, 0.5000], dtype=torch.float64)
    >>> bool(fit.grad_norm < 1e-4)
    True
    """

    x: Tensor
    log_posterior: Tensor
    log_lik: Tensor
    grad_norm: Tensor


def map_trajectory(sensor: SensorModel, motion: MotionModel, z: object, start: Tensor, *,
                   prior_mean: Tensor | None = None, prior_cov: Tensor | None = None,
                   exclusion: Exclusion | None = None, max_iter: int = 1000) -> MAPTrajectory:
    """The trajectory that locally maximises the model's own posterior over a window of
    frames, found from ``start`` by L-BFGS on autograd gradients: what the model and the data
    say, without a particle approximation.

    The objective of each run is the log density of the whole window,
    ``sum_t log p(z_t | x_t) + sum_{t >= 1} sum_k log f(x_{t,k} | x_{t-1,k})`` plus, with an
    exclusion factor, ``sum_t log Phi(x_t)`` (the multitarget prior's interaction term of the
    filters that have it, :mod:`~torchmcmcpf.models.multitarget`; pass the filter's own to
    maximise its posterior) and, with a prior, ``sum_k log N(x_{0,k}; prior_mean_k,
    prior_cov)`` (without one the first frame's state is free: the window's start is not
    constrained by earlier frames). On a linear-Gaussian model it is the Kalman (RTS)
    smoother's mean (tested). On a nonlinear
    one it is the local maximum uphill from ``start``: started from a filter's estimate, a
    trajectory that stays where the filter is says the data and the model support the
    filter there (a mode of the posterior: a tracker may hold it); one that moves to the
    truth says the filter's estimate is no mode of its own posterior, so the gap between the
    estimate and the truth is the filter's (its particle approximation), not the model's
    (docs/tracks.md: the crossing's late gaps).

    Runs are independent; their objectives are summed and optimised together (the gradient
    separates), ``max_iter`` L-BFGS iterations with a strong-Wolfe line search in all, in the
    dtype of ``start`` (float64 advised). Frames, runs, targets and components are tensor
    dims (the ``T x B`` frames are scored as one batch of runs).

    Parameters
    ----------
    sensor : its ``log_likelihood`` must be differentiable in the state (every sensor of the
        library with a density is; existence flags are not used: every slot is a target).
    motion : a motion model with a density (``log_prob``).
    z : the window's measurements, any :class:`~torchmcmcpf.typing.Measurement` with a
        leading ``T`` dim (for grid sensors ``(T, B, *G)``).
    start : (T, B, K, D) the trajectory to start from (a filter's estimate ``result.mean``,
        or the truth).
    prior_mean : (B, K, D), optional: a Gaussian prior on the first frame's state, with
    prior_cov : (D, D) or (B, K, D, D), its covariance (both or neither).
    exclusion : an :class:`~torchmcmcpf.models.multitarget.Exclusion`, optional (counted only
        when the sensor declares its resolution, as in the filters).
    max_iter : >= 1.

    Returns
    -------
    :class:`MAPTrajectory`.
    """
    check_tensor(start, "start")
    if start.dim() != 4:
        raise ValueError(f"start has shape {tuple(start.shape)}, expected (T, B, K, D)")
    check_finite(start, "start")
    check_positive_int(max_iter, "max_iter")
    from ..models.multitarget import check_exclusion, log_exclusion

    check_exclusion(exclusion)
    t_len, b, k, d = start.shape
    if (prior_mean is None) != (prior_cov is None):
        raise ValueError("prior_mean and prior_cov must be given together, got only "
                         f"{'prior_mean' if prior_cov is None else 'prior_cov'}")
    leaves = measurement_leaves(z, "z")
    if any(a.shape[:1] != (t_len,) for a in leaves):
        raise ValueError(f"z must be measurements with a leading T = {t_len} dim (start's), got leading dims "
                         f"{[tuple(a.shape[:1]) for a in leaves]}")
    dtype = start.dtype
    z = tree_map(lambda a: a.to(dtype) if torch.is_tensor(a) and a.is_floating_point() else a, z)
    prior = None
    if prior_mean is not None and prior_cov is not None:
        check_shape(prior_mean, "prior_mean", (b, k, d))
        if tuple(prior_cov.shape) not in ((d, d), (b, k, d, d)):
            raise ValueError(f"prior_cov has shape {tuple(prior_cov.shape)}, expected {(d, d)} or {(b, k, d, d)}")
        prior = torch.distributions.MultivariateNormal(prior_mean.to(dtype),
                                                       covariance_matrix=prior_cov.to(dtype))

    # the frames as runs of one batch: one likelihood call per evaluation, not one per frame
    frames = tree_map(lambda a: a.reshape((t_len * b,) + tuple(a.shape[2:])) if torch.is_tensor(a) else a, z)

    def terms(x: Tensor) -> tuple[Tensor, Tensor]:  # log_lik (T, B), log_posterior (B,)
        log_lik = sensor.log_likelihood(x.reshape(t_len * b, 1, k, d), frames)[:, 0].reshape(t_len, b)
        total = log_lik.sum(0)
        if t_len > 1:
            total = total + motion.log_prob(x[1:], x[:-1]).sum((0, -1))
        total = total + log_exclusion(exclusion, sensor, x).sum(0)  # zeros without one
        if prior is not None:
            total = total + prior.log_prob(x[0]).sum(-1)
        return log_lik, total

    with torch.no_grad():
        _, first = terms(start)
    if not bool(torch.isfinite(first).all()):
        raise ValueError(f"start has log posterior {first.tolist()} (not finite) in some run: start every run "
                         "where the likelihood and motion densities are finite (inside the sensor's grid)")
    x = start.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        opt = torch.optim.LBFGS([x], lr=1.0, max_iter=max_iter, tolerance_grad=1e-12, tolerance_change=1e-15,
                                history_size=50, line_search_fn="strong_wolfe")

        def closure() -> Tensor:
            opt.zero_grad()
            loss = -terms(x)[1].sum()
            loss.backward()
            return loss

        opt.step(closure)
        x_opt = x.detach()
        at = x_opt.clone().requires_grad_(True)
        log_lik, total = terms(at)
        (grad,) = torch.autograd.grad(total.sum(), at)
    return MAPTrajectory(x_opt, total.detach(), log_lik.detach(), grad.abs().amax((0, 2, 3)))
