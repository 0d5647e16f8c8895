"""What the scenarios share: the :class:`Scenario` container and the grid-cover helper."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import torch

from .._validation import check_generator, check_positive, check_positive_int
from ..models.base import MotionModel
from ..runtime import check_allocation
from ..typing import RHO, VX, VY, Tensor, X, Y

if TYPE_CHECKING:  # the grid sensors are imported lazily by the scenario builders
    from ..models.sensors.grid import SeparableGridSensor

__all__ = ["Scenario", "cover"]


@dataclass(frozen=True, eq=False)
class Scenario:
    """A simulated tracking problem, batched over B Monte Carlo runs.

    Attributes
    ----------
    truth : (T, B, K, D)
        True states at the T frames; layout ``[x, vx, y, vy(, rho)]``.
    measurements : (T, B, *G)
        One simulated frame per step and run.
    initial : (B, K, D)
        True states one step before frame 0 (see the module docstring).
    sensor : the grid sensor that simulated the frames (and that filters should use).
    motion : MotionModel for the filters (the truth may follow a simpler law).
    snr_db : (B, K)
        Signal-to-noise ratio of each target [dB].
    dt : sampling time [s].

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> g = torch.Generator().manual_seed(0)
    >>> scene = tp.scenarios.ground_radar(num_targets=2, num_steps=3, batch_size=4, generator=g)
    >>> scene.truth.shape, scene.measurements.shape      # (T, B, K, D), (T, B, Nr, Nd, Nb)
    (torch.Size([3, 4, 2, 5]), torch.Size([3, 4, 36, 22, 21]))
    >>> type(scene.sensor).__name__, type(scene.motion).__name__   # the models the filters should use
    ('RangeDopplerBearingTBD', 'ConstantVelocity')
    >>> scene.initial_particles(100, generator=g).shape  # (B, N, K, D) around the truth before frame 0
    torch.Size([4, 100, 2, 5])
    """

    truth: Tensor
    measurements: Tensor
    initial: Tensor
    sensor: SeparableGridSensor
    motion: MotionModel
    snr_db: Tensor
    dt: float
    #: the default ``spread`` of :meth:`initial_particles` (a scenario class may change it)
    initial_spread: ClassVar[tuple[float, float, float]] = (5.0, 1.0, 0.1)

    @property
    def num_steps(self) -> int:
        return self.truth.shape[0]

    @property
    def batch_size(self) -> int:
        return self.truth.shape[1]

    @property
    def num_targets(self) -> int:
        return self.truth.shape[2]

    def initial_particles(
        self,
        num_particles: int,
        *,
        generator: torch.Generator,
        spread: Sequence[float] | None = None,
    ) -> Tensor:
        """A Gaussian cloud around the true state one step before frame 0.

        Each particle is ``initial + noise`` with independent normal noise of standard
        deviation ``spread[0]`` [m] on positions, ``spread[1]`` [m/s] on velocities and, for
        states with an amplitude, ``spread[2]`` times the true amplitude on ``rho``
        (defaults: :attr:`initial_spread`, 5 m, 1 m/s, 10 %). Targets keep their true labels,
        as in the comparisons of paper 000 (the filters there are initialised on the tracks).

        Parameters
        ----------
        num_particles : N >= 1.
        generator : the only source of randomness (on the scenario's device).
        spread : (position std, velocity std, relative amplitude std); ``None``:
            :attr:`initial_spread`.

        Returns
        -------
        (B, N, K, D), dtype and device of ``truth``.

        Raises
        ------
        ValueError : when the cloud (and its noise, twice ``B N K D`` values) would exceed
            :func:`torchmcmcpf.runtime.allocation_budget` (the memory available on the device
            unless :func:`~torchmcmcpf.runtime.set_allocation_budget` set one), before
            anything is allocated.
        """
        num_particles = check_positive_int(num_particles, "num_particles")
        check_generator(generator)
        spread = self.initial_spread if spread is None else spread
        if len(spread) != 3:
            raise ValueError(f"spread must be (position std, velocity std, relative amplitude std), got {spread!r}")
        s_pos, s_vel, s_amp = (check_positive(s, "spread", allow_zero=True) for s in spread)
        x0 = self.initial
        std = torch.empty_like(x0)
        std[..., [X, Y]] = s_pos
        std[..., [VX, VY]] = s_vel
        if x0.shape[-1] > RHO:
            std[..., RHO] = s_amp * x0[..., RHO].abs()
        b, k, d = x0.shape
        # the noise and the cloud: two (B, N, K, D) tensors
        check_allocation(2 * b * num_particles * k * d * x0.element_size(),
                         f"initial_particles(num_particles={num_particles}) of {b} runs x {k} targets x {d}",
                         x0.device, hint="use fewer particles or runs")
        eps = torch.randn((b, num_particles, k, d), generator=generator, device=x0.device, dtype=x0.dtype)
        return x0[:, None] + std[:, None] * eps


def cover(lo: float, hi: float, cell: float) -> tuple[float, float]:
    """First and last centre of the fewest cells of size ``cell`` whose centres span
    ``[lo, hi]``, placed symmetrically about its midpoint.
    """
    n = math.ceil((hi - lo) / cell - 1e-9) + 1
    first = 0.5 * (lo + hi) - 0.5 * (n - 1) * cell
    return first, first + (n - 1) * cell
