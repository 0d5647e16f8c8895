"""Batched Hamiltonian (hybrid) Monte Carlo with gradients from ``torch.autograd``.

Duane et al. (1987); Neal (2011), "MCMC using Hamiltonian dynamics", secs. 5.2-5.3; the
move of Maroulas and Stinis (2010, paper 003), sec. 2.1.2: unit-mass Gaussian momenta,
the Verlet leapfrog integrator, a Metropolis accept/reject after each trajectory and the
momenta discarded.

Every tensor has leading *chain* dims ``(*C)`` (e.g. ``(B, N)`` particles of B runs, or
``(B, N, K)`` one chain per target slot when the target factorises over slots, paper 003
eq. 9) followed by the *event* dims of one chain's state. ``log_target(q)`` returns one
value per chain, ``(*C)``; the split between chain and event dims is read off its shape.

Gradients: ``torch.autograd.grad(log_target(q).sum(), q)``. Summing over the chains is
exact, not an approximation: each chain's log-target depends on that chain's state only,
so the derivative of the sum with respect to chain i's state is the derivative of chain
i's own log-target. One backward pass thus gives every gradient of every particle of
every run. (A ``log_target`` that couples chains, e.g. through a batch normalisation,
would break this; none in torchmcmcpf does.)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch

from .._native.select import where
from .._validation import check_generator, check_positive, check_positive_int, check_tensor
from ..typing import Tensor

__all__ = ["HMCInfo", "hmc", "hmc_transition", "leapfrog", "value_and_grad"]

LogTarget = Callable[[Tensor], Tensor]
GradFn = Callable[[Tensor], Tensor]


class HMCInfo(NamedTuple):
    """What :func:`hmc` reports.

    Attributes
    ----------
    acceptance : (*C)
        Fraction of the ``num_steps`` accept/reject rounds that accepted, per chain.
    log_target : (*C)
        ``log_target`` at the returned state.

    Example
    -------
    4000 chains on ``N(3, 1)``:

    >>> import torch
    >>> from torchmcmcpf.kernels import hmc
    >>> q, info = hmc(torch.zeros(4000, 1, dtype=torch.float64), lambda q: -0.5 * (q - 3.0).square().sum(-1),
    ...               step_size=0.5, num_leapfrog=5, num_steps=30, generator=torch.Generator().manual_seed(0))
    >>> info.acceptance.shape, info.log_target.shape        # per chain
    (torch.Size([4000]), torch.Size([4000]))
    >>> round(q.mean().item(), 1), round(q.std().item(), 1)
    (3.0, 1.0)
    >>> bool(info.acceptance.mean() > 0.9)
    True
    """

    acceptance: Tensor
    log_target: Tensor


def value_and_grad(log_target: LogTarget, q: Tensor, grad_fn: GradFn | None = None
                   ) -> tuple[Tensor, Tensor]:
    """``log_target(q)`` and its gradient in ``q``.

    Parameters
    ----------
    log_target : ``(*C, *E) -> (*C)``.
    q : (*C, *E) chain states.
    grad_fn : optional closed-form gradient ``(*C, *E) -> (*C, *E)``; by default the
        gradient comes from one ``torch.autograd.grad`` of the sum over chains (exact,
        see the module docstring).

    Returns
    -------
    value : (*C), detached.
    grad : (*C, *E), detached.

    Raises
    ------
    RuntimeError : under ``torch.inference_mode()`` without ``grad_fn``: the tensors made
    there cannot enter autograd (``torch.no_grad()`` is fine).
    """
    if grad_fn is not None:
        with torch.no_grad():
            return log_target(q), grad_fn(q)
    if torch.is_inference_mode_enabled():
        raise RuntimeError("HMC takes its gradients from autograd, which tensors made under torch.inference_mode() "
                           "cannot enter: run a filter with an HMC move outside inference mode (torch.no_grad() is "
                           "fine)")
    with torch.enable_grad():
        q_ = q.detach().requires_grad_(True)
        value = log_target(q_)
        (grad,) = torch.autograd.grad(value.sum(), q_)
    return value.detach(), grad


def leapfrog(
    q: Tensor,
    p: Tensor,
    grad: Tensor,
    log_target: LogTarget,
    *,
    step_size: float | Tensor,
    num_steps: int,
    grad_fn: GradFn | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Verlet leapfrog integration of Hamilton's equations for ``H = -log_target(q) + |p|^2/2``.

    Neal (2011) eq. 5.18-5.20: a half step in the momentum, ``num_steps`` alternating full
    steps (position, then momentum; the last momentum step is a half step). Pure and
    deterministic: volume preserving and reversible (integrating ``(q', -p')`` returns
    ``(q, -p)``), with an energy error of order ``step_size^2``.

    Parameters
    ----------
    q : (*C, *E) positions; p : (*C, *E) momenta.
    grad : (*C, *E) gradient of ``log_target`` at ``q`` (reused from the previous step).
    log_target : ``(*C, *E) -> (*C)``.
    step_size : float, or a tensor broadcastable to ``q`` (e.g. ``(*C, 1, ...)`` per chain).
    num_steps : number of leapfrog steps L >= 1.
    grad_fn : optional closed-form gradient (see :func:`value_and_grad`).

    Returns
    -------
    q, p : (*C, *E) at the end of the trajectory.
    log_target_value : (*C) at the new ``q``.
    grad : (*C, *E) at the new ``q``.
    """
    p = p + 0.5 * step_size * grad
    for _ in range(num_steps - 1):
        q = q + step_size * p
        _, grad = value_and_grad(log_target, q, grad_fn)
        p = p + step_size * grad
    q = q + step_size * p
    value, grad = value_and_grad(log_target, q, grad_fn)
    p = p + 0.5 * step_size * grad
    return q, p, value, grad


def _check_value(value: Tensor, q: Tensor) -> int:
    """Number of chain dims, checked against ``q``."""
    if value.dim() > q.dim() or tuple(value.shape) != tuple(q.shape[: value.dim()]):
        raise ValueError(
            f"log_target returned shape {tuple(value.shape)}, expected the leading (chain) dims "
            f"of q {tuple(q.shape)}"
        )
    return value.dim()


def hmc(
    q: Tensor,
    log_target: LogTarget,
    *,
    step_size: float | Tensor,
    num_leapfrog: int,
    num_steps: int,
    generator: torch.Generator,
    grad_fn: GradFn | None = None,
) -> tuple[Tensor, HMCInfo]:
    """Run ``num_steps`` HMC transitions on every chain at once.

    Each transition: draw ``p ~ N(0, I)``, integrate ``num_leapfrog`` leapfrog steps of
    ``step_size``, accept with probability ``min(1, exp(-H(q', p') + H(q, p)))``
    (branch-free ``torch.where``; a trajectory that produced NaN/inf is rejected), discard
    ``p``. Leaves ``exp(log_target)`` invariant for every chain (paper 003 sec. 2.1.2 uses
    100 transitions of 1 leapfrog step of 0.1).

    Parameters
    ----------
    q : (*C, *E) initial states (floating point).
    log_target : ``(*C, *E) -> (*C)``, differentiable in ``q``.
    step_size : float > 0, or a positive tensor broadcastable to ``q``.
    num_leapfrog : leapfrog steps per trajectory, >= 1.
    num_steps : accept/reject rounds, >= 1.
    generator : the source of the momenta and of the accept uniforms.
    grad_fn : optional closed-form gradient of ``log_target``; default autograd.

    Returns
    -------
    q : (*C, *E) the final states.
    info : :class:`HMCInfo` with ``acceptance (*C)`` and ``log_target (*C)``.
    """
    check_tensor(q, "q")
    if not q.is_floating_point():
        raise ValueError(f"q must be a floating point tensor, got dtype {q.dtype}")
    if torch.is_tensor(step_size):
        if not bool((step_size > 0).all()):
            raise ValueError("step_size must be > 0 everywhere")
    else:
        check_positive(step_size, "step_size")
    num_leapfrog = check_positive_int(num_leapfrog, "num_leapfrog")
    num_steps = check_positive_int(num_steps, "num_steps")
    check_generator(generator)

    q = q.detach()
    value, grad = value_and_grad(log_target, q, grad_fn)
    _check_value(value, q)
    accepted = torch.zeros_like(value)
    for _ in range(num_steps):
        p = torch.randn(q.shape, generator=generator, device=q.device, dtype=q.dtype)
        u = torch.rand(value.shape, generator=generator, device=q.device, dtype=q.dtype)
        q, value, grad, accept = hmc_transition(q, value, grad, p, u, log_target=log_target, step_size=step_size,
                                                num_leapfrog=num_leapfrog, grad_fn=grad_fn)
        accepted = accepted + accept.to(accepted.dtype)
    return q, HMCInfo(acceptance=accepted / num_steps, log_target=value)


def hmc_transition(q: Tensor, value: Tensor, grad: Tensor, p: Tensor, u: Tensor, *, log_target: LogTarget,
                   step_size: float | Tensor, num_leapfrog: int, grad_fn: GradFn | None = None
                   ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """One HMC transition from pre-drawn momenta ``p (*C, *E)`` and accept uniforms ``u (*C)``
    (pure; what ``ResampleMoveFilter(compile_step=True)`` compiles, with a ``grad_fn``).

    Parameters
    ----------
    q : (*C, *E) states; value : (*C) ``log_target(q)``; grad : (*C, *E) its gradient.
    p, u, log_target, step_size, num_leapfrog, grad_fn : as :func:`hmc`.

    Returns
    -------
    q, value, grad : the new states, log-targets and gradients; accept : (*C) bool.
    """
    event = tuple(range(value.dim(), q.dim()))
    q_new, p_new, value_new, grad_new = leapfrog(
        q, p, grad, log_target, step_size=step_size, num_steps=num_leapfrog, grad_fn=grad_fn
    )
    kinetic = 0.5 * p.square().sum(event) if event else 0.5 * p.square()
    kinetic_new = 0.5 * p_new.square().sum(event) if event else 0.5 * p_new.square()
    log_alpha = (value_new - kinetic_new) - (value - kinetic)
    accept = torch.log(u) < log_alpha  # NaN -> False: a diverged trajectory is rejected
    sel = accept.reshape(accept.shape + (1,) * len(event))
    return (where(sel, q_new, q), where(accept, value_new, value), where(sel, grad_new, grad),
            accept)
