"""One module per algorithm: a Filter subclass and its pure step function.

- :class:`SIRFilter` / :func:`sir_step`: multitarget SIR TBD (Boers and Driessen 2004).
- :class:`MCMCFilter` / :func:`mcmc_step`: sequential MCMC-based PF (Khan et al.; Septier
  et al. 2009; Ling).
- :class:`IPMCMCFilter` / :func:`ipmcmc_step`: interacting population-based MCMC-PF
  (Bocquel et al. 2012).
- :class:`GroupMCMCFilter` / :func:`group_mcmc_step`: marginalised MCMC-based PF for
  coordinated groups (Septier, Pang, Godsill and Carmi 2009).
- :class:`PartitionedSIRFilter` / :func:`partitioned_sir_step`: independent per-target
  partitions, each weighted and resampled on its own (Orton and Fitzgerald; Kreucher et al.).
- :class:`PMMHFilter` / :func:`pmmh_step`: sequential PMMH (particle independent MH over
  prior draws of a static parameter, their SIR filters side by side); :func:`pmmh`: the
  offline random-walk PMMH driven by the SIR log-evidence.
- :class:`ResampleMoveFilter` / :func:`resample_move_step`: SIR + HMC move over the
  Brownian increments (Maroulas and Stinis 2010).
"""

from .base import Filter
from .group import GroupMCMCFilter, GroupMCMCSettings, group_mcmc_step
from .ipmcmc import IPMCMCFilter, IPMCMCSettings, ipmcmc_step
from .mcmc import MCMCFilter, MCMCSettings, mcmc_step
from .partitioned import (
    PartitionedSIRFilter,
    PartitionedSIRSettings,
    partitioned_sir_step,
)
from .pmmh import (
    PMMHFilter,
    PMMHResult,
    PMMHSettings,
    ProcessNoiseScale,
    pmmh,
    pmmh_step,
    sir_log_evidence,
)
from .resample_move import ResampleMoveFilter, ResampleMoveSettings, resample_move_step
from .sir import SIRFilter, SIRSettings, sir_step

# one line per algorithm (module docstring order): its Filter, its settings, its step function
__all__ = [
    "Filter",
    "SIRFilter", "SIRSettings", "sir_step",
    "MCMCFilter", "MCMCSettings", "mcmc_step",
    "IPMCMCFilter", "IPMCMCSettings", "ipmcmc_step",
    "GroupMCMCFilter", "GroupMCMCSettings", "group_mcmc_step",
    "PartitionedSIRFilter", "PartitionedSIRSettings", "partitioned_sir_step",
    "PMMHFilter", "PMMHSettings", "pmmh_step", "PMMHResult", "ProcessNoiseScale", "pmmh", "sir_log_evidence",
    "ResampleMoveFilter", "ResampleMoveSettings", "resample_move_step",
]
