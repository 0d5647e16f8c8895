"""The ``Filter`` base: a thin ``nn.Module`` around a pure step function.

One contract for every algorithm (BlackJAX-style ``init``/``step`` with fixed state and info
types):

- constructor ``(motion, sensor, num_particles, *, settings=None, existence=None,
  compile_step=False, **shortcuts)``; the settings live in one frozen dataclass per
  algorithm (:attr:`Filter.settings_class`, ``filt.settings``). Each field of the dataclass
  is also a keyword of the constructor (a shortcut: ``IPMCMCFilter(m, s, n, burn_in=20)`` is
  ``IPMCMCFilter(m, s, n, settings=IPMCMCSettings(burn_in=20))``), so every default is
  written once, in the dataclass;
- bind once, step many: the constructor resolves everything a step needs that does not
  change from step to step (the settings as the filter runs them, the existence law with its
  proposal, the slots' joint model, the algorithm's program, compiled when
  ``compile_step=True``) into one frozen :class:`~torchmcmcpf.filters._bound.Bound`
  (``filt.bound``), by the algorithm's ``bind_<algo>`` (:attr:`Filter.bind`); each step
  calls the algorithm's ``<algo>_bound_step(state, z, bound, *, generator)``
  (:attr:`Filter.bound_step`), which re-derives nothing. The pure step function of the
  design, ``xxx_step(state, z, *, motion, sensor, settings, generator, existence=None)``, is
  the same step with an eager bind in front of it;
- ``step(state, z, *, generator) -> (state, StepInfo)`` validates its arguments: ``z`` and
  ``generator`` always, the state in full unless it is one the filter made itself and that
  is unchanged since (``Filter.step``), so that stepping its own output costs the step;
- ``forward(measurements, *, init, generator, progress=None) -> FilterResult`` validates the
  whole sequence once, before the first step, then runs the steps without checks;
- ``compile_step=True`` compiles the filter's program (:mod:`torchmcmcpf.runtime`: an MCMC
  iteration, each move of one, an HMC move, or the body of an SIR step) with
  ``torch.compile(fullgraph=True)``; the random numbers are drawn eagerly from the
  generator and passed in, so compiled and eager runs consume the same random stream.

A filter holds models and its bound object; the filtering state is passed in and returned,
never stored on the module, so filters are reentrant. Resume = the state plus
``generator.get_state()``. A pickled filter (``torch.save``, ``copy.deepcopy``) leaves its
program out and binds it again when loaded.
"""

from __future__ import annotations

import dataclasses
import itertools
import weakref
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from typing import Any, ClassVar, cast

import torch
from torch import nn
from torch.utils._pytree import tree_map

from .._validation import check_generator, check_positive_int, check_shape, check_tensor, measurement_leaves
from .._version import __version__
from ..models.base import Motion, MotionModel, SensorModel
from ..models.existence import BirthDeath, TargetDynamics
from ..runtime import check_allocation, compile_program
from ..state import (
    ExistenceEstimate,
    FilterResult,
    ParticleState,
    StepInfo,
    relabelled_estimate,
    stack_infos,
    stack_states,
    weighted_cov,
)
from ..typing import Measurement, Tensor
from ._bound import Bound, Compile, active_prior, check_existence, constructor_signature, settings_from
from ._carry import ESTIMATE, CarriedEstimate, check_carries, typed_extras

__all__ = ["Filter", "CarriedEstimate", "active_prior", "check_existence", "settings_from", "ESTIMATE"]


def _plain(value: Any) -> Any:
    """A settings value as plain Python (dicts, lists, str, int, float, bool, None), so a
    result's ``meta`` loads with ``torch.load(weights_only=True)`` and writes to JSON.
    """
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value) if f.init}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    if torch.is_tensor(value) and value.numel() == 1:
        return value.item()
    return repr(value)


def _maker(keys: list[str]) -> str:
    """The filter classes whose states carry ``keys`` (:attr:`Filter.state_extras`), in words."""
    found = sorted({cls.__name__ for cls in _filter_classes()
                    if cls.state_extras and cls.state_extras == set(keys)})
    return " or ".join(found) if found else "another filter"


def _filter_classes() -> list[type[Filter]]:
    """Every subclass of :class:`Filter` defined so far (the library's, imported with it)."""
    out: list[type[Filter]] = []
    todo = list(Filter.__subclasses__())
    while todo:
        cls = todo.pop()
        out.append(cls)
        todo.extend(cls.__subclasses__())
    return out


#: how many states a filter remembers as its own (:meth:`Filter._trust`): the last few outputs
#: and initial states, so that stepping a few states in turn stays cheap
_TRUSTED_STATES = 4


def _record(state: ParticleState) -> tuple | None:
    """``(ref(x), version of x, ref(exists) or None, version of exists)``, or ``None`` for
    inference tensors (no version counter).
    """
    x, e = state.x, state.exists
    if not torch.is_tensor(x) or x.is_inference() or (e is not None and (not torch.is_tensor(e) or e.is_inference())):
        return None
    return (weakref.ref(x), x._version, None if e is None else weakref.ref(e), 0 if e is None else e._version)


def _inference_tensors(state: ParticleState) -> ParticleState:
    """``state`` with its tensors made outside ``torch.inference_mode()`` copied inside it
    (inference tensors; the others as they are). A step under inference mode returns
    inference tensors, and a compiled program guards on that kind of its inputs (their
    dispatch keys), so a first state made outside (the initial cloud) would compile every
    program of the step a second time at the next step (the Table II SIR step: 17 s at N =
    5000, cold; the MCMC-PF's moves likewise).
    """
    def own(t: Any) -> Any:
        return t.clone() if torch.is_tensor(t) and not t.is_inference() else t

    return tree_map(own, state)


def _same(a: tuple, b: tuple) -> bool:
    """The two records name the same live tensors at the same versions."""
    x = a[0]()
    return (x is not None and x is b[0]() and a[1] == b[1] and a[3] == b[3]
            and (a[2] is None) == (b[2] is None) and (a[2] is None or a[2]() is b[2]()))


def _check_devices_dtypes(state: ParticleState, measurements: Measurement, name: str,
                          model_devices: Iterable[torch.device]) -> None:
    """Devices (none on ``meta``, all equal, the models' ``model_devices`` too) and dtypes
    (floating measurements of the state's dtype) of a state and measurements: metadata only,
    no host synchronisation.
    """
    x = state.x
    tensors = {"init": x, "init.log_w": state.log_w}
    if state.exists is not None:
        tensors["init.exists"] = state.exists
    for i, leaf in enumerate(measurement_leaves(measurements, name)):
        tensors[name if torch.is_tensor(measurements) else f"{name}[{i}]"] = leaf
    for key, t in tensors.items():
        if t.device.type == "meta":
            raise ValueError(f"{key} is on the meta device (no data), expected a tensor on {x.device}")
        if t.device != x.device:
            raise ValueError(f"{key} is on {t.device}, expected {x.device} (the device of init)")
    for device in model_devices:
        if device.type == "meta" or device != x.device:
            raise ValueError(f"the models' parameters are on {device}, expected {x.device} (the device of "
                             "init); move them with filt.to(device)")
    if not x.is_floating_point():
        raise ValueError(f"init has dtype {x.dtype}, expected a floating dtype")
    for key, t in tensors.items():
        if key.startswith(name) and t.dtype != torch.bool:
            if not t.is_floating_point():
                raise ValueError(f"{key} has dtype {t.dtype}, expected a floating dtype ({x.dtype}); "
                                 "convert integer counts with .to(init.dtype)")
            if t.dtype != x.dtype:
                raise ValueError(f"{key} has dtype {t.dtype} but init has {x.dtype}; expected one dtype "
                                 "(convert with .to(init.dtype))")


class Filter(nn.Module):
    """Base of every particle filter in torchmcmcpf (module docstring: the contract).

    Subclasses set :attr:`settings_class`, :attr:`bind` (the algorithm's ``bind_<algo>``,
    which also checks the settings against the models and the size) and :attr:`bound_step`
    (its ``<algo>_bound_step``); the base binds once, in the constructor (:attr:`bound`), and
    every step calls ``bound_step(state, z, self.bound, generator=generator)``.

    Example
    -------
    Every filter takes the same arguments and returns the same result, so one loop runs
    three algorithms:

    >>> import torch
    >>> import torchmcmcpf as tp
    >>> motion, sensor = tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0)
    >>> z = torch.zeros(4, 1, 2, 2)                   # (T, B, K, 2): 4 frames, 1 run, 2 targets at rest
    >>> for cls in (tp.SIRFilter, tp.PartitionedSIRFilter, tp.PMMHFilter):
    ...     filt = cls(motion, sensor, 50)
    ...     result = filt(z, init=torch.zeros(1, 50, 2, 4), generator=torch.Generator().manual_seed(0))
    ...     print(cls.__name__, tuple(result.mean.shape), tuple(result.info.ess.shape))   # (T, B, K, D), (T, B)
    SIRFilter (4, 1, 2, 4) (4, 1)
    PartitionedSIRFilter (4, 1, 2, 4) (4, 1)
    PMMHFilter (4, 1, 2, 4) (4, 1)
    >>> state, info = filt.step(result.state, z[0], generator=torch.Generator())   # or one step at a time
    >>> state.x.shape, info.ess.shape
    (torch.Size([1, 50, 2, 4]), torch.Size([1]))
    """

    motion: Motion
    sensor: SensorModel
    num_particles: int
    existence: BirthDeath | None
    #: seconds the first ``compile_step=True`` step of a new shape takes to compile, cold, on a
    #: 2-core CPU (5-target ground radar, ``benchmarks/bench_compile.py``); shown in the progress
    #: bar while that step runs
    compile_seconds: float = 20.0

    #: copies of the particle state ``(B, N, K, D)`` a step holds at once, at least (the state
    #: in, the prediction or proposal, the resampled cloud, the state out): the factor of
    #: :meth:`working_bytes`, the estimate :meth:`init` checks against the allocation budget
    working_copies: ClassVar[int] = 4
    #: the keys of ``ParticleState.extras`` this filter's states carry between steps (besides
    #: ``forward``'s estimate, :data:`ESTIMATE`), each a typed carry (:mod:`~torchmcmcpf.filters._carry`),
    #: all of them required in a state that resumes a run, none of them in a fresh one
    #: (:meth:`check_resume`)
    state_extras: ClassVar[frozenset[str]] = frozenset()

    #: the settings dataclass of the algorithm: the ``settings=`` of the constructor, and its
    #: fields the constructor's keyword shortcuts (:func:`settings_from`)
    settings_class: ClassVar[type | None] = None
    #: the algorithm's bind function, ``(motion, sensor, settings, existence, *, num_particles,
    #: compile, **models) -> Bound`` (a ``staticmethod``: e.g. ``bind_sir``)
    bind: ClassVar[Callable[..., Bound]]
    #: the algorithm's step on its bound object, ``(state, z, bound, *, generator) -> (state,
    #: StepInfo)`` (a ``staticmethod``: e.g. ``sir_bound_step``)
    bound_step: ClassVar[Callable[..., tuple[ParticleState, StepInfo]]]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """Give a filter class with a :attr:`settings_class` the constructor signature its
        settings imply (``inspect.signature``, ``help``, the documentation).
        """
        super().__init_subclass__(**kwargs)
        if cls.__dict__.get("settings_class") is not None:
            cls.__signature__ = constructor_signature(cls.__dict__["settings_class"])  # type: ignore[attr-defined]

    def __init__(self, motion: Motion, sensor: SensorModel, num_particles: int, settings: Any = None, *,
                 existence: BirthDeath | None = None, compile_step: bool = False,
                 models: Mapping[str, nn.Module] | None = None, **shortcuts: Any):
        """``models``: the algorithm's models besides ``motion``, ``sensor`` and ``existence``,
        by the keyword its :attr:`bind` takes them (the group filter's ``structure_prior``),
        registered as submodules (``.to(device)`` moves them) and passed to :attr:`bind`; a
        filter whose algorithm needs one takes it as its own constructor argument and passes
        it on here. The other arguments: the module docstring.
        """
        super().__init__()
        models = dict(models or {})
        if self.settings_class is not None:
            settings = settings_from(self.settings_class, settings, shortcuts)
        elif shortcuts:
            raise TypeError(f"unexpected keyword argument(s) {sorted(shortcuts)} for {type(self).__name__}")
        if not isinstance(motion, Motion):  # which kind of motion the algorithm takes: its bind checks
            raise ValueError(f"motion must be a MotionModel (or another Motion), got {type(motion).__name__}")
        if not isinstance(sensor, SensorModel):
            raise ValueError(f"sensor must be a SensorModel, got {type(sensor).__name__}")
        if not isinstance(compile_step, bool):
            raise ValueError(f"compile_step must be a bool, got {compile_step!r}")
        self.motion = motion
        self.sensor = sensor
        for name, model in models.items():
            if not isinstance(model, nn.Module):
                raise ValueError(f"{name} must be a model (an nn.Module), got {type(model).__name__}")
            setattr(self, name, model)
        self._model_names = tuple(models)
        self.num_particles = check_positive_int(num_particles, "num_particles")
        self._compile_step = compile_step
        self._compiled_shapes: set[tuple] = set()  # (B, N, K, D, dtype, device) already run compiled
        self._trusted: deque = deque(maxlen=_TRUSTED_STATES)
        self._devices: frozenset | None = None  # _model_devices, until the filter is moved
        self._bind(settings, check_existence(existence))

    def _bind(self, settings: Any, existence: BirthDeath | None) -> None:
        """Resolve the filter's :class:`~torchmcmcpf.filters._bound.Bound` (:attr:`bind`: the
        settings' checks against the models and ``num_particles``, the program compiled when
        :attr:`compile_step`), and register its existence model (with the settings' proposal)
        as the submodule ``existence``, so that ``.to(device)`` moves the one the steps use.
        """
        compile: Compile = compile_program if self._compile_step else None
        self._bound = self.bind(self.motion, self.sensor, settings, existence, num_particles=self.num_particles,
                                compile=compile, **{name: getattr(self, name) for name in self._model_names})
        self.existence = self._bound.existence

    @property
    def bound(self) -> Bound:
        """What every step of this filter runs with, resolved once (module docstring):
        ``type(filt).bound_step(state, z, filt.bound, generator=g)`` is ``filt.step`` without
        its checks.
        """
        return self._bound

    @property
    def settings(self) -> Any:
        """The settings as the filter runs them (``filt.bound.settings``: the prior's terms the
        sensor cannot support turned off, :func:`~torchmcmcpf.filters._bound.active_prior`).
        """
        return self._bound.settings

    @property
    def dynamics(self) -> TargetDynamics:
        """The slots' joint model of this filter (``filt.bound.dynamics``): its motion,
        existence model (with the settings' existence proposal), re-capture (when its settings
        have one) and sensor, the :class:`~torchmcmcpf.models.existence.TargetDynamics` its
        program binds.
        """
        return self._bound.dynamics

    @property
    def compile_step(self) -> bool:
        """Whether the filter's program is compiled (:func:`~torchmcmcpf.runtime.compile_program`);
        setting it binds the program again, compiled or eager.
        """
        return self._compile_step

    @compile_step.setter
    def compile_step(self, value: bool) -> None:
        if not isinstance(value, bool):
            raise ValueError(f"compile_step must be a bool, got {value!r}")
        self._compile_step = value
        self._bind(self.settings, self.existence)

    # -- the states this filter vouches for ----------------------------------------------
    def _trust(self, state: ParticleState) -> ParticleState:
        """Remember ``state`` (checked at the door or produced by a step) as valid, so that
        :meth:`step` skips its full check when it comes back unchanged; returns ``state``.

        The record holds weak references to ``state.x`` and ``state.exists`` and their
        version counters: a new tensor (a state built elsewhere) is not the object recorded,
        and an in-place change (``x[...] = nan``, ``x.add_(1)``) bumps the counter, so both
        get the full check. Inference tensors (``torch.inference_mode``) keep no counter, so
        states made of them are never trusted.
        """
        record = _record(state)
        if record is not None:
            self._trusted.append(record)
        return state

    def _model_devices(self) -> frozenset:
        """The devices of the models' parameters and buffers, remembered until the filter is
        moved or converted (:meth:`_apply`, which ``.to``, ``.cuda`` and ``.double`` call):
        walking the module tree at every call was about a tenth of a public step at B = 1.
        """
        if self._devices is None:
            self._devices = frozenset(t.device for t in itertools.chain(self.parameters(), self.buffers()))
        return self._devices

    def _apply(self, fn: Callable, recurse: bool = True) -> Filter:
        """``nn.Module._apply`` (``.to``, ``.cuda``, ``.double``, ...), forgetting the models'
        devices and the trusted states: a state made before the move gets the full check.
        """
        self._devices = None
        self._trusted.clear()
        return super()._apply(fn, recurse)

    def _is_trusted(self, state: ParticleState) -> bool:
        """Whether ``state`` is one that :meth:`_trust` recorded, unchanged since."""
        record = _record(state)
        if record is None:
            return False
        for i, r in enumerate(self._trusted):
            if _same(record, r):  # most recently used last: a state stepped again and again stays trusted
                del self._trusted[i]  # by position: weak references compare their tensors by value
                self._trusted.append(r)
                return True
        return False

    def __getstate__(self) -> dict:
        """Pickle without the weak references of :meth:`_trust` (a copy trusts nothing), without
        the models' devices (a copy may be loaded elsewhere, ``map_location``) and without the
        program (a closure, compiled or not, does not pickle): :meth:`__setstate__` binds again.
        """
        d = super().__getstate__()
        d["_trusted"] = None
        d["_devices"] = None
        d["_bound"] = dataclasses.replace(self._bound, program=None)  # type: ignore[arg-type]
        return d

    def __setstate__(self, d: dict) -> None:
        super().__setstate__(d)
        self._trusted = deque(maxlen=_TRUSTED_STATES)
        self._devices = None
        if "_model_names" not in d:  # pickled when the further models were a class attribute: its submodules
            self._model_names = tuple(n for n in self._modules if n not in ("motion", "sensor", "existence"))
        if "_bound" not in d:  # pickled before filters bound once: settings and flag were attributes
            self._compile_step = self.__dict__.pop("compile_step")
            self.__dict__.pop("_compiled", None)
            settings = dataclasses.replace(self.__dict__.pop("settings"))  # its derived fields afresh
            self._bound = Bound(self.motion, self.sensor, settings, self.existence, None, None)  # type: ignore[arg-type]
        self._bind(self._bound.settings, self._bound.existence)

    # -- state ---------------------------------------------------------------------------
    def init(self, particles: Tensor, exists: Tensor | None = None) -> ParticleState:
        """Wrap an initial cloud into an equally weighted ``ParticleState``.

        Parameters
        ----------
        particles : (B, N, K, D) with N = ``num_particles`` and D = ``motion.dim``.
        exists : (B, N, K) bool, optional.

        Returns
        -------
        ParticleState with ``log_w = -log N``.
        """
        if isinstance(particles, ParticleState):
            raise ValueError("init takes the particles (B, N, K, D) as a tensor, got a ParticleState; pass the "
                             "state to step() or forward(init=state) as it is")
        self._check_state_tensors(check_tensor(particles, "init"), exists)
        if exists is not None:
            exists = exists.to(torch.bool)
        b, n = particles.shape[:2]
        self.check_memory_estimate(b, particles.shape[2], particles.dtype, particles.device)
        log_w = torch.full((b, n), -torch.log(torch.tensor(float(n), dtype=torch.float64)).item(),
                           device=particles.device, dtype=particles.dtype)
        return self._trust(ParticleState(particles, log_w, exists))

    def working_bytes(self, batch_size: int, num_targets: int, dtype: torch.dtype = torch.float32, *,
                      num_steps: int = 0) -> int:
        """A lower bound on the bytes a run of this filter holds at once: :attr:`working_copies`
        particle states (``x (B, N, K, D)``, ``log_w (B, N)``, ``exists (B, N, K)``), the
        sensor's ``memory_budget`` of temporaries (grid sensors), and ``num_steps`` more states
        for ``forward(..., history=True)``.
        """
        itemsize = torch.empty((), dtype=dtype).element_size()
        b, n, k = batch_size, self.num_particles, num_targets
        state = b * n * (k * self.motion.dim * itemsize + itemsize + k)
        return (self.working_copies + num_steps) * state + int(getattr(self.sensor, "memory_budget", 0) or 0)

    def check_memory_estimate(self, batch_size: int, num_targets: int, dtype: torch.dtype,
                              device: torch.device | str | None, *, num_steps: int = 0) -> None:
        """Refuse a problem whose :meth:`working_bytes` exceed
        :func:`~torchmcmcpf.runtime.allocation_budget` (the memory available on ``device``
        unless :func:`~torchmcmcpf.runtime.set_allocation_budget` set one) with a ``ValueError``
        naming the estimate and the budget, before a step allocates anything.
        """
        need = self.working_bytes(batch_size, num_targets, dtype, num_steps=num_steps)
        history = f", history of {num_steps} steps" if num_steps else ""
        check_allocation(need, f"{type(self).__name__} with N={self.num_particles} particles, B={batch_size} runs, "
                               f"K={num_targets} targets ({self.working_copies} working copies of the state{history})",
                         device, hint="use fewer particles or runs" + (" or history=False" if num_steps else ""))

    def carry_sizes(self) -> dict[str, dict[str, Any]]:
        """The sizes this filter knows of its carries besides the state's shapes, by key of
        ``extras``: the keyword arguments of each carry's ``check`` (:meth:`check_resume`;
        e.g. a ``PMMHFilter``'s ``{"pmmh": {"num_candidates": L}}``). None by default.
        """
        return {}

    def check_resume(self, state: ParticleState) -> None:
        """Refuse a state made by another kind of filter, or one whose carries do not fit it:
        one that carries ``extras`` (a state from ``step`` or ``forward``, not a fresh ``init``)
        must hold every key of :attr:`state_extras` (a ``PMMHFilter`` resumes its candidates)
        and no key of another filter's states (an ``IPMCMCFilter`` given a ``PMMHFilter``'s
        state would drop its candidates without a word), and each typed value must pass its
        type's check (:func:`~torchmcmcpf.filters._carry.check_carries` with
        :meth:`carry_sizes`). ``ValueError`` naming what is missing, foreign or misshapen.
        """
        extras = state.extras
        if not extras:
            return
        if not isinstance(extras, Mapping):
            raise ValueError(f"state.extras must be a dict of typed values or None, got {type(extras).__name__}")
        keys = set(extras) - {ESTIMATE}
        name = type(self).__name__
        foreign = sorted(keys - self.state_extras)
        if foreign:
            raise ValueError(f"state.extras holds {foreign}, which the states of {name} do not carry: a state of "
                             f"{_maker(foreign)}, not of this filter; resume a run with the filter that made its "
                             f"state, or start this one afresh from the particles: filt.init(state.x, state.exists)")
        missing = sorted(self.state_extras - keys)
        if missing and keys & self.state_extras:
            raise ValueError(f"state.extras has no {missing}: a state of {name} carries {sorted(self.state_extras)} "
                             "between steps, and this one is incomplete (build a fresh state with filt.init)")
        if missing:
            maker = _maker(sorted(keys)) if keys else "a filter without them"
            raise ValueError(f"state.extras has no {missing}, which the states of {name} carry between steps: a "
                             f"state of {maker}, not of this filter; "
                             f"resume a run with the filter that made its state, or start this one afresh from "
                             f"the particles: filt.init(state.x, state.exists)")
        check_carries(state, self.carry_sizes())

    def _check_state_tensors(self, x: Tensor, exists: Tensor | None) -> None:
        if x.dim() != 4:
            raise ValueError(f"init has shape {tuple(x.shape)} ({x.dim()} dims), expected (B, N, K, D) = (B, "
                             f"{self.num_particles}, K, {self.motion.dim}): runs, particles, targets, state; add "
                             "the run axis with x.unsqueeze(0) for one run")
        if x.shape[1] != self.num_particles or x.shape[3] != self.motion.dim:
            raise ValueError(f"init has shape {tuple(x.shape)}, expected (B, N, K, D) = (*, {self.num_particles}, *, "
                             f"{self.motion.dim}): N = num_particles of the filter, D = motion.dim")
        if x.shape[0] == 0 or x.shape[2] == 0:
            raise ValueError(f"init has shape {tuple(x.shape)}, expected B >= 1 and K >= 1")
        if x.device.type == "meta":
            raise ValueError("init is on the meta device (no data), expected a tensor with values")
        if not x.is_floating_point():
            raise ValueError(f"init has dtype {x.dtype}, expected a floating dtype")
        if not bool(torch.isfinite(x).all()):
            bad = int((~torch.isfinite(x)).sum())
            raise ValueError(f"init contains {bad} NaN/inf value(s); expected finite values")
        self.sensor.validate_state(x, "init")
        if exists is not None:
            check_shape(exists, "init.exists", tuple(x.shape[:3]))
            if exists.device != x.device:
                raise ValueError(f"init.exists is on {exists.device}, expected {x.device} (the device of init)")

    def _as_state(self, init: Tensor | ParticleState) -> ParticleState:
        if isinstance(init, ParticleState):
            init = init._replace(extras=typed_extras(init.extras))  # a state saved with open keys: typed
            self.check_resume(init)
            state = self.init(init.x, init.exists)
            check_shape(init.log_w, "init.log_w", tuple(init.x.shape[:2]))
            if init.log_w.device != init.x.device or init.log_w.dtype != init.x.dtype:
                raise ValueError(f"init.log_w is {init.log_w.dtype} on {init.log_w.device}, expected "
                                 f"{init.x.dtype} on {init.x.device} (those of init.x)")
            if bool(torch.isnan(init.log_w).any()):
                raise ValueError("init.log_w contains NaN; expected normalised log-weights")
            return state._replace(log_w=init.log_w, extras=init.extras)
        return self.init(check_tensor(init, "init"))

    def estimate(self, state: ParticleState) -> Tensor:
        """Point estimate ``(B, K, D)`` of a state: :meth:`estimate_targets` ``.mean``."""
        return self.estimate_targets(state).mean

    def estimate_targets(self, state: ParticleState, reference: ExistenceEstimate | None = None
                         ) -> ExistenceEstimate:
        """Point estimates ``(B, K, D)`` of a state: the MMSE estimate (paper 000 eq. 6) of
        each target after relabelling the particles' slots (Stephens 2000,
        :func:`~torchmcmcpf.state.relabelled_estimate`), so that a slot's mean is the mean of
        one target even where particles hold the targets under different labels; with
        existence, each target's existence probability and mean given that it exists.

        Parameters
        ----------
        state : ParticleState.
        reference : the previous step's estimate, optional: predicted by the motion model,
            it is the starting reference, so the labels stay the same over time
            (``forward`` passes it). A sensor without
            :meth:`~torchmcmcpf.models.base.SensorModel.resolution_coords` (labelled
            measurements, such as :class:`~torchmcmcpf.models.LinearGaussian`) says which slot
            is which target, as does a motion whose slots' labels are part of the model
            (``motion.exchangeable_slots`` False, :class:`~torchmcmcpf.models.base.Motion`:
            the group filter's): there the particles are not relabelled.

        Returns
        -------
        :class:`~torchmcmcpf.state.ExistenceEstimate` (``exists_prob`` ones without existence).
        """
        return self._estimate(state, reference)[0]

    def _estimate(self, state: ParticleState, reference: ExistenceEstimate | None
                  ) -> tuple[ExistenceEstimate, ParticleState]:
        """:meth:`estimate_targets` and the relabelled cloud it averaged."""
        x_death = None if self.existence is None else self.existence.x_death
        if not (self.motion.exchangeable_slots and self.sensor.resolved):  # labelled measurements or slots
            return relabelled_estimate(state, x_death=x_death, iterations=0)
        ref = present = None
        if reference is not None:
            m = reference.mean
            motion = cast(MotionModel, self.motion)  # exchangeable slots: a per-slot MotionModel
            ref = motion.propagate(m, torch.zeros(m.shape[:-1] + (motion.noise_dim,), dtype=m.dtype, device=m.device))
            present = reference.present if state.exists is not None else None
        return relabelled_estimate(state, ref, reference_exists=present, x_death=x_death)

    # -- validation at the door ----------------------------------------------------------
    def validate(self, state: ParticleState, measurements: Measurement, *, sequence: bool,
                 name: str = "measurements") -> None:
        """Check a state and one frame ``(B, *G)`` (``sequence=False``) or a whole sequence
        ``(T, B, *G)`` (``sequence=True``, one pass for all T frames): devices, dtypes,
        shapes, batch size, finite values (the sensor's :meth:`validate`). Raises
        ``ValueError`` naming the argument.
        """
        if not isinstance(state, ParticleState):
            raise ValueError(f"state must be a ParticleState, got {type(state).__name__}")
        _check_devices_dtypes(state, measurements, name, self._model_devices())
        b = state.batch_size
        if sequence:
            leaves = measurement_leaves(measurements, name)
            if any(t.dim() < 2 for t in leaves):
                raise ValueError(f"{name} has shapes {[tuple(t.shape) for t in leaves]}, expected (T, B, *grid): "
                                 "time first, then runs")
            t0 = leaves[0].shape[0]
            if t0 == 0:
                raise ValueError(f"{name} has shape {tuple(leaves[0].shape)}: a time axis of length 0, "
                                 "expected T >= 1")
            if any(t.shape[0] != t0 for t in leaves):
                raise ValueError(f"{name} have different time lengths: {[tuple(t.shape) for t in leaves]}")
            if any(t.shape[1] != b for t in leaves):
                bad = next(t for t in leaves if t.shape[1] != b)
                single = (" (one frame (B, *grid) without the time axis? add it with measurements.unsqueeze(0))"
                          if bad.shape[0] == b else "")
                raise ValueError(f"{name} has shape {tuple(bad.shape)}, expected (T, B, *grid) with B = {b} runs "
                                 f"(those of init) on axis 1, got {bad.shape[1]}{single}")
            for i, leaf in enumerate(leaves):  # name the first bad frame (one reduction, one sync)
                if leaf.is_floating_point():
                    bad = (~torch.isfinite(leaf)).flatten(1).sum(1)  # (T,)
                    if bool(bad.any()):
                        t = int(bad.nonzero()[0, 0])
                        key = name if len(leaves) == 1 else f"{name}[{i}]"
                        raise ValueError(f"{key}[{t}] contains {int(bad[t])} NaN/inf value(s); expected finite "
                                         "values (checked for the whole sequence before the first step)")
            flat = tree_map(lambda a: a.flatten(0, 1), measurements)
            self.sensor.validate(flat, None, name)
        else:
            self.sensor.validate(measurements, b, name)

    # -- one step ------------------------------------------------------------------------
    def _step(self, state: ParticleState, z: Measurement, generator: torch.Generator
              ) -> tuple[ParticleState, StepInfo]:
        """One step without checks: :attr:`bound_step` with this filter's :attr:`bound`, on
        the frame without the padding no run uses when eager
        (:meth:`~torchmcmcpf.models.base.SensorModel.trim_frame`; a compiled step keeps its
        shapes: a new frame width would compile it again).
        """
        if not self._compile_step:
            z = self.sensor.trim_frame(z)
        elif torch.is_inference_mode_enabled() and not state.x.is_inference():  # a first state, made outside
            state = _inference_tensors(state)
        return self.bound_step(state, z, self._bound, generator=generator)

    def step(self, state: ParticleState, z: Measurement, *, generator: torch.Generator
             ) -> tuple[ParticleState, StepInfo]:
        """Advance ``state`` by one measurement ``z (B, *G)``; returns ``(state, info)``.

        Validates ``z`` and ``generator`` (one host synchronisation) and ``state``: in full
        (shapes, finite values, the sensor's :meth:`~SensorModel.validate_state`) unless it is
        a state this filter returned from :meth:`init`, :meth:`step` or :meth:`forward` and
        that has not been changed in place since (a cheap marker: the tensors' identity and
        version counters), so that stepping a state the filter produced costs the step
        itself. A state from elsewhere, or an altered one, gets the full check.
        """
        check_generator(generator)
        if not isinstance(state, ParticleState):
            hint = (f" (shape {tuple(state.shape)}); wrap initial particles (B, N, K, D) with state = filt.init(x) "
                    "first" if torch.is_tensor(state) else "")
            raise ValueError(f"state must be a ParticleState, got {type(state).__name__}{hint}")
        if not self._is_trusted(state):
            state = state._replace(extras=typed_extras(state.extras))  # a state saved with open keys: typed
            self.check_resume(state)
            self._check_state_tensors(state.x, state.exists)
        self.validate(state, z, sequence=False, name="z")
        new, info = self._step(state, z, generator)
        return self._trust(new), info

    # -- a whole sequence ----------------------------------------------------------------
    def forward(
        self,
        measurements: Measurement,
        *,
        init: Tensor | ParticleState,
        generator: torch.Generator,
        progress: bool | None = None,
        history: bool = False,
    ) -> FilterResult:
        """Filter a sequence of T measurements.

        Parameters
        ----------
        measurements : (T, B, *G) tensor, or a tuple of tensors with leading (T, B)
            (e.g. point measurements and their mask). Validated once, before the first step.
        init : (B, N, K, D) initial particles, or a ``ParticleState`` (e.g. the ``state`` of
            an earlier result, to resume).
        generator : the only source of randomness.
        progress : show a tqdm progress bar over time (it says when the first step of a
            ``compile_step=True`` filter compiles).
        history : keep every step's particle state in ``result.history`` (T times the
            memory of one state; for per-step clouds and chain samples), each particle's
            slots relabelled as the estimate's (:meth:`estimate_targets`).

        Returns
        -------
        FilterResult with ``mean (T, B, K, D)``, ``cov (T, B, K, D, D)``, the final state,
        stacked ``StepInfo`` and ``meta`` (see :class:`~torchmcmcpf.state.FilterResult`).
        """
        check_generator(generator)
        state = self._as_state(init)
        self.validate(state, measurements, sequence=True)
        num_steps = measurement_leaves(measurements, "measurements")[0].shape[0]
        if history:
            self.check_memory_estimate(state.batch_size, state.num_targets, state.x.dtype, state.x.device,
                                       num_steps=num_steps)
        steps, note = self._progress(num_steps, state.x, progress)
        means, covs, infos, exists_prob, states = [], [], [], [], []
        carried = (state.extras or {}).get(ESTIMATE)
        est = None if carried is None else carried.as_estimate()
        if est is None and self.motion.exchangeable_slots and self.sensor.resolved and state.num_targets > 1:
            # a fresh start: the initial cloud's own slot means are the first reference (its
            # labels are the caller's), not one particle of the first step's cloud
            x_death = None if self.existence is None else self.existence.x_death
            first = relabelled_estimate(state, x_death=x_death, iterations=0)[0]
            # an inactive start has no labels to keep: the first step founds them itself
            est = first if self.existence is None or (
                state.exists is not None and bool(first.present.any(-1).all())) else None
        for t in steps:
            z = tree_map(lambda a: a[t], measurements)
            state, info = self._step(state, z, generator)
            if note and t == 0:
                steps.set_postfix_str("", refresh=False)  # compiled: the bar's own rate from here on
            infos.append(info)
            est, relabelled = self._estimate(state, est)  # relabelled against the previous estimate
            # the estimate is the next step's reference: carried in the state, so a resumed run
            # labels its targets as the uninterrupted one does
            state = state._replace(extras={**(state.extras or {}), ESTIMATE: CarriedEstimate(est.mean, est.present)})
            means.append(est.mean)
            covs.append(weighted_cov(relabelled.x, relabelled.log_w, est.mean, relabelled.exists))
            if self.existence is not None and state.exists is not None:
                exists_prob.append(est.exists_prob)
            if history:  # the cloud the estimate averaged: its slots labelled as the estimate's
                states.append(relabelled._replace(extras=state.extras))
        info = stack_infos(infos)
        return FilterResult(
            mean=torch.stack(means),
            state=self._trust(state),
            info=info,
            log_evidence=info.log_evidence.sum(0),
            exists_prob=torch.stack(exists_prob) if exists_prob else None,
            cov=torch.stack(covs),
            history=stack_states(states) if history else None,
            meta=self.result_meta(),
        )

    def result_meta(self) -> dict:
        """What made a result (``FilterResult.meta``): the filter, its settings as plain
        values, the models, the sampling time and the versions.
        """
        dt = getattr(self.motion, "dt", None)
        return {"filter": type(self).__name__, "num_particles": self.num_particles,
                "settings": _plain(self.settings), "motion": type(self.motion).__name__,
                "sensor": type(self.sensor).__name__,
                "existence": None if self.existence is None else type(self.existence).__name__,
                "dt": None if dt is None else float(dt), "compile_step": self.compile_step,
                "versions": {"torchmcmcpf": str(__version__), "torch": str(torch.__version__)}}

    def _progress(self, num_steps: int, x: Tensor, progress: bool | None) -> tuple[Any, str | None]:
        """The loop over time: ``range(num_steps)``, or a tqdm bar when ``progress``. With
        ``compile_step=True`` and a shape not run compiled before, the bar says so while the
        first step compiles (``compiling (first call, about N s)``, :attr:`compile_seconds`)
        instead of sitting silent at 0; returns ``(steps, note)``.
        """
        key = (*x.shape, x.dtype, x.device)
        note = None
        if self.compile_step and key not in self._compiled_shapes:
            self._compiled_shapes.add(key)
            note = f"compiling (first call, about {self.compile_seconds:.0f} s)"
        if not progress:
            return range(num_steps), None
        from tqdm.auto import tqdm

        bar = tqdm(range(num_steps), desc=type(self).__name__, leave=False)
        if note:
            bar.set_postfix_str(note)
        return bar, note

    def extra_repr(self) -> str:
        """Particle count, settings and compile flag, shown inside ``repr(filter)``."""
        return f"num_particles={self.num_particles}, settings={self.settings}, compile_step={self.compile_step}"
