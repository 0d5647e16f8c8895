"""The group-merge scenario of Septier, Pang, Godsill and Carmi (2009, paper 004, sec. 5,
Table 1, Fig. 3), batched over Monte Carlo runs.

Setup
-----
- 100 x 100 pixels of 50 m (a 5000 x 5000 m scene), thresholded with ``P_d,1 = 0.7`` and
  ``P_fa = 0.002`` (:class:`~torchmcmcpf.models.sensors.pixels.ThresholdedPixels`; eq. 41
  gives SNR = 12.2 dB for these, the paper says 17 dB), a frame every ``tau = 5 s``,
  110 steps.
- Four targets in two groups of two, structure ``[0, 0, 1, 1]`` (the paper's ``[1 1 2 2]``)
  for steps 1-45 and ``[0, 0, 0, 0]`` from step 46 on, when the two groups merge: the
  merged group's leader is the average of the two leaders (eq. 38).
- Motion: the virtual-leader model with Table 1's parameters (``alpha = 0.0006``,
  ``beta = 0.05``, ``gamma1 = gamma2 = 0.001``, ``sigma_x = 0.2``, ``sigma_g = 0.5``,
  ``R_1 = 8``, ``R_2 = 12``).

Choices the paper leaves open (ours)
------------------------------------
- Geometry: the leaders start at the positions from which their noise-free motion (eq. 2)
  brings them to ``merge_point -+ (0, gap / 2)`` at step 46 (``gap = 300 m``) with initial
  velocities ``(6, +-3.5)`` m/s; members start ``spread = 75 m`` either side of their
  leader, across its course, with its velocity. The repulsion acts within a group only, so
  the gap keeps the two groups' inner members apart (about 150 m, three pixels) when they
  meet; after the merge the repulsion spreads all four.
- The paper shows one realisation of the tracks (Fig. 3) and "40 sets of observations" of
  it: by default (``same_tracks=True``) every run shares one simulated track set and has its
  own frames. With ``sigma_g = 0.5`` a leader's position spreads by about 1 km over 45 steps,
  so a random leader would rarely meet the other group; by default (``leader_noise=False``)
  the leaders follow the noise-free mean of eq. 2 (the members follow eq. 1 with Table 1's
  noise and the repulsion); ``leader_noise=True`` draws the leaders from eq. 2 as well.
- ``N_max`` slots (default 4); slots beyond the four targets stay inactive at ``x_death``,
  each in its own group.

Closeness
---------
The paper gives no closeness ``h`` for its structure prior (eqs. 21-23). Ours follows the
geometry: ``h(d) = exp(-(d / s)^4 / 2)`` with ``s = gap + spread`` (375 m), flat inside a
group and sharp at its edge: ``h`` is 0.99 at 150 m (two members of a group), 0.61 at 375 m,
0.08 at 560 m and below 1e-3 beyond 750 m. On the noise-free tracks the prior's own score
``pi`` (eq. 21) of two groups of two is 0.92 on average over steps 11-45 and that of the
merged group 0.99 from step 46 on (a Gaussian of scale 300 m, the earlier default: 0.73 and
0.79, because it cannot be both near 1 at the merged group's 300-400 m and near 0 at the
two groups' 600-1000 m).

Timing: ``truth[t]`` is the state at step ``t + 1`` of the paper and ``frames[t]`` observes
it; ``merge_step`` is the 0-based index of the first merged step (45).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch

from .._validation import check_generator, check_positive_int
from ..models.group import (
    GroupExistence,
    GroupStructurePrior,
    VirtualLeaderMotion,
    structure_index,
)
from ..models.sensors.pixels import ThresholdedPixels
from ..typing import Tensor

__all__ = ["GroupMergeScenario", "group_merge", "TABLE1"]

#: Table 1 of paper 004
TABLE1 = dict(alpha=0.0006, beta=0.05, gamma1=0.001, gamma2=0.001, sigma_x=0.2, sigma_g=0.5, dt=5.0,
              r1=8.0, r2=12.0)


class GroupMergeScenario(NamedTuple):
    """A simulated group-merge scenario with its models.

    Attributes
    ----------
    truth : (T, B, K, 4) target states ``[x, vx, y, vy]`` (``x_death`` in inactive slots).
    leaders : (T, B, K, 4) virtual leaders (slot ``h`` = group label ``h``).
    exists : (T, B, K) bool.
    labels : (T, B, K) int64 canonical structure labels; structure : (T, B) int64 row of
        :func:`~torchmcmcpf.models.group.group_structures`.
    frames : (T, B, H, W) bool thresholded frames.
    motion : VirtualLeaderMotion (Table 1, the filter's model); sensor : ThresholdedPixels;
    existence : GroupExistence (paper: ``P_B = 0.2``, ``P_D = 0.05``);
    structure_prior : GroupStructurePrior (paper: ``P_NC = 0.6``, ``P_Q = 0.05``).
    merge_step : 0-based index of the first merged step.

    Example
    -------
    >>> import torch
    >>> import torchmcmcpf as tp
    >>> scene = tp.scenarios.group_merge(1, generator=torch.Generator().manual_seed(0), num_steps=50, merge_step=20)
    >>> scene.truth.shape, scene.frames.shape, scene.frames.dtype   # (T, B, K, 4), (T, B, H, W) pixels
    (torch.Size([50, 1, 4, 4]), torch.Size([50, 1, 100, 100]), torch.bool)
    >>> scene.labels[0], scene.labels[-1]                # two groups of two, then one group of four
    (tensor([[0, 0, 1, 1]]), tensor([[0, 0, 0, 0]]))
    """

    truth: Tensor
    leaders: Tensor
    exists: Tensor
    labels: Tensor
    structure: Tensor
    frames: Tensor
    motion: VirtualLeaderMotion
    sensor: ThresholdedPixels
    existence: GroupExistence
    structure_prior: GroupStructurePrior
    merge_step: int

    @property
    def positions(self) -> Tensor:
        """(T, B, K, 2) true positions."""
        return self.truth[..., 0::2]


def _initial(motion: VirtualLeaderMotion, merge_index: int, merge_point: Sequence[float], speed: Sequence[float],
             spread: float, gap: float, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """Leaders and members at step 1 (module docstring): ``x (4, 4)``, ``v (2, 4)``, on ``device``."""
    Fk = torch.linalg.matrix_power(motion.F_ll.to(device=device, dtype=dtype), merge_index)  # per-axis leader map
    xs, vs = [], []
    for sign in (1.0, -1.0):
        u0 = torch.tensor([speed[0], sign * speed[1]], dtype=dtype, device=device)
        aim = torch.tensor([merge_point[0], merge_point[1] - sign * gap / 2], dtype=dtype, device=device)
        p0 = (aim - Fk[0, 1] * u0) / Fk[0, 0]
        v = torch.stack([p0[0], u0[0], p0[1], u0[1]])
        across = torch.stack([-u0[1], u0[0]]) / u0.norm()
        for side in (1.0, -1.0):
            p = p0 + side * spread * across
            xs.append(torch.stack([p[0], u0[0], p[1], u0[1]]))
        vs.append(v)
    return torch.stack(xs), torch.stack(vs)


def group_merge(batch_size: int, *, generator: torch.Generator, num_slots: int = 4, num_steps: int = 110,
                merge_step: int = 46, same_tracks: bool = True, leader_noise: bool = False,
                merge_point: Sequence[float] = (2300.0, 2500.0), speed: Sequence[float] = (6.0, 3.5),
                spread: float = 75.0, gap: float = 300.0, p_d1: float = 0.7, p_fa: float = 0.002,
                closeness_scale: float | None = None, closeness_power: float = 4.0,
                dtype: torch.dtype = torch.float64) -> GroupMergeScenario:
    """Simulate ``batch_size`` runs of the group-merge scenario (module docstring).

    Parameters
    ----------
    batch_size : B >= 1 runs; generator : the only source of randomness (its device is used).
    num_slots : ``N_max = K >= 4``.
    num_steps : T (paper: 110); merge_step : 1-based first merged step (paper: 46).
    same_tracks : one track set for all runs (paper) or one per run.
    leader_noise : draw the leaders from eq. 2 (``sigma_g = 0.5``) instead of its mean.
    merge_point, speed, spread, gap : geometry [m, m/s, m, m] (module docstring).
    p_d1, p_fa : sensor (paper: 0.7, 0.002).
    closeness_scale, closeness_power : the structure prior's closeness (eq. 23,
        :func:`~torchmcmcpf.models.group.gaussian_closeness`); default ``gap + spread`` and 4
        (module docstring, "Closeness").

    Returns
    -------
    GroupMergeScenario.
    """
    check_generator(generator)
    b = check_positive_int(batch_size, "batch_size")
    k = check_positive_int(num_slots, "num_slots", minimum=4)
    t_max = check_positive_int(num_steps, "num_steps")
    m_idx = check_positive_int(merge_step, "merge_step", minimum=2) - 1
    dev = generator.device
    motion = VirtualLeaderMotion(**TABLE1)
    truth_motion = motion if leader_noise else VirtualLeaderMotion(**{**TABLE1, "sigma_g": 0.0})
    sensor = ThresholdedPixels((100, 100), 50.0, p_fa=p_fa, p_d1=p_d1)
    existence = GroupExistence(0.2, 0.05, sensor.area)
    scale = gap + spread if closeness_scale is None else closeness_scale
    prior = GroupStructurePrior(0.6, 0.05, scale=scale, power=closeness_power)
    for mod in (motion, truth_motion, existence, sensor, prior):  # every model on the generator's device
        mod.to(device=dev)

    bt = 1 if same_tracks else b
    x0, v0 = _initial(truth_motion, m_idx, merge_point, speed, spread, gap, dtype, dev)
    x = torch.zeros(bt, k, 4, dtype=dtype, device=dev)
    v = torch.zeros(bt, k, 4, dtype=dtype, device=dev)
    x[:, :4], v[:, :2] = x0, v0
    alive = torch.zeros(bt, k, dtype=torch.bool, device=dev)
    alive[:, :4] = True
    extra = torch.arange(k, device=dev) - 2  # dead slots 4.. in their own groups
    before = torch.cat([torch.tensor([0, 0, 1, 1], dtype=extra.dtype, device=dev), extra[4:]]).expand(bt, k)
    after = torch.cat([torch.tensor([0, 0, 0, 0], dtype=extra.dtype, device=dev), extra[4:] - 1]).expand(bt, k)
    labels = [before if t < m_idx else after for t in range(t_max)]
    xs, vs = [x], [v]
    for t in range(1, t_max):
        x, v = truth_motion.sample(x, v, labels[t - 1], labels[t], alive, alive, existence=existence,
                                   generator=generator)
        xs.append(x)
        vs.append(v)
    truth = torch.stack(xs).expand(t_max, b, k, 4).contiguous()
    leaders = torch.stack(vs).expand(t_max, b, k, 4).contiguous()
    exists = alive.expand(t_max, b, k).contiguous()
    lab = torch.stack(labels).expand(t_max, b, k).contiguous()
    frames = torch.stack([sensor.simulate(truth[t], exists=exists[t], generator=generator) for t in range(t_max)])
    return GroupMergeScenario(truth, leaders, exists, lab, structure_index(lab), frames, motion, sensor,
                              existence, prior, m_idx)
