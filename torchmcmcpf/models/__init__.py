"""Models by role: motion (transition densities), existence (births and deaths) and
sensors (likelihoods).
"""

from ..state import ExistenceEstimate, existence_estimate
from .base import Motion, MotionModel, SensorModel
from .existence import BirthDeath
from .group import (
    AffineTransition,
    GroupExistence,
    GroupPrediction,
    GroupStructurePrior,
    KalmanStats,
    VirtualLeaderMotion,
    group_structures,
    pairwise_kalman_init,
    pairwise_kalman_predict,
    pairwise_kalman_sample,
    pairwise_kalman_update,
    structure_index,
)
from .motion import ConstantVelocity, LinearGaussianMotion, WhiteAccelerationMotion
from .sensors import *  # noqa: F401,F403
from .sensors import __all__ as _sensors

__all__ = [
    "Motion",
    "MotionModel",
    "SensorModel",
    "ConstantVelocity",
    "LinearGaussianMotion",
    "WhiteAccelerationMotion",
    "BirthDeath",
    "ExistenceEstimate",
    "existence_estimate",
    "VirtualLeaderMotion",
    "GroupExistence",
    "GroupStructurePrior",
    "group_structures",
    "structure_index",
    "AffineTransition",
    "KalmanStats",
    "GroupPrediction",
    "pairwise_kalman_init",
    "pairwise_kalman_predict",
    "pairwise_kalman_sample",
    "pairwise_kalman_update",
    *_sensors,
]
