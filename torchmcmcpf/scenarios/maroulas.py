"""The multi-target scenario of Maroulas and Stinis (2010, paper 003, sec. 2), batched over runs.

- Motion (eqs. 11-13): ``x_t = A x_{t-1} + B v_t``, ``v ~ N(0, diag(s_x^2, s_y^2))``,
  ``T = 1``, ``s_x^2 = s_y^2 = 1``: :class:`WhiteAccelerationMotion`.
- Targets: ``K_t = 2, 2, 1, 2, 3`` for ``t = 0..4``, then 4 up to ``t = 200``; newborn
  positions ``U[-100, 100]^2``, velocities ``U[-1, 1]^2``.
- Observations: one per target, no clutter, shuffled (unknown association); linear
  position with ``s_obs^2 = 1`` (eqs. 14, 16) or bearing-range with ``s_theta^2 = 1e-4``,
  ``s_r^2 = 1`` (eqs. 15, 17).

Design for the known, time-varying number of targets (the paper's filter knows K_t): the
state has ``K_max = 4`` slots and an ``exists (B, N, K)`` mask dictated by the scenario's
schedule ``alive (T+1, K)``. Slot 0 lives throughout; slot 1 holds the second initial
target (t = 0, 1), dies at t = 2 and is reused by the target born at t = 3; slots 2 and 3
are born at t = 4 and t = 5. A filter runs over the scenario
(:func:`torchmcmcpf.experiments.maroulas_hmc.track`; scenarios never import filters): before each
step the slots that died are switched off; after it, the newborn slots get particles
from the birth density. Birth density (paper 003 sec. 2: "the perturbed bearing and range
were transformed back to xy space to create the position of the newborn target"): per
particle, the newborn's own measurement perturbed by the measurement noise and mapped to
xy, and a velocity ``U[-1, 1]^2``. Which measurement belongs to the newborn is taken from
the simulation (the paper's filter is told about births as well); every later
association is unknown to the filter.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .._validation import check_generator, check_positive_int
from ..models.base import MotionModel
from ..models.motion import WhiteAccelerationMotion
from ..models.sensors.association import (
    AssociationBearingRange,
    AssociationPosition,
    AssociationSensor,
    PointFrame,
    shuffle,
)
from ..runtime import check_allocation
from ..typing import VX, VY, Tensor, X, Y

__all__ = [
    "WhiteAccelerationMotion",
    "MaroulasData",
    "target_counts",
    "alive_schedule",
    "paper_sensor",
    "simulate",
    "birth_particles",
    "rmse_per_target",
    "OBSERVATIONS",
    "K_MAX",
]

K_MAX = 4
OBSERVATIONS = ("linear", "bearing_range")


def target_counts(num_steps: int) -> list[int]:
    """``K_t`` for ``t = 0..num_steps``: 2, 2, 1, 2, 3, 4, 4, ... (paper 003 sec. 2)."""
    return alive_schedule(num_steps).sum(-1).tolist()


def alive_schedule(num_steps: int, device: torch.device | str | None = None) -> Tensor:
    """``(num_steps + 1, K_MAX)`` bool on ``device`` (default CPU): which slot holds a target
    at each time (module doc).
    """
    t = torch.arange(num_steps + 1, device=device).unsqueeze(-1)
    return torch.cat([t >= 0, (t <= 1) | (t >= 3), t >= 4, t >= 5], -1)


def paper_sensor(observation: str) -> AssociationSensor:
    """The sensor of paper 003: ``"linear"`` (eq. 14, s_obs = 1) or ``"bearing_range"``
    (eq. 15, s_theta = 1e-2, s_r = 1).
    """
    if observation == "linear":
        return AssociationPosition(1.0)
    if observation == "bearing_range":
        return AssociationBearingRange(1e-2, 1.0)
    raise ValueError(f"observation must be one of {OBSERVATIONS}, got {observation!r}")


class MaroulasData(NamedTuple):
    """A simulated scenario.

    Attributes
    ----------
    x : (T+1, B, K, 4) true states (meaningless where ``alive`` is False).
    alive : (T+1, B, K) bool.
    frames : ``PointFrame(z (T+1, B, K, d), mask (T+1, B, K))``, shuffled per run and time.
    z_slot : (T+1, B, K, d) the same measurements in slot order (for births and plots).
    """

    x: Tensor
    alive: Tensor
    frames: PointFrame
    z_slot: Tensor


def _uniform(shape: tuple[int, ...], low: float, high: float, *, generator: torch.Generator, dtype: torch.dtype,
             device: torch.device | str | None) -> Tensor:
    return low + (high - low) * torch.rand(shape, generator=generator, dtype=dtype, device=device)


def _new_targets(shape: tuple[int, ...], *, generator: torch.Generator, dtype: torch.dtype,
                 device: torch.device | str | None) -> Tensor:
    """Positions ``U[-100, 100]^2``, velocities ``U[-1, 1]^2``: ``(*shape, 4)``."""
    pos = _uniform(shape + (2,), -100.0, 100.0, generator=generator, dtype=dtype, device=device)
    vel = _uniform(shape + (2,), -1.0, 1.0, generator=generator, dtype=dtype, device=device)
    return torch.stack([pos[..., 0], vel[..., 0], pos[..., 1], vel[..., 1]], -1)


def simulate(
    num_runs: int,
    num_steps: int = 200,
    *,
    sensor: AssociationSensor,
    generator: torch.Generator,
    motion: MotionModel | None = None,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> MaroulasData:
    """Simulate ``num_runs`` independent realisations of the paper-003 scenario.

    Parameters
    ----------
    num_runs : B >= 1.
    num_steps : T >= 0; times ``0..T`` (the paper: T = 200).
    sensor : :func:`paper_sensor` ``("linear")`` or ``("bearing_range")``.
    generator : source of randomness.
    motion : default ``WhiteAccelerationMotion()`` (T = 1, s = 1).
    dtype, device : of the returned tensors.

    Returns
    -------
    :class:`MaroulasData`.
    """
    num_runs = check_positive_int(num_runs, "num_runs")
    num_steps = check_positive_int(num_steps, "num_steps", minimum=0)
    check_generator(generator)
    if not isinstance(sensor, AssociationSensor):
        raise ValueError(f"sensor must be an AssociationSensor, got {type(sensor).__name__}")
    motion = motion or WhiteAccelerationMotion().to(device)
    alive = alive_schedule(num_steps, device).unsqueeze(1).expand(-1, num_runs, -1)
    xs, frames, z_slot = [], [], []
    x = _new_targets((num_runs, K_MAX), generator=generator, dtype=dtype, device=device)
    for t in range(num_steps + 1):
        if t > 0:
            x = motion.sample(x, generator=generator)
            born = alive[t] & ~alive[t - 1]
            fresh = _new_targets((num_runs, K_MAX), generator=generator, dtype=dtype, device=device)
            x = torch.where(born.unsqueeze(-1), fresh, x)
        zs = sensor.measure_noisy(x, generator=generator)
        frames.append(shuffle(zs, alive[t], generator=generator))
        xs.append(x)
        z_slot.append(zs)
    return MaroulasData(
        x=torch.stack(xs),
        alive=alive,
        frames=PointFrame(torch.stack([f.z for f in frames]), torch.stack([f.mask for f in frames])),
        z_slot=torch.stack(z_slot),
    )


def birth_particles(sensor: AssociationSensor, z: Tensor, num_particles: int, *,
                    generator: torch.Generator) -> Tensor:
    """Birth density (module docstring): ``z (B, K, d) -> particles (B, N, K, 4)``.

    Per particle: ``z + w``, ``w ~ N(0, diag(noise_std^2))``, mapped to xy by
    ``sensor.to_position``; velocity ``U[-1, 1]^2``.
    """
    b, k, d = z.shape
    num_particles = check_positive_int(num_particles, "num_particles")
    # the noise, the positions, the velocities and the stacked cloud: about 3 (B, N, K, 4)
    check_allocation(3 * b * num_particles * k * 4 * z.element_size(),
                     f"birth_particles(num_particles={num_particles}) of {b} runs x {k} targets", z.device,
                     hint="use fewer particles or runs")
    w = torch.randn((b, num_particles, k, d), generator=generator, dtype=z.dtype, device=z.device)
    pos = sensor.to_position(z.unsqueeze(1) + w * sensor.noise_std.to(z.dtype))
    vel = _uniform((b, num_particles, k, 2), -1.0, 1.0, generator=generator, dtype=z.dtype, device=z.device)
    return torch.stack([pos[..., 0], vel[..., 0], pos[..., 1], vel[..., 1]], -1)


def rmse_per_target(mean: Tensor, x_true: Tensor, alive: Tensor) -> Tensor:
    """RMS error per target, paper 003 eq. 31, over position and velocity.

    ``RMSE(t) = sqrt(1/K_t sum_k ||x_{k,t} - E[x_{k,t} | Z_1..Z_t]||^2)``, the norm over
    ``[x, vx, y, vy]``.

    Parameters
    ----------
    mean, x_true : (T, B, K, 4); alive : (T, B, K) bool.

    Returns
    -------
    (T, B).
    """
    sq = (mean - x_true)[..., [X, VX, Y, VY]].square().sum(-1)
    a = alive.to(sq.dtype)
    return torch.sqrt((sq * a).sum(-1) / a.sum(-1).clamp(min=1))
