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
from torch.utils._pytree import tree_map

from ._native.select import where
from .interop import result_to_arviz, result_to_xarray, tracks_to_stonesoup
from .runtime import flagged_first, squared_norm, take_along
from .typing import Tensor, X, Y

__all__ = ["ParticleState", "StepInfo", "FilterResult", "ExistenceEstimate", "existence_estimate", "stack_infos",
           "stack_states", "weighted_mean", "weighted_cov", "summary", "relabel", "relabel_order",
           "relabelled_estimate"]


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
    extras : dict name -> typed value (a NamedTuple of tensors with the run dim first), optional
        Filtering state beyond the weighted cloud that an algorithm carries from step to
        step, so that a checkpoint of the state alone resumes it: one typed carry per concern
        (:mod:`torchmcmcpf.filters._carry`), e.g. ``forward``'s last estimate (a
        :class:`~torchmcmcpf.filters.CarriedEstimate` under ``"estimate"``), PMMHFilter's
        candidates (a :class:`~torchmcmcpf.filters.PMMHState` under ``"pmmh"``), the group
        filter's fields (a :class:`~torchmcmcpf.filters.group.GroupState` under ``"group"``);
        ``None`` for a fresh state.

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
    extras: dict[str, Any] | None = None

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
        state), each particle's slots relabelled as ``mean``'s (so slot ``k`` of the cloud is
        the target of ``mean[..., k, :]``): per-step clouds for :meth:`to_stonesoup`
        (``kind="particle"``) and the chain samples of any step for :meth:`to_arviz`.
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
    >>> filt = tp.SIRFilter(tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0), 100)
    >>> result = filt(torch.zeros(5, 2, 3, 2), init=torch.zeros(2, 100, 3, 4), generator=torch.Generator())
    >>> result                                        # shapes, never values
    FilterResult(mean=float32(5, 2, 3, 4), state=ParticleState(...), ...)
    >>> result.cov.shape                              # (T, B, K, D, D): each slot's posterior covariance
    torch.Size([5, 2, 3, 4, 4])
    >>> result.to_numpy()["info.ess"].shape            # a flat dict of NumPy arrays
    (5, 2)
    >>> result.meta["filter"], result.meta["settings"]
    ('SIRFilter', {'resample_method': 'systematic', 'ess_threshold': 1.0, 'exclusion': None})
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
        return result_to_xarray(self)

    def to_arviz(self, *, step: int = -1, run: int = 0) -> Any:
        """The kept chain samples of an MCMC filter at ``step`` (default the last) for run
        ``run`` as ArviZ ``InferenceData`` with ``chain`` and ``draw`` dims
        (:func:`torchmcmcpf.interop.chains_to_arviz`); a step before the last needs
        ``history``. Needs ``pip install 'torchmcmcpf[interop]'``.
        """
        return result_to_arviz(self, step=step, run=run)

    def to_stonesoup(self, *, run: int = 0, kind: str = "gaussian", start_time: Any = None,
                     dt: float | None = None, threshold: float = 0.5) -> list:
        """Stone Soup ``Track`` s of run ``run``, one per slot (and per stretch of existence
        with births and deaths), of ``GaussianState`` s (``kind="gaussian"``, from ``mean``
        and ``cov``) or ``ParticleState`` s (``kind="particle"``, from ``history``)
        (:func:`torchmcmcpf.interop.tracks_to_stonesoup`). Needs Stone Soup
        (``pip install 'torchmcmcpf[interop]'``).
        """
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
    w = torch.softmax(log_w, dim=-1).to(x.dtype)[:, None, None, :]  # (B, 1, 1, N)
    # the particles along the last dim, (B, K, D, N): the centring and the weighting then
    # broadcast over whole rows (laid out (B, N, K, D) their inner loop was D = 4 long, 1.0
    # against 0.88 ms at B = 100, N = 2000, K = 1: CHANGELOG.md, 2026-12-04)
    d = x.permute(0, 2, 3, 1) - mean.unsqueeze(-1)
    if exists is not None:
        live = exists.transpose(1, 2).unsqueeze(2)  # (B, K, 1, N)
        d = where(live, d, torch.zeros_like(d))  # dead slots hold x_death: no NaN/inf
        w = w * live.to(x.dtype)
    num = (d * w) @ d.mT  # (B, K, D, D): sum_n w_n d_n d_n^T, one batched product over n
    num = 0.5 * (num + num.transpose(-1, -2))  # symmetric to the last bit (float rounding of the product)
    mass = w.sum(-1).expand(x.shape[0], x.shape[2], 1)  # (B, K, 1)
    return num / mass.clamp(min=torch.finfo(x.dtype).tiny)[..., None]


def stack_states(states: list[ParticleState]) -> ParticleState:
    """Stack per-step states into one with a leading time dim ``T`` (``extras`` stacked too)."""
    if not states:
        raise ValueError("states is empty, expected at least one ParticleState")
    first = states[0]
    exists = None if first.exists is None else torch.stack([s.exists for s in states])  # type: ignore[misc]
    extras = None if first.extras is None else {  # a typed value (a NamedTuple of tensors) stacks field by field
        k: tree_map(lambda *ts: None if ts[0] is None else torch.stack(ts), *[s.extras[k] for s in states])  # type: ignore[index]
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

    Example
    -------
    >>> import math
    >>> import torch
    >>> from torchmcmcpf.state import ParticleState, existence_estimate
    >>> x = torch.zeros(1, 8, 2, 4)                        # (B, N, K, D)
    >>> x[..., 0] = torch.arange(8.0).view(1, 8, 1)        # particle n sits at x = n
    >>> exists = torch.zeros(1, 8, 2, dtype=torch.bool)
    >>> exists[:, :6, 0] = True                            # slot 0 exists in 6 of 8 particles
    >>> exists[:, :2, 1] = True                            # slot 1 in 2 of 8
    >>> est = existence_estimate(ParticleState(x, torch.full((1, 8), -math.log(8)), exists))
    >>> est.exists_prob, est.expected_count, est.present
    (tensor([[0.7500, 0.2500]]), tensor([1.]), tensor([[ True, False]]))
    >>> est.mean[..., 0]                                   # mean over the particles where it exists
    tensor([[2.5000, 0.5000]])
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
    num = torch.einsum("bnk,bnkd->bkd", we, where(state.exists.unsqueeze(-1), state.x,
                                                        torch.zeros_like(state.x)))
    fill = torch.zeros(state.x.shape[-1], dtype=state.x.dtype, device=state.x.device) \
        if x_death is None else x_death.to(state.x)
    mean = where(prob.unsqueeze(-1) > 0, num / prob.clamp(min=torch.finfo(w.dtype).tiny).unsqueeze(-1),
                       fill)
    return ExistenceEstimate(prob, prob.sum(-1), mean, prob > threshold)


def relabel(x: Tensor, reference: Tensor, *, exists: Tensor | None = None, reference_exists: Tensor | None = None,
            cutoff: float = 100.0, max_sweeps: int | None = None) -> tuple[Tensor, Tensor | None]:
    """Permute each particle's slots to best match a reference state (the relabelling step
    of Stephens 2000, "Dealing with label switching in mixture models").

    A multitarget posterior is (nearly) symmetric in its slot labels: a particle may hold
    target A in slot 0 and another particle target A in slot 1. Averaging slots across such
    particles puts both slot means between the targets; relabelling first makes the slot
    means means of *targets*. The cost of giving particle slot ``a`` the reference label
    ``r`` is the squared position distance, cut off at ``cutoff^2`` (OSPA-like); with
    existence flags a live slot against an absent reference slot, or a dead slot against a
    present one, costs ``cutoff^2 / 2`` and two absent ones 0. A particle keeps its own labels
    unless the permutation found lowers its cost by more than ``(cutoff / 4)^2`` (625 m^2 at
    the default cutoff): where targets are too close for positions to tell them apart, a
    particle's own labels are the better guess of identity. Where every slot's cheapest
    label differs, that permutation is optimal and one pass finds it; the other particles go
    through a search that swaps the pair of labels lowering a particle's cost most, sweep
    after sweep (vectorised over them; one host check per sweep ends it when none improves),
    so it reaches a permutation no single swap improves: the optimal one when labels are
    exchanged in pairs, the usual case after targets cross.

    Parameters
    ----------
    x : (B, N, K, D) particles (positions at the ``X``, ``Y`` indices).
    reference : (B, K, D).
    exists : (B, N, K) bool, optional; reference_exists : (B, K) bool, optional (present
        reference slots; default all).
    cutoff : [m] > 0.
    max_sweeps : at most this many swaps per particle (default ``K (K - 1) / 2``).

    Returns
    -------
    x : (B, N, K, D) with ``x[b, n, r]`` the slot given label ``r``; exists : the flags
    permuted alike (None without).
    """
    b, n, k, _ = x.shape
    if k < 2:
        return x, exists
    slot_of = relabel_order(x, reference, exists=exists, reference_exists=reference_exists, cutoff=cutoff,
                            max_sweeps=max_sweeps)
    x = take_along(x, slot_of.unsqueeze(-1), 2)
    return x, None if exists is None else take_along(exists, slot_of, 2)


def relabel_order(x: Tensor, reference: Tensor, *, exists: Tensor | None = None,
                  reference_exists: Tensor | None = None, cutoff: float = 100.0,
                  max_sweeps: int | None = None) -> Tensor:
    """The permutation :func:`relabel` applies: ``slot_of (B, N, K)`` int64, the particle slot
    that carries reference label ``r`` (``x.take_along_dim(slot_of[..., None], 2)`` is the
    relabelled cloud). Same arguments as :func:`relabel`; for anything with slots in dim 2
    that should follow the positions' labels (the chains of a convergence check, say).
    """
    b, n, k, _ = x.shape
    if k < 2:
        return torch.zeros((b, n, k), dtype=torch.int64, device=x.device)
    if tuple(reference.shape) != (b, k, x.shape[-1]):
        raise ValueError(f"reference has shape {tuple(reference.shape)}, expected {(b, k, x.shape[-1])}")
    if not cutoff > 0:
        raise ValueError(f"cutoff must be > 0, got {cutoff!r}")
    pos = torch.stack([x[..., X], x[..., Y]], -1).reshape(b, n * k, 2)
    ref = torch.stack([reference[..., X], reference[..., Y]], -1).to(x.dtype)  # (B, K, 2)
    # |p - r|^2 = |p|^2 + |r|^2 - 2 p.r: one batched product, not a (B, N, K, K, 2) difference
    norms = squared_norm(pos).unsqueeze(-1) + squared_norm(ref).unsqueeze(1)  # (B, N K, K)
    cost = torch.baddbmm(norms, pos, ref.mT, alpha=-2.0).clamp_(min=0.0, max=cutoff**2).reshape(b, n, k, k)
    if exists is not None or reference_exists is not None:
        e = torch.ones((b, n, k), dtype=torch.bool, device=x.device) if exists is None else exists
        r = torch.ones((b, k), dtype=torch.bool, device=x.device) if reference_exists is None else reference_exists
        live, present = e.unsqueeze(-1), r[:, None, None, :]
        cost = where(live & present, cost,
                           where(live ^ present, torch.full_like(cost, cutoff**2 / 2), torch.zeros_like(cost)))
    # Where every slot's cheapest label is a different one, that permutation is optimal (each
    # slot at its row minimum): one pass settles most particles. The others (two slots
    # nearest to one label: the targets they hold are close) go through the swap search.
    nearest = cost.argmin(-1)  # (B, N, K)
    distinct = (nearest.sort(-1).values == torch.arange(k, device=x.device)).all(-1)  # (B, N): a permutation
    label = where(distinct.unsqueeze(-1), nearest, torch.arange(k, device=x.device))
    # No permutation costs less than the sum of the row minima, so a particle whose own labels
    # cost at most (cutoff / 4)^2 more than that keeps them below whatever a search finds:
    # it needs none (most particles of a cloud, and every chain state whose absent slots
    # share x_death, where the row minima tie and no permutation is distinct).
    settled = (torch.diagonal(cost, dim1=-2, dim2=-1) - cost.amin(-1)).sum(-1) <= (cutoff / 4) ** 2
    rows = (~distinct & ~settled).flatten().nonzero().squeeze(1)  # one host read: the particles left
    if rows.numel():
        c_rows, l_rows = cost.reshape(b * n, k, k)[rows], label.reshape(b * n, k)[rows]
        # a row equal to the one before it (an MCMC chain's repeated state) gets its labels: the
        # search is a function of the row alone, so it runs on the first of each run of equal rows
        first = torch.ones(rows.shape, dtype=torch.bool, device=x.device)
        first[1:] = (c_rows[1:] != c_rows[:-1]).flatten(1).any(-1) | (l_rows[1:] != l_rows[:-1]).any(-1)
        sub = _swap_search(c_rows[first], l_rows[first], cutoff, k * (k - 1) // 2 if max_sweeps is None else max_sweeps)
        label = label.reshape(b * n, k).index_copy(0, rows, sub[first.cumsum(0) - 1]).reshape(b, n, k)
    # a particle keeps its own labels unless relabelling lowers its cost by more than
    # (cutoff / 4)^2: where two targets are close, the positions alone cannot tell which is
    # which, and a particle's own labels carry their identity through the crossing
    own = torch.arange(k, device=x.device).expand(b, n, k)
    gain = (take_along(cost, own.unsqueeze(-1), -1) - take_along(cost, label.unsqueeze(-1), -1))
    label = where((gain.sum((-2, -1)) <= (cutoff / 4) ** 2).unsqueeze(-1), own, label)
    return torch.argsort(label, -1)  # label r is carried by particle slot slot_of[r]


def _swap_search(cost: Tensor, label: Tensor, cutoff: float, sweeps: int) -> Tensor:
    """Pairwise label swaps of :func:`relabel` on ``cost (P, K, K)`` from ``label (P, K)``
    (particle slot ``a`` carries ``label[a]``): each sweep makes, in every row, the swap that
    lowers its cost most, until none does. Returns the labels ``(P, K)``.

    A row that no swap improves is done (nothing it depends on changes), so each sweep works
    on the rows the previous one changed only: the same labels as sweeping every row, at the
    cost of the rows still moving (the R-hat window of a births/deaths step sends ~70,000
    chain states through the first sweep and few through the later ones).
    """
    pair = torch.ones((label.shape[-1],) * 2, dtype=torch.bool, device=cost.device).triu(1)
    active = torch.arange(label.shape[0], device=label.device)  # the rows still moving
    act_cost, act_label = cost, label
    for _ in range(sweeps):  # sweeps, not slots
        p, k = act_label.shape
        # [a, c] = cost[a, label[c]]
        cross = take_along(act_cost, act_label.unsqueeze(-2).expand(p, k, k), -1)
        own = torch.diagonal(cross, dim1=-2, dim2=-1)  # (P, K)
        gain = own.unsqueeze(-1) + own.unsqueeze(-2) - cross - cross.mT  # swap a <-> c
        gain = where(pair, gain, torch.zeros_like(gain)).flatten(-2)
        best, at = gain.max(-1)  # (P,)
        moving = (best > 1e-9 * cutoff**2).nonzero().squeeze(1)  # one host read a sweep
        if not moving.numel():
            break
        at, act_cost, act_label, active = at[moving], act_cost[moving], act_label[moving], active[moving]
        a, c = (at // k).unsqueeze(-1), (at % k).unsqueeze(-1)
        la, lc = take_along(act_label, a, -1), take_along(act_label, c, -1)
        act_label = act_label.scatter(-1, a, lc).scatter(-1, c, la)
        label = label.index_copy(0, active, act_label)
    return label


class _Runs(NamedTuple):
    """The runs of equal consecutive particles of a cloud (an MCMC chain's rejected moves repeat
    its state: 80 % of an IP-MCMC-PF cloud on the births/deaths scene), for the estimate's
    per-particle searches, which are functions of a particle alone: made once per cloud
    (:func:`_runs`), each search then runs on the first particle of each run and copies.

    Attributes
    ----------
    firsts : (B, m) int64, the first particle of each run in order, then (beyond the run's own
        count) any particles, never read; rank : (B, N) int64, the run of each particle.
    x : (B, m, K, D), exists : (B, m, K) bool or None: those particles.
    """

    firsts: Tensor
    rank: Tensor
    x: Tensor
    exists: Tensor | None


def _runs(x: Tensor, exists: Tensor | None) -> _Runs | None:
    """:class:`_Runs` of a cloud ``x (B, N, K, D)`` with optional ``exists (B, N, K)``, by
    position and flags (what the relabelling reads); None where the runs would save less than a
    fifth (an MCMC-PF cloud of 2-sample chains). One host read (the most runs in one batch row).
    """
    b, n = x.shape[:2]
    pos = torch.stack([x[..., X], x[..., Y]], -1)
    first = torch.ones((b, n), dtype=torch.bool, device=x.device)
    first[:, 1:] = (pos[:, 1:] != pos[:, :-1]).flatten(2).any(-1)  # NaN differs: kept, never merged
    if exists is not None:
        first[:, 1:] |= (exists[:, 1:] != exists[:, :-1]).any(-1)
    rank = first.cumsum(1) - 1  # (B, N)
    m = int(rank[:, -1].max()) + 1  # one host read
    if 5 * m >= 4 * n:
        return None
    at = where(first, torch.arange(n, device=x.device), n + torch.arange(n, device=x.device))
    firsts = at.sort(-1).values[:, :m].remainder_(n)  # (B, m)
    return _Runs(firsts, rank, take_along(x, firsts[:, :, None, None], 1),
                 None if exists is None else take_along(exists, firsts[:, :, None], 1))


def _relabel_order_runs(x: Tensor, reference: Tensor, runs: _Runs | None, **kwargs: Any) -> Tensor:
    """:func:`relabel_order` of ``x (B, N, K, D)`` (keywords as there, ``exists`` included),
    computed on the first particle of each of its ``runs`` and copied to the repeats: the same
    permutations (each a function of its particle, its flags and the reference alone).
    """
    if runs is None:
        return relabel_order(x, reference, **kwargs)
    kwargs["exists"] = runs.exists
    order = relabel_order(runs.x, reference, **kwargs)
    return take_along(order, runs.rank.unsqueeze(-1), 1)


def _densest(pos: Tensor, runs: _Runs | None, slot_of: Tensor, live: Tensor, log_w: Tensor, cutoff: float,
             candidates: int = 32) -> tuple[Tensor, Tensor]:
    """The densest place of the live slots of a relabelled cloud: among the live slots of
    ``candidates`` evenly spaced particles, the one with the most weight of live slots within
    ``cutoff`` (each counted once per particle); ties go to the first in label order.

    Only the candidates' live slots are measured against the cloud (a few percent of their
    slots on the births/deaths scene: the spare slots of the estimate's search), each pair's
    distance alone (:func:`torch.cdist` without the matrix product), so the support of a slot
    does not depend on which other slots are measured with it.

    Parameters
    ----------
    pos : (B, N, K, 2) the cloud's positions in its own slot order.
    runs : the cloud's :class:`_Runs` (the distances are taken to the first particle of each run,
        and each particle gets its run's test), or None (every particle).
    slot_of : (B, N, K) int64, the relabelling (:func:`relabel_order`: label ``r`` is carried by
        slot ``slot_of[..., r]``); live : (B, N, K) bool in label order; log_w : (B, N).
    cutoff : [m] > 0; candidates : how many particles offer their slots.

    Returns
    -------
    at : (B, 2) that slot's position; support : (B,) the weight of the particles with a live
    slot within ``cutoff`` of it (0 where no slot is live: ``at`` is then the first candidate's
    label-0 slot).
    """
    b, n, k = live.shape
    dtype = pos.dtype
    pick = torch.linspace(0, n - 1, min(candidates, n), device=pos.device).round().to(torch.int64)
    p = pick.numel()
    own_live = torch.zeros_like(live).scatter(2, slot_of, live)  # the particles' own slot order
    cand_live = own_live[:, pick].reshape(b, p * k)
    s = int(cand_live.sum(-1).max())  # one host read: the most live candidate slots of a batch row
    idx = flagged_first(cand_live)[:, :s]  # (B, S): each row's live candidate slots, then padding
    valid = take_along(cand_live, idx, -1)
    cand_pos = pos[:, pick].reshape(b, p * k, 2)  # own slot order
    at_own = take_along(cand_pos, idx.unsqueeze(-1), 1)  # (B, S, 2)
    sub, sub_live = (pos, own_live) if runs is None else \
        (take_along(pos, runs.firsts[:, :, None, None], 1), take_along(own_live, runs.firsts.unsqueeze(-1), 1))
    m = sub.shape[1]
    dist = torch.cdist(at_own, sub.reshape(b, m * k, 2), compute_mode="donot_use_mm_for_euclid_dist")
    near = ((dist <= cutoff).reshape(b, s, m, k) & sub_live.unsqueeze(1)).any(-1)  # (B, S, m): a live slot near
    if runs is not None:  # each particle the test of its run's first
        near = near.gather(2, runs.rank.unsqueeze(1).expand(b, s, n))  # (B, S, N)
    w = torch.softmax(log_w, -1).to(dtype)
    # w where near, else 0: the values of near * w (w finite, >= 0) without a float copy of near
    found = where(near, w.unsqueeze(1), 0.0).sum(-1).masked_fill(~valid, 0.0)  # (B, S)
    # into label order (candidate c's own slot j carries label r where slot_of[c, r] = j); the pad
    # goes to a column past the end, dropped
    order = slot_of[:, pick]  # (B, P, K)
    label_of = torch.empty_like(order).scatter_(-1, order, torch.arange(k, device=pos.device).expand(b, p, k))
    flat = (label_of + k * torch.arange(p, device=pos.device).unsqueeze(-1)).reshape(b, p * k)
    dest = where(valid, take_along(flat, idx, -1), p * k)
    support = torch.zeros((b, p * k + 1), dtype=dtype, device=pos.device).scatter_(1, dest, found)[:, :p * k]
    best = support.argmax(-1)  # (B,)
    cand, slot = best // k, best % k
    own = take_along(order.reshape(b, p * k), (k * cand + slot).unsqueeze(-1), -1)  # (B, 1): its own slot
    at = take_along(cand_pos, (k * cand.unsqueeze(-1) + own).unsqueeze(-1), 1).squeeze(1)
    return at, take_along(support, best[:, None], 1).squeeze(1)


def relabelled_estimate(state: ParticleState, reference: Tensor | None = None, *,
                        reference_exists: Tensor | None = None, x_death: Tensor | None = None,
                        iterations: int = 2, cutoff: float = 100.0) -> tuple[ExistenceEstimate, ParticleState]:
    """The slot estimates of a cloud after relabelling its particles (:func:`relabel`):
    the default estimate of every filter with two or more slots.

    Starting from ``reference`` (default: the heaviest particle, whose labels are consistent
    by construction), each of ``iterations`` rounds relabels the particles against the
    current estimate and recomputes it (Stephens 2000's algorithm); a filter passes its
    previous estimate, predicted, so that the labels also stay the same over time.

    Parameters
    ----------
    state : ParticleState ``x (B, N, K, D)``, ``log_w (B, N)``, optional ``exists (B, N, K)``.
    reference : (B, K, D), optional; reference_exists : (B, K) bool, optional.
    x_death : (D,) for slots that exist in no particle (with existence).
    iterations : relabelling rounds (0: the plain estimate); cutoff : [m], as :func:`relabel`.

    Returns
    -------
    estimate : :class:`ExistenceEstimate` of the relabelled cloud (without existence flags:
    ``exists_prob`` ones and ``mean`` the weighted mean of the slots within ``cutoff`` of the
    label's reference where they hold at least half of the weight, else of those beyond it).
    With existence flags, a label's mean and existence probability count only the particles
    whose slot of that label lies within ``cutoff`` of the label's reference (a particle
    holding two slots on one target and none on another does not pull a mean half-way to the
    wrong target); ``expected_count`` is the expected number of live slots.
    relabelled : the relabelled cloud (a ParticleState, its slots in the estimate's labels;
    with existence, its flags those the estimate counted).
    """
    x, log_w, exists = state.x, state.log_w, state.exists
    b, n, k, d = x.shape
    present = reference_exists
    ref: Tensor | None = reference
    if reference is None and iterations > 0 and k > 1:  # one particle's labels are consistent: the heaviest one's
        # (no rounds or one slot: the reference is not read, so not made)
        best = log_w.argmax(-1)[:, None, None]
        ref = take_along(x, best[..., None], 1).squeeze(1)
        present = None if exists is None else take_along(exists, best, 1).squeeze(1)
    # the relabelling's searches once per run of equal particles (an MCMC cloud's repeats)
    runs = _runs(x, exists) if iterations > 0 and k > 1 else None
    unchanged: Tensor | None = None  # a relabelling order still valid for (ref, present)
    if exists is not None and present is not None and ref is not None and k > 1:
        # labels the reference has no target for: the densest place of the live slots the
        # present labels leave over (relabelled against them first) founds one new label per
        # round (one host read a round ends the search), so a target that appeared since the
        # reference gets one label in every particle, not a share of each, and a stray slot
        # of one particle founds none
        ref, present = ref.clone(), present.clone()
        pos = torch.stack([x[..., X], x[..., Y]], -1)
        for _ in range(k if iterations > 0 else 0):  # one new label a round, while one is found
            slot_of = _relabel_order_runs(x, ref, runs, exists=exists, reference_exists=present, cutoff=cutoff)
            unchanged = slot_of  # the order for (ref, present) as they are, until a label is founded
            spare = take_along(exists, slot_of, 2) & ~present.unsqueeze(1)  # (B, N, K), label order
            at, support = _densest(pos, runs, slot_of, spare, log_w, cutoff)
            new = (~present).to(torch.int64).argmax(-1)  # (B,): the first absent label
            found = (support > 0.5) & (~present).any(-1)  # most of the weight has a slot there
            onto = found.unsqueeze(-1) & (torch.arange(k, device=x.device) == new.unsqueeze(-1))  # (B, K)
            ref[..., X] = where(onto, at[:, None, 0].to(ref.dtype), ref[..., X])
            ref[..., Y] = where(onto, at[:, None, 1].to(ref.dtype), ref[..., Y])
            present = present | onto
            if not bool(found.any()):
                break
            unchanged = None
    out = None
    xr, er = x, exists
    for _ in range(max(1, int(iterations))):
        near = None  # (B, N, K): the slots within the cutoff of their label's reference
        if iterations > 0 and k > 1:
            assert ref is not None  # made above when there are rounds and slots to relabel
            # the search's last round founded no label: its order is this round's (the same
            # reference and flags), not searched again
            slot_of = _relabel_order_runs(x, ref, runs, exists=exists, reference_exists=present, cutoff=cutoff) \
                if unchanged is None else unchanged
            unchanged = None
            xr = take_along(x, slot_of.unsqueeze(-1), 2)  # as relabel
            er = None if exists is None else take_along(exists, slot_of, 2)
            pos, at = torch.stack([xr[..., X], xr[..., Y]], -1), torch.stack([ref[..., X], ref[..., Y]], -1)
            near = squared_norm(pos - at.unsqueeze(1).to(pos.dtype)) <= cutoff**2
        if exists is None:
            if near is None:
                mean = weighted_mean(xr, log_w)
            else:
                # the mean of the slots on the side of the cutoff that holds most of the label's
                # weight (the two sides' weights sum to one): near its reference, unless most
                # particles moved the slot away (a re-capture after two slots had coalesced on
                # one target), where the label follows them
                gated = existence_estimate(ParticleState(xr, log_w, near))
                moved = existence_estimate(ParticleState(xr, log_w, ~near))
                mean = where((gated.exists_prob >= 0.5).unsqueeze(-1), gated.mean, moved.mean)
            ones = torch.ones((b, k), dtype=x.dtype, device=x.device)
            out = ExistenceEstimate(ones, ones.sum(-1), mean, ones > 0)
        else:
            assert er is not None  # the relabelled flags of a cloud with flags
            eg = er
            if near is not None and present is not None:
                # a live slot farther than the cutoff from its label's reference holds another
                # target (a particle with two slots on one target and none on another): it
                # counts neither in this label's mean nor in its existence; a label without a
                # reference (no target founded for it) reports none
                eg = er & near & present.unsqueeze(1)
            out = existence_estimate(ParticleState(xr, log_w, eg), x_death=x_death)
            # the expected number of targets stays the filter's: the expected number of live slots
            count = (torch.softmax(log_w, -1).to(x.dtype).unsqueeze(-1) * er.to(x.dtype)).sum((1, 2))
            out = out._replace(expected_count=count)
            er_out = eg
        ref, present = out.mean, out.present if exists is not None else None
    assert out is not None
    return out, state._replace(x=xr, exists=er_out if exists is not None else er)


torch.serialization.add_safe_globals([ParticleState, StepInfo, FilterResult, ExistenceEstimate])
