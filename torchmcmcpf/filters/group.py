"""Marginalised MCMC-based particle filter for coordinated groups (Septier, Pang, Godsill and
Carmi 2009, paper 004, sec. 4, Algorithms 1-2, eqs. 59-66), with a fixed-lag move on each
target's recent past.

The state of a particle is ``(x_{p,t}, g_t, e_t)``: the positions ``x_p (K, 2)``, the group
structure ``g`` (canonical labels ``(K,)``, row ``g`` of
:func:`~torchmcmcpf.models.group.group_structures`) and the existence flags ``e (K,)`` of
``K = N_max`` slots; the velocities and the virtual leaders ``w`` are integrated out by one
pairwise Kalman filter per particle (:mod:`torchmcmcpf.models.group`, eqs. 42-58). Each chain
samples the target of eq. 43 with the previous cloud in place of the previous posterior
(eq. 59),

    pi(j, g, e, x) ∝ w_j p(g | j) p(e | e^j) p(x | j, g, e) p(Z_t | x, e),

``j`` the index of the previous particle (its whole past), ``w_j`` its weight (``1 / N`` for
an MCMC cloud), ``p(g | j)`` eq. 19 from ``(x_p^j, g^j, e^j)``, ``p(e | e^j)`` eq. 25,
``p(x | j, g, e) = prod_{free births} p_0(x_i) N(x_obs; x~, L)`` (eq. 44: the uniform
``p_0`` of eq. 33 for the independent newborns ``Upsilon_2^1``, the pairwise Kalman
predictive of eq. 58 for the survivors and group births, a point mass at ``x_death`` for the
dead slots) and ``p(Z | x, e)`` the thresholded-pixel likelihood ratio (eqs. 39-41).

Moves and their acceptance ratios
---------------------------------
**Joint draw** (Algorithm 1, eq. 60). Propose ``j* ~ q(j) = P_a alpha_j + (1 - P_a) w_j``
(eqs. 61-62), ``g* ~ p(g | j*)`` (eq. 19), ``e* ~ p(e | e^{j*})`` (eq. 25), the survivors'
and group births' positions from the Kalman predictive ``N(x~, L)`` (eq. 58) and the
independent newborns' from the data-driven ``q_0`` (eqs. 63-65). The prior terms cancel:

    rho_1 = min(1, [p(Z|x*, e*) w_{j*} / q(j*) prod_{free*} p_0(x*_i) / q_0(x*_i)]
                 / [p(Z|x, e)   w_j    / q(j)  prod_{free}  p_0(x_i)  / q_0(x_i) ]).

Any ``alpha`` and any ``q_0`` keep the move exact (they are proposals): ``alpha="mean"``
scores particle ``j``'s predicted mean positions with its structure and existence unchanged,
``alpha_j ∝ w_j p(Z_t | x~^j, e^j)`` (eq. 62); ``alpha="predictive"`` by its predictive
likelihood ``w_j prod_i [(1 - P_D) E_{N(x~_i, L_ii)} p(Z_t | x_i) + P_D]`` over its live
slots (the Gaussian's mass on each pixel of a 5 x 5 window times the pixel's ratio, 1 outside:
a target 2 m from a pixel edge counts half, not all or nothing). ``birth="eq65"`` draws
newborns on the detections of ``Z_t`` with a detection of ``Z_{t-1}`` in their 3 x 3
neighbourhood (eq. 65); ``birth="frame"`` on every detection of ``Z_t``, so a target can be
born at its first detection.

**Structure** (Algorithm 2, steps 1-3). Propose ``g* ~ p(g | j)``; ``p(g | j)`` cancels and
``rho_2 = min(1, p(x | j, g*, e) / p(x | j, g, e))``.

**Each target** (Algorithm 2, steps 4-10, eq. 66), for slot ``i = 0 .. K-1`` in turn:
``e_i* ~ p(e_i | e^j_i)`` (cancels), then ``x_i*`` from ``q_i``: the conditional of the
Kalman predictive given the other observed slots if ``i`` is a survivor or a group birth,
``q_0`` if an independent newborn, ``x_death`` if dead:

    rho_3 = min(1, [p(Z|x*, e*) p(x* | j, g, e*) / q_i(x_i* | x_rest, e*)]
                 / [p(Z|x, e)   p(x  | j, g, e)  / q_i(x_i  | x_rest, e) ]).

**A target's recent past** (``lag = L >= 1``; issue 23). With the tiny process noise of
Table 1 (a predictive standard deviation of about 2 m against 50 m pixels), a particle's
velocities are fixed by its own past positions, and the moves above can change them only by
changing the ancestor ``j`` (the joint draw, which must then predict every target at once).
This move changes the past instead, as in MCMC-based smoothing (fixed-lag resample-move,
Gilks and Berzuini 2001): each chain carries its own copy of its ancestor's positions at
``t - L .. t - 1``, ``x_w`` (the window), and its pairwise Kalman statistics are re-run from
those at ``t - L - 1`` (stored per particle, the *anchor*). The target is extended to the
window given the ancestor's prefix ``x^j_{0:t-L-1}``,

    pi(j, x_w, g, e, x) ∝ w_j prod_{s in window} p(x_s | x_{0:s-1}) p(g_s | .) p(Z_s | x_s)
                           / c_j  x  p(g | x_w) p(e | e^j) p(x | x_w, g, e) p(Z_t | x, e),

whose marginal in ``(j, g, e, x)`` is the posterior when the window's conditional given
the prefix is exact (``c_j`` its normaliser, the same for every window of ``j``). The move
picks one slot ``i`` and translates its live positions at ``t - L .. t`` by ``a + b (s - t)``
(``a, b ~ N(0, diag(past_step^2))`` per axis: a shift and a change of velocity, a symmetric
proposal), re-runs the Kalman filter over the window from the anchor and accepts with

    rho_4 = min(1, pi(j, x_w*, g, e, x*) / pi(j, x_w, g, e, x))

(``w_j``, ``c_j``, ``p(e | e^j)`` cancel; the structure prior terms stay, as they depend on
the positions). A mispredicted target is then corrected in place rather than killed and
re-born. The joint draw copies ``j*``'s window as it is, i.e. treats the previous particles'
windows as draws from their conditional (the sequential MCMC approximation, eq. 59, one
level down); each move is invariant for its target (tests/filters/test_group_filter.py).

**A target born in the window** (``p_window_birth > 0``, ``lag >= 1``; issue 23). The cloud
is joint over the ``K`` slots: a target first detected at ``t - 1`` is carried by the few
particles (about 3% at the paper's ``P_B``, ``P_fa``) that put a newborn on that detection,
and two or more such targets together by almost none, so the joint draw, which can only pick
ancestors, acquires them late (a per-target filter does not have this problem). The window's
existence is therefore a chain variable too (the target above with ``p(e_s | e_{s-1})`` of
eq. 25 in each window step, and ``p(e | e_{t-1})`` at ``t``): the move picks a slot ``i``
and a window step ``s`` uniformly among the ``n(x)`` pairs where one of the two directions
below is possible in the chain's state and, if the slot is dead from ``s - 1`` through
``t``, proposes it born at ``s`` at ``y``, uniform over the pixels of ``Z_s`` that have a
detection of ``Z_{s+1}`` within two pixels (``q_y(y) = 1 / (n_pair s^2)``), and alive at
each later step ``r <= t`` at ``x_r ~ q_x``, the conditional of the Kalman predictive (run
from the anchor through the new window) given the other observed slots; if the slot is dead
at ``s - 1`` and alive from ``s`` through ``t``, the reverse (its positions to ``x_death``):

    rho_5 = min(1, pi(j, x_w*, e_w*, g, e*, x*) / pi(j, x_w, e_w, g, e, x)
                   x n(x) / n(x*)
                   x [1 / (q_y(y) prod_r q_x(x_r))  for a birth  |  q_y(y) prod_r q_x(x_r)  for a death]).

Each MH iteration runs one move for every chain of every run: the joint draw with
probability ``xi`` (paper: 0.75), the past move with ``p_past`` (``lag >= 1``), the window
birth with ``p_window_birth``, else one refinement sweep. The picks of a whole step are drawn at once
(:func:`~torchmcmcpf.filters.mcmc.pick_moves`, one host transfer per step); they do not
depend on the state, so each chain's kernel is the mixture.

Chains
------
``C`` chains per run are a tensor dimension (``(B, C, ...)``); each starts from a joint
proposal (accepted), runs ``burn_in + thinning N / C`` iterations and keeps every
``thinning``-th state after the burn-in (``N / C`` each). The kept states' Kalman statistics
(eqs. 56-57; from the anchor through the window with ``lag``) are computed once, after the
chains ran. ``marginalise=False`` gives the same sampler without Rao-Blackwellisation: each
kept particle *samples* its velocities and leaders from their Kalman posterior and carries a
point mass (zero covariance), so the next step's position prior is conditional on sampled
``w`` (issue 11, item 4a).

State and outputs
-----------------
The filtering state is a :class:`~torchmcmcpf.state.ParticleState` like every filter's:
``x (B, N, K, 4)`` holds ``[x, vx, y, vy]`` (the sampled positions and each particle's Kalman
posterior-mean velocities, so ``existence_estimate`` gives positions and velocities),
``log_w``, ``exists``, and ``extras`` holds the rest (run dim first):

- ``labels (B, N, K)`` int64, the structure; ``w_mean (B, N, 2, 3K)``, ``w_cov (B, N, 3K,
  3K)``, the Kalman statistics of ``w = [velocities, leader positions, leader velocities]``
  per axis; ``frames (B, F, H, W)`` bool, the last ``F`` frames (eq. 65 and the window);
- with ``lag >= 1``, the path ``t - P + 1 .. t`` (``P <= L + 1`` entries, the first the
  anchor): ``path_pos (B, N, P, K, 2)``, ``path_labels``, ``path_exists (B, N, P, K)``,
  ``path_log (B, N, P)`` (each entry's term of the target above), ``anchor_w_mean``,
  ``anchor_w_cov``.

``StepInfo.extras`` has ``structure_prob (B, Bell(K))`` (posterior probability of every row
of :func:`~torchmcmcpf.models.group.group_structures`), ``exists_prob (B, K)``,
``expected_count (B,)`` and the acceptance rate of each move. The group filter takes the
group models in place of ``Filter``'s (:class:`VirtualLeaderMotion`, a
:class:`GroupExistence`, which is a ``BirthDeath``, and the structure prior of eq. 19); the
per-target refinement loops over the ``K`` slots (a Gibbs sweep is sequential by definition).
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F

from .._validation import check_positive, check_positive_int, check_shape
from ..kernels.mh import mh_accept, mh_select
from ..models.base import neighbourhood
from ..models.group import (
    GroupExistence,
    GroupStructurePrior,
    KalmanStats,
    VirtualLeaderMotion,
    bell_number,
    group_structures,
    pairwise_kalman_init,
    pairwise_kalman_predict,
    pairwise_kalman_update,
    structure_index,
)
from ..models.sensors.pixels import ThresholdedPixels
from ..resampling import cdf, inverse_cdf
from ..runtime import repeating
from ..state import ParticleState, StepInfo
from ..typing import Tensor
from .base import Filter
from .mcmc import pick_moves

__all__ = ["GroupMCMCFilter", "GroupMCMCSettings", "group_mcmc_step", "JointNoise", "RefineNoise", "PastNoise",
           "BirthNoise", "default_chains", "estimate_step_bytes"]

LOG_2PI = math.log(2 * math.pi)
ALPHAS = ("mean", "predictive")
BIRTHS = ("eq65", "frame")


def default_chains(num_particles: int, most: int = 20) -> int:
    """The largest divisor of ``num_particles`` not above ``most`` (20): the default number of
    chains of :class:`GroupMCMCFilter`.

    Why 20: chains are a tensor dimension, so an iteration of 20 chains costs about what one
    of one chain costs on a CPU (B = 40 runs: 6 ms for the joint draw), while 20 chains need
    20x fewer iterations for the same number of kept samples (each with its own burn-in).
    With paper 004's one chain, burn-in 1000 and thinning 6, a step of N = 400 is 3400
    iterations; with 20 chains and burn-in 100 it is 220 (README, issue 11 item 4b: equal
    accuracy at equal kept samples, 19x less time).
    """
    n = check_positive_int(num_particles, "num_particles")
    return max(d for d in range(1, min(most, n) + 1) if n % d == 0)


def estimate_step_bytes(batch_size: int, num_particles: int, num_slots: int, *, lag: int = 0) -> int:
    """A rough upper estimate of the memory [bytes] one step of :class:`GroupMCMCFilter` needs.

    The terms that grow: the ``Bell(K)`` structures (the same-group masks ``(Bell(K), K, K)``
    of eq. 21, twice, and ``p(g | j)`` of every structure for every particle
    ``(B, N, Bell(K))``, with the step's structure histogram), float64; and the Kalman
    statistics ``(B, N, 3K, 3K)`` (in, out and the temporaries of a chunked update; twice
    more with a lag). ``Bell(K)`` grows faster than exponentially: 15 structures at K = 4,
    115,975 at 10, 4,213,597 at 12.
    """
    b, n = check_positive_int(batch_size, "batch_size"), check_positive_int(num_particles, "num_particles")
    k = check_positive_int(num_slots, "num_slots")
    g = bell_number(k)
    structures = 8 * g * (2 * k * k + 3 * b * n)
    kalman = 8 * b * n * (3 * k) ** 2 * (3 + (2 if lag else 0))
    return structures + kalman


@dataclass(frozen=True)
class GroupMCMCSettings:
    """Settings of :class:`GroupMCMCFilter` (paper 004 sec. 5 values where given).

    Attributes
    ----------
    num_chains : C >= 1 chains per run (a divisor of N; :func:`default_chains`).
    burn_in : iterations discarded per chain and step (paper, one chain: 1000).
    thinning : keep every ``thinning``-th state (paper: 6).
    xi : probability of the joint draw per iteration (paper: 0.75).
    p_a : ``P_a`` of eq. 61, weight of ``alpha`` in the choice of the ancestor (paper: 0.5).
    p_i : ``P_I`` of eq. 64, weight of the uniform birth proposal (paper: 0.01).
    marginalise : integrate the velocities and leaders out (paper); ``False`` samples them.
    alpha : ``"mean"`` (eq. 62) or ``"predictive"`` (module docstring).
    birth : ``"eq65"`` (paper) or ``"frame"`` (module docstring).
    lag : L >= 0, positions of each target's past the past move changes (0: no past move).
    p_past : probability of the past move per iteration (needs ``lag >= 1``).
    past_step : ``(s_a [m], s_b [m per step])``, the shift and velocity steps of the past move.
    p_window_birth : probability of the window birth/death move per iteration (needs
        ``lag >= 1``; 0: off, the paper's sampler).
    max_memory_gb : refuse a problem whose step needs more (:func:`estimate_step_bytes`).
    """

    num_chains: int = 20
    burn_in: int = 100
    thinning: int = 6
    xi: float = 0.75
    p_a: float = 0.5
    p_i: float = 0.01
    marginalise: bool = True
    alpha: str = "mean"
    birth: str = "eq65"
    lag: int = 0
    p_past: float = 0.0
    past_step: tuple[float, float] = (10.0, 5.0)
    p_window_birth: float = 0.0
    max_memory_gb: float = 8.0

    def __post_init__(self) -> None:
        check_positive_int(self.num_chains, "num_chains")
        check_positive_int(self.burn_in, "burn_in", minimum=0)
        check_positive_int(self.thinning, "thinning")
        check_positive_int(self.lag, "lag", minimum=0)
        for name, lo_open in (("xi", False), ("p_a", False), ("p_i", True), ("p_past", False),
                              ("p_window_birth", False)):
            v = float(getattr(self, name))
            if not (0.0 <= v <= 1.0) or (lo_open and v == 0.0):
                raise ValueError(f"{name} must be a probability in {'(0, 1]' if lo_open else '[0, 1]'}, got {v!r}")
        if not isinstance(self.marginalise, bool):
            raise ValueError(f"marginalise must be a bool, got {self.marginalise!r}")
        if self.alpha not in ALPHAS:
            raise ValueError(f"alpha must be one of {ALPHAS}, got {self.alpha!r}")
        if self.birth not in BIRTHS:
            raise ValueError(f"birth must be one of {BIRTHS}, got {self.birth!r}")
        if (self.lag > 0) != (self.p_past > 0):
            raise ValueError(f"lag >= 1 and p_past > 0 go together (the past move needs a past), got lag={self.lag}, "
                             f"p_past={self.p_past}")
        if self.xi + self.p_past + self.p_window_birth > 1.0 + 1e-12:
            raise ValueError(f"xi + p_past + p_window_birth must be <= 1 (the rest is the refinement's), got "
                             f"{self.xi} + {self.p_past} + {self.p_window_birth}")
        if self.p_window_birth > 0 and self.lag == 0:
            raise ValueError(f"p_window_birth > 0 needs lag >= 1 (the move births a target at t - 1, in the window), "
                             f"got p_window_birth={self.p_window_birth}, lag=0")
        if self.xi == 0.0:
            raise ValueError("xi must be > 0: only the joint draw changes a chain's ancestor")
        if self.lag > 0 and not self.marginalise:
            raise ValueError("lag >= 1 needs marginalise=True (the window's Kalman statistics are re-run)")
        if len(self.past_step) != 2:
            raise ValueError(f"past_step must be (shift [m], velocity step [m per step]), got {self.past_step!r}")
        object.__setattr__(self, "past_step", tuple(check_positive(s, "past_step") for s in self.past_step))
        check_positive(self.max_memory_gb, "max_memory_gb")

    def check(self, num_particles: int) -> None:
        """Raise ``ValueError`` unless ``num_particles`` is a multiple of ``num_chains``."""
        if num_particles % self.num_chains:
            raise ValueError(f"num_particles ({num_particles}) must be a multiple of num_chains ({self.num_chains}): "
                             f"each chain keeps num_particles / num_chains samples (default_chains({num_particles}) "
                             f"= {default_chains(num_particles)})")

    def moves(self) -> tuple[tuple[str, float], ...]:
        """The mixture's ``(move, probability)`` pairs with probability > 0."""
        pairs = (("joint", self.xi), ("refine", 1.0 - self.xi - self.p_past - self.p_window_birth),
                 ("past", self.p_past), ("birth", self.p_window_birth))
        return tuple((name, p) for name, p in pairs if p > 1e-12)


# ----------------------------------------------------------------------------------------
# the noise of one move (drawn eagerly, passed into the pure moves)
# ----------------------------------------------------------------------------------------
#: the dims of each noise field after the chains' ``(B, C)`` ("K": the slots); every field is
#: ``U(0, 1)`` but the standard normals ``eps`` and ``step``
_FIELD_DIMS: dict[str, tuple[int | str, ...]] = {
    "mix": (), "j": (), "g": (), "u": (), "u_g": (), "slot": (), "e": ("K",), "u_x": ("K",), "b_sel": ("K",),
    "b_pix": ("K",), "eps": ("K", 2), "b_xy": ("K", 2), "step": (2, 2), "y_pix": (), "y_xy": (2,),
    "x_eps": ("L", 2)}
_NORMALS = ("eps", "step", "x_eps")


def _draw_fields(cls: Any, shape: tuple[int, int, int], generator: torch.Generator, dtype: torch.dtype,
                 device: torch.device | str | None, window: int = 1) -> Any:
    """One noise tuple of class ``cls`` for ``shape = (B, C, K)``, its fields drawn in
    declaration order with the dims of :data:`_FIELD_DIMS` (``"L"``: ``window``).
    """
    b, c, k = shape
    fields = []
    sizes = {"K": k, "L": window}
    for name in cls._fields:
        size = (b, c, *(sizes[d] if isinstance(d, str) else d for d in _FIELD_DIMS[name]))
        draw = torch.randn if name in _NORMALS else torch.rand
        fields.append(draw(size, generator=generator, dtype=dtype, device=device))
    return cls(*fields)


class JointNoise(NamedTuple):
    """Uniforms and normals of one joint draw for chains ``(B, C)`` of ``K`` slots: ``mix``,
    ``j``, ``g``, ``u (B, C)``; ``e (B, C, K)``; ``eps (B, C, K, 2)``; the birth proposal's
    ``b_sel``, ``b_pix (B, C, K)`` and ``b_xy (B, C, K, 2)`` (eqs. 64-65).
    """

    mix: Tensor
    j: Tensor
    g: Tensor
    e: Tensor
    eps: Tensor
    u: Tensor
    b_sel: Tensor
    b_pix: Tensor
    b_xy: Tensor

    @classmethod
    def draw(cls, shape: tuple[int, int, int], *, generator: torch.Generator, dtype: torch.dtype = torch.float64,
             device: torch.device | str | None = None) -> JointNoise:
        """Draw for ``shape = (B, C, K)``."""
        return _draw_fields(cls, shape, generator, dtype, device)


class RefineNoise(NamedTuple):
    """Uniforms and normals of one refinement sweep for chains ``(B, C)`` of ``K`` slots:
    ``g``, ``u_g (B, C)``; ``e``, ``u_x (B, C, K)``; ``eps (B, C, K, 2)``; the birth uniforms.
    """

    g: Tensor
    u_g: Tensor
    e: Tensor
    eps: Tensor
    u_x: Tensor
    b_sel: Tensor
    b_pix: Tensor
    b_xy: Tensor

    @classmethod
    def draw(cls, shape: tuple[int, int, int], *, generator: torch.Generator, dtype: torch.dtype = torch.float64,
             device: torch.device | str | None = None) -> RefineNoise:
        """Draw for ``shape = (B, C, K)``."""
        return _draw_fields(cls, shape, generator, dtype, device)


class PastNoise(NamedTuple):
    """Noise of one past move for chains ``(B, C)``: ``slot`` uniforms (the slot moved),
    ``step (B, C, 2, 2)`` standard normals (shift, velocity step; per axis), ``u (B, C)``.
    """

    slot: Tensor
    step: Tensor
    u: Tensor

    @classmethod
    def draw(cls, shape: tuple[int, int, int], *, generator: torch.Generator, dtype: torch.dtype = torch.float64,
             device: torch.device | str | None = None) -> PastNoise:
        """Draw for ``shape = (B, C, K)``."""
        return _draw_fields(cls, shape, generator, dtype, device)


class BirthNoise(NamedTuple):
    """Noise of one window birth/death move for chains ``(B, C)``: ``slot`` uniforms (the slot
    and the window step of the birth or death), ``y_pix (B, C)`` and ``y_xy (B, C, 2)``
    uniforms (the pixel of ``Z_s`` and the place in it), ``x_eps (B, C, L, 2)`` standard
    normals (the positions after ``s``; ``L = window``, the lag), ``u (B, C)``.
    """

    slot: Tensor
    y_pix: Tensor
    y_xy: Tensor
    x_eps: Tensor
    u: Tensor

    @classmethod
    def draw(cls, shape: tuple[int, int, int], *, generator: torch.Generator, dtype: torch.dtype = torch.float64,
             device: torch.device | str | None = None, window: int = 1) -> BirthNoise:
        """Draw for ``shape = (B, C, K)`` and a window of ``window`` steps."""
        return _draw_fields(cls, shape, generator, dtype, device, check_positive_int(window, "window"))


NOISES: dict[str, Any] = {"joint": JointNoise, "refine": RefineNoise, "past": PastNoise, "birth": BirthNoise}


# ----------------------------------------------------------------------------------------
# the containers of one step
# ----------------------------------------------------------------------------------------
class GroupView(NamedTuple):
    """A state's fields unpacked from its ``ParticleState`` (:func:`unpack`), ``(B, N, ...)``:
    the particles at ``t - 1`` (``pos``, ``g``, ``labels``, ``exists``, ``w_mean``, ``w_cov``,
    ``log_w``), ``frames (B, F, H, W)`` (the last ``F`` frames, the window's last), and the
    path: the anchor (``anchor_*``) and the window ``win_* (B, N, W, ...)`` of ``W`` past
    steps with their terms ``win_log (B, N, W)`` (``W = 0`` and the anchor the particles
    themselves without a lag).
    """

    pos: Tensor
    g: Tensor
    labels: Tensor
    exists: Tensor
    w_mean: Tensor
    w_cov: Tensor
    log_w: Tensor
    frames: Tensor
    anchor_pos: Tensor
    anchor_g: Tensor
    anchor_labels: Tensor
    anchor_exists: Tensor
    anchor_w_mean: Tensor
    anchor_w_cov: Tensor
    win_pos: Tensor
    win_g: Tensor
    win_labels: Tensor
    win_exists: Tensor
    win_log: Tensor


class Cloud(NamedTuple):
    """The previous particles and the per-step quantities of the proposals (eager, once per
    step): ``view`` (:class:`GroupView`); ``log_pg (B, N, G)`` eq. 19 for every structure;
    ``log_win (B, N)`` the window's terms; ``cdf_alpha``, ``cdf_w (B, N)`` float64 cumulative
    weights of ``alpha`` and ``w``; ``log_wq (B, N)`` ``log w_j - log q(j)`` (eq. 61);
    ``beta (B, HW)`` bool, the pixels of the birth proposal, ``cdf_beta (B, HW)``,
    ``n_obs (B,)``; ``table (G, K)`` the structures; the window birth's pixels, per window
    step ``s``, of ``Z_s`` with a detection of ``Z_{s+1}`` within two pixels, ``pair (B, W,
    HW)`` bool, ``cdf_pair (B, W, HW)``, ``n_pair (B, W)``.
    """

    view: GroupView
    log_pg: Tensor
    log_win: Tensor
    cdf_alpha: Tensor
    cdf_w: Tensor
    log_wq: Tensor
    beta: Tensor
    cdf_beta: Tensor
    n_obs: Tensor
    table: Tensor
    pair: Tensor
    cdf_pair: Tensor
    n_pair: Tensor


class Prev(NamedTuple):
    """A chain's past ``(B, C, ...)``: the positions, structure (``g`` row, ``labels``),
    existence and Kalman statistics at ``t - 1``; ``log_pg (B, C, G)``, ``p(g_t | .)`` of
    every structure; the window positions ``win_pos (B, C, W, K, 2)`` at ``t - W .. t - 1``
    and their terms ``log_win (B, C)``; the window's existence ``win_exists (B, C, W, K)``.
    """

    pos: Tensor
    g: Tensor
    labels: Tensor
    exists: Tensor
    w_mean: Tensor
    w_cov: Tensor
    log_pg: Tensor
    win_pos: Tensor
    log_win: Tensor
    win_exists: Tensor


class Chain(NamedTuple):
    """Chain states ``(B, C, ...)``: ancestor ``j``, structure ``g`` (row) and ``labels``,
    ``exists``, ``pos (B, C, K, 2)``; cached ``log_lik`` (eq. 40), ``log_px``
    (``log p(x | past, g, e)``), ``log_wq`` (``log w_j - log q(j)``), ``log_birth``
    (``sum_free log p_0 - log q_0``); the configuration's predictive ``pm (B, C, K, 2)``,
    ``S (B, C, K, K)``, ``observed``, ``free``; and its :class:`Prev`.
    """

    j: Tensor
    g: Tensor
    labels: Tensor
    exists: Tensor
    pos: Tensor
    log_lik: Tensor
    log_px: Tensor
    log_wq: Tensor
    log_birth: Tensor
    pm: Tensor
    S: Tensor
    observed: Tensor
    free: Tensor
    prev: Prev


class Models(NamedTuple):
    """The models and the proposal constants a move needs (bound, not traced)."""

    motion: VirtualLeaderMotion
    sensor: ThresholdedPixels
    existence: GroupExistence
    structure_prior: GroupStructurePrior
    p_i: float
    p_a: float
    past_step: tuple[float, float] = (10.0, 5.0)


# ----------------------------------------------------------------------------------------
# small pieces
# ----------------------------------------------------------------------------------------
def _lift(pos: Tensor, sensor: ThresholdedPixels) -> Tensor:
    """Positions ``(*S, K, 2)`` into the sensor's state layout ``(*S, K, D)``."""
    ix, iy = sensor.position_index
    d = max(ix, iy) + 1
    out = pos.new_zeros(pos.shape[:-1] + (d,))
    out[..., ix] = pos[..., 0]
    out[..., iy] = pos[..., 1]
    return out


def _log_lik(pos: Tensor, exists: Tensor, z: Tensor, sensor: ThresholdedPixels) -> Tensor:
    """``log p(Z | x, e)`` (eq. 40) of positions ``(B, *S, K, 2)``: ``-> (B, *S)``."""
    return sensor.log_likelihood(_lift(pos, sensor), z, exists)


def _gather(t: Tensor, j: Tensor) -> Tensor:
    """Rows ``j (B, C)`` of ``t (B, N, ...)`` -> ``(B, C, ...)``."""
    b = torch.arange(t.shape[0], device=t.device).unsqueeze(-1)
    return t[b, j]


def _death_pos(existence: GroupExistence, like: Tensor) -> Tensor:
    """The position ``(2,)`` of ``x_death`` in ``like``'s dtype and device."""
    return existence.x_death[0::2].to(like)


def _predict(prev: Prev, labels: Tensor, exists: Tensor, models: Models) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Kalman predictive of the positions of configuration ``(g, e)`` after ``prev``:
    ``pm (B, C, K, 2)``, ``S (B, C, K, K)``, ``observed``, ``free (B, C, K)`` (eqs. 47, 51-52).
    """
    tr = models.motion.transition(prev.pos, prev.labels, labels, prev.exists, exists, existence=models.existence)
    pred = pairwise_kalman_predict(KalmanStats(prev.w_mean, prev.w_cov), prev.pos, tr)
    # contiguous: a chain's fields keep one layout, eager or compiled (no recompilation)
    return pred.position_mean.contiguous(), pred.position_cov.contiguous(), tr.observed, tr.free_birth


def _log_px(pos: Tensor, pm: Tensor, S: Tensor, obs: Tensor, free: Tensor, existence: GroupExistence) -> Tensor:
    """``log p(x | past, g, e)`` (eq. 44): Gaussian over the observed slots (both axes) plus
    ``log p_0`` of the free births: ``-> (B, C)``.
    """
    o = obs.to(pos.dtype)
    Sm = S * o.unsqueeze(-1) * o.unsqueeze(-2) + torch.diag_embed(1.0 - o)
    L = torch.linalg.cholesky(Sm)
    y = torch.linalg.solve_triangular(L, (pos - pm) * o.unsqueeze(-1), upper=False)
    logdet = torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
    log_g = -0.5 * y.square().sum((-1, -2)) - 2 * logdet - o.sum(-1) * LOG_2PI
    log_p0 = torch.where(free, existence.log_p0_position(pos), torch.zeros_like(pos[..., 0])).sum(-1)
    return log_g + log_p0


def _log_q0(pos: Tensor, cloud: Cloud, sensor: ThresholdedPixels, existence: GroupExistence, p_i: float) -> Tensor:
    """``log q_0(x)`` of eq. 64 per slot: ``(B, C, K, 2) -> (B, C, K)``."""
    log_p0 = existence.log_p0_position(pos)
    h, w = sensor.shape
    s = sensor.pixel_size
    col = torch.floor(pos[..., 0] / s).clamp(0, w - 1).long()
    row = torch.floor(pos[..., 1] / s).clamp(0, h - 1).long()
    flat = (row * w + col).reshape(pos.shape[0], -1)
    hit = torch.gather(cloud.beta, 1, flat).reshape(pos.shape[:-1]).to(pos.dtype)
    n = cloud.n_obs.to(pos.dtype).reshape((-1,) + (1,) * (pos.dim() - 2))
    phi = hit / (n.clamp(min=1) * s * s)
    q = torch.where(n > 0, p_i * log_p0.exp() + (1 - p_i) * phi, log_p0.exp())
    return torch.where(torch.isfinite(log_p0), q.log(), log_p0)


def _draw_q0(noise: JointNoise | RefineNoise, cloud: Cloud, sensor: ThresholdedPixels, existence: GroupExistence,
             p_i: float) -> Tensor:
    """Positions from ``q_0`` (eqs. 64-65): ``(B, C, K, 2)`` from the birth noise (pixels by
    the shared inverse CDF).
    """
    uniform = existence.uniform_position(noise.b_xy)
    b = noise.b_pix.shape[0]
    idx = inverse_cdf(cloud.cdf_beta, noise.b_pix.reshape(b, -1)).reshape(noise.b_pix.shape)
    w = sensor.shape[1]
    pix = torch.stack([(idx % w).to(noise.b_xy.dtype), (idx // w).to(noise.b_xy.dtype)], -1)
    in_pixel = (pix + noise.b_xy) * sensor.pixel_size
    n = cloud.n_obs.reshape((-1,) + (1,) * (noise.b_sel.dim() - 1))
    use_uniform = (noise.b_sel < p_i) | (n == 0)
    return torch.where(use_uniform.unsqueeze(-1), uniform, in_pixel)


def _birth_ratio(pos: Tensor, free: Tensor, cloud: Cloud, models: Models) -> Tensor:
    """``sum_free log p_0(x_i) - log q_0(x_i)``: ``-> (B, C)``."""
    r = models.existence.log_p0_position(pos) - _log_q0(pos, cloud, models.sensor, models.existence, models.p_i)
    return torch.where(free, r, torch.zeros_like(r)).sum(-1)


def _draw_structure(log_pg: Tensor, u: Tensor) -> Tensor:
    """Row index from ``log_pg (B, C, G)`` by ``u (B, C)`` (eq. 19)."""
    return inverse_cdf(cdf(log_pg), u.unsqueeze(-1)).squeeze(-1)


def _path_step(stats: KalmanStats, pos_p: Tensor, g_p: Tensor, lab_p: Tensor, ex_p: Tensor, pos: Tensor, g: Tensor,
               lab: Tensor, ex: Tensor, z: Tensor, models: Models) -> tuple[Tensor, KalmanStats]:
    """One step of a particle's path: its term of the target, ``log p(x_s | x_{0:s-1}, g, e)
    + log p(g_s | x_{s-1}, g_{s-1}, e_{s-1}) + log p(Z_s | x_s, e_s)`` (eqs. 19, 44, 40; the
    existence prior, which the past move does not change, left out), and the Kalman
    statistics at ``s``. Leading dims ``(B, *S)``.
    """
    tr = models.motion.transition(pos_p, lab_p, lab, ex_p, ex, existence=models.existence)
    log_pred, stats = pairwise_kalman_update(pairwise_kalman_predict(stats, pos_p, tr), pos)
    log_p0 = torch.where(tr.free_birth, models.existence.log_p0_position(pos), torch.zeros_like(pos[..., 0])).sum(-1)
    log_pg = models.structure_prior.log_probs(g_p, pos_p, ex_p)
    log_g = torch.gather(log_pg, -1, g.unsqueeze(-1)).squeeze(-1)
    return log_pred + log_p0 + log_g + _log_lik(pos, ex, z, models.sensor), stats


def _past(j: Tensor, win_pos: Tensor, cloud: Cloud, models: Models, win_exists: Tensor | None = None) -> Prev:
    """The past of chains with ancestors ``j (B, C)``, window positions ``win_pos (B, C, W,
    K, 2)`` and existence ``win_exists (B, C, W, K)`` (default the ancestor's): the Kalman
    filter re-run from the anchor through the window (:class:`Prev`).
    """
    v = cloud.view
    stats = KalmanStats(_gather(v.anchor_w_mean, j), _gather(v.anchor_w_cov, j))
    pos, g, lab, ex = (_gather(t, j) for t in (v.anchor_pos, v.anchor_g, v.anchor_labels, v.anchor_exists))
    win_g, win_lab = (_gather(t, j) for t in (v.win_g, v.win_labels))
    win_ex = _gather(v.win_exists, j) if win_exists is None else win_exists
    log_win = torch.zeros_like(pos[..., 0, 0])
    off = v.frames.shape[1] - win_pos.shape[2]  # the window's frames are the last W
    for s in range(win_pos.shape[2]):  # the window's steps (time, not particles)
        term, stats = _path_step(stats, pos, g, lab, ex, win_pos[:, :, s], win_g[:, :, s], win_lab[:, :, s],
                                 win_ex[:, :, s], v.frames[:, off + s], models)
        log_win = log_win + term
        pos, g, lab, ex = win_pos[:, :, s], win_g[:, :, s], win_lab[:, :, s], win_ex[:, :, s]
    log_pg = models.structure_prior.log_probs(g, pos, ex)
    return Prev(pos, g, lab, ex, stats.mean, stats.cov, log_pg, win_pos, log_win, win_ex)


def _prev_of(cloud: Cloud, j: Tensor) -> Prev:
    """The past of chains whose ancestors are ``j (B, C)``, as the cloud holds it."""
    v = cloud.view
    return Prev(*(_gather(t, j) for t in (v.pos, v.g, v.labels, v.exists, v.w_mean, v.w_cov, cloud.log_pg,
                                          v.win_pos, cloud.log_win, v.win_exists)))


# ----------------------------------------------------------------------------------------
# the moves (pure: noise in, no generator; compile-friendly)
# ----------------------------------------------------------------------------------------
def make_chain(j: Tensor, g: Tensor, exists: Tensor, pos: Tensor, cloud: Cloud, z: Tensor, models: Models,
               win_pos: Tensor | None = None, win_exists: Tensor | None = None) -> Chain:
    """A chain state ``(B, C, ...)`` with its caches from ``(j, g, e, x_p)`` and, optionally,
    its window ``win_pos (B, C, W, K, 2)`` and ``win_exists (B, C, W, K)`` (default the
    ancestor's); dead slots' positions are set to ``x_death``.
    """
    if win_pos is None and win_exists is not None:
        win_pos = _gather(cloud.view.win_pos, j)
    prev = _prev_of(cloud, j) if win_pos is None else _past(j, win_pos, cloud, models, win_exists)
    labels = cloud.table[g]
    pm, S, obs, free = _predict(prev, labels, exists, models)
    pos = torch.where(exists.unsqueeze(-1), pos, _death_pos(models.existence, pos))
    return Chain(j, g, labels, exists, pos, _log_lik(pos, exists, z, models.sensor),
                 _log_px(pos, pm, S, obs, free, models.existence), _gather(cloud.log_wq, j),
                 _birth_ratio(pos, free, cloud, models), pm, S, obs, free, prev)


def joint_proposal(noise: JointNoise, cloud: Cloud, z: Tensor, models: Models) -> Chain:
    """Algorithm 1 steps 1-4 (eqs. 61-65) for every chain: the proposed state with its caches."""
    existence = models.existence
    use_alpha = noise.mix < models.p_a
    j = torch.where(use_alpha, inverse_cdf(cloud.cdf_alpha, noise.j), inverse_cdf(cloud.cdf_w, noise.j))
    prev = _prev_of(cloud, j)
    g = _draw_structure(prev.log_pg, noise.g)
    labels = cloud.table[g]
    exists = existence.draw_exists(prev.exists, noise.e)
    pm, S, obs, free = _predict(prev, labels, exists, models)
    o = obs.to(pm.dtype)
    L = torch.linalg.cholesky(S * o.unsqueeze(-1) * o.unsqueeze(-2) + torch.diag_embed(1.0 - o))
    x_obs = pm + L @ noise.eps
    x_born = _draw_q0(noise, cloud, models.sensor, existence, models.p_i)
    pos = torch.where(obs.unsqueeze(-1), x_obs, torch.where(free.unsqueeze(-1), x_born, _death_pos(existence, pm)))
    return Chain(j, g, labels, exists, pos, _log_lik(pos, exists, z, models.sensor),
                 _log_px(pos, pm, S, obs, free, existence), _gather(cloud.log_wq, j),
                 _birth_ratio(pos, free, cloud, models), pm, S, obs, free, prev)


def joint_move(chain: Chain, noise: JointNoise, cloud: Cloud, z: Tensor, models: Models) -> tuple[Chain, Tensor]:
    """Algorithm 1 with the acceptance ratio ``rho_1`` of eq. 60 (module docstring).
    Returns the new chain and ``accepted (B, C)`` bool.
    """
    prop = joint_proposal(noise, cloud, z, models)
    log_rho = (prop.log_lik + prop.log_wq + prop.log_birth) - (chain.log_lik + chain.log_wq + chain.log_birth)
    acc = mh_accept(log_rho, noise.u)
    return mh_select(acc, prop, chain), acc


def refine_move(chain: Chain, noise: RefineNoise, cloud: Cloud, z: Tensor, models: Models
                ) -> tuple[Chain, Tensor, Tensor]:
    """Algorithm 2: the structure by ``rho_2``, then each slot's ``(x_i, e_i)`` by ``rho_3``
    (eq. 66; module docstring). Returns the chain, ``accepted_structure (B, C)`` bool and
    ``accepted_targets (B, C, K)`` bool.
    """
    existence, sensor = models.existence, models.sensor
    k = chain.pos.shape[-2]
    prev = chain.prev
    # -- structure (rho_2)
    g = _draw_structure(prev.log_pg, noise.g)
    labels = cloud.table[g]
    pm, S, obs, free = _predict(prev, labels, chain.exists, models)
    log_px = _log_px(chain.pos, pm, S, obs, free, existence)
    acc_g = mh_accept(log_px - chain.log_px, noise.u_g)
    prop = chain._replace(g=g, labels=labels, log_px=log_px, log_birth=_birth_ratio(chain.pos, free, cloud, models),
                          pm=pm, S=S, observed=obs, free=free)
    chain = mh_select(acc_g, prop, chain)
    # -- each target (rho_3)
    x_born = _draw_q0(noise, cloud, sensor, existence, models.p_i)  # (B, C, K, 2)
    dead = _death_pos(existence, chain.pos)
    accs = []
    for i in range(k):
        onehot = torch.arange(k, device=chain.pos.device) == i
        e_i = existence.draw_exists(prev.exists[..., i], noise.e[..., i])
        exists = torch.where(onehot, e_i.unsqueeze(-1), chain.exists)
        pm, S, obs, free = _predict(prev, chain.labels, exists, models)
        cm, cv = _conditional(chain.pos, pm, S, obs, i)
        x_i = torch.where(obs[..., i, None], cm + cv.sqrt().unsqueeze(-1) * noise.eps[..., i, :],
                          torch.where(free[..., i, None], x_born[..., i, :], dead))
        pos = torch.where(onehot.unsqueeze(-1), x_i.unsqueeze(-2), chain.pos)
        log_q_fwd = _log_q_slot(x_i, cm, cv, obs[..., i], free[..., i], cloud, models)
        cm0, cv0 = _conditional(chain.pos, chain.pm, chain.S, chain.observed, i)
        log_q_rev = _log_q_slot(chain.pos[..., i, :], cm0, cv0, chain.observed[..., i], chain.free[..., i],
                                cloud, models)
        log_lik = _log_lik(pos, exists, z, sensor)
        log_px = _log_px(pos, pm, S, obs, free, existence)
        log_rho = (log_lik + log_px - log_q_fwd) - (chain.log_lik + chain.log_px - log_q_rev)
        acc = mh_accept(log_rho, noise.u_x[..., i])
        prop = chain._replace(exists=exists, pos=pos, log_lik=log_lik, log_px=log_px,
                              log_birth=_birth_ratio(pos, free, cloud, models), pm=pm, S=S, observed=obs, free=free)
        chain = mh_select(acc, prop, chain)
        accs.append(acc)
    return chain, acc_g, torch.stack(accs, -1)


def past_move(chain: Chain, noise: PastNoise, cloud: Cloud, z: Tensor, models: Models) -> tuple[Chain, Tensor]:
    """One slot's live positions at ``t - W .. t`` translated by ``a + b (s - t)`` and
    accepted by ``rho_4`` (module docstring, "A target's recent past"). Returns the new
    chain and ``accepted (B, C)`` bool.
    """
    k = chain.pos.shape[-2]
    prev = chain.prev
    w = prev.win_pos.shape[2]
    onehot = F.one_hot((noise.slot * k).long().clamp(max=k - 1), k).to(torch.bool)  # (B, C, K)
    a = noise.step[..., 0, :] * models.past_step[0]  # (B, C, 2)
    b = noise.step[..., 1, :] * models.past_step[1]
    tau = torch.arange(-w, 0, device=a.device, dtype=a.dtype)  # (W,) time relative to t
    win_live = prev.win_exists & onehot.unsqueeze(-2)  # (B, C, W, K)
    shift = a[:, :, None, None, :] + b[:, :, None, None, :] * tau[:, None, None]  # (B, C, W, 1, 2)
    win_pos = prev.win_pos + shift * win_live.unsqueeze(-1).to(a.dtype)
    pos = chain.pos + a.unsqueeze(-2) * (chain.exists & onehot).unsqueeze(-1).to(a.dtype)
    new_prev = _past(chain.j, win_pos, cloud, models, prev.win_exists)
    pm, S, obs, free = _predict(new_prev, chain.labels, chain.exists, models)
    prop = chain._replace(pos=pos, log_lik=_log_lik(pos, chain.exists, z, models.sensor),
                          log_px=_log_px(pos, pm, S, obs, free, models.existence),
                          log_birth=_birth_ratio(pos, free, cloud, models), pm=pm, S=S, observed=obs, free=free,
                          prev=new_prev)
    acc = mh_accept(_past_log_target(prop) - _past_log_target(chain), noise.u)
    return mh_select(acc, prop, chain), acc


def _past_log_target(chain: Chain) -> Tensor:
    """``log pi(j, x_w, g, e, x)`` of the past move's target up to the terms it does not change
    (``w_j``, ``c_j``, the existence prior): the window's terms, ``log p(g | x_{t-1}, .)``,
    ``log p(x | past, g, e)`` and ``log p(Z_t | x, e)``, ``(B, C)``.
    """
    log_g = torch.gather(chain.prev.log_pg, -1, chain.g.unsqueeze(-1)).squeeze(-1)
    return chain.prev.log_win + log_g + chain.log_px + chain.log_lik


def _pixel_log_q(pos: Tensor, mask: Tensor, n: Tensor, sensor: ThresholdedPixels) -> Tensor:
    """``log`` of the density uniform over the pixels of ``mask (B, C, HW)`` (``n (B, C)`` of
    them) at positions ``pos (B, C, 2)``: ``-log(n s^2)`` in a pixel of the mask, ``-inf``
    elsewhere (and where ``n = 0``): ``-> (B, C)``.
    """
    h, w = sensor.shape
    s = sensor.pixel_size
    col, row = torch.floor(pos[..., 0] / s), torch.floor(pos[..., 1] / s)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    flat = (row.clamp(0, h - 1) * w + col.clamp(0, w - 1)).long()
    hit = torch.gather(mask, -1, flat.unsqueeze(-1)).squeeze(-1) & inside & (n > 0)
    log_q = -torch.log(n.to(pos.dtype).clamp(min=1) * s * s)
    return torch.where(hit, log_q, torch.full_like(log_q, -math.inf))


def _alive_path(chain: Chain, cloud: Cloud, models: Models, onehot: Tensor, s: Tensor, sample: Tensor, y: Tensor,
                eps: Tensor, win_exists: Tensor, exists: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The positions of slot ``i`` (``onehot (B, C, K)``) alive from window step ``s (B, C)``
    through ``t``, and their proposal density: at ``s`` the position ``y (B, C, 2)``, at each
    later step the conditional of the Kalman predictive (re-run from the anchor with
    ``win_exists (B, C, W, K)``, ``exists (B, C, K)``) given the other observed slots, drawn
    from ``eps (B, C, L, 2)`` where ``sample`` else the chain's own. Returns the window
    positions ``(B, C, W, K, 2)``, the positions at ``t`` ``(B, C, K, 2)`` and ``log q
    (B, C)`` of the steps after ``s`` (the pixel density of ``y`` is the caller's).
    """
    v = cloud.view
    j, prev = chain.j, chain.prev
    stats = KalmanStats(_gather(v.anchor_w_mean, j), _gather(v.anchor_w_cov, j))
    pos_p, lab_p, ex_p = (_gather(t, j) for t in (v.anchor_pos, v.anchor_labels, v.anchor_exists))
    win_lab = _gather(v.win_labels, j)
    w = prev.win_pos.shape[2]
    sel = onehot.unsqueeze(-1)
    log_q = torch.zeros_like(y[..., 0])
    out = []
    for r in range(w + 1):  # the window's steps and t (time, not particles)
        pos_r, lab_r, ex_r = ((prev.win_pos[:, :, r], win_lab[:, :, r], win_exists[:, :, r]) if r < w
                              else (chain.pos, chain.labels, exists))
        tr = models.motion.transition(pos_p, lab_p, lab_r, ex_p, ex_r, existence=models.existence)
        pred = pairwise_kalman_predict(stats, pos_p, tr)
        cm, cv = _conditional_slot(pos_r, pred.position_mean.contiguous(), pred.position_cov.contiguous(),
                                   tr.observed, onehot)
        own = (pos_r * sel.to(y.dtype)).sum(-2)
        x = torch.where(sample.unsqueeze(-1), cm + cv.clamp(min=0).sqrt().unsqueeze(-1) * eps[:, :, max(r - 1, 0)],
                        own)
        after = s < r
        log_q = log_q + torch.where(after, _log_normal2(x, cm, cv), torch.zeros_like(cv))
        x = torch.where(after.unsqueeze(-1), x, torch.where((s == r).unsqueeze(-1), y, own))
        pos_r = torch.where(sel & (s <= r)[..., None, None], x.unsqueeze(-2), pos_r)
        _, stats = pairwise_kalman_update(pred, pos_r)
        out.append(pos_r)
        pos_p, lab_p, ex_p = pos_r, lab_r, ex_r
    return torch.stack(out[:w], 2), out[w], log_q


def window_birth_move(chain: Chain, noise: BirthNoise, cloud: Cloud, z: Tensor, models: Models
                      ) -> tuple[Chain, Tensor]:
    """One slot ``i`` born at a window step ``s`` and alive through ``t``, or the reverse
    (module docstring, "A target born in the window"); accepted by ``rho_5``. Returns the new
    chain and ``accepted (B, C)`` bool (False where the slot's existence pattern allows
    neither direction).
    """
    existence, sensor = models.existence, models.sensor
    k = chain.pos.shape[-2]
    prev = chain.prev
    w = prev.win_pos.shape[2]
    if w == 0:  # no window (a state without a path): nothing to do
        return chain, torch.zeros_like(noise.u, dtype=torch.bool)
    anchor_ex = _gather(cloud.view.anchor_exists, chain.j)
    # (slot, s) uniform over the eligible pairs of the chain's state (a birth or a death is possible)
    births, deaths = _eligible(anchor_ex, prev.win_exists, chain.exists, cloud.n_pair)  # (B, C, K, W)
    elig = (births | deaths).flatten(-2)
    n_elig = elig.sum(-1)  # (B, C)
    rank = (noise.slot * n_elig).long().clamp(max=(n_elig - 1).clamp(min=0)).unsqueeze(-1)
    pick = (elig.cumsum(-1) > rank).to(torch.int64).argmax(-1)  # (B, C): the first with rank + 1 eligible
    onehot = F.one_hot(pick // w, k).to(torch.bool)  # (B, C, K)
    s = pick % w  # (B, C) the birth step in the window
    steps = torch.arange(w, device=s.device)
    birth = torch.gather(births.flatten(-2), -1, pick.unsqueeze(-1)).squeeze(-1) & (n_elig > 0)
    death = torch.gather(deaths.flatten(-2), -1, pick.unsqueeze(-1)).squeeze(-1) & (n_elig > 0)
    n_s = torch.gather(cloud.n_pair, 1, s)  # (B, C)
    # y ~ uniform over the paired detections of Z_s (a pixel by the shared inverse CDF, then a place in it)
    b, c = s.shape
    cdf_s = torch.gather(cloud.cdf_pair, 1, s.unsqueeze(-1).expand(b, c, cloud.cdf_pair.shape[-1]))
    mask_s = torch.gather(cloud.pair, 1, s.unsqueeze(-1).expand(b, c, cloud.pair.shape[-1]))
    idx = inverse_cdf(cdf_s, noise.y_pix.unsqueeze(-1)).squeeze(-1)
    width = sensor.shape[1]
    pix = torch.stack([(idx % width).to(noise.y_xy.dtype), (idx // width).to(noise.y_xy.dtype)], -1)
    y_new = (pix + noise.y_xy) * sensor.pixel_size  # (B, C, 2)
    sel = onehot.unsqueeze(-1)
    y_own = (torch.gather(prev.win_pos, 2, s[:, :, None, None, None].expand(b, c, 1, k, 2)).squeeze(2)
             * sel.to(y_new.dtype)).sum(-2)
    y = torch.where(birth.unsqueeze(-1), y_new, y_own)
    # the configuration with slot i alive from s on: proposed (a birth) or the chain's own (a death)
    in_window = (steps.reshape(1, 1, w) >= s.unsqueeze(-1)).unsqueeze(-1) & onehot.unsqueeze(2)  # (B, C, W, K)
    alive_win_ex = prev.win_exists | in_window
    alive_ex = chain.exists | onehot
    win_alive, pos_alive, log_qx = _alive_path(chain, cloud, models, onehot, s, birth, y, noise.x_eps,
                                               alive_win_ex, alive_ex)
    log_q = _pixel_log_q(y, mask_s, n_s, sensor) + log_qx
    # the proposed state: alive from s (a birth) or dead from s (a death; positions to x_death)
    dead = _death_pos(existence, y_new)
    win_exists = torch.where(birth[..., None, None], alive_win_ex, prev.win_exists & ~in_window)
    exists = torch.where(birth.unsqueeze(-1), alive_ex, chain.exists & ~onehot)
    win_pos = torch.where(birth[..., None, None, None], win_alive,
                          torch.where(in_window.unsqueeze(-1), dead, prev.win_pos))
    pos = torch.where(birth[..., None, None], pos_alive, torch.where(sel, dead, chain.pos))
    new_prev = _past(chain.j, win_pos, cloud, models, win_exists)
    pm, S, obs, free = _predict(new_prev, chain.labels, exists, models)
    prop = chain._replace(exists=exists, pos=pos, log_lik=_log_lik(pos, exists, z, sensor),
                          log_px=_log_px(pos, pm, S, obs, free, existence),
                          log_birth=_birth_ratio(pos, free, cloud, models), pm=pm, S=S, observed=obs, free=free,
                          prev=new_prev)

    def log_e(win_ex: Tensor, ex: Tensor) -> Tensor:  # eq. 25 over the window and t
        full = torch.cat([anchor_ex.unsqueeze(2), win_ex, ex.unsqueeze(2)], 2)
        return existence.log_prob_exists(full[:, :, 1:], full[:, :, :-1]).sum((-1, -2))

    log_rho = (_past_log_target(prop) - _past_log_target(chain)
               + (log_e(win_exists, exists) - log_e(prev.win_exists, chain.exists)).to(y.dtype))
    log_rho = log_rho + torch.where(birth, -log_q, log_q)
    n_new = torch.stack(_eligible(anchor_ex, win_exists, exists, cloud.n_pair)).any(0).flatten(-2).sum(-1)
    log_rho = log_rho + torch.log(n_elig.to(y.dtype)) - torch.log(n_new.to(y.dtype))  # the pick's 1 / n ratio
    acc = (birth | death) & mh_accept(log_rho, noise.u)
    return mh_select(acc, prop, chain), acc


def _eligible(anchor_ex: Tensor, win_ex: Tensor, ex: Tensor, n_pair: Tensor) -> tuple[Tensor, Tensor]:
    """The window birth's possible ``(slot, s)`` pairs: ``births (B, C, K, W)``, the slot dead
    from ``s - 1`` through ``t`` (and a paired detection at ``s``), and ``deaths``, dead at
    ``s - 1`` and alive from ``s`` through ``t``; from the existence at the anchor ``(B, C,
    K)``, in the window ``(B, C, W, K)`` and at ``t`` ``(B, C, K)``; ``n_pair (B, W)``.
    """
    w = win_ex.shape[2]
    f = torch.cat([anchor_ex.unsqueeze(2), win_ex, ex.unsqueeze(2)], 2).transpose(-1, -2)  # (B, C, K, W + 2)
    dead_on = torch.flip(torch.cumprod(torch.flip(~f, [-1]).to(torch.int64), -1), [-1]).to(torch.bool)  # dead from
    alive_on = torch.flip(torch.cumprod(torch.flip(f, [-1]).to(torch.int64), -1), [-1]).to(torch.bool)
    before = ~f[..., :w]
    births = before & dead_on[..., 1:w + 1] & (n_pair > 0)[:, None, None, :]
    return births, before & alive_on[..., 1:w + 1]


def _log_normal2(x: Tensor, mean: Tensor, var: Tensor) -> Tensor:
    """``log N(x; mean, var I_2)``: ``(B, C, 2), (B, C, 2), (B, C) -> (B, C)``."""
    return -0.5 * (x - mean).square().sum(-1) / var - torch.log(var) - LOG_2PI


def _conditional_slot(pos: Tensor, pm: Tensor, S: Tensor, obs: Tensor, onehot: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`_conditional` for a slot chosen per chain by ``onehot (B, C, K)`` (it must be
    observed): mean ``(B, C, 2)``, variance ``(B, C)``; independent of the slot's own position.
    """
    o = obs.to(pos.dtype)
    P = _observed_precision(S, o)
    sel = onehot.to(pos.dtype)
    p_i = (P * sel.unsqueeze(-1)).sum(-2)  # (B, C, K): row i
    pii = (p_i * sel).sum(-1)
    d = (pos - pm) * (o * (1.0 - sel)).unsqueeze(-1)  # the other observed slots
    return (pm * sel.unsqueeze(-1)).sum(-2) - (p_i.unsqueeze(-2) @ d).squeeze(-2) / pii.unsqueeze(-1), 1.0 / pii


def _observed_precision(S: Tensor, o: Tensor) -> Tensor:
    """The precision of the observed block of ``S (B, C, K, K)`` (``o (B, C, K)`` 1 where
    observed; the unobserved rows and columns replaced by the identity): ``(B, C, K, K)``.
    """
    Sm = S * o.unsqueeze(-1) * o.unsqueeze(-2) + torch.diag_embed(1.0 - o)
    return torch.cholesky_inverse(torch.linalg.cholesky(Sm))


def _conditional(pos: Tensor, pm: Tensor, S: Tensor, obs: Tensor, i: int) -> tuple[Tensor, Tensor]:
    """Conditional of slot ``i``'s position given the other observed slots under the
    predictive ``N(pm, S)`` (per axis): mean ``(B, C, 2)``, variance ``(B, C)``. Through the
    precision ``P`` of the observed block: ``var = 1 / P_ii``,
    ``mean = x_i - (P d)_i / P_ii`` with ``d = (x - pm)`` on the observed slots.
    """
    o = obs.to(pos.dtype)
    P = _observed_precision(S, o)
    d = (pos - pm) * o.unsqueeze(-1)
    Pd = P[..., i, :].unsqueeze(-2) @ d  # (B, C, 1, 2)
    pii = P[..., i, i]
    return pos[..., i, :] - Pd.squeeze(-2) / pii.unsqueeze(-1), 1.0 / pii


def _log_q_slot(x_i: Tensor, cm: Tensor, cv: Tensor, obs_i: Tensor, free_i: Tensor, cloud: Cloud,
                models: Models) -> Tensor:
    """``log q_i(x_i)``: conditional Gaussian if observed, ``q_0`` if a free birth, 0 (point
    mass) if dead: ``-> (B, C)``.
    """
    log_n = _log_normal2(x_i, cm, cv)
    log_q0 = _log_q0(x_i.unsqueeze(-2), cloud, models.sensor, models.existence, models.p_i).squeeze(-1)
    return torch.where(obs_i, log_n, torch.where(free_i, log_q0, torch.zeros_like(log_n)))


# ----------------------------------------------------------------------------------------
# the state: a ParticleState whose extras hold the group fields
# ----------------------------------------------------------------------------------------
PATH_KEYS = ("path_pos", "path_labels", "path_exists", "path_log", "anchor_w_mean", "anchor_w_cov")


def unpack(state: ParticleState, lag: int) -> GroupView:
    """The group fields of a state (module docstring, "State and outputs") as a
    :class:`GroupView`; a state without a path (or with a longer one than ``lag``) starts one
    at its current step.
    """
    ex = state.extras or {}
    pos = state.x[..., 0::2]
    exists = state.exists if state.exists is not None else torch.zeros(pos.shape[:-1], dtype=torch.bool,
                                                                       device=pos.device)
    labels, w_mean, w_cov, frames = ex["labels"], ex["w_mean"], ex["w_cov"], ex["frames"]
    g = structure_index(labels)
    b, n, k = labels.shape
    if lag > 0 and all(key in ex for key in PATH_KEYS) and ex["path_pos"].shape[2] <= lag + 1:
        pp, pl, pe, plog = ex["path_pos"], ex["path_labels"], ex["path_exists"], ex["path_log"]
        pg = structure_index(pl)
        return GroupView(pos, g, labels, exists, w_mean, w_cov, state.log_w, frames,
                         pp[:, :, 0], pg[:, :, 0], pl[:, :, 0], pe[:, :, 0], ex["anchor_w_mean"], ex["anchor_w_cov"],
                         pp[:, :, 1:], pg[:, :, 1:], pl[:, :, 1:], pe[:, :, 1:], plog[:, :, 1:])
    none = pos.new_zeros((b, n, 0))
    return GroupView(pos, g, labels, exists, w_mean, w_cov, state.log_w, frames,
                     pos, g, labels, exists, w_mean, w_cov, pos.new_zeros((b, n, 0, k, 2)), g.new_zeros((b, n, 0)),
                     labels.new_zeros((b, n, 0, k)), exists.new_zeros((b, n, 0, k)), none)


# ----------------------------------------------------------------------------------------
# the step
# ----------------------------------------------------------------------------------------
def _predictive_log_lik(pm: Tensor, var: Tensor, exists: Tensor, z: Tensor, sensor: ThresholdedPixels,
                        p_death: float, radius: int = 2) -> Tensor:
    """``sum_i log[(1 - P_D) E_{N(pm_i, var_i I)} p(Z | x_i) + P_D]`` over the live slots
    (alpha ``"predictive"``, module docstring): ``pm (B, n, K, 2)``, ``var (B, n, K)`` ->
    ``(B, n)``. The Gaussian's mass on each pixel of a ``(2 radius + 1)^2`` window around its
    mean times the pixel's one-target ratio (eq. 40); mass outside the window or the grid
    counts with ratio 1 (the mean ratio of a pixel without a target is ``1``).
    """
    s = sensor.pixel_size
    h, w = sensor.shape
    sd = var.clamp(min=1e-12).sqrt().unsqueeze(-1)
    offs = torch.arange(-radius, radius + 1, device=pm.device, dtype=pm.dtype)
    cols = torch.floor(pm[..., 0] / s).unsqueeze(-1) + offs  # (B, n, K, R)
    rows = torch.floor(pm[..., 1] / s).unsqueeze(-1) + offs

    def mass(c: Tensor, mu: Tensor) -> Tensor:
        mu = mu.unsqueeze(-1)
        return torch.special.ndtr(((c + 1) * s - mu) / sd) - torch.special.ndtr((c * s - mu) / sd)

    m2 = mass(rows, pm[..., 1]).unsqueeze(-1) * mass(cols, pm[..., 0]).unsqueeze(-2)  # (B, n, K, R, R)
    inside = (((rows >= 0) & (rows < h)).unsqueeze(-1) & ((cols >= 0) & (cols < w)).unsqueeze(-2))
    flat = (rows.clamp(0, h - 1).long().unsqueeze(-1) * w + cols.clamp(0, w - 1).long().unsqueeze(-2))
    b = flat.shape[0]
    hit = torch.gather(z.reshape(b, -1).to(torch.bool), 1, flat.reshape(b, -1)).reshape(flat.shape)
    lr1 = sensor.p_d1 / sensor.p_fa
    lr0 = (1.0 - sensor.p_d1) / (1.0 - sensor.p_fa)
    lr = torch.where(inside, hit.to(pm.dtype) * (lr1 - lr0) + lr0, torch.ones_like(m2))
    e_lr = (m2 * lr).sum((-1, -2)) + (1.0 - m2.sum((-1, -2))).clamp(min=0.0)
    term = torch.log((1.0 - p_death) * e_lr + p_death)
    return torch.where(exists, term, torch.zeros_like(term)).sum(-1)


def _log_alpha_lik(v: GroupView, z: Tensor, models: Models, alpha: str, chunk: int = 512) -> Tensor:
    """``log p(Z_t | j)`` of eq. 62 (``"mean"``) or the predictive likelihood
    (``"predictive"``) of every particle, ``(B, N)`` (chunks of particles bound the memory).
    """
    out = []
    for s in range(0, v.pos.shape[1], chunk):
        sl = slice(s, s + chunk)
        pos, lab, ex = v.pos[:, sl], v.labels[:, sl], v.exists[:, sl]
        tr = models.motion.transition(pos, lab, lab, ex, ex, existence=models.existence)
        pred = pairwise_kalman_predict(KalmanStats(v.w_mean[:, sl], v.w_cov[:, sl]), pos, tr)
        if alpha == "mean":
            pm = torch.where(ex.unsqueeze(-1), pred.position_mean, _death_pos(models.existence, pos))
            out.append(_log_lik(pm, ex, z, models.sensor))
        else:
            var = torch.diagonal(pred.position_cov, dim1=-2, dim2=-1)
            out.append(_predictive_log_lik(pred.position_mean, var, ex, z, models.sensor, models.existence.p_death))
    return torch.cat(out, 1)


def make_cloud(state: ParticleState, z: Tensor, *, models: Models, settings: GroupMCMCSettings) -> Cloud:
    """Per-step quantities of the proposals (eqs. 19, 61-62, 65), eager."""
    v = unpack(state, settings.lag)
    b, _, k = v.exists.shape
    table = group_structures(k, device=v.pos.device)
    log_pg = models.structure_prior.log_probs(v.g, v.pos, v.exists)
    log_w = torch.log_softmax(state.log_w.to(torch.float64), -1)
    log_alpha = torch.log_softmax(log_w + _log_alpha_lik(v, z, models, settings.alpha).to(torch.float64), -1)
    log_q = torch.log(settings.p_a * log_alpha.exp() + (1.0 - settings.p_a) * log_w.exp())  # eq. 61
    zb = z.to(torch.bool)
    if settings.birth == "eq65":  # without a previous frame (or an empty one: the start), the current one
        prev = zb if v.frames.shape[1] == 0 else v.frames[:, -1].to(torch.bool)
        prev = torch.where(prev.flatten(1).any(-1)[:, None, None], prev, zb)
        beta = (zb & _near(prev, 1)).reshape(b, -1)
    else:
        beta = zb.reshape(b, -1)
    # the window birth: per window step s, the detections of Z_s with a detection of Z_{s+1} within two
    # pixels (a step of <= 100 m; Z_{W} = Z_t)
    w = v.win_pos.shape[2]
    seq = torch.cat([v.frames[:, v.frames.shape[1] - w:].to(torch.bool), zb.unsqueeze(1)], 1)  # (B, W + 1, H, W)
    pair = (seq[:, :-1] & _near(seq[:, 1:], 2)).flatten(2)  # (B, W, HW)
    return Cloud(v, log_pg, v.win_log.sum(-1), cdf(log_alpha), cdf(log_w), (log_w - log_q).to(v.pos.dtype),
                 beta, _uniform_cdf(beta), beta.sum(-1), table, pair, _uniform_cdf(pair), pair.sum(-1))


def _near(frames: Tensor, radius: int) -> Tensor:
    """Pixels within ``radius`` pixels (a square) of a detection of the binary ``frames (*S, H,
    W)``: ``-> (*S, H, W)`` bool.
    """
    return neighbourhood(frames.to(torch.float32), "max", 2, radius) > 0


def _uniform_cdf(mask: Tensor) -> Tensor:
    """The CDF (:func:`~torchmcmcpf.resampling.cdf`) of the distribution uniform over the True
    entries of each row of ``mask (*S, M)``; uniform over all ``M`` where a row has none (the
    draw is then unused but finite).
    """
    return cdf(torch.where(mask | ~mask.any(-1, keepdim=True), 0.0, -math.inf).to(torch.float64))


def _keep(cloud: Cloud, j: Tensor, g: Tensor, exists: Tensor, pos: Tensor, win_pos: Tensor, win_exists: Tensor,
          z: Tensor, models: Models, settings: GroupMCMCSettings, generator: torch.Generator, chunk: int = 512
          ) -> dict[str, Tensor]:
    """The extras of the kept states ``(B, N, ...)`` at ``t``: the Kalman statistics (eqs.
    53-57; from the anchor through the window with a lag, sampled with zero covariance when
    not marginalising), the frames and, with a lag, the new path.
    """
    v = cloud.view
    lag, w = settings.lag, win_pos.shape[2]
    labels = cloud.table[g]
    trim = lag > 0 and w == lag  # the path is full: its first entry leaves, the next is the anchor
    parts: dict[str, list[Tensor]] = {}
    for s in range(0, j.shape[1], chunk):
        sl = slice(s, s + chunk)
        jj = j[:, sl]
        if lag == 0:
            prev = _prev_of(cloud, jj)
            tr = models.motion.transition(prev.pos, prev.labels, labels[:, sl], prev.exists, exists[:, sl],
                                          existence=models.existence)
            _, st = pairwise_kalman_update(pairwise_kalman_predict(KalmanStats(prev.w_mean, prev.w_cov), prev.pos, tr),
                                           pos[:, sl])
            mean, cov = st.mean, st.cov
            if not settings.marginalise:
                d = cov.shape[-1]
                jitter = 1e-9 * (1.0 + torch.diagonal(cov, dim1=-2, dim2=-1).amax(-1))[..., None, None]
                L = torch.linalg.cholesky(cov + jitter * torch.eye(d, dtype=cov.dtype, device=cov.device))
                eps = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
                mean = mean + eps @ L.transpose(-1, -2)
                cov = torch.zeros_like(cov)
            parts.setdefault("w_mean", []).append(mean)
            parts.setdefault("w_cov", []).append(cov)
            continue
        stats = KalmanStats(_gather(v.anchor_w_mean, jj), _gather(v.anchor_w_cov, jj))
        a_pos, a_g, a_lab, a_ex = (_gather(t, jj) for t in (v.anchor_pos, v.anchor_g, v.anchor_labels,
                                                             v.anchor_exists))
        wg, wl = (_gather(t, jj) for t in (v.win_g, v.win_labels))
        we = win_exists[:, sl]
        off = v.frames.shape[1] - w  # the window's frames are the last W
        steps = [(win_pos[:, sl, i], wg[:, :, i], wl[:, :, i], we[:, :, i], v.frames[:, off + i]) for i in range(w)]
        steps.append((pos[:, sl], g[:, sl], labels[:, sl], exists[:, sl], z))
        path = [(a_pos, a_lab, a_ex)]
        terms, first = [], stats
        p_pos, p_g, p_lab, p_ex = a_pos, a_g, a_lab, a_ex
        for i, (q_pos, q_g, q_lab, q_ex, q_z) in enumerate(steps):
            term, stats = _path_step(stats, p_pos, p_g, p_lab, p_ex, q_pos, q_g, q_lab, q_ex, q_z, models)
            terms.append(term)
            path.append((q_pos, q_lab, q_ex))
            if i == 0:
                first = stats
            p_pos, p_g, p_lab, p_ex = q_pos, q_g, q_lab, q_ex
        anchor = first if trim else KalmanStats(_gather(v.anchor_w_mean, jj), _gather(v.anchor_w_cov, jj))
        if trim:
            path, terms = path[1:], terms[1:]
        for key, val in (("w_mean", stats.mean), ("w_cov", stats.cov), ("anchor_w_mean", anchor.mean),
                         ("anchor_w_cov", anchor.cov), ("path_pos", torch.stack([p[0] for p in path], 2)),
                         ("path_labels", torch.stack([p[1] for p in path], 2)),
                         ("path_exists", torch.stack([p[2] for p in path], 2)),
                         ("path_log", torch.stack([torch.zeros_like(terms[0])] + terms, 2))):
            parts.setdefault(key, []).append(val)
    extras = {key: torch.cat(val, 1) for key, val in parts.items()}
    frames = torch.cat([v.frames, z.to(torch.bool).unsqueeze(1)], 1)
    extras["frames"] = frames[:, frames.shape[1] - (extras["path_pos"].shape[2] - 1 if lag else 1):].contiguous()
    extras["labels"] = labels
    return extras


def group_mcmc_step(state: ParticleState, z: Tensor, *, motion: VirtualLeaderMotion, sensor: ThresholdedPixels,
                    settings: GroupMCMCSettings = GroupMCMCSettings(), generator: torch.Generator,
                    existence: GroupExistence, structure_prior: GroupStructurePrior,
                    moves: Callable[..., Any] | None = None) -> tuple[ParticleState, StepInfo]:
    """One time step of the marginalised MCMC-based particle filter (module docstring).

    Parameters
    ----------
    state : ParticleState at ``t - 1`` with the group extras (``x (B, N, K, 4)``;
        :meth:`GroupMCMCFilter.init`).
    z : (B, H, W) binary frame at ``t``.
    motion, sensor, existence, structure_prior : the models (eqs. 13, 41, 25/33, 19).
    settings : GroupMCMCSettings; generator : the only source of randomness (eager draws).
    moves : ``moves(move, chain, noise, cloud, z)`` running the move ``"joint"``,
        ``"refine"``, ``"past"`` or ``"birth"`` (compiled ones, ``GroupMCMCFilter(compile_step=True)``);
        default eager.

    Returns
    -------
    state : ParticleState at ``t`` (chain-major particles, equal weights).
    info : ``acceptance (B,)`` over all MH decisions; ``extras``: ``acceptance_joint``,
        ``acceptance_structure``, ``acceptance_target`` and, with a lag, ``acceptance_past``
        and, with ``p_window_birth``, ``acceptance_birth`` (B,) (NaN where the move never
        ran; the window birth counts its no-op proposals as rejections), ``structure_prob (B, Bell(K))``,
        ``exists_prob (B, K)``, ``expected_count (B,)``, ``all_exist_prob (B,)`` (every slot
        alive) and ``structure_prob_all_exist (B, Bell(K))``, the structure given that every
        slot is alive (NaN where no particle has them all).
    """
    b, n, k, _ = state.x.shape
    settings.check(n)
    c = settings.num_chains
    models = Models(motion, sensor, existence, structure_prior, float(settings.p_i), float(settings.p_a),
                    settings.past_step)
    moves = moves or _bind(models)
    dtype, dev = state.x.dtype, state.x.device
    cloud = make_cloud(state, z, models=models, settings=settings)
    chain = joint_proposal(JointNoise.draw((b, c, k), generator=generator, dtype=dtype, device=dev), cloud, z, models)
    per_chain = n // c
    names = (["joint", "structure", "target"] + (["past"] if settings.lag else [])
             + (["birth"] if settings.p_window_birth else []))
    acc = {name: state.x.new_zeros(b) for name in names}
    cnt = {name: state.x.new_zeros(b) for name in names}
    kept = []
    count = settings.burn_in + settings.thinning * per_chain
    with repeating():  # compiled moves: repeats skip Dynamo's guards (runtime.repeating)
        for m, move in enumerate(pick_moves(settings.moves(), count, generator=generator), start=1):
            noise = _draw_fields(NOISES[move], (b, c, k), generator, dtype, dev, window=max(settings.lag, 1))
            out = moves(move, chain, noise, cloud, z)
            chain = out[0]
            if move == "refine":
                acc["structure"] += out[1].to(dtype).sum(1)
                cnt["structure"] += c
                acc["target"] += out[2].to(dtype).sum((1, 2))
                cnt["target"] += c * k
            else:
                acc[move] += out[1].to(dtype).sum(1)
                cnt[move] += c
            if m > settings.burn_in and (m - settings.burn_in) % settings.thinning == 0:
                kept.append((chain.j, chain.g, chain.exists, chain.pos, chain.prev.win_pos, chain.prev.win_exists))
    j, g, exists, pos, win_pos, win_ex = (torch.stack(t, 2).flatten(1, 2) for t in zip(*kept))  # (B, C * N/C, ...)
    extras = _keep(cloud, j, g, exists, pos, win_pos, win_ex, z, models, settings, generator)
    vel = extras["w_mean"][..., :k].transpose(-1, -2)  # (B, N, K, 2)
    x = torch.stack([pos[..., 0], vel[..., 0], pos[..., 1], vel[..., 1]], -1)
    new = ParticleState(x, x.new_full((b, n), -math.log(n)), exists, extras)
    one_hot = F.one_hot(g, cloud.table.shape[0]).to(x.dtype)  # (B, N, G)
    all_exist = exists.all(-1).to(x.dtype)  # (B, N)
    exists_prob = exists.to(x.dtype).mean(1)
    info = {f"acceptance_{name}": acc[name] / cnt[name] for name in names}
    info.update(structure_prob=one_hot.mean(1), exists_prob=exists_prob, expected_count=exists_prob.sum(-1),
                all_exist_prob=all_exist.mean(1),
                structure_prob_all_exist=(one_hot * all_exist.unsqueeze(-1)).sum(1) / all_exist.sum(1, keepdim=True))
    acceptance = sum(acc.values(), x.new_zeros(b)) / sum(cnt.values(), x.new_zeros(b))
    return new, StepInfo.make(acceptance, acceptance=acceptance, extras=info)


def _bind(models: Models, compile: Callable[[Callable], Callable] | None = None) -> Callable[..., Any]:
    """``moves(move, chain, noise, cloud, z)``: the moves with the models bound (each compiled
    on its own with ``compile``: three functions, so that each has its own compile cache).
    """
    def joint(chain: Chain, noise: JointNoise, cloud: Cloud, z: Tensor) -> Any:
        return joint_move(chain, noise, cloud, z, models)

    def refine(chain: Chain, noise: RefineNoise, cloud: Cloud, z: Tensor) -> Any:
        return refine_move(chain, noise, cloud, z, models)

    def past(chain: Chain, noise: PastNoise, cloud: Cloud, z: Tensor) -> Any:
        return past_move(chain, noise, cloud, z, models)

    def birth(chain: Chain, noise: BirthNoise, cloud: Cloud, z: Tensor) -> Any:
        return window_birth_move(chain, noise, cloud, z, models)

    programs: dict[str, Callable[..., Any]] = {"joint": joint, "refine": refine, "past": past, "birth": birth}
    if compile is not None:
        programs = {name: compile(fn) for name, fn in programs.items()}

    def run(move: str, chain: Chain, noise: Any, cloud: Cloud, z: Tensor) -> Any:
        return programs[move](chain, noise, cloud, z)

    return run


# ----------------------------------------------------------------------------------------
# the filter
# ----------------------------------------------------------------------------------------
class GroupMCMCFilter(Filter):
    """Marginalised MCMC-based particle filter for coordinated groups (paper 004, sec. 4).

    Parameters
    ----------
    motion : VirtualLeaderMotion (eqs. 1-16); sensor : ThresholdedPixels (eqs. 39-41) or
        a pixel sensor with ``shape``, ``pixel_size``, ``position_index``.
    num_particles : N, a multiple of ``num_chains``.
    existence : GroupExistence (eq. 25, births eqs. 29-37); structure_prior :
        GroupStructurePrior (eq. 19).
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

    motion: VirtualLeaderMotion  # type: ignore[assignment]  # a whole-configuration motion (motion_type)
    sensor: ThresholdedPixels
    existence: GroupExistence
    settings: GroupMCMCSettings
    #: the group fields of the state (module docstring, "State and outputs"); the fixed-lag
    #: path's fields only with ``lag > 0``
    state_extras = frozenset({"labels", "w_mean", "w_cov", "frames"})
    optional_state_extras = frozenset(PATH_KEYS)
    settings_class = GroupMCMCSettings
    motion_type = VirtualLeaderMotion
    relabels = False  # a slot's label is its place in the group structure

    def __init__(self, motion: VirtualLeaderMotion, sensor: ThresholdedPixels, num_particles: int,
                 settings: GroupMCMCSettings | None = None, *, existence: GroupExistence,
                 structure_prior: GroupStructurePrior, compile_step: bool = False, **shortcuts: Any) -> None:
        if not all(hasattr(sensor, a) for a in ("shape", "pixel_size", "position_index", "log_likelihood")):
            raise ValueError(f"sensor must be a pixel sensor (ThresholdedPixels), got {type(sensor).__name__}")
        if not isinstance(existence, GroupExistence):
            raise ValueError(f"existence must be a GroupExistence, got {type(existence).__name__}")
        if not isinstance(structure_prior, GroupStructurePrior):
            raise ValueError(f"structure_prior must be a GroupStructurePrior, got {type(structure_prior).__name__}")
        n = check_positive_int(num_particles, "num_particles")
        if shortcuts.get("num_chains", 0) is None:
            del shortcuts["num_chains"]
        if settings is None and "num_chains" not in shortcuts:  # the one default that depends on N
            shortcuts["num_chains"] = default_chains(n)
        if "past_step" in shortcuts:
            shortcuts["past_step"] = tuple(shortcuts["past_step"])
        super().__init__(motion, sensor, n, settings, existence=existence,  # type: ignore[arg-type]
                         compile_step=compile_step, **shortcuts)
        self.settings.check(n)
        self.structure_prior = structure_prior

    def models(self) -> Models:
        """The models and proposal constants the moves are bound to."""
        s = self.settings
        return Models(self.motion, self.sensor, self.existence, self.structure_prior, float(s.p_i), float(s.p_a),
                      s.past_step)

    def _build_compiled(self, compile: Callable[[Callable], Callable]) -> Callable:
        return _bind(self.models(), compile)

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
        x = torch.where(exists.unsqueeze(-1), particles, self.existence.x_death.to(particles))
        st = pairwise_kalman_init((b, n), k, existence=self.existence, dtype=particles.dtype, device=particles.device)
        w_mean = st.mean.clone()
        w_mean[..., :k] = x[..., 1::2].transpose(-1, -2)
        labels = labels.to(torch.int64).contiguous()
        h, w = self.sensor.shape
        extras = {"labels": labels, "w_mean": w_mean, "w_cov": st.cov,
                  "frames": torch.zeros((b, 0, h, w), dtype=torch.bool, device=particles.device)}
        lag = self.settings.lag
        if lag:
            # all inactive: a past of L inactive steps (empty frames) is the same start, and the state
            # has its final shapes from the first step on (compiled moves compile once)
            p = lag + 1 if not bool(exists.any()) else 1
            extras.update(path_pos=x[..., 0::2].unsqueeze(2).expand(b, n, p, k, 2).clone(),
                          path_labels=labels.unsqueeze(2).expand(b, n, p, k).clone(),
                          path_exists=exists.unsqueeze(2).expand(b, n, p, k).clone(), path_log=x.new_zeros((b, n, p)),
                          anchor_w_mean=w_mean.clone(), anchor_w_cov=st.cov.clone())
            extras["frames"] = torch.zeros((b, p - 1, h, w), dtype=torch.bool, device=particles.device)
        return ParticleState(x, particles.new_full((b, n), -math.log(n)), exists, extras)

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
        """The group fields of ``state.extras`` (module docstring): keys, shapes, dtypes and
        devices against ``x (B, N, K, 4)``; ``ValueError`` naming the field otherwise.
        """
        b, n, k, _ = state.x.shape
        if state.exists is None:
            raise ValueError("state.exists is None; the group filter's state has existence flags (filt.init)")
        ex = state.extras or {}
        h, w = self.sensor.shape
        f = ex["frames"].shape[1] if torch.is_tensor(ex.get("frames")) and ex["frames"].dim() == 4 else None
        p = ex["path_pos"].shape[2] if torch.is_tensor(ex.get("path_pos")) and ex["path_pos"].dim() == 5 else None
        expected: dict[str, tuple[tuple[int | None, ...], torch.dtype | None]] = {
            "labels": ((b, n, k), torch.int64), "w_mean": ((b, n, 2, 3 * k), state.x.dtype),
            "w_cov": ((b, n, 3 * k, 3 * k), state.x.dtype), "frames": ((b, f, h, w), torch.bool)}
        if any(key in ex for key in PATH_KEYS):
            expected.update(path_pos=((b, n, p, k, 2), state.x.dtype), path_labels=((b, n, p, k), torch.int64),
                            path_exists=((b, n, p, k), torch.bool), path_log=((b, n, p), state.x.dtype),
                            anchor_w_mean=((b, n, 2, 3 * k), state.x.dtype),
                            anchor_w_cov=((b, n, 3 * k, 3 * k), state.x.dtype))
        for key, (shape, dtype) in expected.items():
            t = ex.get(key)
            if not torch.is_tensor(t):
                raise ValueError(f"state.extras[{key!r}] is missing; expected a tensor of shape {shape} "
                                 "(build the state with filt.init or filt.init_inactive)")
            check_shape(t, f"state.extras[{key!r}]", shape)
            if t.dtype != dtype or t.device != state.x.device:
                raise ValueError(f"state.extras[{key!r}] is {t.dtype} on {t.device}, expected {dtype} on "
                                 f"{state.x.device}")

    def validate(self, state: ParticleState, measurements: Any, *, sequence: bool,
                 name: str = "measurements") -> None:
        """:meth:`Filter.validate`, the group fields (:meth:`check_extras`) and the memory
        estimate (:meth:`check_memory`).
        """
        super().validate(state, measurements, sequence=sequence, name=name)
        self.check_extras(state)
        self.check_memory(state.batch_size, state.num_targets)

    def _step(self, state: ParticleState, z: Any, generator: torch.Generator) -> tuple[ParticleState, StepInfo]:
        """One call of :func:`group_mcmc_step` with this filter's models and settings."""
        return group_mcmc_step(state, z, motion=self.motion, sensor=self.sensor, settings=self.settings,
                               generator=generator, existence=self.existence, structure_prior=self.structure_prior,
                               moves=self.compiled())


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
