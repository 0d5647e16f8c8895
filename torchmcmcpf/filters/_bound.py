"""Bind once, step many: the :class:`Bound` object a filter's pure step function receives.

Everything a step needs that does not change from step to step is resolved once, when a
filter is built (or when a caller binds by hand), into one frozen :class:`Bound`: the models,
the settings with the multitarget prior's terms the sensor cannot support turned off
(:func:`active_prior`) and the algorithm's checks done, the existence law with the settings'
existence proposal, the slots' joint model (:class:`~torchmcmcpf.models.existence.TargetDynamics`)
and the algorithm's **program**: the pure function the step calls in its loop (the body of an
SIR step, one MCMC iteration, one HMC move), compiled by
:func:`~torchmcmcpf.runtime.compile_program` or eager. Each algorithm has its
``bind_<algo>(motion, sensor, settings=None, existence=None, *, num_particles=None,
compile=None) -> Bound`` (built on :func:`bind`) and its ``<algo>_bound_step(state, z, bound,
*, generator) -> (state, info)``, which re-derives nothing; the eager and the compiled paths
share the one object, so they cannot drift apart.

The settings' helpers live here too: :func:`settings_from` (a filter's settings from its
keyword shortcuts), :func:`constructor_signature` and :func:`check_existence_proposal`.
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath, TargetDynamics

__all__ = ["Bound", "bind", "active_prior", "check_existence", "settings_from", "check_existence_proposal"]

#: ``compile`` of a bind function: a pure function -> its compiled program
#: (:func:`~torchmcmcpf.runtime.compile_program`), or None for the eager program
Compile = Callable[[Callable], Callable] | None


def active_prior(settings: Any, sensor: SensorModel) -> Any:
    """``settings`` with the multitarget prior's terms the sensor cannot support turned off:
    ``exclusion=None`` for a sensor without ``resolution_coords``, ``recapture=None`` for one
    without a data-driven proposal (:mod:`torchmcmcpf.models.multitarget`) and with it the
    IP-MCMC-PF's ``joint_pairs`` (whose pairs the re-capture's two-slot move re-draws), so that
    ``filt.settings`` says what the filter does. Idempotent.
    """
    changes: dict[str, None] = {}
    if getattr(settings, "exclusion", None) is not None and not sensor.resolved:
        changes["exclusion"] = None
    if getattr(settings, "recapture", None) is not None and not sensor.data_driven:
        changes["recapture"] = None
        if getattr(settings, "joint_pairs", None) is not None:
            changes["joint_pairs"] = None
    return dataclasses.replace(settings, **changes) if changes else settings


def check_existence(existence: object) -> BirthDeath | None:
    """``existence`` must be a :class:`~torchmcmcpf.models.existence.BirthDeath` or ``None``."""
    if existence is not None and not isinstance(existence, BirthDeath):
        raise ValueError(f"existence must be a BirthDeath model or None, got {type(existence).__name__}")
    return existence


@dataclass(frozen=True)
class Bound:
    """What one algorithm's step needs besides the state, the frame and the generator,
    resolved once (module docstring): ``<algo>_bound_step(state, z, bound, generator=g)``.

    Attributes
    ----------
    motion : the MotionModel of every slot; sensor : the SensorModel.
    settings : the algorithm's settings dataclass as the filter runs it (:func:`active_prior`
        applied, checked against the models).
    existence : the BirthDeath model with the settings' existence proposal, or None (a known
        number of targets).
    dynamics : the slots' joint model the moves draw and propagate through
        (:class:`~torchmcmcpf.models.existence.TargetDynamics` of ``motion``, ``existence``,
        the settings' re-capture and ``sensor``; the group filter's
        :class:`~torchmcmcpf.filters.group.moves.Models`).
    program : the algorithm's pure program, compiled or eager (its call signature is the
        algorithm's: ``sir_body``'s arguments for the SIR and PMMH filters, one chain
        iteration for the MCMC filters, one HMC transition for the resample-move filter, the
        move runner for the group filter). ``None`` only in a pickled filter, which binds it
        again when it is loaded.

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.filters import bind_sir, sir_bound_step
    >>> bound = bind_sir(tp.ConstantVelocity(), tp.LinearGaussian.position(noise_std=1.0))
    >>> bound.settings                  # this sensor declares no resolution: no exclusion term
    SIRSettings(resample_method='systematic', ess_threshold=1.0, exclusion=None)
    >>> state = tp.ParticleState(torch.zeros(2, 50, 1, 4), torch.full((2, 50), -50.0).log_softmax(-1))
    >>> state, info = sir_bound_step(state, torch.zeros(2, 1, 2), bound, generator=torch.Generator())
    >>> state.x.shape, info.ess.shape   # (B, N, K, D), (B,)
    (torch.Size([2, 50, 1, 4]), torch.Size([2]))
    """

    motion: MotionModel
    sensor: SensorModel
    settings: Any
    existence: BirthDeath | None
    dynamics: Any
    program: Callable[..., Any]


def bind(motion: MotionModel, sensor: SensorModel, settings: Any, existence: BirthDeath | None, *,
         program: Callable[[Bound, Compile], Callable], compile: Compile = None,
         check: Callable[[Bound], None] | None = None) -> Bound:
    """The :class:`Bound` of one algorithm: ``settings`` through :func:`active_prior`,
    ``existence`` with the settings' ``existence_proposal`` (when they have one), the one
    :class:`~torchmcmcpf.models.existence.TargetDynamics`, then ``check(bound)`` (the
    algorithm's checks against the models: a ``ValueError`` naming the setting) and
    ``program(bound, compile)``, the algorithm's program (compiled with ``compile``, eager
    when it is None). ``motion`` must be a per-slot
    :class:`~torchmcmcpf.models.base.MotionModel` (a ``ValueError`` otherwise). Every step
    of binding is idempotent, so a bound object binds again to itself (a filter loaded from
    a pickle, or switched to ``compile_step``).
    """
    if not isinstance(motion, MotionModel):  # e.g. a whole-configuration Motion, which its own filter binds
        raise ValueError(f"motion must be a MotionModel (one transition for every slot), got {type(motion).__name__}")
    existence = check_existence(existence)
    settings = active_prior(settings, sensor)
    proposal = getattr(settings, "existence_proposal", None)
    if existence is not None and proposal is not None:  # the MCMC filters' birth and death proposals
        existence = existence.with_proposal(proposal)
    dynamics = TargetDynamics(motion, existence, getattr(settings, "recapture", None), sensor)
    bound = Bound(motion, sensor, settings, existence, dynamics, None)  # type: ignore[arg-type]  # program next
    if check is not None:
        check(bound)
    return dataclasses.replace(bound, program=program(bound, compile))


# ----------------------------------------------------------------------------- settings
def settings_from(settings_class: type, settings: Any, shortcuts: Mapping[str, Any]) -> Any:
    """A filter's settings: ``settings`` (an instance of ``settings_class``, or ``None`` for
    its defaults) with the keyword ``shortcuts`` (fields of ``settings_class``) replaced.
    An unknown keyword is a ``TypeError`` naming it and the fields.
    """
    fields = [f.name for f in dataclasses.fields(settings_class) if f.init]
    unknown = sorted(set(shortcuts) - set(fields))
    if unknown:
        raise TypeError(f"unexpected keyword argument(s) {unknown}; the settings of this filter are "
                        f"{fields} ({settings_class.__name__}), plus settings=, existence=, compile_step=")
    if settings is None:
        return settings_class(**shortcuts)
    if not isinstance(settings, settings_class):
        raise ValueError(f"settings must be a {settings_class.__name__}, got {type(settings).__name__}")
    return dataclasses.replace(settings, **shortcuts) if shortcuts else settings  # type: ignore[type-var]


def constructor_signature(settings_class: type) -> inspect.Signature:
    """The constructor signature of a filter whose settings are ``settings_class``: the
    models, the size, ``settings``, ``existence``, ``compile_step`` and one keyword per field,
    with the field's default (what ``help()`` and the documentation show).
    """
    kw = inspect.Parameter.KEYWORD_ONLY
    params = [inspect.Parameter("motion", inspect.Parameter.POSITIONAL_OR_KEYWORD),
              inspect.Parameter("sensor", inspect.Parameter.POSITIONAL_OR_KEYWORD),
              inspect.Parameter("num_particles", inspect.Parameter.POSITIONAL_OR_KEYWORD),
              inspect.Parameter("settings", inspect.Parameter.POSITIONAL_OR_KEYWORD, default=None),
              inspect.Parameter("existence", kw, default=None),
              inspect.Parameter("compile_step", kw, default=False)]
    params += [inspect.Parameter(f.name, kw, default=f.default) for f in dataclasses.fields(settings_class) if f.init]
    return inspect.Signature(params)


def check_existence_proposal(value: object) -> tuple[float, float] | None:
    """``existence_proposal`` of the MCMC filters' settings: ``None`` or ``(q_birth, q_death)``,
    two probabilities in (0, 1); returns it as a tuple of floats.
    """
    if value is None:
        return None
    try:
        q = tuple(float(v) for v in value)  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        q = ()
    if len(q) != 2 or not all(0.0 < v < 1.0 for v in q):
        raise ValueError(f"existence_proposal must be None or (q_birth, q_death) in (0, 1), got {value!r}")
    return (q[0], q[1])
