"""The three-target azimuth-range TBD scenario of Ling (2016), paper 002 sec. 4; batched over
Monte Carlo runs.

What the paper fixes
--------------------
35 frames, three targets of known number, Swerling-I power measurements on an azimuth x
range grid (eqs. 3-9), nearly-constant-velocity motion (eqs. 1-2); "target 1 is well
separated from the else, target 2 and target 3 are close and parallel" (Fig. 1); one SNR
for all targets, the x axis of Fig. 3.

What we chose (the paper gives no numbers for these)
----------------------------------------------------
- Sensor at the origin, sampling time ``T = 1 s``, cells of ``1 deg`` in azimuth and
  ``10 m`` in range (the range resolution the RMSE is compared with), point-spread widths
  equal to the cell sizes, noise power ``sigma^2 = 1``, ``SNR = P / sigma^2``
  (:class:`~torchmcmcpf.models.sensors.swerling.AzimuthRangeSwerlingTBD`). At the targets'
  ranges (510-660 m) one azimuth cell spans 9-12 m, so the cells are about square.
- True tracks: noise-free constant velocity from :data:`INITIAL_STATES` (one step before
  frame 0; [m], [m/s]), the same in every run (only the noise and the SNR differ):

  ======  ====================  ===========  ============================================
  target  start (x, y) [m]      v [m/s]      track
  ======  ====================  ===========  ============================================
  1       (500, 220)            (4, -2)      alone: >= 225 m from the others throughout
  2       (520, -180)           (3, 3)       parallel to 3
  3       (534.14, -194.14)     (3, 3)       2's track shifted 20 m (two cells) across it
  ======  ====================  ===========  ============================================

  Targets 2 and 3 stay 20 m apart: their point spreads overlap (``h = exp(-2) = 0.14``
  halfway) and so do their likelihood windows.
- The grid covers every track plus ``MARGIN_CELLS = 3`` cells on each side of each axis
  (``51 x 19`` cells for 35 frames).
- The target power is part of the state (``[x, vx, y, vy, P]``) but, as in the paper,
  known: the truth keeps it constant, the initial cloud puts it at its true value and the
  filters' motion gives it a random walk of standard deviation ``sqrt(power_q) = 1e-3``
  per step (negligible against ``P >= sigma^2``). The kinematic part is eqs. 1-2 with
  ``q = 1 m^2 s^-3`` (the level paper 000 uses with the same 10 m cells).
- Initial particle cloud (:meth:`LingScenario.initial_particles`): Gaussian around the true
  state one step before frame 0, standard deviations 5 m on positions, 1 m/s on velocities,
  0 on the power (:data:`INITIAL_SPREAD`); the slot labels follow the truth.

Timing convention as in :mod:`~torchmcmcpf.scenarios.ground_radar`: ``truth[t] = F^(t+1)
initial`` and a filter started from the initial cloud propagates it onto frame 0 first.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from .._validation import check_generator, check_positive, check_positive_int
from ..models.motion import ConstantVelocity
from ..typing import VX, VY, Tensor, X, Y
from ._common import Scenario, cover
from .ground_radar import MARGIN_CELLS

__all__ = ["LingScenario", "ling", "INITIAL_STATES", "INITIAL_SPREAD"]

#: True ``[x, vx, y, vy]`` of the three targets one step before frame 0 (see the module docstring).
INITIAL_STATES = (
    (500.0, 4.0, 220.0, -2.0),
    (520.0, 3.0, -180.0, 3.0),
    (520.0 + 20.0 / math.sqrt(2.0), 3.0, -180.0 - 20.0 / math.sqrt(2.0), 3.0),
)

#: Initial cloud: (position std [m], velocity std [m/s], relative power std).
INITIAL_SPREAD = (5.0, 1.0, 0.0)


@dataclass(frozen=True, eq=False)
class LingScenario(Scenario):
    """:class:`~torchmcmcpf.scenarios.ground_radar.Scenario` of paper 002; the state is
    ``[x, vx, y, vy, P]``, the frames ``(T, B, Na, Nr)``, ``snr_db (B, K)``. Its
    :meth:`~Scenario.initial_particles` know the power by default (``spread = (5 m, 1 m/s, 0)``,
    :data:`INITIAL_SPREAD`).

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> scene = tp.scenarios.ling(10.0, 2, generator=torch.Generator().manual_seed(0), num_steps=3)
    >>> scene.truth.shape, scene.measurements.shape      # three targets; (T, B, Na, Nr) frames
    (torch.Size([3, 2, 3, 5]), torch.Size([3, 2, 51, 10]))
    >>> scene.range_resolution, scene.snr_db[0]
    (10.0, tensor([10., 10., 10.]))
    """

    initial_spread = INITIAL_SPREAD

    @property
    def range_resolution(self) -> float:
        """Range cell size [m] (10 m): the yardstick of paper 002's Fig. 3."""
        return self.sensor.cell_sizes[1]


def ling(
    snr_db: float | Sequence[float] | Tensor = 10.0,
    batch_size: int = 1,
    *,
    generator: torch.Generator,
    num_steps: int = 35,
    dt: float = 1.0,
    q: float = 1.0,
    power_q: float = 1e-6,
    noise_power: float = 1.0,
    device: str | torch.device | None = None,
    dtype: torch.dtype = torch.float32,
) -> LingScenario:
    """Simulate the scenario of paper 002 sec. 4 (see the module docstring).

    Parameters
    ----------
    snr_db : SNR of every target [dB] (``P / sigma^2``): one value for all runs, or ``B``
        values, one per run (so a whole SNR sweep filters as one batch).
    batch_size : B Monte Carlo runs; with per-run SNRs it must equal their number.
    generator : the only source of randomness (the frames); must live on ``device``.
    num_steps : T frames (35 in the paper).
    dt : sampling time [s].
    q : acceleration noise level of the filters' motion model (eq. 2's ``q^j``).
    power_q : random-walk level of the power in the filters' motion model.
    noise_power : ``sigma^2``, the mean noise power of a cell.
    device, dtype : of every tensor (and of the models).

    Returns
    -------
    LingScenario with ``truth (T, B, 3, 5)``, ``measurements (T, B, Na, Nr)``,
    ``initial (B, 3, 5)``, ``snr_db (B, 3)``, the Swerling ``sensor`` and the ``motion``.
    """
    from ..models.sensors.swerling import AzimuthRangeSwerlingTBD

    b = check_positive_int(batch_size, "batch_size")
    t_len = check_positive_int(num_steps, "num_steps")
    check_generator(generator)
    dt = check_positive(dt, "dt")
    device = torch.device(device) if device is not None else torch.device("cpu")
    if generator.device.type != device.type:
        raise ValueError(f"generator is on {generator.device}, expected a generator on {device}")
    snr = torch.as_tensor(snr_db, dtype=dtype, device=device)
    if snr.dim() > 1 or not bool(torch.isfinite(snr).all()):
        raise ValueError(f"snr_db must be a finite number or a (B,) sequence, got shape {tuple(snr.shape)}")
    if snr.dim() == 1 and snr.shape[0] != b:
        raise ValueError(f"snr_db has shape {tuple(snr.shape)}, expected ({b},) (one SNR per run) or a number")
    snr = snr.expand(b)

    # Noise-free constant velocity, float64 for the grid limits: truth[t] = F^(t+1) initial.
    # on the CPU on purpose: the grid's limits are read to the host (then moved to ``device``)
    kin = torch.tensor(INITIAL_STATES, dtype=torch.float64, device="cpu")  # (K, 4)
    elapsed = dt * torch.arange(0, t_len + 1, dtype=torch.float64, device="cpu")[:, None]  # (T + 1, 1), 0 = initial
    px = kin[:, X] + elapsed * kin[:, VX]
    py = kin[:, Y] + elapsed * kin[:, VY]
    az, rng = torch.atan2(py, px), torch.hypot(px, py)

    az_cell, r_cell, m = math.pi / 180, 10.0, MARGIN_CELLS
    sensor = AzimuthRangeSwerlingTBD.uniform(
        cover(float(az.min()) - m * az_cell, float(az.max()) + m * az_cell, az_cell),
        cover(float(rng.min()) - m * r_cell, float(rng.max()) + m * r_cell, r_cell),
        azimuth_cell=az_cell,
        range_cell=r_cell,
        noise_power=noise_power,
    ).to(device)
    motion = ConstantVelocity(dt, q=q, amplitude_q=power_q).to(device=device, dtype=dtype)

    k = kin.shape[0]
    power = torch.as_tensor(sensor.power_from_snr(snr), device=device, dtype=dtype)  # (B,)
    states = torch.stack([px, kin[:, VX].expand_as(px), py, kin[:, VY].expand_as(py)], dim=-1)  # (T + 1, K, 4)
    states = states.to(device=device, dtype=dtype)[:, None].expand(t_len + 1, b, k, 4)
    states = torch.cat([states, power[None, :, None, None].expand(t_len + 1, b, k, 1)], dim=-1)
    initial, truth = states[0].contiguous(), states[1:].contiguous()

    frames = torch.stack([sensor.simulate(truth[t], generator=generator) for t in range(t_len)])
    return LingScenario(truth=truth, measurements=frames, initial=initial, sensor=sensor, motion=motion,
                        snr_db=snr[:, None].expand(b, k).contiguous(), dt=dt)
