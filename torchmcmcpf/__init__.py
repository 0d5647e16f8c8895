"""torchmcmcpf: MCMC-based particle filters for multi-target track-before-detect.

Particles, chains and targets are tensor dimensions (see :mod:`torchmcmcpf.typing`);
each algorithm is a pure step function wrapped by a thin ``nn.Module`` Filter.
"""

from . import diagnostics, interop, kernels, metrics, models, plotting, resampling, runtime, scenarios
from ._version import __version__ as __version__
from .filters import (
    Filter,
    GroupMCMCFilter,
    IPMCMCFilter,
    MCMCFilter,
    PartitionedSIRFilter,
    PMMHFilter,
    ResampleMoveFilter,
    SIRFilter,
    group_mcmc_step,
    ipmcmc_step,
    mcmc_step,
    partitioned_sir_step,
    pmmh,
    pmmh_step,
    resample_move_step,
    sir_step,
)
from .models import (
    AzimuthRangeSwerlingTBD,
    BirthDeath,
    ConstantVelocity,
    LinearGaussian,
    PoissonClutterPoints,
    RangeDopplerBearingTBD,
)
from .state import FilterResult, ParticleState, StepInfo

__all__ = [
    "Filter",
    "SIRFilter",
    "sir_step",
    "MCMCFilter",
    "mcmc_step",
    "IPMCMCFilter",
    "ipmcmc_step",
    "pmmh",
    "PMMHFilter",
    "pmmh_step",
    "PartitionedSIRFilter",
    "partitioned_sir_step",
    "ResampleMoveFilter",
    "resample_move_step",
    "GroupMCMCFilter",
    "group_mcmc_step",
    "ConstantVelocity",
    "LinearGaussian",
    "RangeDopplerBearingTBD",
    "AzimuthRangeSwerlingTBD",
    "PoissonClutterPoints",
    "BirthDeath",
    "ParticleState",
    "StepInfo",
    "FilterResult",
    "diagnostics",
    "interop",
    "kernels",
    "metrics",
    "models",
    "plotting",
    "resampling",
    "runtime",
    "scenarios",
]
