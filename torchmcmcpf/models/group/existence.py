"""Group existence and births (paper 004 eqs. 24-37), and the Bayes limit of detection of one
perfectly localised target (eqs. 25, 33, 41).

Paper 004's model as a whole, its state layouts and notation: the docstring of :mod:`torchmcmcpf.models.group`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch

from ..._native.select import where
from ..._validation import check_positive, check_positive_int
from ...typing import Tensor
from ..existence import BirthDeath
from ..sensors.points import AreaLike

__all__ = ["GroupExistence", "ExistenceLimit", "localised_existence", "existence_limit"]


class GroupExistence(BirthDeath):
    """Existence chain and birth/death densities of a group configuration (eqs. 24-37).

    A :class:`~torchmcmcpf.models.existence.BirthDeath` (the library's one birth/death law:
    the existence chain of eq. 25, its draws, the area and the uniform birth position of
    eqs. 32-33) with the group model's extra birth densities:

    - independent birth (``Upsilon_2^1``: newborn in a group with no survivor), eqs. 32-33:
      position uniform over ``area``, velocity ``N(0, velocity_std^2 I)``;
    - group birth (``Upsilon_2^2``), eqs. 29-31: ``N(F~_1 s_bar_{t-1}, Q_bT)``, ``s_bar`` the
      mean state of the group's survivors and the group's (merged / kept) leader at ``t-1``,
      ``F~_1`` the member rows of ``F_1``; ``Q_bT = diag(s_p^2, s_v^2)`` per axis with
      ``(s_p, s_v) = group_birth_std``;
    - new leader of a group with newborns only (``Upsilon_6``), eq. 35:
      ``N(mean of the newborns' states, Q_bVL)``, ``Q_bVL = diag(s_p^2, s_v^2)`` per axis,
      ``(s_p, s_v) = leader_birth_std``;
    - dead target at ``x_death``, dead leader (group with no live member, or unused label) at
      ``v_death`` (eqs. 36-37), both ``(4,)`` in the ``[x, vx, y, vy]`` layout.

    The paper gives no numbers for ``sigma_Vmax``, ``Q_bT``, ``Q_bVL``; the defaults are ours.

    Parameters
    ----------
    p_birth, p_death : ``P_B``, ``P_D`` (paper: 0.2, 0.05).
    area : ``((x_lo, x_hi), (y_lo, y_hi))`` [m].
    velocity_std : ``sigma_Vmax`` [m/s] (default 5).
    group_birth_std : ``(s_p [m], s_v [m/s])`` of ``Q_bT`` (default (50, 2)).
    leader_birth_std : ``(s_p, s_v)`` of ``Q_bVL`` (default (50, 2)).
    x_death, v_death : (4,) (default zeros).

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.models.group import GroupExistence
    >>> existence = GroupExistence(0.2, 0.05, ((0.0, 1000.0), (0.0, 2000.0)))   # P_B, P_D, area
    >>> pos = torch.tensor([[500.0, 500.0], [1500.0, 500.0]])    # (K, 2): inside, outside
    >>> existence.log_p0_position(pos)                      # uniform: -log(1000 * 2000) inside
    tensor([-14.5087,     -inf])
    >>> existence.sample_p0_position((3, 2), generator=torch.Generator()).shape
    torch.Size([3, 2, 2])
    >>> existence.group_birth_cov                           # Q_bT per axis, diag(50^2, 2^2)
    tensor([[2500.,    0.],
            [   0.,    4.]], dtype=torch.float64)
    """

    group_birth_cov: Tensor  # (2, 2) Q_bT per axis
    leader_birth_cov: Tensor  # (2, 2) Q_bVL per axis
    v_death: Tensor  # (4,)

    def __init__(self, p_birth: float, p_death: float, area: AreaLike, *, velocity_std: float = 5.0,
                 group_birth_std: Sequence[float] = (50.0, 2.0),
                 leader_birth_std: Sequence[float] = (50.0, 2.0),
                 x_death: Tensor | None = None, v_death: Tensor | None = None) -> None:
        super().__init__(p_birth, p_death, area, velocity_std=velocity_std, dim=4, x_death=x_death)
        dtype = torch.float64
        for name, std in (("group_birth_std", group_birth_std), ("leader_birth_std", leader_birth_std)):
            if len(std) != 2:
                raise ValueError(f"{name} must be (position std, velocity std), got {std!r}")
            sp, sv = check_positive(std[0], name), check_positive(std[1], name)
            self.register_buffer(name.replace("_std", "_cov"), torch.diag(torch.tensor([sp**2, sv**2], dtype=dtype)))
        val = torch.zeros(4, dtype=dtype) if v_death is None else torch.as_tensor(v_death, dtype=dtype)
        if val.shape != (4,) or not bool(torch.isfinite(val).all()):
            raise ValueError(f"v_death must be a finite (4,) vector, got shape {tuple(val.shape)}")
        self.register_buffer("v_death", val)

    def log_p0_position(self, pos: Tensor) -> Tensor:
        """Log density of the uniform birth position (eq. 32): ``(*S, K, 2) -> (*S, K)``,
        ``-inf`` outside the area (the area check of :class:`BirthDeath`, in ``pos``'s dtype).
        """
        return where(self._in_area(pos), pos.new_full((), -self.log_volume), pos.new_full((), -math.inf))

    def sample_p0_position(self, shape: Sequence[int], *, generator: torch.Generator,
                           dtype: torch.dtype = torch.float64,
                           device: torch.device | str | None = None) -> Tensor:
        """Uniform birth positions (eq. 32): ``-> (*shape, 2)``."""
        return self.uniform_position(torch.rand(tuple(shape) + (2,), generator=generator, dtype=dtype,
                                                device=device))


# ----------------------------------------------------------------------------------------
# the Bayes limit of detection: one perfectly localised target (eqs. 25, 33, 41)
# ----------------------------------------------------------------------------------------
class ExistenceLimit(NamedTuple):
    """What the existence model allows for one target whose position is known exactly
    (:func:`existence_limit`).

    Attributes
    ----------
    per_step : (T,) float64 ``E[P(alive at t | d_1:t)]`` over the detections of a target that
        is alive from step 1 on, starting from ``P(alive) = 0`` (an all-inactive start).
    per_step_error : (T,) half-width of the bracket around ``per_step`` (0 where the
        expectation is an exact enumeration, ``t <= window``).
    stationary : the long-run mean of the posterior, ``lim_t E[P(alive at t | d_1:t)]``.
    stationary_error : half-width of its bracket.

    Example
    -------
    >>> from torchmcmcpf.models.group import existence_limit
    >>> limit = existence_limit(30, p_birth=0.2, p_death=0.05, p_d1=0.9, p_fa=0.01, window=8)
    >>> limit.per_step[:3]                                  # exact for t <= window
    tensor([0.8642, 0.9438, 0.9576], dtype=torch.float64)
    >>> round(limit.stationary, 4), limit.stationary_error < 1e-6   # x K targets: the count's ceiling
    (0.9594, True)
    """

    per_step: Tensor
    per_step_error: Tensor
    stationary: float
    stationary_error: float


def _check_existence_law(p_birth: float, p_death: float, p_d1: float, p_fa: float, p_here: float) -> None:
    for name, v in (("p_birth", p_birth), ("p_death", p_death), ("p_here", p_here)):
        if not 0.0 <= float(v) <= 1.0:
            raise ValueError(f"{name} must be a probability in [0, 1], got {v!r}")
    if not 0.0 < float(p_fa) < float(p_d1) < 1.0:
        raise ValueError(f"need 0 < p_fa < p_d1 < 1, got p_fa={p_fa!r}, p_d1={p_d1!r}")


def localised_existence(detected: Tensor, *, p_birth: float, p_death: float, p_d1: float, p_fa: float,
                        p_here: float = 1.0, p_alive: float | Tensor = 0.0) -> Tensor:
    """Exact posterior existence of one target at a known pixel: a two-state hidden Markov
    model over its detection sequence (paper 004 eqs. 25, 33, 41).

    The hidden state is "the target is alive at the pixel" (1) or not (0). From 1 it stays
    with ``1 - P_D`` (eq. 25); from 0 it appears at the pixel with ``P_B p_here``, ``p_here``
    the chance that a newborn's uniform position (eq. 33) falls in this pixel (pixel area
    over scene area: 1e-4 for paper 004's 100 x 100 pixels; 1 if newborns appear at the
    known pixel). The pixel fires with ``P_d,1`` in state 1 and ``P_fa`` in state 0 (eq. 41).
    The forward recursion, in probability space (two states, renormalised every step)::

        prior_t = p_{t-1} (1 - P_D) + (1 - p_{t-1}) P_B p_here
        p_t = prior_t l_1(d_t) / (prior_t l_1(d_t) + (1 - prior_t) l_0(d_t)).

    Every filter of the group model that knows the target's pixel perfectly can do no better
    than this; a real filter, which must also find the pixel, does worse on the target (its
    expected count can still exceed ``K p_t`` through targets it believes born on false
    alarms).

    Parameters
    ----------
    detected : (*S, T) bool, the pixel's value in frames 1..T.
    p_birth, p_death, p_d1, p_fa, p_here : the model above.
    p_alive : ``P(alive)`` before frame 1, a float or ``(*S,)`` (default 0: inactive).

    Returns
    -------
    (*S, T) float64, ``P(alive at t | d_1:t)``.
    """
    _check_existence_law(p_birth, p_death, p_d1, p_fa, p_here)
    d = torch.as_tensor(detected).to(torch.bool)
    p = torch.as_tensor(p_alive, dtype=torch.float64, device=d.device).expand(d.shape[:-1])
    one = torch.ones((), dtype=torch.float64, device=d.device)  # float64 probabilities (not torch.where's float32)
    out = []
    for t in range(d.shape[-1]):
        prior = p * (1.0 - p_death) + (1.0 - p) * (p_birth * p_here)
        l1 = where(d[..., t], one * p_d1, one - p_d1)
        l0 = where(d[..., t], one * p_fa, one - p_fa)
        p = prior * l1 / (prior * l1 + (1.0 - prior) * l0)
        out.append(p)
    return torch.stack(out, -1) if out else p.new_zeros(d.shape)


def existence_limit(num_steps: int, *, p_birth: float, p_death: float, p_d1: float, p_fa: float,
                    p_here: float = 1.0, window: int = 20) -> ExistenceLimit:
    """The mean posterior existence of a perfectly localised target that is alive from step 1
    on (:func:`localised_existence`), per step and in the long run: multiply by the number
    of targets for the ceiling of the expected number of targets.

    The expectation is over the target's detections, independent ``Bernoulli(P_d,1)``. For
    ``t <= window`` it is an exact sum over all ``2^t`` sequences (from ``P(alive) = 0``).
    Beyond, the posterior depends on the last ``window`` detections and on ``p_{t-window}``,
    and it increases with ``p_{t-window}``, so the sums over the last ``window`` detections
    started from 0 and from 1 bracket it; ``per_step`` is the midpoint and
    ``per_step_error`` the half-width (below 1e-5 for paper 004's numbers at the default
    window). The stationary mean has the same bracket.

    Parameters
    ----------
    num_steps : T >= 1; p_birth, p_death, p_d1, p_fa, p_here : as :func:`localised_existence`.
    window : enumeration length (``2^window`` sequences; default 20, about 1e6).

    Returns
    -------
    ExistenceLimit.
    """
    t_max = check_positive_int(num_steps, "num_steps")
    w = check_positive_int(window, "window")
    if w > 24:
        raise ValueError(f"window must be <= 24 (2^window sequences are enumerated), got {window}")
    _check_existence_law(p_birth, p_death, p_d1, p_fa, p_here)
    codes = torch.arange(2 ** w)
    d = ((codes.unsqueeze(-1) >> torch.arange(w)) & 1).to(torch.bool)  # (2^w, w), every sequence once
    one = torch.ones((), dtype=torch.float64)
    prob = where(d, one * p_d1, one - p_d1).prod(-1)  # (2^w,)
    law = dict(p_birth=p_birth, p_death=p_death, p_d1=p_d1, p_fa=p_fa, p_here=p_here)
    lo = prob @ localised_existence(d, **law, p_alive=0.0)  # (w,): exact from an inactive start
    hi = prob @ localised_existence(d, **law, p_alive=1.0)
    lo_w, hi_w = float(lo[-1]), float(hi[-1])
    mean = torch.full((t_max,), 0.5 * (lo_w + hi_w), dtype=torch.float64)
    err = torch.full((t_max,), 0.5 * (hi_w - lo_w), dtype=torch.float64)
    n = min(t_max, w)
    mean[:n], err[:n] = lo[:n], 0.0
    return ExistenceLimit(mean, err, 0.5 * (lo_w + hi_w), 0.5 * (hi_w - lo_w))
