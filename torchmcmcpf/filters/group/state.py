"""The group filter's typed state: what it carries from step to step besides the weighted
cloud (:class:`GroupState`, with the fixed-lag path :class:`GroupPath`), held in a
:class:`~torchmcmcpf.state.ParticleState` under one key, ``extras["group"]`` (:data:`KEY`), and
validated by its type and shapes in one place (:meth:`GroupState.check`).

A ``ParticleState`` stays the one state type of every filter (``forward`` adds its estimate
to ``extras``, results stack and save alike); the group filter's fields are one typed value
in it instead of ten open keys. :class:`GroupState` is a typed carry (:func:`~torchmcmcpf.filters._carry.carry`:
``Filter.check_resume`` checks it as every filter's carries, a state saved with the open keys
is converted on resume); both tuples are registered with
:func:`torch.serialization.add_safe_globals`, so a result saved with ``torch.save`` loads with
``torch.load(weights_only=True)`` and resumes (``filt(z, init=result.state)``).

The maths of the fields: the docstring of :mod:`torchmcmcpf.filters.group`, "State and outputs".
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from ...state import ParticleState
from ...typing import Tensor
from .._carry import carry, check_fields

__all__ = ["GroupState", "GroupPath", "KEY"]

#: the key of ``ParticleState.extras`` under which the group filter carries its :class:`GroupState`
KEY = "group"


class GroupPath(NamedTuple):
    """The fixed-lag path ``t - P + 1 .. t`` of every particle (``lag >= 1``; ``P <= L + 1``
    entries, the first the anchor), run dim first.

    Attributes
    ----------
    pos : (B, N, P, K, 2) positions; labels : (B, N, P, K) int64, the structure of each entry;
    exists : (B, N, P, K) bool; log : (B, N, P), each entry's term of the target (eq. 43, the
        first zero); anchor_w_mean : (B, N, 2, 3K) and anchor_w_cov : (B, N, 3K, 3K), the
        Kalman statistics (eqs. 56-57) at the anchor.

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.filters.group import GroupPath
    >>> b, n, p, k = 1, 2, 3, 4
    >>> path = GroupPath(torch.zeros(b, n, p, k, 2), torch.zeros(b, n, p, k, dtype=torch.int64),
    ...                  torch.zeros(b, n, p, k, dtype=torch.bool), torch.zeros(b, n, p),
    ...                  torch.zeros(b, n, 2, 3 * k), torch.zeros(b, n, 3 * k, 3 * k))
    >>> path.length                     # P, the anchor included
    3
    """

    pos: Tensor
    labels: Tensor
    exists: Tensor
    log: Tensor
    anchor_w_mean: Tensor
    anchor_w_cov: Tensor

    @property
    def length(self) -> int:
        """P, the entries of the path (the anchor included)."""
        return self.pos.shape[2]


class GroupState(NamedTuple):
    """The group filter's fields of a state (``ParticleState.extras["group"]``), run dim first.

    Attributes
    ----------
    labels : (B, N, K) int64, the group structure (canonical labels, a row of
        :func:`~torchmcmcpf.models.group.group_structures`).
    w_mean : (B, N, 2, 3K) and w_cov : (B, N, 3K, 3K), the pairwise Kalman statistics of
        ``w = [velocities, leader positions, leader velocities]`` per axis (eqs. 56-57).
    frames : (B, F, H, W) bool, the last ``F`` frames (eq. 65 and the window birth).
    path : :class:`GroupPath` with ``lag >= 1``, else None.

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf import GroupMCMCFilter
    >>> from torchmcmcpf.filters.group import GroupState
    >>> from torchmcmcpf.scenarios.group_merge import group_merge
    >>> scn = group_merge(1, generator=torch.Generator().manual_seed(0), num_steps=2)
    >>> filt = GroupMCMCFilter(scn.motion, scn.sensor, 8, existence=scn.existence,
    ...                        structure_prior=scn.structure_prior, burn_in=2)
    >>> group = filt.init_inactive(1).extras["group"]
    >>> isinstance(group, GroupState), tuple(group.w_mean.shape), group.path is None   # (B, N, 2, 3K)
    (True, (1, 8, 2, 12), True)
    >>> state = filt.init_inactive(1)
    >>> group._replace(labels=group.labels[:, :4]).check(state, frame_shape=(100, 100))
    Traceback (most recent call last):
    ...
    ValueError: state.extras['group'].labels has shape (1, 4, 4), expected (1, 8, 4)
    """

    labels: Tensor
    w_mean: Tensor
    w_cov: Tensor
    frames: Tensor
    path: GroupPath | None = None

    def check(self, state: ParticleState, name: str = f"state.extras[{KEY!r}]", *,
              frame_shape: tuple[int, int] | None = None) -> None:
        """Every field's shape, dtype and device against the particles ``state.x (B, N, K, 4)``
        and frames of ``frame_shape = (H, W)`` (any when None); a ``ValueError`` naming the
        field, the shape seen and the shape expected otherwise.
        """
        x = state.x
        b, n, k, _ = x.shape
        h, w = frame_shape if frame_shape is not None else (None, None)
        real, flag, index = x.dtype, torch.bool, torch.int64
        f = self.frames.shape[1] if torch.is_tensor(self.frames) and self.frames.dim() == 4 else None
        fields: list[tuple[str, object, tuple[int | None, ...], torch.dtype]] = [
            ("labels", self.labels, (b, n, k), index), ("w_mean", self.w_mean, (b, n, 2, 3 * k), real),
            ("w_cov", self.w_cov, (b, n, 3 * k, 3 * k), real), ("frames", self.frames, (b, f, h, w), flag)]
        if self.path is not None:
            if not isinstance(self.path, GroupPath):
                raise ValueError(f"{name}.path must be a GroupPath or None, got {type(self.path).__name__}")
            pp = self.path
            p = pp.pos.shape[2] if torch.is_tensor(pp.pos) and pp.pos.dim() == 5 else None
            fields += [("path.pos", pp.pos, (b, n, p, k, 2), real), ("path.labels", pp.labels, (b, n, p, k), index),
                       ("path.exists", pp.exists, (b, n, p, k), flag), ("path.log", pp.log, (b, n, p), real),
                       ("path.anchor_w_mean", pp.anchor_w_mean, (b, n, 2, 3 * k), real),
                       ("path.anchor_w_cov", pp.anchor_w_cov, (b, n, 3 * k, 3 * k), real)]
        check_fields(name, fields, x.device)


#: the open keys of ``extras`` under which the group filter's states carried these fields before
#: they were typed (:func:`from_keys`): the four of :class:`GroupState`, then the path's six
_KEYS = ("labels", "w_mean", "w_cov", "frames")
_PATH_KEYS = ("path_pos", "path_labels", "path_exists", "path_log", "anchor_w_mean", "anchor_w_cov")


def from_keys(extras: dict) -> dict:
    """``extras`` with the group fields of a state saved before they were typed (the open
    keys ``labels``, ``w_mean``, ``w_cov``, ``frames`` and the ``path_*`` / ``anchor_*`` ones)
    gathered into one :class:`GroupState` under :data:`KEY`, the other keys kept; any other
    ``extras`` unchanged. Lets ``filt(z, init=old_result.state)`` resume an old checkpoint.
    """
    if KEY in extras or not all(k in extras for k in _KEYS):
        return extras
    rest = {k: v for k, v in extras.items() if k not in _KEYS + _PATH_KEYS}
    path = GroupPath(*(extras[k] for k in _PATH_KEYS)) if all(k in extras for k in _PATH_KEYS) else None
    return {**rest, KEY: GroupState(extras["labels"], extras["w_mean"], extras["w_cov"], extras["frames"], path)}


carry(KEY, convert=from_keys)(GroupState)  # its key, torch.load(weights_only=True), old keys
torch.serialization.add_safe_globals([GroupPath])
