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
``log_w``, ``exists``, and ``extras["group"]`` the rest, one typed
:class:`~torchmcmcpf.filters.group.GroupState` (run dim first; validated by
:meth:`GroupState.check <torchmcmcpf.filters.group.GroupState.check>`):

- ``labels (B, N, K)`` int64, the structure; ``w_mean (B, N, 2, 3K)``, ``w_cov (B, N, 3K,
  3K)``, the Kalman statistics of ``w = [velocities, leader positions, leader velocities]``
  per axis; ``frames (B, F, H, W)`` bool, the last ``F`` frames (eq. 65 and the window);
- ``path``, with ``lag >= 1``, a :class:`~torchmcmcpf.filters.group.GroupPath`: the path
  ``t - P + 1 .. t`` (``P <= L + 1`` entries, the first the anchor): ``pos (B, N, P, K, 2)``,
  ``labels``, ``exists (B, N, P, K)``, ``log (B, N, P)`` (each entry's term of the target
  above), ``anchor_w_mean``, ``anchor_w_cov``; None without a lag.

``StepInfo.extras`` has ``structure_prob (B, Bell(K))`` (posterior probability of every row
of :func:`~torchmcmcpf.models.group.group_structures`), ``exists_prob (B, K)``,
``expected_count (B,)`` and the acceptance rate of each move. The group filter takes the
group models in place of ``Filter``'s (:class:`VirtualLeaderMotion`, a
:class:`GroupExistence`, which is a ``BirthDeath``, and the structure prior of eq. 19); the
per-target refinement loops over the ``K`` slots (a Gibbs sweep is sequential by definition).
"""

from .filter import GroupMCMCFilter
from .noise import GroupJointNoise, GroupPastNoise, GroupRefineNoise, GroupWindowBirthNoise, draw_noise
from .settings import GroupMCMCSettings, default_chains, estimate_step_bytes
from .state import GroupPath, GroupState
from .step import bind_group, group_mcmc_bound_step, group_mcmc_step

__all__ = ["GroupMCMCFilter", "GroupMCMCSettings", "GroupState", "GroupPath", "group_mcmc_step", "bind_group",
           "group_mcmc_bound_step", "GroupJointNoise", "GroupRefineNoise",
           "GroupPastNoise", "GroupWindowBirthNoise", "draw_noise", "default_chains", "estimate_step_bytes"]

# The moves, their containers and the step's pieces stay importable from here (as before the
# split) for code that drives the moves one by one (tests/filters/test_group_filter.py,
# benchmarks/bench_group.py); each module's __all__ lists its own.
from .moves import Chain as Chain  # noqa: E402
from .moves import Cloud as Cloud  # noqa: E402
from .moves import GroupView as GroupView  # noqa: E402
from .moves import Models as Models  # noqa: E402
from .moves import Prev as Prev  # noqa: E402
from .moves import joint_move as joint_move  # noqa: E402
from .moves import joint_proposal as joint_proposal  # noqa: E402
from .moves import make_chain as make_chain  # noqa: E402
from .moves import past_move as past_move  # noqa: E402
from .moves import refine_move as refine_move  # noqa: E402
from .moves import window_birth_move as window_birth_move  # noqa: E402
from .noise import NOISES as NOISES  # noqa: E402
from .settings import ALPHAS as ALPHAS  # noqa: E402
from .settings import BIRTHS as BIRTHS  # noqa: E402
from .step import make_cloud as make_cloud  # noqa: E402
from .step import unpack as unpack  # noqa: E402
