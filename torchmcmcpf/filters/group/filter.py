"""The group filter's driver: :class:`GroupMCMCFilter`, a :class:`~torchmcmcpf.filters.base.Filter`
whose step is :func:`~torchmcmcpf.filters.group.step.group_mcmc_bound_step` on the object
:func:`~torchmcmcpf.filters.group.step.bind_group` binds once, at construction.

The maths, the moves' targets and acceptance ratios: the docstring of :mod:`torchmcmcpf.filters.group`.
"""

from __future__ import annotations

import inspect
import math
from typing import Any

import torch

from ..._native.select import where
from ..._validation import check_positive_int, check_shape
from ...models.group import (
    GroupExistence,
    GroupStructurePrior,
    VirtualLeaderMotion,
    bell_number,
    pairwise_kalman_init,
)
from ...models.sensors.pixels import ThresholdedPixels
from ...state import ParticleState
from ...typing import Tensor
from .._carry import check_carries
from ..base import Filter
from .moves import Models
from .settings import GroupMCMCSettings, default_chains, estimate_step_bytes
from .state import KEY, GroupPath, GroupState
from .step import bind_group, group_mcmc_bound_step

__all__ = ["GroupMCMCFilter"]


class GroupMCMCFilter(Filter):
    """Marginalised MCMC-based particle filter for coordinated groups (paper 004, sec. 4):
    :func:`~torchmcmcpf.filters.group.step.group_mcmc_bound_step` on the filter's
    :func:`~torchmcmcpf.filters.group.step.bind_group` (bound once, at construction).

    Parameters
    ----------
    motion : VirtualLeaderMotion (eqs. 1-16); sensor : ThresholdedPixels (eqs. 39-41) or
        a pixel sensor with ``shape``, ``pixel_size``, ``position_index``.
    num_particles : N, a multiple of ``num_chains``.
    existence : GroupExistence (eq. 25, births eqs. 29-37); structure_prior :
        GroupStructurePrior (eq. 19), the transition of the group structure: a model like the
        others, handed to the base as ``models={"structure_prior": ...}`` (registered as a
        submodule, passed to :func:`~torchmcmcpf.filters.group.step.bind_group`, which checks
        the classes of the models). The motion is a whole-configuration
        :class:`~torchmcmcpf.models.base.Motion` whose slots are not exchangeable, so the
        estimate never relabels them; the state carries a typed
        :class:`~torchmcmcpf.filters.group.GroupState`.
    settings : :class:`GroupMCMCSettings`, optional; each of its fields is also a keyword
        shortcut (``burn_in=50``), with its default written once, in the dataclass, except
        ``num_chains``, whose default depends on N: :func:`default_chains` (the largest
        divisor of N up to 20) unless ``settings`` is given.
    compile_step : compile each move (``torch.compile(fullgraph=True)``; noise drawn
        eagerly, so compiled == eager).

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf import GroupMCMCFilter
    >>> from torchmcmcpf.scenarios.group_merge import group_merge
    >>> scn = group_merge(2, generator=torch.Generator().manual_seed(0), num_steps=3)
    >>> filt = GroupMCMCFilter(scn.motion, scn.sensor, 40, existence=scn.existence,
    ...                        structure_prior=scn.structure_prior, burn_in=10)
    >>> filt.settings.num_chains
    20
    >>> res = filt(scn.frames, init=filt.init_inactive(2), generator=torch.Generator().manual_seed(1))
    >>> res.info.extras["structure_prob"].shape  # (T, B, Bell(4)): the probability of each structure
    torch.Size([3, 2, 15])
    >>> res.exists_prob.shape  # (T, B, K)
    torch.Size([3, 2, 4])
    """

    motion: VirtualLeaderMotion  # type: ignore[assignment]  # a whole-configuration Motion
    structure_prior: GroupStructurePrior
    sensor: ThresholdedPixels
    existence: GroupExistence
    #: the state carries its group fields as one :class:`~torchmcmcpf.filters.group.GroupState`
    #: under ``extras["group"]`` (package docstring, "State and outputs")
    state_extras = frozenset({KEY})
    settings_class = GroupMCMCSettings
    bind = staticmethod(bind_group)
    bound_step = staticmethod(group_mcmc_bound_step)

    def __init__(self, motion: VirtualLeaderMotion, sensor: ThresholdedPixels, num_particles: int,
                 settings: GroupMCMCSettings | None = None, *, existence: GroupExistence,
                 structure_prior: GroupStructurePrior, compile_step: bool = False, **shortcuts: Any) -> None:
        if not isinstance(motion, VirtualLeaderMotion):
            raise ValueError(f"motion must be a VirtualLeaderMotion, got {type(motion).__name__}")
        if not all(hasattr(sensor, a) for a in ("shape", "pixel_size", "position_index", "log_likelihood")):
            raise ValueError(f"sensor must be a pixel sensor (ThresholdedPixels), got {type(sensor).__name__}")
        n = check_positive_int(num_particles, "num_particles")
        if shortcuts.get("num_chains", 0) is None:
            del shortcuts["num_chains"]
        if settings is None and "num_chains" not in shortcuts:  # the one default that depends on N
            shortcuts["num_chains"] = default_chains(n)
        if "past_step" in shortcuts:
            shortcuts["past_step"] = tuple(shortcuts["past_step"])
        super().__init__(motion, sensor, n, settings, existence=existence,  # type: ignore[arg-type]
                         compile_step=compile_step, models={"structure_prior": structure_prior}, **shortcuts)

    def models(self) -> Models:
        """The models and proposal constants the moves are bound to (``filt.bound.dynamics``)."""
        return self.bound.dynamics

    # -- state ---------------------------------------------------------------------------
    def check_memory(self, batch_size: int, num_slots: int) -> None:
        """Refuse (``ValueError`` with the estimate) a problem whose step would need more than
        ``max_memory_gb`` (:func:`estimate_step_bytes`), before anything is allocated.
        """
        need = estimate_step_bytes(batch_size, self.num_particles, num_slots, lag=self.settings.lag)
        if need > self.settings.max_memory_gb * 2**30:
            raise ValueError(
                f"num_slots={num_slots} with batch_size={batch_size} and num_particles={self.num_particles} needs "
                f"about {need / 2**30:.1f} GiB per step (Bell({num_slots}) = {bell_number(num_slots)} group "
                f"structures), above max_memory_gb={self.settings.max_memory_gb:g}; use fewer slots (N_max) or "
                "particles, or raise max_memory_gb")

    def init(self, particles: Tensor, exists: Tensor | None = None,  # type: ignore[override]
             labels: Tensor | None = None) -> ParticleState:
        """Wrap initial particles ``(B, N, K, 4)`` (``[x, vx, y, vy]``; ``exists (B, N, K)``,
        default all inactive; ``labels (B, N, K)``, default each slot its own group) into a
        state with exact (zero-covariance) Kalman statistics: velocities from ``particles``,
        leaders at ``v_death``.
        """
        self._check_state_tensors(particles, exists)
        b, n, k, _ = particles.shape
        self.check_memory(b, k)
        for t in list(self.buffers()) + list(self.parameters()):  # init reads the models (x_death, v_death)
            if t.device != particles.device:
                raise ValueError(f"the models' parameters are on {t.device}, expected {particles.device} (the device "
                                 "of init); move them with filt.to(device)")
        if exists is None:
            exists = torch.zeros((b, n, k), dtype=torch.bool, device=particles.device)
        if labels is None:
            labels = torch.arange(k, device=particles.device).expand(b, n, k)
        check_shape(labels, "init.labels", (b, n, k))
        exists = exists.to(torch.bool)
        x = where(exists.unsqueeze(-1), particles, self.existence.x_death.to(particles))
        st = pairwise_kalman_init((b, n), k, existence=self.existence, dtype=particles.dtype, device=particles.device)
        w_mean = st.mean.clone()
        w_mean[..., :k] = x[..., 1::2].transpose(-1, -2)
        labels = labels.to(torch.int64).contiguous()
        h, w = self.sensor.shape
        lag, p, path = self.settings.lag, 1, None
        if lag:
            # all inactive: a past of L inactive steps (empty frames) is the same start, and the state
            # has its final shapes from the first step on (compiled moves compile once)
            p = lag + 1 if not bool(exists.any()) else 1
            path = GroupPath(x[..., 0::2].unsqueeze(2).expand(b, n, p, k, 2).clone(),
                             labels.unsqueeze(2).expand(b, n, p, k).clone(),
                             exists.unsqueeze(2).expand(b, n, p, k).clone(), x.new_zeros((b, n, p)), w_mean.clone(),
                             st.cov.clone())
        frames = torch.zeros((b, p - 1, h, w), dtype=torch.bool, device=particles.device)
        group = GroupState(labels, w_mean, st.cov, frames, path)
        return ParticleState(x, particles.new_full((b, n), -math.log(n)), exists, {KEY: group})

    def init_inactive(self, batch_size: int, num_slots: int = 4, *, dtype: torch.dtype = torch.float64,
                      device: torch.device | str | None = None) -> ParticleState:
        """``K = num_slots`` slots, all inactive in every particle of every run (paper 004 sec. 5).
        Refuses a ``num_slots`` whose ``Bell(K)`` structures do not fit ``max_memory_gb``.
        """
        b = check_positive_int(batch_size, "batch_size")
        k = check_positive_int(num_slots, "num_slots")
        self.check_memory(b, k)
        return self.init(torch.zeros((b, self.num_particles, k, 4), dtype=dtype, device=device))

    def _as_state(self, init: Tensor | ParticleState) -> ParticleState:
        state = super()._as_state(init)
        if state.extras is None:  # a plain ParticleState: the group fields start as init's
            state = self.init(state.x, state.exists)._replace(log_w=state.log_w)
        return state

    def check_extras(self, state: ParticleState) -> None:
        """The group fields of a state: ``extras["group"]`` a :class:`GroupState` whose fields
        fit ``x (B, N, K, 4)`` and the sensor's frames (:meth:`GroupState.check`), and
        existence flags; a ``ValueError`` naming the field otherwise.
        """
        if state.exists is None:
            raise ValueError("state.exists is None; the group filter's state has existence flags (filt.init)")
        if KEY not in (state.extras or {}):
            raise ValueError(f"state.extras has no {KEY!r}, expected a GroupState (build the state with filt.init "
                             "or filt.init_inactive)")
        check_carries(state, self.carry_sizes())

    def carry_sizes(self) -> dict[str, dict[str, Any]]:
        """:meth:`Filter.carry_sizes`: the sensor's frame shape ``(H, W)`` of :class:`GroupState`."""
        h, w = self.sensor.shape
        return {KEY: {"frame_shape": (h, w)}}

    def validate(self, state: ParticleState, measurements: Any, *, sequence: bool,
                 name: str = "measurements") -> None:
        """:meth:`Filter.validate`, the group fields (:meth:`check_extras`) and the memory
        estimate (:meth:`check_memory`).
        """
        super().validate(state, measurements, sequence=sequence, name=name)
        self.check_extras(state)
        self.check_memory(state.batch_size, state.num_targets)


def _group_signature() -> inspect.Signature:
    """The constructor's signature (``help``, the documentation): the common one of
    :class:`Filter` with its settings' fields, ``existence`` and ``structure_prior`` required.
    """
    sig = inspect.signature(GroupMCMCFilter)
    params = [p.replace(default=inspect.Parameter.empty) if p.name == "existence" else p
              for p in sig.parameters.values()]
    at = [p.name for p in params].index("existence") + 1
    params.insert(at, inspect.Parameter("structure_prior", inspect.Parameter.KEYWORD_ONLY))
    return sig.replace(parameters=params)


GroupMCMCFilter.__signature__ = _group_signature()  # type: ignore[attr-defined]
