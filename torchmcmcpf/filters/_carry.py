"""Typed carries: what a filter keeps in ``ParticleState.extras`` from step to step, one typed
value (a ``NamedTuple`` of tensors, run dim first) under one key, validated by its type.

A carry type is a ``NamedTuple`` with a ``check(state, name, **sizes)`` method (the
:class:`Carry` protocol: every field's shape, dtype and device against the state's ``x (B, N,
K, D)``, a ``ValueError`` naming the field, the shape seen and the shape expected; the
``sizes`` a filter knows besides the state, such as the number of candidates, keyword
arguments that default to "any"), registered with :func:`carry`:

- under its key of ``extras`` (:func:`carry_type` finds the type of a key), so that
  :meth:`Filter.check_resume <torchmcmcpf.filters.base.Filter.check_resume>` checks every
  carried value of a state the same way (:func:`check_carries`);
- with :func:`torch.serialization.add_safe_globals`, so that a result saved with
  ``torch.save`` loads with ``torch.load(weights_only=True)`` and resumes;
- with the open keys under which older states held its fields, so that ``forward(init=...)``
  and ``step`` resume such a state (:func:`typed_extras` gathers them into the type).

``stack_states`` stacks a typed value field by field (a ``NamedTuple`` is a pytree), so a
``history`` of states needs nothing more. The carries of the library:
:class:`CarriedEstimate` (``forward``'s estimate, every filter, here),
:class:`~torchmcmcpf.filters.pmmh.PMMHState` and
:class:`~torchmcmcpf.filters.group.GroupState`.

To give a filter's state a new carry (say a fixed-lag window of five tensors):

1. write ``class Window(NamedTuple)`` with the five fields (shapes in the docstring) and a
   ``check(self, state, name=..., *, lag=None)`` that lists ``(field, tensor, shape,
   dtype)`` rows and hands them to :func:`check_fields`;
2. decorate it with ``@carry("window", old_keys=(...))`` (the open keys it replaces, in field
   order, if states were ever saved with them);
3. set the filter's ``state_extras = frozenset({"window"})`` (a carry present only with some
   settings: set it on the instance once the settings are bound, ``self.state_extras =
   frozenset({"window"}) if self.settings.window else frozenset()``, since
   ``check_resume`` refuses a key the filter does not list) and return the sizes it knows
   from :meth:`Filter.carry_sizes <torchmcmcpf.filters.base.Filter.carry_sizes>`
   (``{"window": {"lag": L}}``);
4. the step reads ``state.extras["window"].paths`` and writes ``{**extras, "window": new}``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple, Protocol, cast

import torch

from .._validation import check_fields
from ..state import ExistenceEstimate, ParticleState
from ..typing import Tensor

__all__ = ["Carry", "CarriedEstimate", "ESTIMATE", "carry", "carry_type", "check_carries", "check_fields",
           "typed_extras"]


class Carry(Protocol):
    """What a typed carry offers (module docstring): its key of ``extras`` and one check."""

    KEY: str

    def check(self, state: ParticleState, name: str = ..., **sizes: Any) -> None:
        """Every field against ``state`` (and the ``sizes`` given); ``ValueError`` otherwise."""


#: key of ``extras`` -> its carry type, and the converter of the open keys it replaced
_TYPES: dict[str, type] = {}
_CONVERT: dict[str, Callable[[dict], dict]] = {}


def carry(key: str, *, old_keys: Sequence[str] = (), convert: Callable[[dict], dict] | None = None
          ) -> Callable[[type], type]:
    """Class decorator that registers a carry type under ``key`` (module docstring): sets its
    ``KEY``, allows it in ``torch.load(weights_only=True)`` and records how an older state's
    ``extras`` become typed: ``convert(extras) -> extras``, or by default, where every one of
    ``old_keys`` (the type's fields in order) is present and ``key`` is not, the type built
    from them, the old keys dropped.
    """
    def register(cls: type) -> type:
        cls.KEY = key  # type: ignore[attr-defined]
        _TYPES[key] = cls
        torch.serialization.add_safe_globals([cls])
        if convert is not None:
            _CONVERT[key] = convert
        elif old_keys:
            def from_keys(extras: dict) -> dict:
                if key in extras or not all(k in extras for k in old_keys):
                    return extras
                rest = {k: v for k, v in extras.items() if k not in old_keys}
                return {**rest, key: cls(*(extras[k] for k in old_keys))}
            _CONVERT[key] = from_keys
        return cls
    return register


def carry_type(key: str) -> type | None:
    """The carry type registered under ``key`` of ``extras``, or None."""
    return _TYPES.get(key)


def typed_extras(extras: Any) -> Any:
    """``extras`` with the open keys of an older state gathered into their carry types (each
    registered conversion in turn, :func:`carry`); anything else unchanged.
    """
    if not isinstance(extras, dict):
        return extras
    for convert in _CONVERT.values():
        extras = convert(extras)
    return extras


def check_carries(state: ParticleState, sizes: Mapping[str, Mapping[str, Any]] | None = None) -> None:
    """Check every typed value of ``state.extras``: the value under a registered key must be
    of its type (:func:`carry`) and pass its ``check`` with the ``sizes`` given for that key;
    a ``ValueError`` naming ``state.extras[key]`` otherwise. Keys of no carry type pass.
    """
    for key, value in (state.extras or {}).items():
        cls = _TYPES.get(key)
        if cls is None:
            continue
        name = f"state.extras[{key!r}]"
        if not isinstance(value, cls):
            raise ValueError(f"{name} must be a {cls.__name__}, got {type(value).__name__} "
                             "(build the state with the filter's init, or resume one of its results)")
        cast(Carry, value).check(state, name, **dict((sizes or {}).get(key, {})))


#: the key of ``ParticleState.extras`` under which ``forward`` carries its last estimate
#: (:class:`CarriedEstimate`): the reference of the next step's relabelling
ESTIMATE = "estimate"
#: the open key under which older states held the estimate's ``present`` flags (converted on resume)
_PRESENT = "estimate_present"


def _estimate_from_keys(extras: dict) -> dict:
    """An older state's estimate (a tensor under ``"estimate"``, the flags under
    ``"estimate_present"``) as one :class:`CarriedEstimate`; other ``extras`` unchanged.
    """
    if not (torch.is_tensor(extras.get(ESTIMATE)) and _PRESENT in extras):
        return extras
    rest = {k: v for k, v in extras.items() if k not in (ESTIMATE, _PRESENT)}
    return {**rest, ESTIMATE: CarriedEstimate(extras[ESTIMATE], extras[_PRESENT].to(torch.bool))}


@carry(ESTIMATE, convert=_estimate_from_keys)
class CarriedEstimate(NamedTuple):
    """The estimate ``forward`` carries in a state (``extras["estimate"]``): the reference of
    the next step's relabelling, so that a resumed run labels its targets as the uninterrupted
    one does (:meth:`Filter.estimate_targets <torchmcmcpf.filters.base.Filter.estimate_targets>`).

    Attributes
    ----------
    mean : (B, K, D), the last step's estimate of each slot.
    present : (B, K) bool, the slots it reported (all True without existence).

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> from torchmcmcpf.filters import CarriedEstimate
    >>> filt = tp.SIRFilter(tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0), 50)
    >>> result = filt(torch.zeros(3, 2, 2, 2), init=torch.zeros(2, 50, 2, 4), generator=torch.Generator())
    >>> carried = result.state.extras["estimate"]
    >>> isinstance(carried, CarriedEstimate), tuple(carried.mean.shape), tuple(carried.present.shape)
    (True, (2, 2, 4), (2, 2))
    >>> carried._replace(present=carried.present[:1]).check(result.state)
    Traceback (most recent call last):
    ...
    ValueError: state.extras['estimate'].present has shape (1, 2), expected (2, 2)
    """

    mean: Tensor
    present: Tensor

    def check(self, state: ParticleState, name: str = f"state.extras[{ESTIMATE!r}]") -> None:
        """``mean (B, K, D)`` of the dtype of ``state.x (B, N, K, D)`` and ``present (B, K)``
        bool, on its device; a ``ValueError`` naming the field and the shapes otherwise.
        """
        b, _, k, d = state.x.shape
        check_fields(name, [("mean", self.mean, (b, k, d), state.x.dtype),
                            ("present", self.present, (b, k), torch.bool)], state.x.device)

    def as_estimate(self) -> ExistenceEstimate:
        """The :class:`~torchmcmcpf.state.ExistenceEstimate` it stands for (``exists_prob`` the
        flags as numbers), the ``reference`` of ``Filter.estimate_targets``.
        """
        prob = self.present.to(self.mean.dtype)
        return ExistenceEstimate(prob, prob.sum(-1), self.mean, self.present)
