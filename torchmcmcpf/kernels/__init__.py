"""Pure, batched MCMC kernels: Metropolis-Hastings accept/reject (:mod:`.mh`), the moves of
the sequential MCMC particle filter (:mod:`.moves`) and Hamiltonian Monte Carlo (:mod:`.hmc`).

Every kernel takes its noise pre-drawn (or an explicit ``generator``) and decides with
``torch.where``, so chains, targets and runs are tensor dimensions.
"""

from .hmc import HMCInfo, hmc, leapfrog, value_and_grad
from .mh import mh_accept, mh_select
from .moves import (
    MOVES,
    ChainState,
    JointNoise,
    PreviousCloud,
    RandomWalkNoise,
    RefineNoise,
    evaluate,
    init_chains,
    joint_move,
    log_transition,
    previous_cloud,
    propose_joint,
    propose_random_walk,
    propose_refine,
    random_walk_move,
    refine_move,
)

__all__ = [
    "mh_accept",
    "mh_select",
    "MOVES",
    "ChainState",
    "PreviousCloud",
    "JointNoise",
    "RefineNoise",
    "RandomWalkNoise",
    "previous_cloud",
    "evaluate",
    "init_chains",
    "propose_joint",
    "joint_move",
    "propose_refine",
    "refine_move",
    "log_transition",
    "propose_random_walk",
    "random_walk_move",
    "HMCInfo",
    "hmc",
    "leapfrog",
    "value_and_grad",
]
