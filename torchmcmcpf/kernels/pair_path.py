"""A triggered move on a pair's recent past: conditional SMC with ancestor sampling over a
fixed-lag window, for two target slots that came close (issue 50).

Why
---
Where two targets stay unresolved for tens of frames and then separate, a fixed-slot filter's
cloud can hold a *ghost arrangement* that one frame scores nearly as well as the truth; the
filtering prior built from such a cloud charges the repaired state hundreds of nats, so no
move within one frame leaves it, while the model's posterior over the last 20-60 frames
prefers the truth (docs/tracks.md). This move re-draws the two slots' *paths* over the last
``W <= L`` frames jointly, conditioned on the window's first state, so the data of the whole
window decide between the arrangements.

The density it leaves invariant
-------------------------------
The model's path posterior (the filtering recursion of Khan, Balch and Dellaert 2005, with
the exclusion factor ``Phi`` on each time's state, read over paths),

    (1)  ``pi(x_{0:t} | z_{1:t}) ∝ p(x_0) prod_{s=1..t} f(x_s | x_{s-1}) Phi(x_s) p(z_s | x_s)``,

with ``f(x_s | x_{s-1}) = prod_k f(x_{s,k} | x_{s-1,k})`` the motion model of every slot.
For a pair of slots ``(a, b)`` and the window ``s_0 + 1 .. t`` (``s_0 = t - W``), its
conditional given everything outside the pair's window is, by the Markov property,

    (2)  ``pi(x^{ab}_{s_0+1:t} | x^{ab}_{s_0}, x^{-ab}_{s_0+1:t}, z_{s_0+1:t})
            ∝ prod_{s=s_0+1..t} f(x^a_s | x^a_{s-1}) f(x^b_s | x^b_{s-1}) Phi(x_s) p(z_s | x_s)``,

``x_s`` the state of all ``K`` slots with the pair's two at ``x^{ab}_s`` and the others at
their (fixed) path. :func:`conditional_smc` is a Markov kernel that leaves (2) invariant, so
it is a Gibbs block of (1) and leaves (1), hence its filtering marginal at ``t``, invariant
(resample-move on paths: Gilks and Berzuini 2001; the fixed-lag window of Doucet, Briers and
Senecal 2006). The re-capture tail of :class:`~torchmcmcpf.models.multitarget.Recapture`
(``delta = 1e-3``) is not part of ``f`` here: (2) is the posterior under the motion model
itself, and a relocation jump inside the window is one of the arrangements it may replace.

The kernel (Andrieu, Doucet and Holenstein 2010, the conditional SMC of particle Gibbs; Lindsten,
Jordan and Schon 2014, ancestor sampling), ``M`` particles of the pair, the motion model as
proposal (both slots), the reference path ``x'`` (the particle's current pair path) kept as
particle ``M - 1``:

- ``s = s_0 + 1``: ``x^m_s ~ f(. | x'_{s_0})`` for ``m < M - 1``; ``x^{M-1}_s = x'_s``;
- ``s > s_0 + 1``: ``a^m ~ Cat(w_{s-1})`` and ``x^m_s ~ f(. | x^{a^m}_{s-1})`` for
  ``m < M - 1``; ``x^{M-1}_s = x'_s`` with its ancestor drawn anew,

      (3)  ``P(a^{M-1} = i) ∝ w^i_{s-1} f(x'_s | x^i_{s-1})``  (ancestor sampling);

- weights ``log w^m_s = log p(z_s | x^m_s) + log Phi(x^m_s)`` (others at their path);
- the output path: ``m ~ Cat(w_t)`` traced back through the ancestors.

With ``M >= 2`` the kernel is invariant for (2) for any ``M`` (the invariance results of both
papers); ancestor sampling lets the output leave the reference's early part.
Tested against the exact Gaussian conditional (a Kalman smoother's, by conditioning) on a
linear-Gaussian model, and against an importance-sampling oracle with exclusion
(``tests/kernels/test_pair_path.py``).

The trigger and the filter's window (:func:`pair_path_update`)
-------------------------------------------------------------
Paths need genealogy: the filter state keeps, per particle, the last ``L + 1`` states of
every slot (``extras["pair_path"].x (B, N, L + 1, K, D)``, a :class:`PairPathWindow`: each new particle's slot ``k``
continues the path of its source particle's slot ``k``, the previous particle its proposal
came from) and the last ``L`` frames (``.z (B, L, *G)``). Memory per run:
``4 (N (L + 1) K D + L G)`` bytes in float32 (the crossing, ``N = 500, L = 50, K = 2``, G =
the grid's cells: 1.0 MB of paths; bench's 10-target radar at ``N = 500``: 5.1 MB of paths
and 12.2 MB of frames). It fires for a run when two slots' *predicted estimates* (the
previous step's, before the chains run: the move's choice does not depend on the new
particles) came within ``distance`` resolution cells
(:meth:`~torchmcmcpf.models.base.SensorModel.resolution_coords`) during the last ``L``
frames and ``every`` steps have passed since it last fired; one such pair is drawn uniformly
per run and the kernel moves ``num_paths`` particles of the run (at a fixed stride, so the
choice does not depend on their values) over the window ``W = min(L, frames seen)``. One call
costs ``num_paths * M * W`` pair likelihoods in ``W`` batched evaluations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch

from .._native.select import where
from .._validation import check_fields, check_positive, check_positive_int
from ..models.base import MotionModel, SensorModel
from ..models.multitarget import Exclusion, log_exclusion
from ..resampling import cdf, inverse_cdf
from ..runtime import pairwise_squared_distances, take_along
from ..typing import Measurement, Tensor

__all__ = ["PairPath", "PairPathWindow", "conditional_smc", "pair_path_update", "window_bytes"]

#: the window's fields by name inside :func:`pair_path_update` (:class:`PairPathWindow`'s order)
_KEYS = ("pair_path_x", "pair_path_z", "pair_path_frames", "pair_path_since", "pair_path_clock")


@dataclass(frozen=True)
class PairPath:
    """Settings of the triggered pair-path move (module docstring).

    Attributes
    ----------
    lag : L >= 1, frames of the window (and of each particle's stored path).
    distance : > 0, resolution cells: a pair whose predicted estimates came this close in
        the last ``lag`` frames triggers the move.
    every : >= 1, a run fires at most once every ``every`` steps.
    num_paths : >= 1, particles of a run the move re-draws per call (at most N).
    num_particles : M >= 2, particles of the conditional SMC.

    Example
    -------
    >>> from torchmcmcpf.kernels.pair_path import PairPath
    >>> PairPath(lag=50).distance, PairPath().num_particles
    (1.5, 32)
    >>> PairPath(num_particles=1)
    Traceback (most recent call last):
    ...
    ValueError: num_particles must be an integer >= 2, got 1
    """

    lag: int = 50
    distance: float = 1.5
    every: int = 5
    num_paths: int = 8
    num_particles: int = 32

    def __post_init__(self):
        object.__setattr__(self, "lag", check_positive_int(self.lag, "lag"))
        object.__setattr__(self, "distance", check_positive(self.distance, "distance"))
        object.__setattr__(self, "every", check_positive_int(self.every, "every"))
        object.__setattr__(self, "num_paths", check_positive_int(self.num_paths, "num_paths"))
        object.__setattr__(self, "num_particles", check_positive_int(self.num_particles, "num_particles", minimum=2))


class PairPathWindow(NamedTuple):
    """The move's window in the filter state, ``extras["pair_path"]`` (module docstring), a
    typed carry (:mod:`torchmcmcpf.filters._carry`; the IP-MCMC-PF registers it).

    Attributes
    ----------
    x : (B, N, L + 1, K, D), each particle's last ``L + 1`` states per slot (the last: ``x``).
    z : (B, L, *G), the last ``L`` frames (the newest last).
    frames : (B,) int64, frames seen, at most ``L``.
    since : (B, K, K) int64, steps since each pair of slots came close (``L``: not within the
        window).
    clock : (B,) int64, steps since the move last fired.

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.kernels.pair_path import PairPathWindow
    >>> w = PairPathWindow(torch.zeros(2, 10, 4, 2, 4), torch.zeros(2, 3, 8, 8), torch.zeros(2, dtype=torch.int64),
    ...                    torch.full((2, 2, 2), 3), torch.zeros(2, dtype=torch.int64))
    >>> w.lag
    3
    """

    x: Tensor
    z: Tensor
    frames: Tensor
    since: Tensor
    clock: Tensor

    @property
    def lag(self) -> int:
        """L, the frames the window holds."""
        return self.z.shape[1]

    def check(self, state: Any, name: str = "state.extras['pair_path']", *, lag: int | None = None) -> None:
        """Every field against ``state.x (B, N, K, D)`` (and ``lag`` when given): shapes,
        dtypes and device; a ``ValueError`` naming the field and both shapes otherwise.
        """
        b, n, k, d = state.x.shape
        el = self.lag if lag is None else lag
        rows = [("x", self.x, (b, n, el + 1, k, d), state.x.dtype),
                ("z", self.z, (b, el) + tuple(self.z.shape[2:]), None),
                ("frames", self.frames, (b,), torch.int64), ("since", self.since, (b, k, k), torch.int64),
                ("clock", self.clock, (b,), torch.int64)]
        check_fields(name, rows, state.x.device)


def window_bytes(num_particles: int, num_targets: int, dim: int, num_cells: int, lag: int,
                 itemsize: int = 4) -> int:
    """Bytes per run of the move's window in the filter state: ``N (L + 1) K D`` path entries
    and ``L G`` frame cells (module docstring).

    >>> window_bytes(500, 2, 5, 0, 50)           # the crossing's paths, float32
    1020000
    """
    return itemsize * (num_particles * (lag + 1) * num_targets * dim + lag * num_cells)


def _set_pair(x: Tensor, pair_x: Tensor, pair: Tensor) -> Tensor:
    """``x (B, *S, K, D)`` with slots ``pair (B, 2)`` set to ``pair_x (B, *S, 2, D)``."""
    k = x.shape[-2]
    shape = (pair.shape[0],) + (1,) * (x.dim() - 3) + (k,)
    slots = torch.arange(k, device=x.device)
    at_a = (slots == pair[:, :1]).reshape(shape).unsqueeze(-1)
    at_b = (slots == pair[:, 1:]).reshape(shape).unsqueeze(-1)
    return where(at_a, pair_x[..., 0:1, :], where(at_b, pair_x[..., 1:2, :], x))


def _get_pair(x: Tensor, pair: Tensor) -> Tensor:
    """Slots ``pair (B, 2)`` of ``x (B, *S, K, D)``: ``(B, *S, 2, D)``."""
    idx = pair.reshape((pair.shape[0],) + (1,) * (x.dim() - 3) + (2, 1))
    return take_along(x, idx, -2)


def conditional_smc(path: Tensor, frames: Tensor, pair: Tensor, *, motion: MotionModel, sensor: SensorModel,
                    exclusion: Exclusion | None = None, num_particles: int = 32,
                    generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """One conditional SMC kernel with ancestor sampling on the paths of two slots over a
    window of ``W`` frames (module docstring, eqs. 2-3): invariant for the pair's
    conditional path posterior given the window's first state and the other slots' paths.

    Parameters
    ----------
    path : (B, P, W + 1, K, D) the current paths of ``P`` particles per run (entry 0: the
        state before the first frame, held fixed; entries 1..W: the states at the frames).
    frames : (W, B, *G) the window's frames (a tensor measurement per run).
    pair : (B, 2) int64, the two slots moved in each run (distinct).
    motion : the per-slot motion model (``propagate``, ``log_prob``); sensor : the
        SensorModel (``log_likelihood`` of ``(B, P, M, K, D)`` states); exclusion : the
        exclusion factor ``Phi`` of the target, optional.
    num_particles : M >= 2 particles of the pair.
    generator : the only source of randomness.

    Returns
    -------
    path : (B, P, W + 1, K, D), the new paths (the other slots and entry 0 unchanged);
    moved : (B, P) bool, whether the pair's state at the last frame changed.
    """
    if path.dim() != 5:
        raise ValueError(f"path has shape {tuple(path.shape)}, expected (B, P, W + 1, K, D)")
    b, p, w1, k, d = path.shape
    w = w1 - 1
    if w < 1:
        raise ValueError(f"path has {w1} entries, expected at least 2 (the start and one frame)")
    if k < 2:
        raise ValueError(f"path has K = {k} slots, expected at least 2 (a pair)")
    if not torch.is_tensor(frames) or frames.shape[:2] != (w, b):
        raise ValueError(f"frames must be a tensor (W, B, *G) = ({w}, {b}, ...), got "
                         f"{tuple(frames.shape) if torch.is_tensor(frames) else type(frames).__name__}")
    if pair.shape != (b, 2) or bool((pair[:, 0] == pair[:, 1]).any()) or bool(((pair < 0) | (pair >= k)).any()):
        raise ValueError(f"pair must be (B, 2) = ({b}, 2) distinct slots in [0, {k}), got {pair.tolist()}")
    m = check_positive_int(num_particles, "num_particles", minimum=2)
    dev, dt = path.device, path.dtype
    ref = _get_pair(path, pair)  # (B, P, W + 1, 2, D)
    states, ancestors = [], []  # per frame: (B, P, M, 2, D), (B, P, M)
    prev = ref[:, :, 0].unsqueeze(2).expand(b, p, m, 2, d)
    log_w = None
    rows = torch.arange(m, device=dev)
    for s in range(1, w + 1):
        r_s = ref[:, :, s]  # (B, P, 2, D)
        if log_w is None:  # every particle starts at the window's fixed first state
            anc = torch.zeros((b, p, m), dtype=torch.int64, device=dev)
        else:
            u = torch.rand((b * p, m), generator=generator, device=dev, dtype=torch.float64)
            free = inverse_cdf(cdf(log_w.reshape(b * p, m)), u[:, : m - 1])
            # eq. 3: the reference's ancestor, w^i f(x'_s | x^i_{s-1})
            log_as = log_w + motion.log_prob(r_s.unsqueeze(2).expand_as(prev), prev).sum(-1)
            back = inverse_cdf(cdf(log_as.reshape(b * p, m)), u[:, m - 1:])
            anc = torch.cat([free, back], -1).reshape(b, p, m)
        parent = take_along(prev, anc.reshape(b, p, m, 1, 1), 2)
        eps = torch.randn((b, p, m, 2, motion.noise_dim), generator=generator, device=dev, dtype=dt)
        x_s = motion.propagate(parent, eps)
        x_s = where((rows == m - 1).reshape(1, 1, m, 1, 1), r_s.unsqueeze(2), x_s)
        full = _set_pair(path[:, :, s].unsqueeze(2).expand(b, p, m, k, d), x_s, pair)  # (B, P, M, K, D)
        log_w = sensor.log_likelihood(full, frames[s - 1]) + log_exclusion(exclusion, sensor, full)
        log_w = torch.nan_to_num(log_w.to(torch.float64), nan=-math.inf)
        states.append(x_s)
        ancestors.append(anc)
        prev = x_s
    if log_w is None:  # unreachable: w >= 1 frames were weighed
        raise ValueError("path has no frame to weigh")
    u = torch.rand((b * p, 1), generator=generator, device=dev, dtype=torch.float64)
    pick = inverse_cdf(cdf(log_w.reshape(b * p, m)), u).reshape(b, p, 1)  # (B, P, 1)
    out = []
    for s in range(w, 0, -1):  # trace the chosen particle back through its ancestors
        out.append(take_along(states[s - 1], pick.reshape(b, p, 1, 1, 1), 2).squeeze(2))
        pick = take_along(ancestors[s - 1], pick, 2)
    new_pair = torch.stack([ref[:, :, 0]] + out[::-1], 2)  # (B, P, W + 1, 2, D)
    moved = (new_pair[:, :, -1] != ref[:, :, -1]).flatten(-2).any(-1)
    return _set_pair(path, new_pair, pair), moved


def _advance(extras: dict, x_new: Tensor, source: Tensor, z: Tensor, lag: int) -> dict:
    """The window one frame on: each new particle's slot ``k`` continues its source's path of
    slot ``k``; the oldest state and frame drop out once ``lag`` frames are held.
    """
    paths = extras["pair_path_x"]  # (B, N, L + 1, K, D)
    b, n, l1, k, d = paths.shape
    by_slot = paths.permute(0, 3, 1, 2, 4)  # (B, K, N, L + 1, D)
    idx = source.permute(0, 2, 1).reshape(b, k, n, 1, 1)
    inherited = take_along(by_slot, idx, 2).permute(0, 2, 3, 1, 4)  # (B, N, L + 1, K, D)
    paths = torch.cat([inherited[:, :, 1:], x_new.unsqueeze(2)], 2)
    frames = torch.cat([extras["pair_path_z"][:, 1:], z.unsqueeze(1).to(extras["pair_path_z"].dtype)], 1)
    count = (extras["pair_path_frames"] + 1).clamp(max=lag)
    return {**extras, "pair_path_x": paths, "pair_path_z": frames, "pair_path_frames": count}


def _fresh(x_prev: Tensor, z: Tensor, lag: int) -> dict:
    """The window of a state that has none: the previous cloud as every past entry, no frame."""
    b, n, k, d = x_prev.shape
    return {"pair_path_x": x_prev.unsqueeze(2).expand(b, n, lag + 1, k, d).clone(),
            "pair_path_z": torch.zeros((b, lag) + tuple(z.shape[1:]), dtype=z.dtype, device=z.device),
            "pair_path_frames": torch.zeros(b, dtype=torch.int64, device=x_prev.device),
            "pair_path_since": torch.full((b, k, k), lag, dtype=torch.int64, device=x_prev.device),
            "pair_path_clock": torch.full((b,), 1 << 30, dtype=torch.int64, device=x_prev.device)}


def pair_path_update(window: PairPathWindow | None, x_prev: Tensor, centre: Tensor, x_new: Tensor, source: Tensor,
                     z: Measurement,
                     *, motion: MotionModel, sensor: SensorModel, exclusion: Exclusion | None, settings: PairPath,
                     generator: torch.Generator) -> tuple[Tensor, PairPathWindow, dict]:
    """One step of the move's bookkeeping and, where it fires, the move (module docstring).

    Parameters
    ----------
    window : the previous state's :class:`PairPathWindow` (None, or one of another size: a
        fresh window).
    x_prev : (B, N, K, D) the previous particles; centre : (B, K, D) the predicted estimate
        of each slot (from the previous cloud: the trigger).
    x_new : (B, N, K, D) the new particles; source : (B, N, K) int64, the previous particle
        each new slot came from.
    z : (B, *G) this step's frame (a tensor measurement).
    motion, sensor, exclusion : the filter's models and exclusion factor.
    settings : :class:`PairPath`; generator : the only source of randomness.

    Returns
    -------
    x_new : (B, N, K, D) with the moved particles' pairs at their new state;
    window : the new state's :class:`PairPathWindow`;
    report : ``"pair_path_fired" (B,)`` (0/1) and ``"pair_path_moved" (B,)`` (the share of
    the moved particles whose pair changed at the last frame), floats.
    """
    if not torch.is_tensor(z):
        raise ValueError(f"z must be a tensor frame (B, *G) for the pair-path move, got {type(z).__name__}")
    if not sensor.resolved:
        raise ValueError(f"the pair-path move needs a sensor with a resolution (resolution_coords); "
                         f"{type(sensor).__name__} declares none")
    b, n, k, d = x_new.shape
    if source.shape != (b, n, k):
        raise ValueError(f"source has shape {tuple(source.shape)}, expected {(b, n, k)}")
    lag = settings.lag
    old = {} if window is None else dict(zip(_KEYS, window))
    if not old or old["pair_path_x"].shape != (b, n, lag + 1, k, d):
        old = _fresh(x_prev, z, lag)
    # the trigger, from the previous cloud's prediction
    u = sensor.resolution_coords(centre)  # (B, K, r)
    close = pairwise_squared_distances(u, u) < settings.distance ** 2
    since = where(close, 0, (old["pair_path_since"] + 1).clamp(max=lag))
    new = _advance({**old, "pair_path_since": since}, x_new, source, z, lag)
    upper = torch.ones((k, k), dtype=torch.bool, device=x_new.device).triu(1)
    eligible = (since < lag) & upper  # (B, K, K)
    frames = int(new["pair_path_frames"][0])  # every run has seen the same frames
    fire = eligible.flatten(1).any(-1) & (old["pair_path_clock"] + 1 >= settings.every) & (frames >= 1)
    new["pair_path_clock"] = where(fire, 0, old["pair_path_clock"] + 1)
    report = {"pair_path_fired": fire.to(x_new.dtype), "pair_path_moved": torch.zeros(b, dtype=x_new.dtype,
                                                                                     device=x_new.device)}
    runs = fire.nonzero().squeeze(1)  # one host read; only the runs that fire pay
    if runs.numel() == 0:
        return x_new, PairPathWindow(*(new[key] for key in _KEYS)), report
    log_p = where(eligible[runs].flatten(1), 0.0, -math.inf).to(torch.float64)
    at = inverse_cdf(cdf(log_p), torch.rand((runs.numel(), 1), generator=generator, device=x_new.device,
                                            dtype=torch.float64)).squeeze(1)
    pair = torch.stack([at // k, at % k], -1)  # (R, 2), a < b
    p = min(settings.num_paths, n)
    chosen = torch.arange(p, device=x_new.device) * (n // p)  # a fixed stride
    paths_w = new["pair_path_x"][runs][:, chosen, lag - frames:]  # (R, P, W + 1, K, D)
    zs = new["pair_path_z"][runs][:, lag - frames:].movedim(1, 0)  # (W, R, *G)
    moved_path, moved = conditional_smc(paths_w, zs, pair, motion=motion, sensor=sensor, exclusion=exclusion,
                                        num_particles=settings.num_particles, generator=generator)
    paths = new["pair_path_x"].clone()
    sub = paths[runs]
    sub[:, chosen, lag - frames:] = moved_path
    paths[runs] = sub
    new["pair_path_x"] = paths
    x_new = paths[:, :, -1].contiguous()
    report["pair_path_moved"][runs] = moved.to(x_new.dtype).mean(-1)
    return x_new, PairPathWindow(*(new[key] for key in _KEYS)), report
