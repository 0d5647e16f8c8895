"""Sensor models, one file per family (DESIGN.md).

- :class:`LinearGaussian`: one point measurement per target, known association.
- :class:`SeparableGridSensor`: the shared machinery of TBD sensors on a cell grid.
- :class:`RangeDopplerBearingTBD`: radar power, Rician (Bocquel et al. 2012, eqs. 18-21).
- :class:`AzimuthRangeSwerlingTBD`: Swerling-I exponential power (Ling, eqs. 3-9).
- :class:`AssociationPosition`, :class:`AssociationBearingRange`: point measurements with
  unknown association (Maroulas and Stinis 2010, eqs. 14-17).
- :class:`PoissonClutterPoints`: point measurements in Poisson clutter, association-free.
- :class:`ThresholdedPixels`: binary pixel frames (Septier et al. 2009, eqs. 39-41).
"""

from .association import AssociationBearingRange, AssociationPosition, AssociationSensor, PointFrame
from .grid import SeparableGridSensor
from .linear import LinearGaussian
from .pixels import ThresholdedPixels
from .points import PoissonClutterPoints
from .radar import RangeDopplerBearingTBD
from .swerling import AzimuthRangeSwerlingTBD

__all__ = [
    "LinearGaussian",
    "SeparableGridSensor",
    "RangeDopplerBearingTBD",
    "AzimuthRangeSwerlingTBD",
    "AssociationSensor",
    "AssociationPosition",
    "AssociationBearingRange",
    "PoissonClutterPoints",
    "PointFrame",
    "ThresholdedPixels",
]
