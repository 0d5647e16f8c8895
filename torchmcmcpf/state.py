"""Containers passed between step functions: ParticleState, StepInfo, FilterResult.

All three are ``NamedTuple`` s, hence pytrees: ``torch.compile`` and
``torch.utils._pytree`` see through them, and a step function can return them from a
compiled region. They are registered with :func:`torch.serialization.add_safe_globals`, so
``torch.save(result, path)`` / ``torch.load(path)`` work with the default
``weights_only=True`` (a checkpoint is a ``ParticleState`` plus ``generator.get_state()``).
Their ``repr`` shows field names, shapes and dtypes, never tensor values.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch

from .typing import Tensor

__all__ = ["ParticleState", "StepInfo", "FilterResult", "ExistenceEstimate", "existence_estimate", "stack_infos",
           "stack_states", "weighted_mean", "weighted_cov", "summary"]


def summary(value: Any) -> str:
    """Short description of a field: ``float32(4, 100, 2, 4)`` for a tensor, recursively for
    dicts and tuples, ``repr`` otherwise.
    """
    if torch.is_tensor(value):
        return f"{str(value.dtype).removeprefix('torch.')}{tuple(value.shape)}"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k!r}: {summary(v)}" for k, v in value.items()) + "}"
    if isinstance(value, tuple) and hasattr(value, "_fields"):
        return _short_repr(value)
    return repr(value)


def _short_repr(value: Any) -> str:
    """``Name(field=summary, ...)`` of a NamedTuple."""
    return f"{type(value).__name__}(" + ", ".join(f"{f}={summary(getattr(value, f))}" for f in value._fields) + ")"


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
    extras : dict name -> tensor with the run dim first, optional
        Filtering state beyond the weighted cloud that an algorithm carries from step to
        step, so that a checkpoint of the state alone resumes it (PMMHFilter: the candidate
        parameters ``theta (B, L)``, their accumulated log-evidence ``log_evidence (B, L)``
        and the within-candidate log-weights ``log_w_candidate (B, N)``); ``None`` for the
        filters that need none.

    Example
    -------
    >>> import math
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> x = torch.zeros(2, 100, 3, 4)                 # (B, N, K, D)
    >>> state = tp.ParticleState(x, torch.full((2, 100), -math.log(100)))
    >>> state.batch_size, state.num_particles, state.num_targets, state.mean().shape
    (2, 100, 3, torch.Size([2, 3, 4]))
    """

    x: Tensor
    log_w: Tensor
    exists: Tensor | None = None
    extras: dict[str, Tensor] | None = None

    def __repr__(self) -> str:
        return _short_repr(self)

    @property
    def batch_size(self) -> int:
        """B, the number of independent runs (``x.shape[0]``)."""
        return self.x.shape[0]

    @property
    def num_particles(self) -> int:
        """N, the number of particles per run (``x.shape[1]``)."""
        return self.x.shape[1]

    @property
    def num_targets(self) -> int:
        """K, the number of target slots (``x.shape[2]``)."""
        return self.x.shape[2]

    def mean(self) -> Tensor:
        """Weighted (MMSE) estimate of each target slot, ``(B, K, D)`` (paper 000 eq. 6)."""
        return weighted_mean(self.x, self.log_w)


class StepInfo(NamedTuple):
    """What one filter step reports besides the new state: the same fields for every filter,
    each a ``(B,)`` tensor (``(T, B)`` once stacked over time).

    Attributes
    ----------
    ess : (B,)
        Effective sample size of the importance weights (SIR, resample-move, PMMH's
        filters); NaN for the MCMC filters, which have no importance weights.
    log_evidence : (B,)
        Estimate of ``log p(z_k | z_{1:k-1})`` (importance-sampling filters, relative to the
        sensor's "no target" hypothesis for likelihood-ratio sensors); NaN where the
        algorithm has no such estimate (MCMC filters).
    acceptance : (B,)
        Fraction of the step's Metropolis-Hastings decisions that accepted (all moves
        together); NaN where the step makes none (SIR, resample-move without HMC).
    extras : dict name -> (B,) tensor
        Algorithm-specific quantities (documented by each filter), e.g.
        ``"acceptance_joint"``, ``"rhat"``, ``"extensions"``. Empty for SIR.

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> info = tp.StepInfo.make(torch.zeros(2), ess=torch.tensor([80.0, 95.0]))   # B = 2
    >>> info.ess, info.acceptance                     # what a filter does not compute is NaN
    (tensor([80., 95.]), tensor([nan, nan]))
    """

    ess: Tensor
    log_evidence: Tensor
    acceptance: Tensor
    extras: dict

    def __repr__(self) -> str:
        return _short_repr(self)

    @staticmethod
    def make(template: Tensor, *, ess: Tensor | None = None, log_evidence: Tensor | None = None,
             acceptance: Tensor | None = None, extras: dict | None = None) -> StepInfo:
        """Fill the fields a filter does not compute with NaN ``(B,)`` shaped like
        ``template (B,)`` (its dtype and device).
        """
        nan = torch.full_like(template, float("nan"))
        return StepInfo(nan if ess is None else ess, nan if log_evidence is None else log_evidence,
                        nan if acceptance is None else acceptance, {} if extras is None else dict(extras))


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
    log_evidence : (B,)
        ``sum_k log p(z_k | z_{1:k-1})`` (NaN for filters that do not estimate it).
    exists_prob : (T, B, K), optional
        Posterior existence probability of each slot (filters with births and deaths).
    cov : (T, B, K, D, D), optional
        Posterior covariance of each slot around ``mean`` (given existence, with births and
        deaths; zeros where no particle has the slot): the weighted covariance of the cloud.
    history : ParticleState with a leading T dim, optional
        Every step's particle state, ``x (T, B, N, K, D)``, ``log_w (T, B, N)``, ``exists
        (T, B, N, K)``, kept when ``forward(..., history=True)`` (T times the memory of one
        state): per-step clouds for :meth:`to_stonesoup` (``kind="particle"``) and the chain
        samples of any step for :meth:`to_arviz`.
    meta : dict, optional
        What made the result: ``filter`` (class name), ``num_particles``, ``settings`` (the
        settings dataclass as plain values), ``motion``, ``sensor``, ``existence``, ``dt``
        (the motion's sampling time, or None), ``compile_step`` and ``versions``; plain
        Python values, so ``torch.load(weights_only=True)`` reads it.

    Interoperability (optional packages, imported only when called): :meth:`to_numpy` (a
    dict of NumPy arrays), :meth:`to_xarray` (an ``xarray.Dataset``), :meth:`to_arviz` (the
    kept chain samples of an MCMC filter's step as ArviZ ``InferenceData``) and
    :meth:`to_stonesoup` (Stone Soup ``Track`` s); see :mod:`torchmcmcpf.interop`.

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> g = torch.Generator().manual_seed(0)
    >>> motion, sensor = tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0)
    >>> x0 = torch.randn(2, 100, 3, 4, generator=g)   # (B, N, K, D): 2 runs, 100 particles, 3 targets
    >>> z = torch.randn(5, 2, 3, 2, generator=g)      # (T, B, K, 2): 5 frames of positions
    >>> result = tp.SIRFilter(motion, sensor, 100)(z, init=x0, generator=g)
    >>> result                                        # shapes, never values
    FilterResult(mean=float32(5, 2, 3, 4), state=ParticleState(...), ...)
    >>> result.cov.shape                              # (T, B, K, D, D): each slot's posterior covariance
    torch.Size([5, 2, 3, 4, 4])
    >>> result.to_numpy()["info.ess"].shape            # a flat dict of NumPy arrays
    (5, 2)
    >>> result.meta["filter"], result.meta["settings"]
    ('SIRFilter', {'resample_method': 'systematic', 'ess_threshold': 1.0})
    """

    mean: Tensor
    state: ParticleState
    info: StepInfo
    log_evidence: Tensor
    exists_prob: Tensor | None = None
    cov: Tensor | None = None
    history: ParticleState | None = None
    meta: dict | None = None

    def __repr__(self) -> str:
        fields = [f"{f}={summary(getattr(self, f))}" for f in self._fields if f != "meta"]
        if self.meta is not None:  # its settings are long: name the filter only
            fields.append(f"meta={{'filter': {self.meta.get('filter')!r}, ...}}")
        return "FilterResult(" + ", ".join(fields) + ")"

    def to_xarray(self) -> Any:
        """The result as an ``xarray.Dataset`` (:func:`torchmcmcpf.interop.result_to_xarray`):
        ``mean`` on dims ``(time, run, target, component)`` with the components named from
        the state layout, the info fields as variables, the settings and provenance as
        attributes. Needs ``pip install 'torchmcmcpf[interop]'``.
        """
        from .interop import result_to_xarray

        return result_to_xarray(self)

    def to_arviz(self, *, step: int = -1, run: int = 0) -> Any:
        """The kept chain samples of an MCMC filter at ``step`` (default the last) for run
        ``run`` as ArviZ ``InferenceData`` with ``chain`` and ``draw`` dims
        (:func:`torchmcmcpf.interop.chains_to_arviz`); a step before the last needs
        ``history``. Needs ``pip install 'torchmcmcpf[interop]'``.
        """
        from .interop import result_to_arviz

        return result_to_arviz(self, step=step, run=run)

    def to_stonesoup(self, *, run: int = 0, kind: str = "gaussian", start_time: Any = None,
                     dt: float | None = None, threshold: float = 0.5) -> list:
        """Stone Soup ``Track`` s of run ``run``, one per slot (and per stretch of existence
        with births and deaths), of ``GaussianState`` s (``kind="gaussian"``, from ``mean``
        and ``cov``) or ``ParticleState`` s (``kind="particle"``, from ``history``)
        (:func:`torchmcmcpf.interop.tracks_to_stonesoup`). Needs Stone Soup
        (``pip install 'torchmcmcpf[interop]'``).
        """
        from .interop import tracks_to_stonesoup

        return tracks_to_stonesoup(self, run=run, kind=kind, start_time=start_time, dt=dt, threshold=threshold)

    def to_numpy(self) -> dict[str, Any]:
        """The result as a flat dict of NumPy arrays (for pandas): ``"mean"``,
        ``"log_evidence"``, ``"exists_prob"``, ``"cov"``, ``"state.x"``, ``"state.log_w"``,
        ``"state.exists"``, ``"info.ess"``, ``"info.<extra>"``, ... (``None`` fields left
        out).
        """
        out: dict[str, Any] = {}

        def put(name: str, value: Any) -> None:
            if torch.is_tensor(value):
                out[name] = value.detach().cpu().numpy()

        put("mean", self.mean)
        put("log_evidence", self.log_evidence)
        put("exists_prob", self.exists_prob)
        put("cov", self.cov)
        for f in ParticleState._fields:
            put(f"state.{f}", getattr(self.state, f))
        for f in ("ess", "log_evidence", "acceptance"):
            put(f"info.{f}", getattr(self.info, f))
        for k, v in self.info.extras.items():
            put(f"info.{k}", v)
        return out


def weighted_mean(x: Tensor, log_w: Tensor) -> Tensor:
    """Weighted (MMSE) mean of particles ``x (B, N, K, D)`` under log-weights ``log_w (B, N)``
    (normalised or not): ``(B, K, D)``, paper 000 eq. 6.
    """
    w = torch.softmax(log_w, dim=-1)
    return torch.einsum("bn,bnkd->bkd", w.to(x.dtype), x)


def weighted_cov(x: Tensor, log_w: Tensor, mean: Tensor, exists: Tensor | None = None) -> Tensor:
    """Weighted covariance of each slot around ``mean``: ``x (B, N, K, D)``, ``log_w (B,
    N)``, ``mean (B, K, D)`` -> ``(B, K, D, D)``. With ``exists (B, N, K)`` it is the
    covariance given existence (weights ``w_n e_nk``, normalised per slot); zeros where no
    particle has the slot.
    """
    w = torch.softmax(log_w, dim=-1).to(x.dtype)  # (B, N)
    we = w.unsqueeze(-1).expand(x.shape[:3]) if exists is None else w.unsqueeze(-1) * exists.to(x.dtype)
    d = x - mean.unsqueeze(1)  # (B, N, K, D)
    if exists is not None:
        d = torch.where(exists.unsqueeze(-1), d, torch.zeros_like(d))  # dead slots hold x_death: no NaN/inf
    num = torch.einsum("bnk,bnkd,bnke->bkde", we, d, d)
    num = 0.5 * (num + num.transpose(-1, -2))  # symmetric to the last bit (float rounding of the einsum)
    mass = we.sum(1)  # (B, K)
    return num / mass.clamp(min=torch.finfo(x.dtype).tiny)[..., None, None]


def stack_states(states: list[ParticleState]) -> ParticleState:
    """Stack per-step states into one with a leading time dim ``T`` (``extras`` stacked too)."""
    if not states:
        raise ValueError("states is empty, expected at least one ParticleState")
    first = states[0]
    exists = None if first.exists is None else torch.stack([s.exists for s in states])  # type: ignore[misc]
    extras = None if first.extras is None else {k: torch.stack([s.extras[k] for s in states])  # type: ignore[index]
                                                 for k in first.extras}
    return ParticleState(torch.stack([s.x for s in states]), torch.stack([s.log_w for s in states]), exists, extras)


def stack_infos(infos: list[StepInfo]) -> StepInfo:
    """Stack a list of per-step ``StepInfo`` into one with a leading time dim ``T``."""
    if not infos:
        raise ValueError("infos is empty, expected at least one StepInfo")
    return StepInfo(
        torch.stack([i.ess for i in infos]),
        torch.stack([i.log_evidence for i in infos]),
        torch.stack([i.acceptance for i in infos]),
        {k: torch.stack([i.extras[k] for i in infos]) for k in infos[0].extras},
    )


class ExistenceEstimate(NamedTuple):
    """Point estimates of a weighted cloud with existence flags.

    Attributes
    ----------
    exists_prob : (B, K) posterior existence probability of each slot.
    expected_count : (B,) expected number of targets, ``sum_k exists_prob``.
    mean : (B, K, D) posterior mean of each slot given that it exists (``x_death`` where
        no particle has it).
    present : (B, K) bool, the slots reported as targets: ``exists_prob > threshold``.
    """

    exists_prob: Tensor
    expected_count: Tensor
    mean: Tensor
    present: Tensor


def existence_estimate(state: ParticleState, *, threshold: float = 0.5,
                       x_death: Tensor | None = None) -> ExistenceEstimate:
    """Existence probabilities, expected count and the state of every slot whose existence
    probability exceeds ``threshold`` (0.5: the marginal MAP existence).

    Parameters
    ----------
    state : ParticleState with ``x (B, N, K, D)``, ``log_w (B, N)``, ``exists (B, N, K)``.
    threshold : in [0, 1).
    x_death : (D,) value for slots that exist in no particle (default zeros).

    Returns
    -------
    ExistenceEstimate.
    """
    if state.exists is None:
        raise ValueError("state.exists is None; existence_estimate needs a state with existence flags")
    if not 0.0 <= float(threshold) < 1.0:
        raise ValueError(f"threshold must be in [0, 1), got {threshold!r}")
    w = torch.softmax(state.log_w, -1).to(state.x.dtype)  # (B, N)
    we = w.unsqueeze(-1) * state.exists.to(w.dtype)  # (B, N, K)
    prob = we.sum(1)  # (B, K)
    num = torch.einsum("bnk,bnkd->bkd", we, torch.where(state.exists.unsqueeze(-1), state.x,
                                                        torch.zeros_like(state.x)))
    fill = torch.zeros(state.x.shape[-1], dtype=state.x.dtype, device=state.x.device) \
        if x_death is None else x_death.to(state.x)
    mean = torch.where(prob.unsqueeze(-1) > 0, num / prob.clamp(min=torch.finfo(w.dtype).tiny).unsqueeze(-1),
                       fill)
    return ExistenceEstimate(prob, prob.sum(-1), mean, prob > threshold)


torch.serialization.add_safe_globals([ParticleState, StepInfo, FilterResult, ExistenceEstimate])
