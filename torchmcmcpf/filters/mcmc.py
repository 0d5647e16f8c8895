"""Sequential MCMC-based particle filter with C parallel chains per run.

Khan, Balch and Dellaert (2005); Septier, Pang, Carmi and Godsill (paper 001; paper 004
sec. 4); Ling (paper 002 sec. 3). The importance sampling and resampling of the SIR filter
are replaced by an MCMC run whose target is the approximate filtering density

    ``p(x_k | z_{1:k}) ∝ p(z_k | x_k) sum_i w_{k-1}^i p(x_k | x_{k-1}^i)``    (paper 002 eq. 11)

sampled jointly with the ancestor index (see :mod:`torchmcmcpf.kernels.moves`). Chains are a
tensor dimension: ``num_chains = 1`` is the classic single long chain (paper 002: B + M N
iterations), ``num_chains = N`` many short chains with one sample each, and everything in
between runs the same code. Each chain keeps every ``thinning``-th state after ``burn_in``
iterations until it holds ``N / C`` samples; the new cloud has equal weights.

With a :class:`~torchmcmcpf.models.existence.BirthDeath` model (``existence=``) the number of
targets is unknown: K = N_max slots with existence flags, and the chains sample
``p(x_k, e_k, x_{k-1}, e_{k-1} | z_{1:k})`` by paper 001's adapted algorithm (joint draw of
``(x_k, e_k, x_{k-1}, e_{k-1})``, then a refinement of ``(x_{k,n}, e_{k,n})`` per slot from
the existence and motion priors; acceptance ratios in :mod:`torchmcmcpf.kernels.moves`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import torch

from .._validation import check_positive_int
from ..kernels.chains import (
    ChainState,
    JointNoise,
    PreviousCloud,
    RefineNoise,
    evaluate,
    previous_cloud,
)
from ..kernels.hmc_refine import (
    HMCRefine,
    HMCRefineNoise,
    ancestor_log_prior,
    check_hmc_motion,
    hmc_refine,
    with_exclusion,
)
from ..kernels.moves import MOVES, init_chains, joint_move, refine_move, refine_slot
from ..kernels.random_walk import RandomWalkNoise, RunningMoments, adapted_step, prior_covariance, random_walk_move
from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath, TargetDynamics
from ..models.multitarget import Exclusion, Recapture, RelocationNoise, check_exclusion, check_recapture, exclusion_on
from ..runtime import repeating
from ..state import ParticleState, StepInfo
from ..typing import Measurement, Tensor
from ._bound import Bound, Compile, bind, check_existence_proposal
from .base import Filter

__all__ = ["MCMCFilter", "MCMCSettings", "mcmc_step", "bind_mcmc", "mcmc_bound_step", "mcmc_iteration", "mcmc_program",
           "draw_iteration_noise", "pick_moves", "parse_moves", "MOVE_PRESETS"]

MoveSpec = str | Sequence[tuple[str, float]]
MoveNoise = JointNoise | RefineNoise | RandomWalkNoise
"""The noise of one iteration of one move (:func:`draw_iteration_noise`)."""

#: Named kernels: ``"mixture"`` is paper 004's (joint draw with probability xi = 0.75, else
#: a refinement sweep); ``"joint"`` the pure joint draw (an independence sampler);
#: ``"random_walk"`` paper 002's kernel.
MOVE_PRESETS: dict[str, tuple[tuple[str, float], ...]] = {
    "mixture": (("joint", 0.75), ("refine", 0.25)),
    "joint": (("joint", 1.0),),
    "random_walk": (("random_walk", 1.0),),
}


def parse_moves(moves: MoveSpec) -> tuple[tuple[str, float], ...]:
    """Normalise a kernel choice to ``((name, probability), ...)``.

    Parameters
    ----------
    moves : a preset name (``"mixture"``, ``"joint"``, ``"random_walk"``, see
        :data:`MOVE_PRESETS`), or a sequence of ``(name, probability)`` pairs over the
        primitive moves ``"joint"``, ``"refine"``, ``"random_walk"``; probabilities > 0,
        summing to 1. Each iteration, each chain picks one move with these probabilities
        (a mixture kernel, paper 004 sec. 4). ``"refine"`` never moves the ancestor, so it
        must be mixed with ``"joint"`` or ``"random_walk"``.

    Returns
    -------
    tuple of ``(name, probability)``.
    """
    if isinstance(moves, str):
        if moves not in MOVE_PRESETS:
            raise ValueError(
                f"moves must be one of {sorted(MOVE_PRESETS)} or a sequence of (name, probability) "
                f"pairs over {list(MOVES)}, got {moves!r}"
            )
        return MOVE_PRESETS[moves]
    try:
        pairs = tuple((name, float(p)) for name, p in moves)
    except (TypeError, ValueError) as err:
        raise ValueError(f"moves must be a preset name or (name, probability) pairs, got {moves!r}") from err
    names = [name for name, _ in pairs]
    if not pairs or any(name not in MOVES for name in names) or len(set(names)) != len(names):
        raise ValueError(f"moves must name distinct moves among {list(MOVES)}, got {names}")
    probs = [p for _, p in pairs]
    if any(not p > 0 for p in probs) or not math.isclose(sum(probs), 1.0, abs_tol=1e-9):
        raise ValueError(f"moves probabilities must be > 0 and sum to 1, got {probs}")
    if set(names) == {"refine"}:
        raise ValueError(
            "moves=('refine',) alone never changes a chain's ancestor x_{k-1}, so it does not target "
            "p(x_k | z_1:k); mix it with 'joint' or 'random_walk' (e.g. moves='mixture')"
        )
    return pairs


@dataclass(frozen=True)
class MCMCSettings:
    """Settings of the sequential MCMC particle filter (validated on construction).

    Attributes
    ----------
    num_chains : C >= 1 chains per run (a divisor of N; checked by the filter / step).
    burn_in : iterations discarded per chain and time step, >= 0.
    thinning : keep every ``thinning``-th state after the burn-in, >= 1.
    moves : a preset name or ``(name, probability)`` pairs (:func:`parse_moves`); stored parsed.
    pairs : the parsed ``moves``, ``((name, probability), ...)`` (set on construction).
    rw_scale : random-walk step ``s``, a float or a ``(D,)`` vector (tuple or tensor; stored as a
        tuple of floats) (``S = diag(s^2)``,
        paper 002 eq. 13); or ``"adaptive"``: a full per-target covariance ``S_k = 2.38^2 /
        (K D) * Sigma_k`` that fits the posterior (:func:`~torchmcmcpf.kernels.random_walk.adapted_step`),
        ``Sigma_k`` starting as the prior mixture's covariance of target k and, during the
        burn-in, following the chains' history (Haario et al. 2001's adaptive Metropolis,
        re-factored every tenth of the burn-in), frozen before the first kept sample (the
        kept samples come from one fixed, symmetric kernel). Needs a linear-Gaussian motion.
        Required by ``"random_walk"``.
    hmc : :class:`~torchmcmcpf.kernels.hmc_refine.HMCRefine`, optional: one HMC transition
        of every chain's ``x_k`` given its ancestor after every ``hmc.every``-th iteration
        (target ``p(z_k | x_k) p(x_k | x_{k-1}^a)``, see :mod:`..kernels.hmc_refine`).
    exclusion : :class:`~torchmcmcpf.models.multitarget.Exclusion` (default) or None: the
        exclusion factor between slots in the target (Khan et al. 2005); None is the paper's
        factorised prior.
    recapture : :class:`~torchmcmcpf.models.multitarget.Recapture` (default) or None: the
        heavy-tailed slot prior and the data-driven proposal of the joint draw and the
        refinement (:mod:`torchmcmcpf.models.multitarget`). Set to None when ``moves`` use
        ``"random_walk"`` or with ``hmc`` (their ratios use the prior without the relocation
        component).

    existence_proposal : ``(q_birth, q_death)``: with an existence model, the proposals turn
        an inactive slot on with probability ``q_birth`` and an active one off with
        ``q_death`` (:meth:`~torchmcmcpf.models.existence.BirthDeath.with_proposal`; the
        ratio ``p(e' | e) / q(e' | e)`` keeps the target). Default ``(0.5, 0.1)``: proposing
        births from the chain's ``P_B = 0.02`` left a target that four points show beyond
        doubt unbelieved for several frames (issue 27). ``None``: the chain's own
        probabilities.

    Both are turned off (set to None) for a sensor that cannot support them
    (:func:`~torchmcmcpf.filters.base.active_prior`).

    Example
    -------
    >>> from torchmcmcpf.filters.mcmc import MCMCSettings
    >>> settings = MCMCSettings(num_chains=50, burn_in=20, moves="mixture")
    >>> settings.pairs                                  # paper 004: joint draw w.p. 0.75, else a sweep
    (('joint', 0.75), ('refine', 0.25))
    >>> settings.check(5000, 4, None)                   # N = 5000, D = 4: 50 chains of 100 samples
    >>> MCMCSettings(moves="gibbs")
    Traceback (most recent call last):
    ...
    ValueError: moves must be one of ['joint', 'mixture', 'random_walk'] or a sequence of ... got 'gibbs'
    """

    num_chains: int = 1
    burn_in: int = 100
    thinning: int = 1
    moves: MoveSpec = "mixture"
    rw_scale: float | Sequence[float] | Tensor | str | None = None
    hmc: HMCRefine | None = None
    exclusion: Exclusion | None = Exclusion()
    recapture: Recapture | None = Recapture()
    existence_proposal: tuple[float, float] | None = (0.5, 0.1)
    pairs: tuple[tuple[str, float], ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "num_chains", check_positive_int(self.num_chains, "num_chains"))
        object.__setattr__(self, "burn_in", check_positive_int(self.burn_in, "burn_in", minimum=0))
        check_exclusion(self.exclusion)
        check_recapture(self.recapture)
        object.__setattr__(self, "thinning", check_positive_int(self.thinning, "thinning"))
        pairs = parse_moves(self.moves)
        object.__setattr__(self, "moves", pairs)
        object.__setattr__(self, "pairs", pairs)
        if self.hmc is not None or any(name == "random_walk" for name, _ in pairs):
            object.__setattr__(self, "recapture", None)  # their ratios use the prior without relocation
        object.__setattr__(self, "existence_proposal", check_existence_proposal(self.existence_proposal))
        if self.hmc is not None and not isinstance(self.hmc, HMCRefine):
            raise ValueError(f"hmc must be an HMCRefine or None, got {type(self.hmc).__name__}")
        if self.rw_scale is None:
            if any(name == "random_walk" for name, _ in pairs):
                raise ValueError("rw_scale must be given (a float, a (D,) tensor of steps or 'adaptive') "
                                 "for the 'random_walk' move")
            return
        if isinstance(self.rw_scale, str) and self.rw_scale == "adaptive":
            return
        if isinstance(self.rw_scale, str):
            raise ValueError(f"rw_scale must be a float, a (D,) vector or 'adaptive', got {self.rw_scale!r}")
        scale = torch.as_tensor(self.rw_scale, dtype=torch.float64)
        if scale.dim() > 1 or not bool(torch.isfinite(scale).all()) or not bool((scale > 0).all()):
            raise ValueError(f"rw_scale must be > 0 and finite, a float or a (D,) vector, got {self.rw_scale!r}")
        object.__setattr__(self, "rw_scale", float(scale) if scale.dim() == 0 else tuple(scale.tolist()))

    def check(self, num_particles: int, dim: int, existence: BirthDeath | None) -> None:
        """The checks that need the problem: ``C | N``, the size of ``rw_scale``, no random walk
        with existence.
        """
        if num_particles % self.num_chains:
            raise ValueError(
                f"num_particles ({num_particles}) must be a multiple of num_chains ({self.num_chains}): "
                "each chain keeps num_particles / num_chains samples"
            )
        if isinstance(self.rw_scale, tuple) and len(self.rw_scale) != dim:
            raise ValueError(f"rw_scale has shape ({len(self.rw_scale)},), expected () or ({dim},)")
        if existence is not None and any(name == "random_walk" for name, _ in self.pairs):
            raise ValueError(
                f"moves={[name for name, _ in self.pairs]}: 'random_walk' is not available with existence (it has "
                "no move on the existence flags); use 'joint' and 'refine' (e.g. moves='mixture')"
            )



def pick_moves(moves: tuple[tuple[str, float], ...], count: int, *, generator: torch.Generator) -> list[str]:
    """The move of each of ``count`` iterations, one pick per iteration for every chain.

    The pick is independent of the chains' states, so every chain still runs the mixture
    kernel ``sum_m p_m K_m`` (each ``K_m`` leaves the target invariant): only the one picked
    move is computed per iteration, instead of every move for every chain and a
    ``torch.where`` (half the cost of the ``"mixture"`` kernel). One draw of ``count``
    uniforms from ``generator`` (one host transfer per time step).

    Parameters
    ----------
    moves : parsed moves (:func:`parse_moves`); count : number of iterations.

    Returns
    -------
    list of ``count`` move names.
    """
    if len(moves) == 1:
        return [moves[0][0]] * count
    u = torch.rand(count, generator=generator, dtype=torch.float64, device=generator.device).cpu()
    edges = torch.tensor([p for _, p in moves[:-1]], dtype=torch.float64).cumsum(0)
    return [moves[i][0] for i in (u.unsqueeze(-1) >= edges).sum(-1).tolist()]


def draw_iteration_noise(move: str, x: Tensor, dynamics: TargetDynamics, *, generator: torch.Generator,
                         z: Measurement | None = None, relocation: RelocationNoise | None = None,
                         cloud: PreviousCloud | None = None, exists_prev: Tensor | None = None) -> MoveNoise:
    """The noise of one MCMC iteration of the move ``move``, drawn in eager code from ``generator``.

    Parameters
    ----------
    move : ``"joint"``, ``"refine"`` or ``"random_walk"`` (:func:`pick_moves`).
    x : (B, C, K, D) chain states (for shape, dtype, device).
    dynamics : the slots' joint model (:class:`~torchmcmcpf.models.existence.TargetDynamics`):
        the motion's noise size; with births and deaths, the birth noise (births may be drawn
        near the points of the frame ``z``); with re-capture, the relocation noise (from ``z``,
        or ``relocation``, leading ``(B, C, K)``, when drawn beforehand: :func:`relocations`).
    cloud, exists_prev : with births, the previous cloud (a joint draw's ancestors) and the
        chains' ancestors' flags ``(B, C, K)`` (:attr:`ChainState.exists_prev`, a refinement's):
        the newborn candidates are then drawn only where an ancestor's slot is inactive (else
        wherever the existence uniform lets a slot be born; the same kernel either way).

    Returns
    -------
    the move's noise NamedTuple (:class:`JointNoise`, :class:`RefineNoise`, :class:`RandomWalkNoise`).
    """
    if move == "random_walk":  # no existence variant (refused with existence)
        return RandomWalkNoise.draw(x, dynamics.motion, generator=generator)
    if move not in ("joint", "refine"):
        raise ValueError(f"move must be one of {list(MOVES)}, got {move!r}")
    if move == "joint":
        return JointNoise.draw(x, dynamics, generator=generator, z=z, relocation=relocation, cloud=cloud)
    return RefineNoise.draw(x, dynamics, generator=generator, z=z, relocation=relocation, exists=exists_prev)


#: At most this many slots' relocations are drawn at once by :func:`relocations` (their data
#: density is evaluated against every peak of the frame: about 2 kB per slot on the radar).
RELOCATION_BLOCK = 2**17


def relocations(dynamics: TargetDynamics, shape: tuple[int, int, int], count: int, z: Measurement | None, *,
                generator: torch.Generator, dtype: torch.dtype, device: torch.device
                ) -> Iterator[RelocationNoise | None]:
    """The relocation noise of ``count`` iterations for chains' slots ``shape = (B, C, K)``,
    one iteration's after the other, drawn in blocks of iterations (the frame's peaks found
    once per block instead of once per iteration; at most :data:`RELOCATION_BLOCK` slots a
    block), the coordinates for the slots whose uniform picks the relocation only (a tenth at
    the default ``p_propose``, packed: :meth:`RelocationNoise.draw`); ``None`` each without
    re-capture.
    """
    per = max(1, RELOCATION_BLOCK // math.prod(shape))
    b, c, k = shape
    for first in range(0, count, per):
        block = dynamics.draw_relocations((b, min(per, count - first), c, k), z, generator=generator, dtype=dtype,
                                          device=device, packed=True)
        for i in range(min(per, count - first)):  # iterations of the block, not particles
            yield None if block is None else RelocationNoise(*(t[:, i] for t in block))


def mcmc_iteration(
    chain: ChainState,
    noise: MoveNoise,
    *,
    move: str,
    cloud: PreviousCloud,
    z: Measurement,
    dynamics: TargetDynamics,
    sensor: SensorModel,
    rw_scale: Tensor | None = None,
    exclusion: Exclusion | None = None,
    programs: dict | None = None,
) -> tuple[ChainState, Tensor]:
    """One MCMC iteration of every chain by the move ``move`` (picked by :func:`pick_moves`).

    Pure: no generator, no ``.item()``; each move is ready for ``torch.compile`` (K static).

    Parameters
    ----------
    chain : ChainState ``(B, C, K, D)``.
    noise : the move's noise (:func:`draw_iteration_noise`).
    move : ``"joint"``, ``"refine"`` or ``"random_walk"``.
    cloud : the previous particles; z : frame ``(B, *G)``.
    dynamics : the slots' joint model (motion, optionally births and deaths and re-capture;
        ``noise`` drawn with it); sensor : the SensorModel.
    rw_scale : (D,) or scalar step of the random walk.
    exclusion : the exclusion term, optional.
    programs : move name -> the move compiled (``MCMCFilter(compile_step=True)``), optional.

    Returns
    -------
    chain : the new ChainState.
    accepted : (B, C) fraction of the move's accept/reject decisions that accepted (per
        target for ``refine``).
    """
    if programs is not None:
        fn = programs[move]
        new, acc = (fn(chain, noise, z) if move == "refine" else
                    fn(chain, noise, cloud, z, rw_scale) if move == "random_walk" else
                    fn(chain, noise, cloud, z))
    elif move == "joint" and isinstance(noise, JointNoise):
        new, acc = joint_move(chain, noise, cloud=cloud, z=z, dynamics=dynamics, sensor=sensor, exclusion=exclusion)
    elif move == "refine" and isinstance(noise, RefineNoise):
        new, acc = refine_move(chain, noise, z=z, dynamics=dynamics, sensor=sensor, exclusion=exclusion)
    elif move == "random_walk" and isinstance(noise, RandomWalkNoise):
        if rw_scale is None:
            raise ValueError("rw_scale must be given (a scalar or (D,) tensor) for the 'random_walk' move")
        new, acc = random_walk_move(chain, noise, cloud=cloud, z=z, motion=dynamics.motion, sensor=sensor,
                                    scale=rw_scale, exclusion=exclusion)
    else:
        raise ValueError(f"move must be one of {list(MOVES)} with its noise (draw_iteration_noise(move, ...)), "
                         f"got move={move!r} with {type(noise).__name__}")
    if move == "refine":
        acc = acc.to(chain.x.dtype).mean(-1)
    return new, acc.to(chain.x.dtype)


def bind_mcmc(motion: MotionModel, sensor: SensorModel, settings: MCMCSettings | None = None,
              existence: BirthDeath | None = None, *, num_particles: int | None = None, compile: Compile = None
              ) -> Bound:
    """The sequential MCMC filter's :class:`~torchmcmcpf.filters._bound.Bound`: the models,
    ``settings`` (default :class:`MCMCSettings`) checked against them
    (:meth:`MCMCSettings.check` with ``num_particles`` when given; ``hmc`` needs a
    linear-Gaussian motion and no existence), the existence model with the settings'
    ``existence_proposal``, and the program, one iteration of the chains
    (:func:`mcmc_program`, its moves compiled with ``compile``).
    """
    def check(bound: Bound) -> None:
        if num_particles is not None:
            bound.settings.check(num_particles, motion.dim, bound.existence)
        if bound.settings.hmc is not None:
            check_hmc_motion(motion, bound.existence)

    return bind(motion, sensor, MCMCSettings() if settings is None else settings, existence, check=check,
                program=lambda b, c: mcmc_program(b.dynamics, b.sensor, b.settings, c), compile=compile)


def mcmc_step(
    state: ParticleState,
    z: Measurement,
    *,
    motion: MotionModel,
    sensor: SensorModel,
    settings: MCMCSettings = MCMCSettings(),
    generator: torch.Generator,
    existence: BirthDeath | None = None,
) -> tuple[ParticleState, StepInfo]:
    """One time step of the sequential MCMC particle filter: :func:`mcmc_bound_step` after an
    eager :func:`bind_mcmc` (a filter binds once). Parameters and returns:
    :func:`mcmc_bound_step`, with the models ``motion``, ``sensor``, ``existence`` and
    ``settings`` (:class:`MCMCSettings`) in place of ``bound``: ``state`` with ``x (B, N, K,
    D)``, ``log_w (B, N)`` (``exists (B, N, K)`` with births and deaths) and ``z`` one frame per
    run ``(B, *G)`` give a state of the same shapes.
    """
    bound = bind_mcmc(motion, sensor, settings, existence, num_particles=state.x.shape[1])
    return mcmc_bound_step(state, z, bound, generator=generator)


def mcmc_bound_step(state: ParticleState, z: Measurement, bound: Bound, *, generator: torch.Generator
                    ) -> tuple[ParticleState, StepInfo]:
    """One time step of the sequential MCMC particle filter.

    Each of the C chains of each run starts from a previous particle drawn by weight and
    moved by the prior (paper 002, steps 1-2), runs ``burn_in + thinning * N / C``
    iterations of the kernel ``moves`` and keeps its state after iterations ``burn_in +
    thinning * j``, ``j = 1 .. N / C`` (the initial state is never kept).

    Parameters
    ----------
    state : ParticleState ``x (B, N, K, D)``, ``log_w (B, N)`` at time k-1 (weights are
        honoured: the target mixes over ``w^i p(x | x^i)``). Known number of targets
        (``existence`` None): ``state.exists`` must be ``None``.
    z : one frame per run ``(B, *G)``.
    bound : :class:`~torchmcmcpf.filters._bound.Bound` of :func:`bind_mcmc`: the models,
        :class:`MCMCSettings`, the existence model and the program, one iteration of the
        chains (:func:`mcmc_program`: :func:`mcmc_iteration` with the models and settings
        bound, called as ``program(chain, noise, move, cloud, z, rw_scale)``, its moves
        compiled by ``MCMCFilter(compile_step=True)``). With an existence model the number of
        targets is unknown (paper 001's adapted algorithm; :mod:`torchmcmcpf.kernels.moves`,
        "Existence"): ``state.exists (B, N, K)`` None means every slot starts inactive;
        births are drawn near the points of ``z`` when the model draws them so.
    generator : the only source of randomness (all draws in eager code).

    Returns
    -------
    state : ParticleState with ``x (B, N, K, D)`` ordered chain by chain (particles
        ``c * N/C .. (c+1) * N/C - 1`` are chain c's kept states in order) and equal weights;
        with existence also ``exists (B, N, K)``.
    info : ``acceptance (B,)`` over every MH decision of the step (burn-in included);
        ``ess`` and ``log_evidence`` NaN; ``extras["acceptance_<move>"] (B,)`` per move
        (per target update for ``"refine"``), NaN where no iteration of the step picked the
        move (one pick per iteration for every chain, :func:`pick_moves`).
    """
    motion, sensor, settings, existence = bound.motion, bound.sensor, bound.settings, bound.existence
    dynamics = bound.dynamics  # (x, exists) jointly: one model of the slots with or without births and re-capture
    x_prev = state.x
    b, n, k, d = x_prev.shape
    pairs, num_chains, burn_in, thinning = settings.pairs, settings.num_chains, settings.burn_in, settings.thinning
    exists = state.exists
    if existence is None and exists is not None:
        raise ValueError("state.exists must be None without an existence model: pass existence= for an "
                         "unknown number of targets")
    if existence is not None and exists is None:
        exists = torch.zeros((b, n, k), dtype=torch.bool, device=x_prev.device)
    adaptive = settings.rw_scale == "adaptive" and any(name == "random_walk" for name, _ in pairs)
    scale = None if settings.rw_scale is None or isinstance(settings.rw_scale, str) else torch.tensor(
        settings.rw_scale, device=x_prev.device, dtype=x_prev.dtype)
    iteration = bound.program
    cloud = previous_cloud(x_prev, state.log_w, exists, motion=motion, draws=b * num_chains)
    template = x_prev.new_empty((b, num_chains, k, d))
    chain = init_chains(cloud, JointNoise.draw(template, dynamics, generator=generator, z=z, cloud=cloud), z,
                        dynamics=dynamics, sensor=sensor)

    if adaptive:  # start from the prior mixture's per-target covariance (Haario et al. 2001 below)
        prior_cov = prior_covariance(cloud, motion)
        scale, moments = adapted_step(prior_cov, x_prev.dtype), RunningMoments.zeros(chain.x)
        adapt_every = max(1, burn_in // 10)
    per_chain = n // num_chains
    hmc = settings.hmc
    hmc_motion = None if hmc is None else check_hmc_motion(motion, existence)
    hmc_acc, hmc_count = x_prev.new_zeros(b), 0
    acc_sum = {name: x_prev.new_zeros(b) for name, _ in pairs}
    sel_sum = {name: x_prev.new_zeros(b) for name, _ in pairs}
    kept, kept_exists = [], []
    moves = pick_moves(pairs, burn_in + thinning * per_chain, generator=generator)
    drawn = relocations(dynamics, (b, num_chains, k), sum(move != "random_walk" for move in moves), z,
                        generator=generator, dtype=x_prev.dtype, device=x_prev.device)
    with repeating():  # compiled moves: repeats skip Dynamo's guards (runtime.repeating)
        for m, move in enumerate(moves, start=1):
            noise = draw_iteration_noise(move, chain.x, dynamics, generator=generator, z=z,
                                         relocation=None if move == "random_walk" else next(drawn), cloud=cloud,
                                         exists_prev=chain.exists_prev)
            chain, accepted = iteration(chain, noise, move, cloud, z, scale)
            acc_sum[move] = acc_sum[move] + accepted.sum(1)
            sel_sum[move] = sel_sum[move] + num_chains
            if hmc is not None and hmc_motion is not None and m % hmc.every == 0:  # eager, also under compile_step
                x_new, _, acc = hmc_refine(chain.x, chain.log_lik, HMCRefineNoise.draw(chain.x, generator=generator), z,
                                           log_prior=with_exclusion(ancestor_log_prior(chain.x_prev, hmc_motion),
                                                                    settings.exclusion, sensor),
                                           sensor=sensor, motion=hmc_motion, settings=hmc)
                log_lik, terms = evaluate(x_new, z, sensor)
                chain = chain._replace(x=x_new, log_lik=log_lik, log_lik_terms=terms, cache=None)
                hmc_acc, hmc_count = hmc_acc + acc.to(hmc_acc.dtype).mean(1), hmc_count + 1
            if adaptive and m <= burn_in:  # adapt during the burn-in only: frozen for the kept samples
                moments = moments.update(chain.x)
                if m % adapt_every == 0:
                    scale = adapted_step(moments.covariance(prior_cov, d + 1.0), x_prev.dtype)
            if m > burn_in and (m - burn_in) % thinning == 0:
                kept.append(chain.x)
                kept_exists.append(chain.exists)
    x = torch.stack(kept, dim=2).reshape(b, n, k, d)  # (B, C, N/C, K, D) -> chain-major (B, N, K, D)
    exists = None if existence is None else torch.stack(kept_exists, dim=2).reshape(b, n, k)
    log_w = x.new_full((b, n), -math.log(n))
    extras = {f"acceptance_{name}": acc_sum[name] / sel_sum[name] for name, _ in pairs}
    if hmc is not None:
        extras["acceptance_hmc"] = hmc_acc / max(hmc_count, 1)
    acceptance = sum(acc_sum.values(), x_prev.new_zeros(b)) / sum(sel_sum.values(), x_prev.new_zeros(b))
    return ParticleState(x, log_w, exists), StepInfo.make(acceptance, acceptance=acceptance, extras=extras)


def mcmc_program(dynamics: TargetDynamics, sensor: SensorModel, settings: MCMCSettings,
                 compile: Compile = None) -> Callable:
    """The MCMC filter's program: :func:`mcmc_iteration` with the models and settings (as
    the filter runs them, :func:`bind_mcmc`) bound, ``program(chain, noise, move, cloud, z,
    rw_scale)``.

    With ``compile``, each move is compiled on its own (the joint draw; the refinement whole
    when the sensor is separable and no exclusion couples the slots, else its one-slot
    update, one program for every slot; the random walk), so a program never holds K
    unrolled slot updates; the mixture's choice between them is made once per iteration in
    eager code (:func:`pick_moves`).
    """
    exclusion = settings.exclusion
    programs = None
    if compile is not None:
        names = {name for name, _ in settings.pairs}
        programs = {}
        if "joint" in names:
            programs["joint"] = compile(lambda chain, noise, cloud, z: joint_move(
                chain, noise, cloud=cloud, z=z, dynamics=dynamics, sensor=sensor, exclusion=exclusion))
        if "refine" in names:
            if sensor.separable and dynamics.existence is None and not exclusion_on(exclusion, sensor):
                programs["refine"] = compile(lambda chain, noise, z: refine_move(
                    chain, noise, z=z, dynamics=dynamics, sensor=sensor))
            else:
                slot = compile(lambda *args: refine_slot(*args, sensor=sensor, exclusion=exclusion))
                programs["refine"] = partial(_refine_with, dynamics=dynamics, sensor=sensor, exclusion=exclusion,
                                             slot_program=slot)
        if "random_walk" in names:
            programs["random_walk"] = compile(lambda chain, noise, cloud, z, scale: random_walk_move(
                chain, noise, cloud=cloud, z=z, motion=dynamics.motion, sensor=sensor, scale=scale,
                exclusion=exclusion))
    return partial(_iteration, dynamics=dynamics, sensor=sensor, exclusion=exclusion, programs=programs)


def _iteration(chain: ChainState, noise: MoveNoise, move: str, cloud: PreviousCloud, z: Measurement,
               rw_scale: Tensor | None, **bound: Any) -> tuple[ChainState, Tensor]:
    return mcmc_iteration(chain, noise, move=move, cloud=cloud, z=z, rw_scale=rw_scale, **bound)


def _refine_with(chain: ChainState, noise: RefineNoise, z: Measurement, **bound: Any) -> tuple[ChainState, Tensor]:
    return refine_move(chain, noise, z=z, **bound)


class MCMCFilter(Filter):
    """Sequential MCMC-based particle filter for a known number of targets, or for an
    unknown one with ``existence`` (K = N_max slots with existence flags, paper 001).

    Parameters
    ----------
    motion : MotionModel applied to every target slot.
    sensor : SensorModel; a ``log_likelihood_per_target`` or ``log_likelihood_delta``
        method speeds up the per-target refinement (:mod:`torchmcmcpf.kernels.moves`).
    num_particles : N >= 1, a multiple of ``num_chains``.
    settings : :class:`MCMCSettings`, optional; its fields are also keywords of the
        constructor, with the dataclass's defaults: ``num_chains`` (C chains per run, each
        keeps N / C samples), ``burn_in``, ``thinning``, ``moves`` (``"mixture"``: joint draw
        w.p. 0.75, else a per-target refinement sweep, paper 004; ``"joint"``;
        ``"random_walk"``, paper 002; or ``(name, probability)`` pairs), ``rw_scale`` (float,
        ``(D,)`` vector or ``"adaptive"``; needed by ``"random_walk"``), ``hmc`` (an HMC
        refinement of ``x_k`` given the ancestor after every ``hmc.every``-th iteration,
        eager, extras ``"acceptance_hmc"``; linear-Gaussian motion, no existence),
        ``exclusion``, ``recapture`` (the multitarget prior's terms, on by default;
        re-capture is off with ``"random_walk"`` or ``hmc``) and ``existence_proposal``.
    existence : BirthDeath, optional: births and deaths (see :func:`mcmc_step`); the
        estimate of a slot is then its mean given existence
        (:func:`torchmcmcpf.state.existence_estimate`).
    compile_step : compile each move of one MCMC iteration (the refinement as one slot
        update) with ``torch.compile(fullgraph=True)`` (:func:`mcmc_program`).

    Each time step runs ``burn_in + thinning * N / C`` iterations of every chain.

    Example
    -------
    Three chains of 20 kept samples, mixing the joint draw with a random walk:

    >>> import torch
    >>> import torchmcmcpf as tp
    >>> filt = tp.MCMCFilter(tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0), 60,
    ...                      num_chains=3, burn_in=10, moves=(("joint", 0.5), ("random_walk", 0.5)), rw_scale=0.5)
    >>> result = filt(torch.zeros(3, 1, 2, 2), init=torch.zeros(1, 60, 2, 4), generator=torch.Generator())
    >>> sorted(result.info.extras)                    # one acceptance rate per kind of move, each (T, B)
    ['acceptance_joint', 'acceptance_random_walk']
    >>> result.state.log_w.unique()                   # equal weights -log N
    tensor([-4.0943])
    """

    compile_seconds = 27.0  # benchmarks/bench_compile.py, 5-target ground radar, 2 CPU cores
    settings_class = MCMCSettings
    bind = staticmethod(bind_mcmc)
    bound_step = staticmethod(mcmc_bound_step)
