"""Births and deaths: a per-slot existence Markov chain and the birth densities.

The multitarget state has ``K = N_max`` slots, each with an existence flag ``e_n``
(Septier et al., paper 001 "Existence vector"; Pang et al., paper 004 sec. 3):

- existence chain, independent per slot (paper 004 eq. 25)::

      p(e_k = 1 | e_{k-1} = 0) = P_B,   p(e_k = 0 | e_{k-1} = 1) = P_D,

  with stationary existence probability ``P_B / (P_B + P_D)`` (:meth:`BirthDeath.stationary`);
- surviving slot (``e_{k-1} = e_k = 1``): the motion model ``p(x_k | x_{k-1})``;
- newborn slot (``e_{k-1} = 0, e_k = 1``): ``p_0(x)`` of paper 004 eqs. 32-33, a position
  uniform over the surveillance area and a velocity ``N(0, s_v^2 I)``;
- inactive slot (``e_k = 0``): ``x_k = x_death`` (paper 004 eq. 36).

``x_death`` convention
----------------------
An inactive slot holds exactly ``x_death`` (default the zero vector), a point mass, so the
transition density of a slot that dies or stays dead is ``p(e_k | e_{k-1})`` alone. Sensors
never read an inactive slot (``exists`` masks it), and estimates condition on existence
(:func:`torchmcmcpf.state.existence_estimate`), so the value only has to be finite.

Birth proposals
---------------
Uniform births almost never land on a target in a 5000 x 5000 m area, so births can be
drawn near the measurements instead: the point-measurement analogue of paper 004
eqs. 64-65,

    q_0(pos) = P_I U(pos; area) + (1 - P_I) (1 / M) sum_m N(pos; z_m, s_b^2 I)     (M > 0)
    q_0(pos) = U(pos; area)                                                        (M = 0)

over the ``M`` valid points of the current frame (the velocity keeps its prior). A filter
that draws births from ``q_0`` multiplies by ``p_0 / q_0`` (:meth:`BirthDeath.propose`
returns its log per slot); that ratio is ``-inf`` for a proposal outside the area.

Filters propagate ``(x, exists)`` jointly with one call, :meth:`BirthDeath.propose`.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import nn

from .._native.select import packed_places, unpacked, where
from .._validation import check_positive
from ..resampling import uniform_pick
from ..runtime import take_along
from ..typing import VX, VY, Measurement, PointMeasurement, Tensor, X, Y, split_points
from .base import MotionModel, SensorModel
from .multitarget import Recapture, RelocationNoise, draw_relocation, relocate
from .sensors.points import AreaLike, as_area, log_near_points

__all__ = ["BirthDeath", "BirthNoise", "TargetDynamics"]


class BirthNoise(NamedTuple):
    """Pre-drawn existence noise for every slot: ``u (*S, K)`` uniforms for
    ``e'_n ~ p(. | e_n)``, newborn candidates ``x (*S, K, D)`` from the birth proposal
    ``q_0`` and their ``log_ratio = log p_0 - log q_0 (*S, K)``, both drawn where a slot can
    be born (``x_death`` and 0 elsewhere: :meth:`draw`).
    """

    u: Tensor
    x: Tensor
    log_ratio: Tensor

    @classmethod
    def draw(cls, x: Tensor, existence: BirthDeath, z: PointMeasurement | None, *,
             generator: torch.Generator, exists: Tensor | None = None) -> BirthNoise:
        """Draw for slots shaped like ``x (B, *S, K, D)`` (dtype and device of ``x``); births
        near the points of ``z`` when ``existence`` draws them so.

        A candidate is drawn, and its ratio (a sum over the frame's points) taken, only where
        a move can read it (:meth:`BirthDeath.propagate`): where the uniform lets a slot be
        born (:meth:`BirthDeath.may_be_born`), narrowed by ``exists (B, *S, K)``, the flags of
        the slots' ancestors when the draw knows them, to :meth:`BirthDeath.can_be_born`.
        """
        shape = x.shape[:-1]
        u = torch.rand(shape, generator=generator, device=x.device, dtype=x.dtype)
        only = existence.may_be_born(u) if exists is None else existence.can_be_born(u, exists)
        born, log_ratio = existence._draw_births(shape, z, generator=generator, dtype=x.dtype, device=x.device,
                                                 only=only)
        return cls(u, born, log_ratio)


def _probability(value: float, name: str) -> float:
    v = float(value)
    if not 0.0 <= v <= 1.0:
        raise ValueError(f"{name} must be a probability in [0, 1], got {value!r}")
    return v


class BirthDeath(nn.Module):
    """Existence Markov chain with births and deaths per target slot (module docstring).

    Parameters
    ----------
    p_birth : ``P_B``, probability that an inactive slot becomes active at the next step.
    p_death : ``P_D``, probability that an active slot becomes inactive.
    area : ``((x_lo, x_hi), (y_lo, y_hi))`` [m], where targets are born.
    velocity_std : ``s_v`` [m/s], standard deviation of a newborn's velocity components
        (paper 004 eq. 32).
    dim : per-target state size D (layout ``[x, vx, y, vy, ...]``; births set the first
        four components and copy the others from ``x_death``).
    x_death : (D,) state of an inactive slot (default zeros).
    birth_std : ``s_b`` [m]: draw births near the measurements (eq. 64 analogue) with this
        spread; ``None`` (default) draws births from the prior ``p_0``.
    p_uniform : ``P_I``, weight of the uniform component of the measurement-driven
        proposal (paper 004 uses 1e-2).
    birth_proposal, death_proposal : the probabilities with which the filters' proposals
        turn an inactive slot on and an active one off, ``q(e_k = 1 | e_{k-1} = 0)`` and
        ``q(e_k = 0 | e_{k-1} = 1)``; ``None`` (default) proposes from the chain itself
        (``P_B``, ``P_D``). Every proposed slot carries ``p(e_k | e_{k-1}) / q(e_k | e_{k-1})``
        in its ratio (:meth:`propagate`), so the target is unchanged. With ``P_B = 0.02`` a
        filter proposes a birth for an inactive slot once in 50 tries and a target that a
        frame shows beyond doubt is believed only after several frames (issue 27); a birth
        proposal of 0.5 lets one frame do it.

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> existence = tp.BirthDeath(0.05, 0.02, ((0, 5000), (0, 5000)), velocity_std=5.0)
    >>> motion = tp.ConstantVelocity(dt=1.0, q=1.0)
    >>> sensor = tp.PoissonClutterPoints(10.0, 4.0, ((0, 5000), (0, 5000)), noise_std=10.0)
    >>> filt = tp.SIRFilter(motion, sensor, 200, existence=existence)   # births and deaths, any filter
    >>> filt.existence is existence
    True
    """

    x_death: Tensor
    area: Tensor
    birth_std: float | None

    def __init__(
        self,
        p_birth: float,
        p_death: float,
        area: AreaLike,
        *,
        velocity_std: float,
        dim: int = 4,
        x_death: Tensor | None = None,
        birth_std: float | None = None,
        p_uniform: float = 0.01,
        birth_proposal: float | None = None,
        death_proposal: float | None = None,
    ) -> None:
        super().__init__()
        self.p_birth = _probability(p_birth, "p_birth")
        self.p_death = _probability(p_death, "p_death")
        self.velocity_std = check_positive(velocity_std, "velocity_std")
        if dim < 4:
            raise ValueError(f"dim must be >= 4 for the [x, vx, y, vy] layout, got {dim}")
        self.dim = dim
        if x_death is None:
            x_death = torch.zeros(dim)
        x_death = torch.as_tensor(x_death, dtype=torch.get_default_dtype())
        if x_death.shape != (dim,) or not bool(torch.isfinite(x_death).all()):
            raise ValueError(f"x_death must be a finite ({dim},) vector, got shape {tuple(x_death.shape)}")
        self.register_buffer("x_death", x_death)
        area_t = as_area(area)
        self.register_buffer("area", area_t.to(torch.get_default_dtype()))
        self.log_volume = float(torch.log(area_t[:, 1] - area_t[:, 0]).sum())
        self.birth_std = None if birth_std is None else check_positive(birth_std, "birth_std")
        self.p_uniform = _probability(p_uniform, "p_uniform")
        self.birth_proposal = self.p_birth if birth_proposal is None else _probability(birth_proposal, "birth_proposal")
        self.death_proposal = self.p_death if death_proposal is None else _probability(death_proposal, "death_proposal")
        for q, p, name in ((self.birth_proposal, self.p_birth, "birth_proposal"),
                           (self.death_proposal, self.p_death, "death_proposal")):
            if q != p and not 0 < q < 1:  # both outcomes must stay proposable
                raise ValueError(f"{name} must lie in (0, 1), got {q!r}")

    def with_proposal(self, proposal: tuple[float, float] | None) -> BirthDeath:
        """The same model with the existence proposal ``(birth_proposal, death_proposal)`` (the
        same parameters and buffers; ``None``: ``self``). The MCMC filters call it with their
        ``existence_proposal`` setting.
        """
        if proposal is None or (self.birth_proposal, self.death_proposal) == tuple(proposal):
            return self
        other = copy.copy(self)  # shares the parameters and buffers
        other.birth_proposal, other.death_proposal = (_probability(q, name) for q, name in
                                                      zip(proposal, ("birth_proposal", "death_proposal")))
        for q, p, name in ((other.birth_proposal, self.p_birth, "birth_proposal"),
                           (other.death_proposal, self.p_death, "death_proposal")):
            if q != p and not 0 < q < 1:
                raise ValueError(f"{name} must lie in (0, 1), got {q!r}")
        return other

    # -- the existence chain (paper 004 eq. 25) ------------------------------------------
    def stationary(self) -> float:
        """Stationary existence probability ``P_B / (P_B + P_D)`` of one slot (1/2 when
        ``P_B = P_D = 0``, where every distribution is stationary).
        """
        total = self.p_birth + self.p_death
        return 0.5 if total == 0 else self.p_birth / total

    def transition_matrix(self) -> Tensor:
        """``P[i, j] = p(e_k = j | e_{k-1} = i)``, ``(2, 2)``."""
        pb, pd = self.p_birth, self.p_death
        return torch.tensor([[1 - pb, pb], [pd, 1 - pd]], dtype=torch.float64)

    def log_prob_exists(self, exists_next: Tensor, exists: Tensor) -> Tensor:
        """``log p(e_k | e_{k-1})`` per slot, eq. 25: ``(*S, K), (*S, K) -> (*S, K)``."""
        p_on = self._p_on(exists)
        return where(exists_next, p_on, 1.0 - p_on).log()

    def _p_on(self, exists: Tensor, *, proposal: bool = False) -> Tensor:
        """``p(e_k = 1 | e_{k-1})`` per slot, float64 ``(*S, K)`` (with ``proposal``, the
        proposal's ``q(e_k = 1 | e_{k-1})``).
        """
        def f64(p: float) -> Tensor:
            return torch.tensor(p, dtype=torch.float64, device=exists.device)

        if proposal:
            return where(exists, f64(1.0 - self.death_proposal), f64(self.birth_proposal))
        return where(exists, f64(1.0 - self.p_death), f64(self.p_birth))

    def draw_exists(self, exists: Tensor, u: Tensor) -> Tensor:
        """``e_k ~ p(e_k | e_{k-1})`` (eq. 25) from uniforms ``u`` shaped like ``exists (*S, K)``:
        ``u < p(e_k = 1 | e_{k-1})`` (the law of :meth:`propagate`, shared with the group filter).
        """
        return u.to(torch.float64) < self._p_on(exists)

    # -- the birth density p_0 (paper 004 eqs. 32-33) ------------------------------------
    def uniform_position(self, u: Tensor) -> Tensor:
        """Positions uniform over the area (eq. 32) from uniforms ``u (*S, 2)`` in [0, 1)."""
        a = self.area.to(u.dtype)
        return a[:, 0] + (a[:, 1] - a[:, 0]) * u

    def _in_area(self, pos: Tensor) -> Tensor:
        a = self.area.to(pos.dtype)
        return ((pos >= a[:, 0]) & (pos <= a[:, 1])).all(-1)

    def _log_uniform(self, pos: Tensor) -> Tensor:
        return where(self._in_area(pos), -self.log_volume, -math.inf).to(pos.dtype)

    def birth_log_prob(self, x: Tensor) -> Tensor:
        """``log p_0(x)`` of a newborn, eq. 33: ``(*S, K, D) -> (*S, K)`` (the components
        beyond ``[x, vx, y, vy]`` are fixed to ``x_death`` and not scored).
        """
        pos = torch.stack([x[..., X], x[..., Y]], -1)
        vel = torch.stack([x[..., VX], x[..., VY]], -1)
        s = self.velocity_std
        log_vel = (-0.5 * (vel / s).square() - math.log(s) - 0.5 * math.log(2 * math.pi)).sum(-1)
        return self._log_uniform(pos) + log_vel

    def _newborn(self, pos: Tensor, vel_eps: Tensor) -> Tensor:
        x = self.x_death.to(pos.dtype).expand(pos.shape[:-1] + (self.dim,)).clone()
        x[..., X], x[..., Y] = pos[..., 0], pos[..., 1]
        x[..., VX], x[..., VY] = self.velocity_std * vel_eps[..., 0], self.velocity_std * vel_eps[..., 1]
        return x

    def sample_birth(self, shape: Sequence[int], *, generator: torch.Generator,
                     dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> Tensor:
        """Draw newborn states from ``p_0`` (eqs. 32-33): ``-> (*shape, D)``."""
        x, _ = self._draw_births(tuple(shape), None, generator=generator, dtype=dtype, device=device)
        return x

    def may_be_born(self, u: Tensor) -> Tensor:
        """Where the existence uniforms ``u (*S, K)`` of a :class:`BirthNoise` can turn an
        inactive slot on, under the chain or the proposal (:meth:`propagate`): ``u <
        max(P_B, birth_proposal)``, bool ``(*S, K)``. Only there is a newborn's ``log p_0 -
        log q_0`` read.
        """
        return u.to(torch.float64) < max(self.p_birth, self.birth_proposal)

    def can_be_born(self, u: Tensor, exists: Tensor) -> Tensor:
        """:meth:`may_be_born` for slots whose ancestors' flags ``exists (*S, K)`` are known:
        only an inactive slot can be born, so only there is the newborn's ratio read
        (:meth:`propagate`), bool ``(*S, K)``.
        """
        return self.may_be_born(u) & ~exists

    def _draw_births(self, shape: Sequence[int], z: PointMeasurement | None, *, generator: torch.Generator,
                     dtype: torch.dtype, device: torch.device | str | None, only: Tensor | None = None
                     ) -> tuple[Tensor, Tensor]:
        """Newborn states ``(*shape, D)`` from ``q_0`` (or ``p_0``) and ``log p_0 - log q_0``
        ``(*shape)``; ``shape = (B, *S, K)``. With ``only (*shape)`` bool, drawn and scored
        there only, ``x_death`` and 0 elsewhere (:meth:`may_be_born`: a half of the slots or
        fewer on the births/deaths scene, 2 % under the chain's own ``P_B``): the candidates of
        each run packed into one ``(B, W)`` block (:func:`~torchmcmcpf._native.select.packed_places`,
        ``W`` the most in a run; one host read), whose ratios read the run's points without
        gathering them per candidate.
        """
        if only is not None:
            b = shape[0]
            flags = only.reshape(b, -1)
            width, place = packed_places(flags)
            born = self.x_death.to(device=device, dtype=dtype).expand(flags.shape + (self.dim,))
            log_ratio = torch.zeros(flags.shape, dtype=dtype, device=device)
            if width > 0:
                block, block_ratio = self._draw_births((b, width), z, generator=generator, dtype=dtype, device=device)
                born, log_ratio = unpacked(block, place, flags, born), unpacked(block_ratio, place, flags, log_ratio)
            return born.reshape(tuple(shape) + (self.dim,)), log_ratio.reshape(tuple(shape))
        u = torch.rand(tuple(shape) + (2,), generator=generator, device=device, dtype=dtype)
        pos = self.uniform_position(u)
        vel_eps = torch.randn(tuple(shape) + (2,), generator=generator, device=device, dtype=dtype)
        if z is None or self.birth_std is None:
            return self._newborn(pos, vel_eps), torch.zeros(shape, dtype=dtype, device=device)
        pts, mask = split_points(z)
        b, m = pts.shape[:2]
        if m == 0:
            return self._newborn(pos, vel_eps), torch.zeros(shape, dtype=dtype, device=device)
        if mask is None:
            mask = torch.ones((b, m), dtype=torch.bool, device=device)
        pts = pts.to(dtype)
        n_valid = mask.sum(-1)  # (B,)
        lead = (b,) + (1,) * (len(shape) - 1)
        # a valid point picked uniformly (resampling.uniform_pick)
        u_pick = torch.rand(tuple(shape) + (2,), generator=generator, device=device, dtype=dtype)
        idx = uniform_pick(mask, u_pick[..., 0].reshape(b, -1)).reshape(shape)  # none valid: unused
        centre = take_along(pts, idx.reshape(b, -1, 1), dim=1).reshape(tuple(shape) + (2,))
        near = centre + self.birth_std * torch.randn(tuple(shape) + (2,), generator=generator,
                                                     device=device, dtype=dtype)
        use_near = (u_pick[..., 1] >= self.p_uniform) & (n_valid.reshape(lead) > 0)
        pos = where(use_near.unsqueeze(-1), near, pos)
        return self._newborn(pos, vel_eps), self._log_birth_ratio(pos, pts, mask, self.birth_std)

    def _log_birth_ratio(self, pos: Tensor, pts: Tensor, mask: Tensor, s: float) -> Tensor:
        """``log U(pos) - log q_0(pos)`` for positions ``(B, *S, K, 2)`` (eq. 64 analogue),
        ``s`` the birth standard deviation (:func:`~torchmcmcpf.models.sensors.points.log_near_points`).
        """
        W = torch.eye(2, dtype=torch.float64, device=pos.device) / s
        log_q = log_near_points(pos, pts, mask, W=W, p_uniform=self.p_uniform, area=self.area, diagonal=True)
        return self._log_uniform(pos) - log_q

    # -- the joint transition of (x, e) ---------------------------------------------------
    def log_prob(self, x_next: Tensor, exists_next: Tensor, x: Tensor, exists: Tensor, *,
                 motion: MotionModel) -> Tensor:
        """``log p(x_k, e_k | x_{k-1}, e_{k-1})`` per slot (paper 004 eqs. 24-25, 33, 36):
        ``log p(e_k | e_{k-1})`` plus ``log p(x_k | x_{k-1})`` for a survivor, ``log p_0(x_k)``
        for a newborn and nothing for an inactive slot (the point mass at ``x_death``).

        Parameters
        ----------
        x_next, x : (*S, K, D); exists_next, exists : (*S, K) bool; motion : MotionModel.

        Returns
        -------
        (*S, K).
        """
        log_e = self.log_prob_exists(exists_next, exists).to(x.dtype)
        survive = exists & exists_next
        born = ~exists & exists_next
        log_x = where(survive, motion.log_prob(x_next, x), torch.zeros_like(log_e))
        log_x = where(born, self.birth_log_prob(x_next), log_x)
        return log_e + log_x

    def propagate(self, x: Tensor, exists: Tensor, eps: Tensor, birth: BirthNoise, *, motion: MotionModel,
                  from_prior: bool = False) -> tuple[Tensor, Tensor, Tensor]:
        """The birth/death law from pre-drawn noise (the one implementation every filter and
        move uses): ``e_k ~ p(e_k | e_{k-1})`` (eq. 25) by ``birth.u < p(e_k = 1 | e_{k-1})``,
        survivors moved by ``motion.propagate``, newborns from ``birth.x`` (the birth proposal),
        inactive slots set to ``x_death``. Pure (``torch.compile`` friendly).

        Parameters
        ----------
        x : (*S, K, D); exists : (*S, K) bool; eps : (*S, K, noise_dim) motion noise;
        birth : :class:`BirthNoise` with leading ``(*S, K)``; motion : MotionModel.
        from_prior : draw the flags from the chain itself even when the proposal differs (an
            MCMC filter's starting points: close to the posterior where births are rare),
            the ratio still taken against the proposal, as the moves that follow need it.

        Returns
        -------
        x_next : (*S, K, D); exists_next : (*S, K) bool;
        log_ratio : (*S, K) ``log p_0(x) - log q_0(x)`` of each newborn slot, 0 elsewhere,
        plus ``log p(e_k | e_{k-1}) - log q(e_k | e_{k-1})`` when the flags are drawn from
        ``birth_proposal`` / ``death_proposal`` rather than the chain.
        """
        q_on = self._p_on(exists, proposal=True)
        exists_next = birth.u.to(torch.float64) < (self._p_on(exists) if from_prior else q_on)
        born = exists_next & ~exists
        x_next = where(born.unsqueeze(-1), birth.x, motion.propagate(x, eps))
        x_next = where(exists_next.unsqueeze(-1), x_next, self.x_death.to(x.dtype))
        log_ratio = where(born, birth.log_ratio, torch.zeros_like(birth.log_ratio))
        if self.birth_proposal != self.p_birth or self.death_proposal != self.p_death:
            p_on = self._p_on(exists)
            log_p = where(exists_next, p_on, 1.0 - p_on).log()
            log_q = where(exists_next, q_on, 1.0 - q_on).log()
            log_ratio = log_ratio + (log_p - log_q).to(log_ratio.dtype)
        return x_next, exists_next, log_ratio

    def propose(self, x: Tensor, exists: Tensor, *, motion: MotionModel, generator: torch.Generator,
                z: PointMeasurement | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Draw the noise and propagate every slot (:meth:`propagate`): newborns from the
        birth proposal (``q_0`` near the points of ``z`` when ``birth_std`` is set and ``z``
        given, else ``p_0``).

        Parameters
        ----------
        x : (B, *S, K, D); exists : (B, *S, K) bool; motion : MotionModel.
        generator : source of randomness.
        z : the current frame ``PointFrame(z (B, M, 2), mask (B, M))``, optional.

        Returns
        -------
        As :meth:`propagate`.
        """
        eps, birth = self.draw_noise(x, motion, z, generator=generator)
        return self.propagate(x, exists, eps, birth, motion=motion)

    def draw_noise(self, x: Tensor, motion: MotionModel, z: PointMeasurement | None = None, *,
                   generator: torch.Generator, every_slot: bool = False) -> tuple[Tensor, BirthNoise]:
        """The noise of one :meth:`propagate` of ``x (B, *S, K, D)``: motion noise
        ``(B, *S, K, noise_dim)`` and :class:`BirthNoise` (existence uniforms, then motion
        noise, then birth candidates: the order every filter draws in). The candidates are
        drawn where a slot may be born (:meth:`may_be_born`), or for ``every_slot``
        (:meth:`sample`'s simulated scenes, whose draws then do not depend on which slots the
        filters read).
        """
        shape = x.shape[:-1]
        u = torch.rand(shape, generator=generator, device=x.device, dtype=x.dtype)
        eps = torch.randn(shape + (motion.noise_dim,), generator=generator, device=x.device, dtype=x.dtype)
        born, log_ratio = self._draw_births(shape, z, generator=generator, dtype=x.dtype, device=x.device,
                                            only=None if every_slot else self.may_be_born(u))
        return eps, BirthNoise(u, born, log_ratio)

    def sample(self, x: Tensor, exists: Tensor, *, motion: MotionModel, generator: torch.Generator
               ) -> tuple[Tensor, Tensor]:
        """Draw ``(x_k, e_k) ~ p(. | x_{k-1}, e_{k-1})`` from the prior (births from ``p_0``):
        ``(B, *S, K, D), (B, *S, K) -> (B, *S, K, D), (B, *S, K)``. A scene's simulator: a
        newborn candidate for every slot (:meth:`draw_noise` ``every_slot``), so a seed's scene
        stays the one it has always been.
        """
        eps, birth = self.draw_noise(x, motion, generator=generator, every_slot=True)
        x_next, exists_next, _ = self.propagate(x, exists, eps, birth, motion=motion)
        return x_next, exists_next

    def extra_repr(self) -> str:
        """The model parameters, shown inside ``repr(module)``."""
        return (f"p_birth={self.p_birth}, p_death={self.p_death}, velocity_std={self.velocity_std}, "
                f"birth_std={self.birth_std}, p_uniform={self.p_uniform}, birth_proposal={self.birth_proposal}, "
                f"death_proposal={self.death_proposal}")


class TargetDynamics(NamedTuple):
    """The joint model of ``(x, exists)`` of every slot: the motion composed with a
    birth/death model (or the motion alone: ``existence=None``, a known number of targets,
    flags passed through) and, with ``recapture``, the relocation component of the slot
    prior (:mod:`torchmcmcpf.models.multitarget`). Step functions draw and propagate through
    it, one code path whatever the number of targets.

    Attributes
    ----------
    motion : MotionModel; existence : BirthDeath or None.
    recapture : :class:`~torchmcmcpf.models.multitarget.Recapture` or None.
    sensor : the SensorModel whose data-driven proposal and ``place`` the relocation uses
        (needed with ``recapture``).
    """

    motion: MotionModel
    existence: BirthDeath | None = None
    recapture: Recapture | None = None
    sensor: SensorModel | None = None

    def draw_noise(self, x: Tensor, z: Measurement | None = None, *, generator: torch.Generator,
                   found: object = None) -> tuple[Tensor, BirthNoise | None, RelocationNoise | None]:
        """Noise of one :meth:`propagate` of ``x (B, *S, K, D)``: motion noise, with births
        and deaths :class:`BirthNoise` (births near the points of ``z`` when the model draws
        them so) and, with ``recapture``, :class:`RelocationNoise` drawn from the frame ``z``
        (``found``: its detections made once per step, :meth:`draw_relocations`).
        """
        if self.existence is None:
            eps = torch.randn(x.shape[:-1] + (self.motion.noise_dim,), generator=generator, device=x.device,
                              dtype=x.dtype)
            birth = None
        else:
            eps, birth = self.existence.draw_noise(x, self.motion, z, generator=generator)
        return eps, birth, self.draw_relocations(tuple(x.shape[:-1]), z, generator=generator, dtype=x.dtype,
                                                 device=x.device, found=found)

    def draw_births(self, x: Tensor, z: Measurement | None = None, *, generator: torch.Generator,
                    exists: Tensor | None = None) -> BirthNoise | None:
        """:class:`BirthNoise` for slots shaped like ``x (B, *S, K, D)`` (births near the points
        of ``z`` when the model draws them so; ``exists``, the ancestors' flags: where the
        candidates are drawn, :meth:`BirthNoise.draw`); ``None`` without an existence model.
        """
        return None if self.existence is None else BirthNoise.draw(x, self.existence, z, generator=generator,
                                                                   exists=exists)

    def draw_relocations(self, shape: tuple[int, ...], z: Measurement | None = None, *, generator: torch.Generator,
                         dtype: torch.dtype, device: torch.device | str, p_propose: float | None = None,
                         found: object = None, packed: bool = False) -> RelocationNoise | None:
        """:class:`~torchmcmcpf.models.multitarget.RelocationNoise` for slots of leading
        ``shape (B, *S, K)``, drawn from the frame ``z`` for proposals with ``epsilon <=
        p_propose`` (default ``recapture.p_propose``); ``None`` without re-capture. ``found``:
        the frame's :meth:`~torchmcmcpf.models.base.SensorModel.frame_detections`, made once per
        step and handed to every draw (None: each draw finds them); ``packed``: the coordinates
        drawn where read only (:meth:`~torchmcmcpf.models.multitarget.RelocationNoise.draw`).
        """
        return draw_relocation(self.recapture, self.sensor, shape, z, generator=generator, dtype=dtype, device=device,
                               p_propose=p_propose, found=found, packed=packed)

    def propagate(self, x: Tensor, exists: Tensor | None, eps: Tensor, birth: BirthNoise | None,
                  relocation: RelocationNoise | None = None) -> tuple[Tensor, Tensor | None, Tensor]:
        """``(x, exists) -> (x', exists', log_ratio (B, *S, K))`` from pre-drawn noise (pure):
        :meth:`BirthDeath.propagate` (or the motion with the flags unchanged), then, with
        ``recapture`` and ``relocation``, :func:`~torchmcmcpf.models.multitarget.relocate`
        of the surviving slots. ``log_ratio`` is ``log r_n`` per slot: target over proposal
        density of the slot's component (``p_0 / q_0`` for a newborn, the relocation ratios of
        :mod:`~torchmcmcpf.models.multitarget`; 0 without births and re-capture).
        """
        x, exists, log_ratio, _ = self.propagate_labelled(x, exists, eps, birth, relocation)
        return x, exists, log_ratio

    def propagate_labelled(self, x: Tensor, exists: Tensor | None, eps: Tensor, birth: BirthNoise | None,
                           relocation: RelocationNoise | None = None, p_propose: float | None = None, *,
                           start: bool = False) -> tuple[Tensor, Tensor | None, Tensor, Tensor | None]:
        """:meth:`propagate`, with the relocation's proposal probability ``p_propose``
        (default ``recapture.p_propose``) and each slot's component ``kind (B, *S, K)`` int8
        (:func:`~torchmcmcpf.models.multitarget.relocate`; None without re-capture). With
        ``start`` the existence flags are drawn from the chain (an MCMC filter's starting
        points, :meth:`BirthDeath.propagate` ``from_prior``).
        """
        if self.existence is None:
            x_next, exists_next, log_ratio = self.motion.propagate(x, eps), exists, torch.zeros_like(x[..., 0])
            survive = None if exists is None else exists
        else:
            if exists is None:
                exists = torch.zeros(x.shape[:-1], dtype=torch.bool, device=x.device)
            if birth is None:
                raise ValueError("birth is None; a model with births and deaths needs the BirthNoise of draw_noise")
            x_next, exists_next, log_ratio = self.existence.propagate(x, exists, eps, birth, motion=self.motion,
                                                                      from_prior=start)
            survive = exists & exists_next
        if self.recapture is None or relocation is None:
            return x_next, exists_next, log_ratio, None
        if self.sensor is None:
            raise ValueError("recapture needs the sensor (TargetDynamics(..., sensor=...))")
        x_next, log_r, kind = relocate(x_next, survive, relocation, self.recapture, self.sensor, p_propose)
        return x_next, exists_next, log_ratio + log_r, kind
