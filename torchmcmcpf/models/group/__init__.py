"""Coordinated groups: virtual-leader motion, group structures, group births and the
pairwise Kalman statistics of Septier, Pang, Godsill and Carmi (2009, paper 004).

Continuous-time model (eqs. 1-7)
--------------------------------
Each member ``i`` of group ``g`` follows, per axis,
``d xdot_i = {-alpha (x_i - v) - gamma1 xdot_i - beta (xdot_i - vdot)} dt + sigma_x dW_i`` and
its virtual leader ``d vdot = -gamma2 vdot dt + sigma_g dG`` (eqs. 1-2). In the paper's state
order of eq. 3, ``s = [x_1..x_n, y_1..y_n, xdot_1..xdot_n, ydot_1..ydot_n, v^x, v^y, vdot^x,
vdot^y]``, ``ds = A s dt + h dt + D dn`` (eqs. 3-8) with the exact discretisation
``s_t = F s_{t-1} + R h + b``, ``b ~ N(0, Q)`` (eqs. 12-16), computed by
:meth:`VirtualLeaderMotion.matrices` with ``torch.linalg.matrix_exp`` (Van Loan 1978).

Whole configurations (``K = N_max`` slots)
-----------------------------------------
A configuration is

- target states ``x (*S, K, 4)`` in the library layout ``[x, vx, y, vy]``;
- leader states ``v (*S, K, 4)``, same layout: leader slot ``h`` belongs to group label ``h``;
- structure labels ``g (*S, K)`` int64, a restricted-growth string (first target in group 0,
  :func:`group_structures`), or equivalently the index of its row in that table;
- existence ``e (*S, K)`` bool.

Members do not interact with each other except through their leader (and the repulsion,
an input), so every ``F_n``, ``R_n``, ``Q_n`` is made of the same few blocks whatever ``n``:
member-member (self and cross), member-leader and leader-leader. :class:`VirtualLeaderMotion`
reads them once from ``matrices(2)``; a configuration's transition is then assembled by
broadcasting these blocks against one-hot membership matrices: no Python loop over
particles, groups or configurations. Both axes share the dynamics and the noise
(``sigma_y = sigma_x``), so the transition of the per-axis state
``[x_1..x_K, xdot_1..xdot_K, v_1..v_K, vdot_1..vdot_K]`` (``4K``) has one ``Psi`` and one
covariance for both axes and an offset per axis (:class:`AffineTransition`).

Marginalisation (eqs. 42-58)
----------------------------
The velocities and leaders ``w = [x_v, v]`` (``3K`` per axis) are integrated out: each
particle carries ``N(w_{t-1}; mean, cov)`` given its positions ``x_{p,0:t-1}``
(:class:`KalmanStats`, one covariance for both axes), :func:`pairwise_kalman_predict` gives
the joint Gaussian of ``(x_{p,t}, w_t)`` and :func:`pairwise_kalman_update` conditions it on
the new positions: the log of eq. 58 and the statistics of eqs. 56-57.
"""


from .existence import ExistenceLimit, GroupExistence, existence_limit, localised_existence
from .kalman import (
    GroupPrediction,
    KalmanStats,
    pairwise_kalman_init,
    pairwise_kalman_predict,
    pairwise_kalman_sample,
    pairwise_kalman_update,
)
from .motion import AffineTransition, VirtualLeaderMotion, from_axes, to_axes
from .structures import (
    GroupStructurePrior,
    bell_number,
    canonical_labels,
    gaussian_closeness,
    group_structures,
    structure_index,
)

__all__ = [
    "VirtualLeaderMotion",
    "GroupExistence",
    "GroupStructurePrior",
    "AffineTransition",
    "KalmanStats",
    "GroupPrediction",
    "group_structures",
    "structure_index",
    "bell_number",
    "pairwise_kalman_init",
    "pairwise_kalman_predict",
    "pairwise_kalman_update",
    "pairwise_kalman_sample",
    "canonical_labels",
    "gaussian_closeness",
    "to_axes",
    "from_axes",
    "ExistenceLimit",
    "localised_existence",
    "existence_limit",
]
