"""The ground-radar track-before-detect scenario of Bocquel, Driessen and Bagchi (2012),
paper 000, Table I and sec. VI; batched over Monte Carlo runs.

Setup (Table I)
---------------
- Radar at the origin, sampling time ``T = 1 s``, range cell ``R = 10 m``, doppler cell
  ``D = 2 m/s``, bearing cell ``B = pi/180 rad``; complex noise of variance
  ``2 sigma^2`` (``sigma = 1``), power measurements (eqs. 18-21).
- Each target starts at bearing ``b0 ~ U[-6, 6] deg``, range ``r0 ~ U[2700, 2900] m``,
  speed ``|v0| ~ U[0, 15] m/s`` with a uniform heading in ``[0, 2 pi)``, and
  ``SNR ~ U[9, 20] dB`` (``SNR = rho^2 / (2 sigma^2)``), independently per target and run.
- "Throughout the simulation the targets move according to the initial conditions along a
  constant velocity trajectory" (sec. VI): the truth is noise-free constant velocity with a
  constant amplitude. Table I's turn parameters (``a0 ~ U[0, 1] m/s^2``,
  ``phi0 ~ U[-3, 3] deg``) contradict that sentence and are not used.
- The filter's motion model is the nearly-constant-velocity model of eqs. 15-17 with a
  1 m/s^2 acceleration standard deviation (``q = 1``) and a small amplitude random walk
  (``amplitude_q = 0.01``: amplitude standard deviation 0.1 sigma per step, 0.7 % to 2.5 %
  of the amplitudes of Table I), so the filter can correct a wrong initial amplitude.

Timing convention
-----------------
``initial`` is the true state one step *before* the first frame; frame ``t`` (``t = 0..T-1``)
is taken at time ``(t + 1) dt``, so ``truth[t] = F^(t+1) initial``. A filter started from
:meth:`Scenario.initial_particles` propagates its cloud onto frame 0 in its first step.

Sensor grid
-----------
The grid covers every track the settings allow, plus a margin of ``MARGIN_CELLS = 3`` cells
on each side of every axis. With ``L = v_max0 * T * dt`` the longest distance a target can
travel by the last frame (``v_max0 = 15 m/s``):

- range ``[r_min - L, r_max + L]`` (a target moves at most L radially);
- bearing ``[b_min - asin(L / r_min), b_max + asin(L / r_min)]`` (a displacement L at a
  range of at least ``r_min`` turns the bearing by at most ``asin(L / r_min)``);
- doppler ``[-v_max0, v_max0]``: the radial velocity of a constant-velocity target never
  exceeds its speed. Table I's "maximum target speed" ``v_max = 40 m/s`` would give a grid
  about twice as large in doppler with nothing but noise in the extra cells; particles
  that wander outside the grid simply explain no cell.

With the defaults (``T = 20``) the frame is ``Nr x Nd x Nb = 87 x 22 x 32`` cells (centres spread
symmetrically over each covered interval).
"""

from __future__ import annotations

import math

import torch

from .._validation import check_generator, check_positive, check_positive_int
from ..models.motion import ConstantVelocity
from ..typing import VX, VY, X, Y
from ._common import Scenario
from ._common import cover as _cover

__all__ = ["Scenario", "ground_radar", "MARGIN_CELLS"]

#: cells added on each side of every axis of the ground-radar grid
MARGIN_CELLS = 3


def _limits(value: float | tuple[float, float], name: str) -> tuple[float, float]:
    lo, hi = (float(value), float(value)) if isinstance(value, (int, float)) else map(float, value)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ValueError(f"{name} must be a number or a pair (low, high) with low <= high, got {value!r}")
    return lo, hi


def ground_radar(
    num_targets: int = 10,
    num_steps: int = 20,
    batch_size: int = 1,
    *,
    generator: torch.Generator,
    dt: float = 1.0,
    snr_db: float | tuple[float, float] = (9.0, 20.0),
    range_limits: tuple[float, float] = (2700.0, 2900.0),
    bearing_limits_deg: tuple[float, float] = (-6.0, 6.0),
    speed_limits: tuple[float, float] = (0.0, 15.0),
    noise_std: float = 1.0,
    q: float = 1.0,
    amplitude_q: float = 0.01,
    point_spread: str = "std",
    device: str | torch.device | None = None,
    dtype: torch.dtype = torch.float32,
) -> Scenario:
    """Simulate the ground-radar scenario of paper 000 (Table I, sec. VI); see the module
    docstring for the settings, the timing convention and the grid.

    ``num_targets=10`` is the multitarget scenario of figs. 4-6 and Table II,
    ``num_targets=1`` the single-target one of figs. 1-3.

    Parameters
    ----------
    num_targets : K.
    num_steps : T frames.
    batch_size : B independent Monte Carlo runs (each with its own targets and noise).
    generator : the only source of randomness; must live on ``device``.
    dt : sampling time [s].
    snr_db : per-target SNR [dB]: a pair ``(low, high)`` drawn uniformly, or one value.
    range_limits, bearing_limits_deg, speed_limits : the uniform laws of ``r0`` [m],
        ``b0`` [deg] and ``|v0|`` [m/s] (Table I by default).
    noise_std : sigma, per real and imaginary component of the complex noise.
    q : acceleration noise level of the filters' motion model (eqs. 15-17; the truth has
        none).
    amplitude_q : amplitude random-walk level of the filters' motion model.
    point_spread : the reading of ``R, D, B`` in eq. 20 (the data are simulated, and the
        filters score, with the same one). ``"std"`` (default): standard deviations equal to
        the cell sizes (10 m, 2 m/s, pi/180 rad). ``"variance"``: variances, as the formula
        writes them with Table I's values, i.e. standard deviations ``sqrt(10) = 3.16 m``,
        ``sqrt(2) = 1.41 m/s`` and ``sqrt(pi/180) = 0.132 rad = 7.6 deg``; the bearing spread
        then covers the whole grid, so the sensor evaluates every cell (``method="grid"``,
        about 10x the cost of the windowed path) instead of a truncated window.
    device, dtype : of every tensor (and of the models).

    Returns
    -------
    Scenario with ``truth (T, B, K, 5)``, ``measurements (T, B, Nr, Nd, Nb)``,
    ``initial (B, K, 5)``, ``snr_db (B, K)``, the radar ``sensor`` and the ``motion`` model.
    """
    from ..models.sensors.radar import RangeDopplerBearingTBD

    k = check_positive_int(num_targets, "num_targets")
    t_len = check_positive_int(num_steps, "num_steps")
    b = check_positive_int(batch_size, "batch_size")
    check_generator(generator)
    dt = check_positive(dt, "dt")
    snr_lo, snr_hi = _limits(snr_db, "snr_db")
    r_lo, r_hi = _limits(range_limits, "range_limits")
    b_lo, b_hi = (math.radians(v) for v in _limits(bearing_limits_deg, "bearing_limits_deg"))
    v_lo, v_hi = _limits(speed_limits, "speed_limits")
    if r_lo <= 0 or v_lo < 0:
        raise ValueError(f"range_limits must be > 0 and speed_limits >= 0, got {range_limits!r}, {speed_limits!r}")
    device = torch.device(device) if device is not None else torch.device("cpu")
    if generator.device.type != device.type:
        raise ValueError(f"generator is on {generator.device}, expected a generator on {device}")

    travel = v_hi * t_len * dt  # the farthest any target gets from its start
    if travel >= r_lo:
        raise ValueError(
            f"num_steps={num_steps} lets a target travel {travel:.0f} m, expected less than the "
            f"minimum initial range {r_lo:.0f} m (the target could pass the radar)"
        )
    range_cell, doppler_cell, bearing_cell = 10.0, 2.0, math.pi / 180
    if point_spread == "std":
        spread = {}
    elif point_spread == "variance":
        spread = dict(range_width=math.sqrt(range_cell), doppler_width=math.sqrt(doppler_cell),
                      bearing_width=math.sqrt(bearing_cell), method="grid")
    else:
        raise ValueError(f"point_spread must be 'std' or 'variance', got {point_spread!r}")
    turn = math.asin(travel / r_lo)
    m = MARGIN_CELLS
    sensor = RangeDopplerBearingTBD.uniform(
        _cover(r_lo - travel - m * range_cell, r_hi + travel + m * range_cell, range_cell),
        _cover(-v_hi - m * doppler_cell, v_hi + m * doppler_cell, doppler_cell),
        _cover(b_lo - turn - m * bearing_cell, b_hi + turn + m * bearing_cell, bearing_cell),
        range_cell=range_cell,
        doppler_cell=doppler_cell,
        bearing_cell=bearing_cell,
        noise_std=noise_std,
        **spread,
    ).to(device)
    motion = ConstantVelocity(dt, q=q, amplitude_q=amplitude_q).to(device=device, dtype=dtype)

    # Initial conditions (Table I), one draw per target and run.
    u = torch.rand((5, b, k), generator=generator, device=device, dtype=dtype)
    bearing = b_lo + (b_hi - b_lo) * u[0]
    rng = r_lo + (r_hi - r_lo) * u[1]
    speed = v_lo + (v_hi - v_lo) * u[2]
    heading = 2 * math.pi * u[3]
    snr = snr_lo + (snr_hi - snr_lo) * u[4]
    rho = torch.as_tensor(sensor.amplitude_from_snr(snr), device=device, dtype=dtype)
    initial = torch.stack(
        [rng * torch.cos(bearing), speed * torch.cos(heading),
         rng * torch.sin(bearing), speed * torch.sin(heading), rho], dim=-1,
    )  # (B, K, 5)

    # Noise-free constant velocity: truth[t] = F^(t+1) initial.
    elapsed = dt * torch.arange(1, t_len + 1, device=device, dtype=dtype)[:, None, None]  # (T, 1, 1)
    truth = initial.expand(t_len, b, k, 5).clone()
    truth[..., X] = initial[..., X] + elapsed * initial[..., VX]
    truth[..., Y] = initial[..., Y] + elapsed * initial[..., VY]

    frames = torch.stack([sensor.simulate(truth[t], generator=generator) for t in range(t_len)])
    return Scenario(truth=truth, measurements=frames, initial=initial, sensor=sensor, motion=motion,
                    snr_db=snr, dt=dt)
