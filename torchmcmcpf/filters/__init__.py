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

Bind once, step many (:mod:`torchmcmcpf.filters._bound`): each algorithm also has
``bind_<algo>(motion, sensor, settings, existence, *, num_particles, compile) -> Bound`` and
``<algo>_bound_step(state, z, bound, *, generator)``, the step with nothing left to resolve;
``xxx_step`` is the two in a row, and a ``Filter`` binds once, at construction.

Typed carries (:mod:`torchmcmcpf.filters._carry`): what a state carries besides the weighted
cloud is one ``NamedTuple`` per concern under one key of ``ParticleState.extras``, checked by
its type: :class:`CarriedEstimate` (``"estimate"``, ``forward``'s reference for relabelling),
:class:`PMMHState` (``"pmmh"``), :class:`~torchmcmcpf.filters.group.GroupState` (``"group"``).
"""

from ._bound import Bound
from .base import CarriedEstimate, Filter
from .group import GroupMCMCFilter, GroupMCMCSettings, bind_group, group_mcmc_bound_step, group_mcmc_step
from .ipmcmc import IPMCMCFilter, IPMCMCSettings, bind_ipmcmc, ipmcmc_bound_step, ipmcmc_step
from .mcmc import MCMCFilter, MCMCSettings, bind_mcmc, mcmc_bound_step, mcmc_step
from .partitioned import (
    PartitionedSIRFilter,
    PartitionedSIRSettings,
    bind_partitioned_sir,
    partitioned_sir_bound_step,
    partitioned_sir_step,
)
from .pmmh import (
    PMMHFilter,
    PMMHResult,
    PMMHSettings,
    PMMHState,
    ProcessNoiseScale,
    bind_pmmh,
    pmmh,
    pmmh_bound_step,
    pmmh_step,
    sir_log_evidence,
)
from .resample_move import (
    ResampleMoveFilter,
    ResampleMoveSettings,
    bind_resample_move,
    resample_move_bound_step,
    resample_move_step,
)
from .sir import SIRFilter, SIRSettings, bind_sir, sir_bound_step, sir_step

# one line per algorithm (module docstring order): its Filter, its settings, its step function,
# its bind function and its step on the bound object
__all__ = [
    "Filter", "Bound", "CarriedEstimate",
    "SIRFilter", "SIRSettings", "sir_step", "bind_sir", "sir_bound_step",
    "MCMCFilter", "MCMCSettings", "mcmc_step", "bind_mcmc", "mcmc_bound_step",
    "IPMCMCFilter", "IPMCMCSettings", "ipmcmc_step", "bind_ipmcmc", "ipmcmc_bound_step",
    "GroupMCMCFilter", "GroupMCMCSettings", "group_mcmc_step", "bind_group", "group_mcmc_bound_step",
    "PartitionedSIRFilter", "PartitionedSIRSettings", "partitioned_sir_step", "bind_partitioned_sir",
    "partitioned_sir_bound_step",
    "PMMHFilter", "PMMHSettings", "PMMHState", "pmmh_step", "bind_pmmh", "pmmh_bound_step", "PMMHResult",
    "ProcessNoiseScale", "pmmh", "sir_log_evidence",
    "ResampleMoveFilter", "ResampleMoveSettings", "resample_move_step", "bind_resample_move",
    "resample_move_bound_step",
]
