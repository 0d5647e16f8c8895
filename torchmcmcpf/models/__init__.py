"""Models by role: motion (transition densities), existence (births and deaths) and
sensors (likelihoods)."""

from .base import MotionModel, SensorModel
from ..state import ExistenceEstimate, existence_estimate
from .existence import BirthDeath
from .motion import ConstantVelocity, LinearGaussianMotion, WhiteAccelerationMotion
from .sensors import *  # noqa: F401,F403
from .sensors import __all__ as _sensors

__all__ = [
    "MotionModel",
    "SensorModel",
    "ConstantVelocity",
    "LinearGaussianMotion",
    "WhiteAccelerationMotion",
    "BirthDeath",
    "ExistenceEstimate",
    "existence_estimate",
    *_sensors,
]
