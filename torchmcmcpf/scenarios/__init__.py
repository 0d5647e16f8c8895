"""Scenario simulators that reproduce each paper's setup, batched over Monte Carlo runs.

- :func:`ground_radar`: range-doppler-bearing TBD, Bocquel et al. (2012) Table I.
- :func:`crossing`: targets that cross unresolved on the same radar (where tracks coalesce).
- :func:`ling`: three targets on an azimuth-range Swerling-I grid (Ling, paper 002).
- :func:`septier`: births and deaths in Poisson clutter, after Septier et al. (paper 001).
- :mod:`maroulas`: the time-varying target count of Maroulas and Stinis (2010).
- :func:`group_merge`: two groups of two targets merge, thresholded pixels (Septier et al. 2009).
"""

from . import maroulas
from .crossing import crossing
from .ground_radar import Scenario, ground_radar
from .group_merge import GroupMergeScenario, group_merge
from .ling import LingScenario, ling
from .septier import SeptierScenario, septier

__all__ = ["Scenario", "ground_radar", "crossing", "LingScenario", "ling", "SeptierScenario", "septier", "maroulas",
           "GroupMergeScenario", "group_merge"]
