"""One module per algorithm: a Filter subclass and its pure step function.

- :class:`SIRFilter` / :func:`sir_step`: multitarget SIR TBD (Boers and Driessen 2004).
- :class:`MCMCFilter` / :func:`mcmc_step`: sequential MCMC-based PF (Khan et al.; Septier
  et al. 2009; Ling).
- :class:`IPMCMCFilter` / :func:`ipmcmc_step`: interacting population-based MCMC-PF
  (Bocquel et al. 2012).
- :func:`pmmh`: particle marginal Metropolis-Hastings driven by the SIR log-evidence.
- :class:`GroupMCMCFilter` / :func:`group_mcmc_step`: marginalised MCMC-based PF for
  coordinated groups (Septier, Pang, Godsill and Carmi 2009).
- :class:`ResampleMoveFilter` / :func:`resample_move_step`: SIR + HMC move over the
  Brownian increments (Maroulas and Stinis 2010).
"""

from .base import Filter
from .group import GroupMCMCFilter, GroupMCMCSettings, GroupState, group_mcmc_step
from .ipmcmc import IPMCMCFilter, IPMCMCSettings, ipmcmc_step
from .mcmc import MCMCFilter, MCMCSettings, mcmc_step
from .pmmh import PMMHResult, ProcessNoiseScale, pmmh, sir_log_evidence
from .resample_move import ResampleMoveFilter, ResampleMoveSettings, resample_move_step
from .sir import SIRFilter, SIRSettings, sir_step

__all__ = [
    "Filter",
    "SIRSettings",
    "MCMCSettings",
    "IPMCMCSettings",
    "ResampleMoveSettings",
    "SIRFilter",
    "sir_step",
    "MCMCFilter",
    "mcmc_step",
    "IPMCMCFilter",
    "ipmcmc_step",
    "pmmh",
    "PMMHResult",
    "ProcessNoiseScale",
    "sir_log_evidence",
    "ResampleMoveFilter",
    "resample_move_step",
    "GroupMCMCFilter",
    "GroupMCMCSettings",
    "GroupState",
    "group_mcmc_step",
]
