"""Containers passed between step functions: ParticleState, StepInfo, FilterResult.

All three are ``NamedTuple`` s, hence pytrees: ``torch.compile`` and
``torch.utils._pytree`` see through them, and a step function can return them from a
compiled region.
"""

from __future__ import annotations

from typing import Mapping, NamedTuple, Optional

import torch

from .typing import Tensor

__all__ = ["ParticleState", "StepInfo", "FilterResult", "stack_infos"]


class ParticleState(NamedTuple):
    """A weighted particle approximation of the filtering density at one time step.

    Attributes
    ----------
    x : (B, N, K, D)
        Particle states, one ``(K, D)`` multitarget state per particle.
    log_w : (B, N)
        Normalised log-weights (``logsumexp(log_w, -1) == 0``). MCMC-based filters return
        equal weights ``-log N``.
    exists : (B, N, K) bool, optional
        Existence flag of each target slot, for filters with births and deaths; ``None``
        when the number of targets is known.
    """

    x: Tensor
    log_w: Tensor
    exists: Optional[Tensor] = None

    @property
    def batch_size(self) -> int:
        return self.x.shape[0]

    @property
    def num_particles(self) -> int:
        return self.x.shape[1]

    @property
    def num_targets(self) -> int:
        return self.x.shape[2]

    def mean(self) -> Tensor:
        """Weighted (MMSE) estimate of each target slot, ``(B, K, D)`` (paper 000 eq. 6)."""
        w = torch.softmax(self.log_w, dim=-1)
        return torch.einsum("bn,bnkd->bkd", w.to(self.x.dtype), self.x)


class StepInfo(NamedTuple):
    """What one filter step reports besides the new state. Fields a filter does not
    compute stay ``None``; tensors are per run, ``(B,)``.

    Attributes
    ----------
    ess : (B,), optional
        Effective sample size of the importance weights before resampling.
    log_evidence : (B,), optional
        Estimate of ``log p(z_k | z_{1:k-1})`` (SIR filters; PMMH sums it over time).
    acceptance : mapping name -> (B,), optional
        Acceptance rate of each MCMC move type during the step.
    rhat : (B,), optional
        Largest Gelman-Rubin R-hat over the state components (paper 000 eq. 13).
    extensions : (B,), optional
        How many times the chains were run longer because R-hat was too large.
    """

    ess: Optional[Tensor] = None
    log_evidence: Optional[Tensor] = None
    acceptance: Optional[Mapping[str, Tensor]] = None
    rhat: Optional[Tensor] = None
    extensions: Optional[Tensor] = None


class FilterResult(NamedTuple):
    """The output of ``Filter.forward`` over a sequence of T measurements.

    Attributes
    ----------
    mean : (T, B, K, D)
        MMSE estimate of each target slot at every step.
    state : ParticleState
        The particle state after the last step (feed it back as ``init`` to continue).
    info : StepInfo
        Per-step information stacked over time: every tensor gains a leading ``T`` dim.
    log_evidence : (B,), optional
        ``sum_k log p(z_k | z_{1:k-1})`` when the filter estimates it.
    exists_prob : (T, B, K), optional
        Posterior existence probability of each slot (filters with births and deaths).
    """

    mean: Tensor
    state: ParticleState
    info: StepInfo
    log_evidence: Optional[Tensor] = None
    exists_prob: Optional[Tensor] = None


def stack_infos(infos: list[StepInfo]) -> StepInfo:
    """Stack a list of per-step ``StepInfo`` into one with a leading time dim ``T``."""
    if not infos:
        return StepInfo()
    fields = {}
    for name in StepInfo._fields:
        values = [getattr(i, name) for i in infos]
        if any(v is None for v in values):
            fields[name] = None
        elif isinstance(values[0], Mapping):
            fields[name] = {k: torch.stack([v[k] for v in values]) for k in values[0]}
        else:
            fields[name] = torch.stack(values)
    return StepInfo(**fields)
