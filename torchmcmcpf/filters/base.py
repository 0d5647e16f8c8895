"""The ``Filter`` base: a thin ``nn.Module`` around a pure step function.

A filter holds models and settings; the filtering state is passed in and returned, never
stored on the module, so filters are reentrant and their steps compile.
"""

from __future__ import annotations

from typing import Any, Optional, Union

import torch
from torch import nn
from torch.utils._pytree import tree_map

from .._validation import check_finite, check_generator, check_shape, check_tensor
from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath, existence_estimate
from ..state import FilterResult, ParticleState, StepInfo, stack_infos
from ..typing import Measurement, Tensor

__all__ = ["Filter", "check_existence"]


def check_existence(existence) -> Optional[BirthDeath]:
    """``existence`` must be a :class:`~torchmcmcpf.models.existence.BirthDeath` or ``None``."""
    if existence is not None and not isinstance(existence, BirthDeath):
        raise ValueError(f"existence must be a BirthDeath model or None, got {type(existence).__name__}")
    return existence


def _num_steps(measurements: Measurement) -> int:
    leaves = [measurements] if torch.is_tensor(measurements) else list(measurements)
    if not leaves or not all(torch.is_tensor(t) and t.dim() >= 1 for t in leaves):
        raise ValueError(
            "measurements must be a tensor (T, B, ...) or a tuple of such tensors, "
            f"got {type(measurements).__name__}"
        )
    t = leaves[0].shape[0]
    if any(leaf.shape[0] != t for leaf in leaves):
        raise ValueError(f"measurements have different time lengths: {[tuple(x.shape) for x in leaves]}")
    return t


class Filter(nn.Module):
    """Base of every particle filter in torchmcmcpf.

    Subclasses set ``motion``, ``sensor``, ``num_particles`` (and ``existence``, a
    ``BirthDeath`` model, for an unknown number of targets) and implement :meth:`step`.

    Usage
    -----
    >>> result = filt(measurements, init=particles, generator=g)   # doctest: +SKIP
    >>> result.mean.shape                                           # (T, B, K, D)
    """

    motion: MotionModel
    sensor: SensorModel
    num_particles: int
    existence: Optional[BirthDeath]  # set by filters with births and deaths (None: known K)

    def __init__(self, motion: MotionModel, sensor: SensorModel):
        super().__init__()
        if not isinstance(motion, MotionModel):
            raise ValueError(f"motion must be a MotionModel, got {type(motion).__name__}")
        if not isinstance(sensor, SensorModel):
            raise ValueError(f"sensor must be a SensorModel, got {type(sensor).__name__}")
        self.motion = motion
        self.sensor = sensor

    # -- state ---------------------------------------------------------------------------
    def init(self, particles: Tensor, exists: Optional[Tensor] = None) -> ParticleState:
        """Wrap an initial cloud into an equally weighted ``ParticleState``.

        Parameters
        ----------
        particles : (B, N, K, D) with N = ``num_particles`` and D = ``motion.dim``.
        exists : (B, N, K) bool, optional.

        Returns
        -------
        ParticleState with ``log_w = -log N``.
        """
        check_shape(particles, "init", (None, self.num_particles, None, self.motion.dim))
        if particles.shape[0] == 0 or particles.shape[2] == 0:
            raise ValueError(f"init has shape {tuple(particles.shape)}, expected B >= 1 and K >= 1")
        check_finite(particles, "init")
        if exists is not None:
            check_shape(exists, "exists", tuple(particles.shape[:3]))
            exists = exists.to(torch.bool)
        b, n = particles.shape[:2]
        log_w = torch.full((b, n), -torch.log(torch.tensor(float(n))).item(), device=particles.device,
                           dtype=particles.dtype)
        return ParticleState(particles, log_w, exists)

    def _as_state(self, init: Union[Tensor, ParticleState]) -> ParticleState:
        if isinstance(init, ParticleState):
            check_shape(init.log_w, "init.log_w", tuple(init.x.shape[:2]))
            state = self.init(init.x, init.exists)
            return state._replace(log_w=init.log_w)
        return self.init(check_tensor(init, "init"))

    def estimate(self, state: ParticleState) -> Tensor:
        """MMSE estimate ``(B, K, D)`` of a state (paper 000 eq. 6); with existence, each
        slot's mean given that it exists (:func:`~torchmcmcpf.models.existence.existence_estimate`)."""
        existence = getattr(self, "existence", None)
        if existence is None or state.exists is None:
            return state.mean()
        return existence_estimate(state, x_death=existence.x_death).mean

    # -- one step ------------------------------------------------------------------------
    def step(self, state: ParticleState, z: Measurement, *, generator: torch.Generator
             ) -> tuple[ParticleState, StepInfo]:
        """Advance ``state`` by one measurement ``z (B, *G)``; returns ``(state, info)``."""
        raise NotImplementedError

    # -- a whole sequence ----------------------------------------------------------------
    def forward(
        self,
        measurements: Measurement,
        *,
        init: Union[Tensor, ParticleState],
        generator: torch.Generator,
        progress: Optional[bool] = None,
    ) -> FilterResult:
        """Filter a sequence of T measurements.

        Parameters
        ----------
        measurements : (T, B, *G) tensor, or a tuple of tensors with leading (T, B)
            (e.g. point measurements and their mask).
        init : (B, N, K, D) initial particles, or a ``ParticleState``.
        generator : the only source of randomness.
        progress : show a tqdm progress bar over time.

        Returns
        -------
        FilterResult with ``mean (T, B, K, D)``, the final state and stacked ``StepInfo``.
        """
        check_generator(generator)
        state = self._as_state(init)
        num_steps = _num_steps(measurements)
        steps: Any = range(num_steps)
        if progress:
            from tqdm.auto import tqdm

            steps = tqdm(steps, desc=type(self).__name__, leave=False)
        means, infos, exists_prob = [], [], []
        for t in steps:
            z = tree_map(lambda a: a[t], measurements)
            self.sensor.validate(z, state.batch_size, f"measurements[{t}]")
            state, info = self.step(state, z, generator=generator)
            means.append(self.estimate(state))
            infos.append(info)
            if state.exists is not None:
                w = torch.softmax(state.log_w, -1)
                exists_prob.append(torch.einsum("bn,bnk->bk", w, state.exists.to(w.dtype)))
        info = stack_infos(infos)
        log_evidence = None if info.log_evidence is None else info.log_evidence.sum(0)
        return FilterResult(
            mean=torch.stack(means),
            state=state,
            info=info,
            log_evidence=log_evidence,
            exists_prob=torch.stack(exists_prob) if exists_prob else None,
        )
