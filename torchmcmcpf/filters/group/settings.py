"""Settings of the group filter (paper 004 sec. 5 values) and the sizes that follow from them:
the default number of chains and the memory estimate of one step.

The maths, the moves' targets and acceptance ratios: the docstring of :mod:`torchmcmcpf.filters.group`.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..._validation import check_positive, check_positive_int
from ...models.group import (
    bell_number,
)

__all__ = ["GroupMCMCSettings", "default_chains", "estimate_step_bytes", "ALPHAS", "BIRTHS"]

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
    alpha : ``"mean"`` (eq. 62) or ``"predictive"`` (package docstring).
    birth : ``"eq65"`` (paper) or ``"frame"`` (package docstring).
    lag : L >= 0, positions of each target's past the past move changes (0: no past move).
    p_past : probability of the past move per iteration (needs ``lag >= 1``).
    past_step : ``(s_a [m], s_b [m per step])``, the shift and velocity steps of the past move.
    p_window_birth : probability of the window birth/death move per iteration (needs
        ``lag >= 1``; 0: off, the paper's sampler).
    max_memory_gb : refuse a problem whose step needs more (:func:`estimate_step_bytes`).

    Example
    -------
    >>> from torchmcmcpf.filters.group import GroupMCMCSettings
    >>> settings = GroupMCMCSettings(num_chains=4, burn_in=20, lag=2, p_past=0.2)   # with the past move
    >>> settings.thinning, settings.xi                      # the paper's values by default
    (6, 0.75)
    >>> GroupMCMCSettings(p_past=0.5)
    Traceback (most recent call last):
    ...
    ValueError: lag >= 1 and p_past > 0 go together (the past move needs a past), got lag=0, p_past=0.5
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
