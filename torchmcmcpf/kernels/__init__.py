"""Pure, batched Markov kernels, one move per kind: Metropolis-Hastings accept/reject
(:mod:`.mh`); the moves of the sequential MCMC particle filter, by concern: chain states and
noise (:mod:`.chains`), joint draw and per-target refinement (:mod:`.moves`), random walk
(:mod:`.random_walk`); the IP-MCMC exchange move and its iteration (:mod:`.exchange`), a segment of its iterations
in C calls (:mod:`.exchange_segment`);
Hamiltonian Monte Carlo (:mod:`.hmc`) and the HMC refinement move of the MCMC filters
(:mod:`.hmc_refine`); the triggered conditional-SMC move on a pair of slots' recent paths
(:mod:`.pair_path`).

Every move takes its noise pre-drawn (or an explicit ``generator``) and decides with
``torch.where``, so chains, targets and runs are tensor dimensions. (Vocabulary: a *move* is
one MH transition of every chain, an *iteration* one MCMC iteration of the chains, a
*program* what :mod:`torchmcmcpf.runtime` compiles.)
"""

from .chains import ChainState, JointNoise, PreviousCloud, RefineNoise, evaluate, evaluate_cached, previous_cloud
from .exchange import (
    ExchangeChains,
    ExchangeNoise,
    ExchangeProposal,
    draw_exchange_noise,
    exchange_iteration,
    propose_slots,
    with_accepted_amplitudes,
)
from .hmc import HMCInfo, hmc, hmc_transition, leapfrog, value_and_grad
from .hmc_refine import HMCRefine, HMCRefineNoise, hmc_refine
from .mh import mh_accept, mh_select
from .moves import MOVES, init_chains, joint_move, propose_joint, refine_move, refine_slot
from .pair_path import PairPath, PairPathWindow, conditional_smc, pair_path_update
from .random_walk import RandomWalkNoise, log_transition, propose_random_walk, random_walk_move

__all__ = [
    "mh_accept",
    "mh_select",
    "PairPath",
    "conditional_smc",
    "pair_path_update",
    "PairPathWindow",
    "MOVES",
    "ChainState",
    "PreviousCloud",
    "JointNoise",
    "RefineNoise",
    "RandomWalkNoise",
    "previous_cloud",
    "evaluate",
    "evaluate_cached",
    "init_chains",
    "propose_joint",
    "joint_move",
    "refine_move",
    "refine_slot",
    "log_transition",
    "propose_random_walk",
    "random_walk_move",
    "ExchangeChains",
    "ExchangeNoise",
    "ExchangeProposal",
    "with_accepted_amplitudes",
    "draw_exchange_noise",
    "propose_slots",
    "exchange_iteration",
    "HMCInfo",
    "hmc",
    "hmc_transition",
    "leapfrog",
    "value_and_grad",
    "HMCRefine",
    "HMCRefineNoise",
    "hmc_refine",
]
