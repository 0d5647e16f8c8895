"""Targets that cross unresolved: the scene on which a factorised multitarget prior loses a
track (:mod:`torchmcmcpf.models.multitarget`).

K targets of the range-doppler-bearing radar of paper 000 (Table I cells: 10 m, 2 m/s,
1 deg; ``sigma = 1``) pass through one point at step ``crossing_step``:

- the crossing point lies at range ``range_`` and bearing 0;
- target ``k`` moves at ``speed`` with heading ``theta_0 + 2 pi k / K`` (``theta_0``
  uniform per run), so two targets pass in opposite directions and more than two form a
  star; at the crossing step target ``k`` is offset from the crossing point by
  ``(k - (K - 1) / 2) * miss_distance`` along the direction perpendicular to
  ``theta_0``, so neighbouring targets miss each other by ``miss_distance``;
- the SNR of target ``k`` is ``snr_db[k]`` (``SNR = rho^2 / (2 sigma^2)``).

At the default speed (0.5 m/s) every radial velocity lies within one doppler cell, and two
targets stay within one bearing cell (49 m at 2800 m) for about 50 steps around the
crossing: unresolved in range, doppler and bearing. The truth is noise-free constant
velocity, like the ground-radar scene (paper 000 sec. VI); the filters' motion model is the
nearly-constant-velocity model with acceleration standard deviation ``q`` (1 m/s^2 by
default, much more than the truth needs: it is the setting under which velocity cannot
carry a slot's identity through the crossing) and the amplitude random walk of
:func:`~torchmcmcpf.scenarios.ground_radar.ground_radar`.

Timing as the ground radar: ``initial`` is the true state one step before frame 0 and
``truth[t] = F^(t+1) initial``. The grid covers every track plus ``MARGIN_CELLS`` cells per
side.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from .._validation import check_generator, check_positive, check_positive_int
from ..models.motion import ConstantVelocity
from ..typing import VX, VY, X, Y
from ._common import Scenario
from ._common import cover as _cover
from .ground_radar import MARGIN_CELLS

__all__ = ["crossing"]


def crossing(
    num_targets: int = 2,
    num_steps: int = 80,
    batch_size: int = 1,
    *,
    generator: torch.Generator,
    snr_db: float | Sequence[float] = (18.9, 13.5),
    speed: float = 0.5,
    miss_distance: float = 2.0,
    crossing_step: int = 20,
    range_: float = 2800.0,
    q: float = 1.0,
    amplitude_q: float = 0.01,
    noise_std: float = 1.0,
    device: str | torch.device | None = None,
    dtype: torch.dtype = torch.float32,
) -> Scenario:
    """Simulate K targets crossing unresolved (module docstring).

    Parameters
    ----------
    num_targets : K >= 2.
    num_steps : T frames.
    batch_size : B runs (each with its own heading ``theta_0`` and noise).
    generator : the only source of randomness; must live on ``device``.
    snr_db : one SNR [dB] for every target, or one per target (length K).
    speed : [m/s] > 0, every target's speed.
    miss_distance : [m] >= 0, the distance between neighbouring targets at the crossing step.
    crossing_step : the frame at which the targets pass the crossing point (may lie outside
        ``0 .. T - 1``).
    range_ : [m] range of the crossing point.
    q, amplitude_q : the filters' motion model (``ConstantVelocity(1, q, amplitude_q)``).
    noise_std : sigma of the radar noise.
    device, dtype : of every tensor.

    Returns
    -------
    Scenario with ``truth (T, B, K, 5)``, ``measurements (T, B, Nr, Nd, Nb)``,
    ``initial (B, K, 5)``, ``snr_db (B, K)``, the radar ``sensor`` and the ``motion`` model.
    """
    from ..models.sensors.radar import RangeDopplerBearingTBD

    k = check_positive_int(num_targets, "num_targets", minimum=2)
    t_len = check_positive_int(num_steps, "num_steps")
    b = check_positive_int(batch_size, "batch_size")
    check_generator(generator)
    speed = check_positive(speed, "speed")
    miss = check_positive(miss_distance, "miss_distance", allow_zero=True)
    if isinstance(crossing_step, bool) or not isinstance(crossing_step, int):
        raise ValueError(f"crossing_step must be an integer, got {crossing_step!r}")
    range_ = check_positive(range_, "range_")
    snr = [float(snr_db)] * k if isinstance(snr_db, (int, float)) else [float(v) for v in snr_db]
    if len(snr) != k or not all(math.isfinite(v) for v in snr):
        raise ValueError(f"snr_db must be a number or {k} finite numbers (one per target), got {snr_db!r}")
    device = torch.device(device) if device is not None else torch.device("cpu")
    if generator.device.type != device.type:
        raise ValueError(f"generator is on {generator.device}, expected a generator on {device}")

    theta0 = 2 * math.pi * torch.rand((b, 1), generator=generator, device=device, dtype=torch.float64)
    heading = theta0 + 2 * math.pi * torch.arange(k, device=device, dtype=torch.float64) / k  # (B, K)
    offset = (torch.arange(k, device=device, dtype=torch.float64) - (k - 1) / 2) * miss  # (K,)
    normal = torch.cat([-torch.sin(theta0), torch.cos(theta0)], -1)  # (B, 2), perpendicular to theta_0
    at_cross = torch.tensor([range_, 0.0], dtype=torch.float64, device=device) + offset[:, None] * normal[:, None]
    velocity = speed * torch.stack([torch.cos(heading), torch.sin(heading)], -1)  # (B, K, 2)
    # one step before frame 0 is time -1; the crossing happens at frame crossing_step, time crossing_step
    pos0 = at_cross - (crossing_step + 1) * velocity  # (B, K, 2)
    sensor_noise = float(noise_std)
    rho = torch.tensor([sensor_noise * math.sqrt(2.0 * 10.0 ** (v / 10.0)) for v in snr], dtype=torch.float64,
                       device=device).expand(b, k)
    initial = torch.stack([pos0[..., 0], velocity[..., 0], pos0[..., 1], velocity[..., 1], rho], -1)

    elapsed = torch.arange(1, t_len + 1, device=device, dtype=torch.float64)[:, None, None]  # (T, 1, 1)
    truth = initial.expand(t_len, b, k, 5).clone()
    truth[..., X] = initial[..., X] + elapsed * initial[..., VX]
    truth[..., Y] = initial[..., Y] + elapsed * initial[..., VY]

    # the grid: every position of every run plus the margin
    every = torch.cat([initial[None], truth])
    r = torch.sqrt(every[..., X] ** 2 + every[..., Y] ** 2)
    bearing = torch.atan2(every[..., Y], every[..., X])
    cells = (10.0, 2.0, math.pi / 180)
    m = MARGIN_CELLS
    sensor = RangeDopplerBearingTBD.uniform(
        _cover(float(r.min()) - m * cells[0], float(r.max()) + m * cells[0], cells[0]),
        _cover(-speed - m * cells[1], speed + m * cells[1], cells[1]),
        _cover(float(bearing.min()) - m * cells[2], float(bearing.max()) + m * cells[2], cells[2]),
        range_cell=cells[0], doppler_cell=cells[1], bearing_cell=cells[2], noise_std=sensor_noise,
    ).to(device)
    motion = ConstantVelocity(1.0, q=q, amplitude_q=amplitude_q).to(device=device, dtype=dtype)
    truth, initial = truth.to(dtype), initial.to(dtype)
    frames = torch.stack([sensor.simulate(truth[t], generator=generator) for t in range(t_len)])
    return Scenario(truth=truth, measurements=frames, initial=initial, sensor=sensor, motion=motion,
                    snr_db=torch.tensor(snr, dtype=dtype, device=device).expand(b, k), dt=1.0)
