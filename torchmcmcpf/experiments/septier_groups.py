"""Septier, Pang, Godsill and Carmi (2009, paper 004) sec. 5, Figs. 4-6: the marginalised
MCMC-based particle filter (:class:`~torchmcmcpf.filters.group.GroupMCMCFilter`) detects four
targets from an all-inactive start and infers that two groups of two (structure
``[1 1 2 2]``) merge into one (``[1 1 1 1]``) at step 46 (the scenario of
:mod:`torchmcmcpf.scenarios.group_merge`), next to what the data allow (issue 23).

Paper settings (defaults): ``P_NC = 0.6``, ``P_Q = 0.05``, ``P_B = 0.2``, ``P_D = 0.05``,
``P_a = 0.5``, ``P_I = 0.01``, burn-in 1000, ``N_p = 4000`` kept with thinning 6, 40 runs,
110 steps. The paper runs one chain; here the ``N_p`` kept samples are shared by ``C``
chains (``--chains``), each with its own burn-in, so a step costs
``burn_in + thinning N_p / C`` iterations of ``B C`` chains. The proposals are ours by
default (issue 23): ``alpha`` from the predictive likelihood, births on every detection, the
move on each target's last ``--lag`` positions (``p_past`` of the iterations) and the window
birth/death move (``p_window_birth``: a target detected in two consecutive frames enters any
particle, not only the few that carried its first detection), both taken from the joint
draw's ``xi``; ``--alpha mean --birth eq65 --lag 0 --xi 0.75`` is the paper's Algorithm 1-2
exactly (``--lag 0`` turns both of ours off). Every choice keeps the sampler exact (tests/filters/test_group_filter.py).

Next to the filter:

- **the ceiling**: the mean posterior existence of a perfectly localised target
  (:func:`~torchmcmcpf.models.group.existence_limit`, a two-state HMM over its detections)
  times the four targets, per step from an inactive start and in the long run;
- **the reference**: a bootstrap particle filter per target with ``--reference-particles``
  particles (:func:`reference_filter`), on the same frames: what the data allow without the
  joint search (each target sees its own detections: the other targets' pixels are masked).

Writes ``metrics.json`` and

- ``tracks.png`` (Fig. 4): run 0's true and estimated tracks (slots with existence > 0.5)
  and, every 15 steps, an ellipse around each group of the modal structure labelled with
  its number of detected members;
- ``structures.png`` (Fig. 5): the probability of each of the 15 structures over time, run 0
  and the mean over runs, and of the merged structure given that all four slots are alive;
- ``existence.png`` (Fig. 6): the mean existence of each slot and the expected number of
  targets, averaged over the runs, with the reference's and the ceiling;
- ``ospa.png``: OSPA and GOSPA (c = 100 m, p = 2) over time, mean over runs, ours and the
  reference's.

``metrics.json`` holds per-step curves, the step at which the merged structure first exceeds
probability 0.5 in each run (after the true merge), the probability of two groups of two
(any of the three slot pairings: slots are exchangeable), the first step with more than 3.5
expected targets in each run, and the wall time. ``--beyond`` adds issue 11's item 4 at the
sizes given by ``--beyond-*``: (a) the same filter without marginalisation at equal
iterations (about equal time: same kernels) -- OSPA per run (a position error) and its
spread over the runs; (b) the same sample budget on ``C`` chains vs one long chain.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch

from .. import metrics
from ..filters.group import GroupMCMCFilter
from ..models.group import existence_limit, group_structures
from ..resampling import cdf, inverse_cdf, systematic
from ..scenarios.group_merge import GroupMergeScenario, group_merge
from ..state import FilterResult
from ..typing import Tensor
from ._figures import pyplot, save_figure
from ._options import RunOptions, nonnegative_int
from ._provenance import write_metrics
from ._study import Settings, Study, cell, generator, option

if TYPE_CHECKING:
    from matplotlib.axes import Axes

#: the proposals' defaults (the notebook reads them)
PROPOSALS = dict(alpha="predictive", birth="frame", lag=2, p_past=0.2, xi=0.45, p_window_birth=0.25)
CUTOFF, ORDER = 100.0, 2.0
MERGED = 0  # row of [0, 0, 0, 0] in group_structures(4): the paper's [1 1 1 1]
#: rows of the two-groups-of-two structures [1 1 2 2], [1 2 1 2], [1 2 2 1]: slots are
#: exchangeable (a target is born into whichever slot), so "two groups of two" is any of them
PAIRS = (3, 6, 8)
#: the steps (1-based) of the headline table
HEADLINE_STEPS = (5, 10, 20, 60, 110)


@dataclass(frozen=True)
class GroupsSettings(Settings):
    """The settings of :class:`Groups` (full values; the second of each pair: ``--quick``);
    ``ValueError`` (a one-line argument error on the command line) for a particle count that
    does not split into the chains or proposal settings the filter refuses.
    """

    runs: int = option(40, 2, help="Monte Carlo runs")
    steps: int = option(110, 8, help="time steps")
    particles: int = option(4000, 40, help="kept samples N_p, a multiple of --chains")
    chains: int = option(20, 10, help="chains C sharing N_p")
    burn_in: int = option(1000, 10, help="burn-in per chain", type=nonnegative_int)
    thinning: int = option(6, 2, help="thinning")
    alpha: str = option(PROPOSALS["alpha"], choices=("mean", "predictive"),
                        help="ancestor proposal: eq. 62 ('mean') or the predictive likelihood")
    birth: str = option(PROPOSALS["birth"], choices=("eq65", "frame"),
                        help="birth proposal: eq. 65 or every detection")
    lag: int = option(PROPOSALS["lag"], type=nonnegative_int,
                      help="past positions the past move changes (default 2; 0: off)")
    p_past: float = option(PROPOSALS["p_past"], help="probability of the past move")
    p_window_birth: float = option(PROPOSALS["p_window_birth"],
                                   help="probability of the window birth/death move (default 0.25; needs --lag >= 1; "
                                        "0: off)")
    xi: float = option(PROPOSALS["xi"], help="probability of the joint draw (default 0.45; the paper's 0.75)")
    reference_particles: int = option(100_000, 2000, type=nonnegative_int,
                                      help="particles of the per-target reference filter, 0 to skip it")
    compile: bool = option(True, False, record=False,
                           help="compile the three moves (GroupMCMCFilter(compile_step=True)): about 2x faster per "
                                "iteration, a few minutes to compile; --no-compile runs eager")
    beyond: bool = option(False, record=False, help="also run issue 11 item 4 (a) and (b)")
    beyond_runs: int = option(10, 2, help="--beyond: runs")
    beyond_steps: int = option(30, 4, help="--beyond: time steps")
    beyond_particles: int = option(400, 20, help="--beyond: kept samples")
    beyond_burn_in: int = option(100, 5, help="--beyond: burn-in per chain")

    def __post_init__(self) -> None:
        if self.particles % self.chains:
            raise ValueError(f"argument --particles: {self.particles} kept samples do not split into --chains "
                             f"{self.chains} chains (each keeps particles / chains); use a multiple of {self.chains}")
        if self.lag == 0:
            object.__setattr__(self, "p_past", 0.0)
            object.__setattr__(self, "p_window_birth", 0.0)
        for key in ("p_past", "xi", "p_window_birth"):
            value = getattr(self, key)
            if not 0.0 <= value <= 1.0 or not math.isfinite(value):
                raise ValueError(f"argument --{key.replace('_', '-')}: must be a probability, got {value}")
        if self.xi + self.p_past + self.p_window_birth > 1.0:
            raise ValueError(f"argument --xi: xi + p_past + p_window_birth must be <= 1, got {self.xi} + "
                             f"{self.p_past} + {self.p_window_birth}")
        if self.lag > 0 and self.p_past == 0.0:
            raise ValueError("argument --p-past: the past move (--lag >= 1) needs --p-past > 0")


def _filter(scn: GroupMergeScenario, cfg: GroupsSettings, *, particles: int | None = None,
            chains: int | None = None, burn_in: int | None = None, marginalise: bool = True,
            compile_step: bool = False) -> GroupMCMCFilter:
    lag = cfg.lag if marginalise else 0
    return GroupMCMCFilter(scn.motion, scn.sensor, particles or cfg.particles, existence=scn.existence,
                           structure_prior=scn.structure_prior, num_chains=chains or cfg.chains,
                           burn_in=cfg.burn_in if burn_in is None else burn_in, thinning=cfg.thinning,
                           xi=cfg.xi, p_a=0.5, p_i=0.01, marginalise=marginalise, alpha=cfg.alpha,
                           birth=cfg.birth, lag=lag, p_past=cfg.p_past if lag else 0.0,
                           p_window_birth=cfg.p_window_birth if lag else 0.0,
                           compile_step=compile_step)


def _ospa(present: Tensor, est: Tensor, scn: GroupMergeScenario, steps: int) -> tuple[Tensor, Tensor]:
    """OSPA and GOSPA ``(T, B)`` of estimates ``est (T, B, K, 2)`` reported where ``present``."""
    true = scn.truth[:steps, ..., 0::2]
    o = metrics.ospa(est, true, c=CUTOFF, p=ORDER, x_mask=present, y_mask=scn.exists[:steps])
    g = metrics.gospa(est, true, c=CUTOFF, p=ORDER, x_mask=present, y_mask=scn.exists[:steps])
    return o, g


def _errors(res: FilterResult, scn: GroupMergeScenario, steps: int) -> tuple[Tensor, Tensor]:
    if res.exists_prob is None:
        raise ValueError("res must carry exists_prob (a GroupMCMCFilter result), got None")
    return _ospa(res.exists_prob > 0.5, res.mean[..., 0::2], scn, steps)


def _run(filt: GroupMCMCFilter, scn: GroupMergeScenario, steps: int, gen: torch.Generator,
         progress: bool | None) -> tuple[FilterResult, float]:
    t0 = time.perf_counter()
    res = filt(scn.frames[:steps], init=filt.init_inactive(scn.frames.shape[1], scn.truth.shape[2],
                                                           device=scn.frames.device),
               generator=gen, progress=progress)
    return res, time.perf_counter() - t0


def reference_filter(scn: GroupMergeScenario, steps: int, num_particles: int, *, generator: torch.Generator,
                     runs_per_chunk: int = 4, mask_radius: float = 75.0, p_uniform: float = 0.01) -> dict[str, Any]:
    """The near-ideal reference (issue 23 item 2): a particle filter per true target with the
    model's birth/death law, on the scenario's frames.

    Each target ``i`` of each run has its own Bernoulli filter of ``num_particles`` particles:
    a particle is alive or not (``P_B``, ``P_D``, eq. 25); alive, its state is one member and
    its virtual leader, ``[x, y, vx, vy, leader x, y, vx, vy]``, moved by the exact
    discretisation of eqs. 1-2 for a group of one (:meth:`VirtualLeaderMotion.matrices`); a
    newborn has a ``N(0, sigma_Vmax^2)`` velocity and its leader drawn around it (``Q_bVL``,
    eq. 35), as in the group filter, and its position from the data-driven ``q_0`` of eq. 64
    on every detection (weight ``p_0 / q_0``: the same posterior as births from the prior,
    with far fewer particles). Its weight is the thresholded-pixel ratio of eq. 40 at its
    pixel, on the frame with the other true targets' detections removed (the pixels nearer
    another target than to target ``i`` and within ``mask_radius`` of it read 0): each filter
    sees its own target's detections and the false alarms (an oracle association, the one
    knowledge it has that the group filter lacks). Resampled every step (systematic). The
    group structure plays no part (P(merged) has no reference).

    Parameters
    ----------
    scn : the scenario (its models and frames); steps : T; num_particles : per target.
    generator : the only source of randomness; runs_per_chunk : runs filtered at once.
    mask_radius : [m]; p_uniform : ``P_I`` of the birth proposal.

    Returns
    -------
    dict: ``exists_prob (T, B, K)`` (0 for slots without a target), ``mean (T, B, K, 2)``
    (the mean position of the live particles within one pixel of the pixel of most posterior
    mass), ``expected_count (T, B)``, ``seconds``.
    """
    t0 = time.perf_counter()
    motion, sensor, existence = scn.motion, scn.sensor, scn.existence
    dev, dtype = scn.frames.device, torch.float32  # positions to 1e-3 m: plenty for pixels of 50 m, 2x faster
    F, _, Q = motion.matrices(1)  # eq. 3 order for n = 1, float64
    L = torch.linalg.cholesky(Q + 1e-9 * torch.eye(8, dtype=Q.dtype)).to(device=dev, dtype=dtype)
    F = F.to(device=dev, dtype=dtype)
    lead = torch.sqrt(torch.diagonal(existence.leader_birth_cov)).to(device=dev, dtype=dtype)  # (s_p, s_v)
    t_max, b, k = scn.exists[:steps].shape
    h, w = sensor.shape
    s = sensor.pixel_size
    centres = torch.stack(torch.meshgrid((torch.arange(w, device=dev, dtype=dtype) + 0.5) * s,
                                         (torch.arange(h, device=dev, dtype=dtype) + 0.5) * s, indexing="xy"), -1)
    lr_hit = math.log(sensor.p_d1 / sensor.p_fa)
    lr_miss = math.log((1 - sensor.p_d1) / (1 - sensor.p_fa))
    log_p0 = -existence.log_volume
    prob = torch.zeros(t_max, b, k, dtype=torch.float64, device=dev)
    mean = torch.zeros(t_max, b, k, 2, dtype=torch.float64, device=dev)
    n = num_particles
    for r0 in range(0, b, runs_per_chunk):
        rs = slice(r0, min(b, r0 + runs_per_chunk))
        r = rs.stop - rs.start
        x = torch.zeros(r, k, n, 8, dtype=dtype, device=dev)
        alive = torch.zeros(r, k, n, dtype=torch.bool, device=dev)
        offset = (torch.arange(k, device=dev) * h * w).repeat_interleave(n)  # flat index of (target, pixel)
        for t in range(steps):
            truth = scn.positions[t, rs].to(dtype)  # (r, K, 2)
            live = scn.exists[t, rs]  # (r, K)
            # each target's frame: the pixels nearer another live target j, within mask_radius of it, read 0
            d = (centres.reshape(1, 1, h, w, 2) - truth.reshape(r, k, 1, 1, 2)).norm(dim=-1)  # (r, K, H, W)
            d = torch.where(live.reshape(r, k, 1, 1), d, torch.full_like(d, math.inf))
            other = (d.unsqueeze(1) < d.unsqueeze(2)) & (d.unsqueeze(1) < mask_radius)  # (r, i, j, H, W)
            other = other & ~torch.eye(k, dtype=torch.bool, device=dev).reshape(1, k, k, 1, 1)
            z = scn.frames[t, rs].to(torch.bool).unsqueeze(1) & ~other.any(2)  # (r, K, H, W)
            zf = z.reshape(r * k, h * w)
            n_det = zf.sum(-1)  # (r K,)
            # propagate: the birth/death law, survivors by the motion, newborns from q_0 (eq. 64)
            alive_next = existence.draw_exists(alive, torch.rand(r, k, n, generator=generator, dtype=dtype,
                                                                 device=dev))
            x = x @ F.T + torch.randn(r, k, n, 8, generator=generator, dtype=dtype, device=dev) @ L.T
            newborn = alive_next & ~alive
            nb = newborn.reshape(r * k, n).nonzero(as_tuple=True)  # eager experiment code: only the newborns
            m = nb[0].shape[0]
            u = torch.rand(m, 4, generator=generator, dtype=torch.float64, device=dev)  # select, pixel, x, y
            log_pick = torch.where(zf | (n_det == 0).unsqueeze(-1), 0.0, -math.inf).to(torch.float64)
            stacked = (cdf(log_pick) + torch.arange(r * k, device=dev, dtype=torch.float64).unsqueeze(-1)).reshape(-1)
            pix = inverse_cdf(stacked, nb[0] + u[:, 1]) % (h * w)  # the row's CDF, offset by the row
            on_det = torch.stack([(pix % w).to(torch.float64), (pix // w).to(torch.float64)], -1) * s + s * u[:, 2:]
            uniform = (u[:, 0] < p_uniform) | (n_det[nb[0]] == 0)
            pos = torch.where(uniform.unsqueeze(-1), existence.uniform_position(u[:, 2:]), on_det)
            col, row = torch.floor(pos[:, 0] / s).clamp(0, w - 1), torch.floor(pos[:, 1] / s).clamp(0, h - 1)
            on_pix = zf[nb[0], (row * w + col).long()]
            q0 = p_uniform * math.exp(log_p0) + (1 - p_uniform) * on_pix.to(torch.float64) / (
                n_det[nb[0]].clamp(min=1) * s * s)
            log_ratio = torch.zeros(r * k, n, dtype=dtype, device=dev)
            log_ratio[nb] = (log_p0 - torch.where(n_det[nb[0]] > 0, q0, torch.full_like(q0, math.exp(log_p0))).log()
                             ).to(dtype)
            e2 = torch.randn(m, 6, generator=generator, dtype=dtype, device=dev)
            vel = existence.velocity_std * e2[:, :2]
            pos = pos.to(dtype)
            x = x.reshape(r * k, n, 8)
            x[nb] = torch.cat([pos, vel, pos + lead[0] * e2[:, 2:4], vel + lead[1] * e2[:, 4:6]], -1)
            x = x.reshape(r, k, n, 8)
            alive = alive_next
            # weigh by eq. 40 at each particle's pixel (off the grid: ratio 1), newborns by p_0 / q_0
            col, row = torch.floor(x[..., 0] / s), torch.floor(x[..., 1] / s)
            on = alive & (col >= 0) & (col < w) & (row >= 0) & (row < h)
            flat = (row.clamp(0, h - 1) * w + col.clamp(0, w - 1)).long().reshape(r, k * n)
            hit = torch.gather(z.reshape(r, k * h * w), 1, flat + offset).reshape(r, k, n)
            log_w = (hit.to(dtype) * (lr_hit - lr_miss) + lr_miss) * on.to(dtype) + log_ratio.reshape(r, k, n)
            wn = torch.softmax(log_w.double(), -1) * alive  # (r, K, N): the live particles' weights
            p_alive = wn.sum(-1)  # (r, K)
            prob[t, rs] = torch.where(live, p_alive, torch.zeros_like(p_alive))
            # the estimate: the mean of the live particles around the pixel of most mass (the
            # posterior can hold a false-alarm track next to the target's: a plain mean falls between)
            mass = torch.zeros(r, k * h * w, dtype=torch.float64, device=dev).scatter_add_(
                1, flat + offset, wn.reshape(r, k * n)).reshape(r, k, h * w)
            top = mass.argmax(-1, keepdim=True)  # (r, K, 1)
            near = ((col.clamp(0, w - 1) - (top % w)).abs() <= 1) & ((row.clamp(0, h - 1) - (top // w)).abs() <= 1)
            wm = wn * near
            mean[t, rs] = (wm.unsqueeze(-1) * x[..., :2].double()).sum(-2) / wm.sum(-1, keepdim=True).clamp(min=1e-300)
            idx = systematic(log_w.reshape(r * k, n), torch.rand(r * k, 1, generator=generator, dtype=dtype,
                                                                  device=dev)).reshape(r, k, n)
            x = torch.gather(x, 2, idx.unsqueeze(-1).expand(r, k, n, 8))
            alive = torch.gather(alive, 2, idx)
    return {"exists_prob": prob, "mean": mean, "expected_count": prob.sum(-1), "seconds": time.perf_counter() - t0}


def bayes_limit(scn: GroupMergeScenario, steps: int) -> dict[str, Any]:
    """The expected-count ceiling of the scenario (:func:`existence_limit` times the number of
    targets): per step from an inactive start and in the long run, for the scenario's
    ``P_d,1`` and for the paper's stated 17 dB (``P_d,1 = 0.885``).
    """
    sensor, existence = scn.sensor, scn.existence
    n_targets = int(scn.exists[0, 0].sum())
    p_here = sensor.pixel_size ** 2 / float(torch.exp(torch.tensor(existence.log_volume)))
    p_d1_17db = sensor.p_fa ** (1.0 / (1.0 + 10 ** 1.7))  # eq. 41 at SNR = 17 dB
    ours, paper = (existence_limit(steps, p_birth=existence.p_birth, p_death=existence.p_death, p_d1=p_d1,
                                   p_fa=sensor.p_fa, p_here=p_here) for p_d1 in (sensor.p_d1, p_d1_17db))
    return {"targets": n_targets, "p_d1": sensor.p_d1, "per_step": n_targets * ours.per_step,
            "stationary": n_targets * ours.stationary, "error": n_targets * ours.stationary_error,
            "p_d1_17db": p_d1_17db, "stationary_17db": n_targets * paper.stationary,
            "per_step_17db": n_targets * paper.per_step}


def first_step_above(prob: torch.Tensor, threshold: float, start: int = 0) -> list[int | None]:
    """1-based first step ``t >= start + 1`` with ``prob[t] > threshold`` per run: ``(T, B) ->
    [B]`` (``None`` where never).
    """
    above = prob[start:] > threshold
    out: list[int | None] = []
    for b in range(prob.shape[1]):
        idx = above[:, b].nonzero()
        out.append(int(idx[0, 0]) + start + 1 if len(idx) else None)
    return out


def plot_groups(ax: Axes, truth: Tensor, est: Tensor, present: Tensor, labels_modal: Tensor, *,
                every: int = 15) -> None:
    """Fig. 4: true tracks (grey), estimated tracks (slots with existence > 0.5) and, every
    ``every`` steps, an ellipse around each group of the modal structure with its number of
    detected members. ``truth (T, K, 2)``, ``est (T, K, 2)``, ``present (T, K)``,
    ``labels_modal (T, K)``.
    """
    from matplotlib.patches import Ellipse

    t_max, k = present.shape
    for i in range(truth.shape[1]):
        ax.plot(truth[:, i, 0], truth[:, i, 1], color="0.6", lw=3, alpha=0.6, label="truth" if i == 0 else None)
    for i in range(k):
        e = torch.where(present[:, i, None], est[:, i], torch.full_like(est[:, i], float("nan")))
        ax.plot(e[:, 0], e[:, 1], lw=1.2, label=f"slot {i}")
    for t in range(every - 1, t_max, every):
        for h in labels_modal[t].unique():
            members = (labels_modal[t] == h) & present[t]
            if not members.any():
                continue
            p = est[t][members]
            centre = p.mean(0)
            span = (p.amax(0) - p.amin(0)) if p.shape[0] > 1 else torch.zeros(2, dtype=p.dtype, device=p.device)
            ax.add_patch(Ellipse((float(centre[0]), float(centre[1])), float(span[0]) + 250, float(span[1]) + 250,
                                 fill=False, color="k", lw=1))
            ax.annotate(str(int(members.sum())), (float(centre[0]), float(centre[1]) + float(span[1]) / 2 + 150),
                        ha="center", fontsize=9)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def _at(curve: Tensor, step: int) -> float | None:
    """``curve[step - 1]`` as a float (1-based step), ``None`` beyond the curve."""
    return float(curve[step - 1]) if step <= curve.shape[0] else None


def _beyond(scn: GroupMergeScenario, cfg: GroupsSettings, gen: torch.Generator, progress: bool | None
            ) -> dict[str, Any]:
    """Issue 11 item 4 on the first ``beyond_runs`` runs and ``beyond_steps`` steps."""
    r, steps, n, burn = cfg.beyond_runs, cfg.beyond_steps, cfg.beyond_particles, cfg.beyond_burn_in
    sub = scn._replace(truth=scn.truth[:, :r], exists=scn.exists[:, :r], frames=scn.frames[:, :r])
    chains = max(d for d in range(1, min(cfg.chains, n) + 1) if n % d == 0)
    out: dict[str, Any] = {"runs": r, "steps": steps, "particles": n, "burn_in": burn, "chains": chains,
                           "thinning": cfg.thinning}
    start = min(10, steps - 1)  # after the detection phase
    for name, marg in (("marginalised", True), ("sampled_velocities_and_leaders", False)):
        res, sec = _run(_filter(sub, cfg, particles=n, chains=chains, burn_in=burn, marginalise=marg), sub, steps,
                        gen, progress)
        o, _ = _errors(res, sub, steps)
        per_run = o[start:].mean(0)
        out[name] = {"seconds": sec, "ospa_per_run": per_run, "ospa_mean": per_run.mean(),
                     "ospa_std_over_runs": per_run.std(), "expected_count_final": res.info.extras["expected_count"][-1]}
    # (b) the same budget of kept samples: C chains (own burn-in each) vs one long chain with
    # the same number of iterations in total per run
    total = chains * burn + cfg.thinning * n
    for name, c, b in (("C_chains", chains, burn), ("one_chain", 1, total - cfg.thinning * n)):
        res, sec = _run(_filter(sub, cfg, particles=n, chains=c, burn_in=b), sub, steps, gen, progress)
        o, _ = _errors(res, sub, steps)
        per_run = o[start:].mean(0)
        out[name] = {"chains": c, "burn_in": b, "seconds": sec, "ospa_mean": per_run.mean(),
                     "ospa_std_over_runs": per_run.std(), "expected_count_final": res.info.extras["expected_count"][-1]}
    return out


class Groups(Study[GroupsSettings]):
    """Figs. 4-6 of paper 004 (module docstring); not sharded."""

    name = "septier-groups"
    description = ("Septier et al. 2009 Figs. 4-6: marginalised MCMC-PF detects 4 targets and infers two groups "
                   "merging, next to the Bayes limit and a large-particle reference")
    outputs = ("metrics.json", "tracks.png", "structures.png", "existence.png", "ospa.png")

    def compute(self, cfg: GroupsSettings, options: RunOptions) -> dict:
        """Run the study (module docstring); writes the figures into ``options.out``."""
        plt = pyplot()
        device, out = options.device, options.out
        gen = generator(device, options.seed)
        steps = cfg.steps
        # the paper's 40 observation sets are drawn whatever --runs (a reduced run filters the first ones)
        runs = cfg.runs
        scn = group_merge(runs if cfg.quick else max(runs, GroupsSettings.runs), generator=gen, num_steps=max(steps, 2),
                          merge_step=min(46, max(steps, 2)))
        scn = scn._replace(truth=scn.truth[:, :runs], leaders=scn.leaders[:, :runs], exists=scn.exists[:, :runs],
                           labels=scn.labels[:, :runs], structure=scn.structure[:, :runs], frames=scn.frames[:, :runs])
        scn = scn._replace(motion=scn.motion.to(device), sensor=scn.sensor.to(device),
                           existence=scn.existence.to(device), structure_prior=scn.structure_prior.to(device))
        filt = _filter(scn, cfg, compile_step=cfg.compile)
        res, seconds = _run(filt, scn, steps, gen, options.progress)
        if res.exists_prob is None:
            raise ValueError("the filter result carries no exists_prob (expected a GroupMCMCFilter result)")
        ex = res.info.extras
        sp = ex["structure_prob"]  # (T, B, 15)
        sp_all = ex["structure_prob_all_exist"]  # (T, B, 15), NaN where no particle has all four
        count = ex["expected_count"]  # (T, B)
        o, g = _errors(res, scn, steps)
        merge = scn.merge_step
        merged_at = first_step_above(sp[..., MERGED], 0.5, start=merge)
        detected_at = first_step_above(count, 3.5)
        table = group_structures(4)
        limit = bayes_limit(scn, steps)
        ref = (reference_filter(scn, steps, cfg.reference_particles, generator=gen)
               if cfg.reference_particles else None)
        if ref is not None:
            ref_o, ref_g = _ospa(ref["exists_prob"] > 0.5, ref["mean"], scn, steps)
        quick = cfg.quick

        # -- figures
        fig, ax = plt.subplots(figsize=(7, 7))
        modal = table[sp[:, 0].argmax(-1)]
        plot_groups(ax, scn.positions[:steps, 0, :4].cpu(), res.mean[:, 0, :, 0::2].cpu(),
                    (res.exists_prob[:, 0] > 0.5).cpu(), modal)
        ax.legend(fontsize=8, loc="upper left")
        ax.set_title("run 0: tracks and the modal group structure (Fig. 4)")
        save_figure(fig, out, "tracks.png", quick=quick)

        fig, axes = plt.subplots(1, 2, figsize=(13, 4.5), sharey=True)
        steps_axis = torch.arange(1, steps + 1)
        cmap = plt.get_cmap("tab20")
        for ax, probs, title in ((axes[0], sp[:, 0], "run 0"), (axes[1], sp.mean(1), f"mean over {cfg['runs']} runs")):
            for s in range(table.shape[0]):
                lab = "[" + " ".join(str(int(v) + 1) for v in table[s]) + "]"
                ax.plot(steps_axis, probs[:, s].cpu(), color=cmap(s), lw=2.5 if s in (MERGED,) + PAIRS else 1,
                        label=lab)
            ax.plot(steps_axis, probs[:, list(PAIRS)].sum(-1).cpu(), "k--", lw=1.5, label="two groups of two (sum)")
            ax.axvline(merge + 1, color="k", ls=":", lw=1)
            ax.set_xlabel("time step")
            ax.set_title(f"group structure probability, {title} (Fig. 5)")
        axes[1].plot(steps_axis, sp_all[..., MERGED].nanmean(1).cpu(), color=cmap(MERGED), ls=":", lw=2,
                     label="[1 1 1 1] given all four alive")
        axes[0].set_ylabel("probability")
        axes[1].legend(fontsize=7, ncol=3, loc="center right")
        save_figure(fig, out, "structures.png", quick=quick)

        fig, ax = plt.subplots(figsize=(7, 4))
        ep = res.exists_prob.mean(1).cpu()  # (T, K)
        for i in range(ep.shape[1]):
            ax.plot(steps_axis, ep[:, i], lw=0.8, alpha=0.7, label=f"slot {i}")
        ax.plot(steps_axis, count.mean(1).cpu(), "k", lw=2, label="expected number of targets")
        if ref is not None:
            ax.plot(steps_axis, ref["expected_count"].mean(1).cpu(), color="C3", lw=1.8, ls="-.",
                    label=f"reference: a bootstrap PF per target, {cfg['reference_particles']:,} particles")
        ax.plot(steps_axis, limit["per_step"], color="C2", lw=1.2, ls="--",
                label="ceiling from an inactive start (target's pixel known)")
        ax.axhline(limit["stationary"], color="C2", lw=1.5,
                   label=f"ceiling {limit['stationary']:.2f} (P_d,1 = {limit['p_d1']:.2f}; "
                         f"{limit['stationary_17db']:.2f} at the paper's 17 dB)")
        ax.axhline(4, color="0.5", ls=":")
        ax.set_xlabel("time step")
        ax.set_title(f"mean existence over {cfg['runs']} runs (Fig. 6)")
        ax.legend(fontsize=7, loc="lower right")
        save_figure(fig, out, "existence.png", quick=quick)

        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        axes[0].plot(steps_axis, o.mean(1).cpu(), label="group MCMC-PF")
        axes[1].plot(steps_axis, g.mean(1).cpu(), label="group MCMC-PF")
        if ref is not None:
            axes[0].plot(steps_axis, ref_o.mean(1).cpu(), color="C3", ls="-.", label="reference")
            axes[1].plot(steps_axis, ref_g.mean(1).cpu(), color="C3", ls="-.", label="reference")
        axes[0].set_ylabel(f"OSPA (c = {CUTOFF:g} m, p = {ORDER:g}) [m]")
        axes[1].set_ylabel(f"GOSPA (c = {CUTOFF:g} m, p = {ORDER:g}) [m]")
        for ax in axes:
            ax.set_xlabel("time step")
            ax.legend(fontsize=8)
        save_figure(fig, out, "ospa.png", quick=quick)

        n_merged = sum(m is not None for m in merged_at)
        ours_count = count.mean(1)
        p_merged = sp[..., MERGED].mean(1)
        p_merged_all = sp_all[..., MERGED].nanmean(1)
        after = slice(min(60, steps), steps)  # steps 61 .. T (the "after step 60")
        payload: dict[str, Any] = {
            "config": cfg.record(),
            "iterations_per_step": cfg.burn_in + cfg.thinning * cfg.particles // cfg.chains,
            "seconds": seconds,
            "seconds_per_step": seconds / steps,
            "merge_step": merge + 1,
            "ceiling": {k: v for k, v in limit.items() if not torch.is_tensor(v)},
            "ceiling_per_step": limit["per_step"],
            "headline": {
                f"step_{t}": {"ceiling": _at(limit["per_step"], t), "ours": _at(ours_count, t),
                              "reference": None if ref is None else _at(ref["expected_count"].mean(1), t),
                              "p_merged": _at(p_merged, t), "p_merged_all_alive": _at(p_merged_all, t)}
                for t in sorted({t for t in HEADLINE_STEPS if t <= steps} | {steps})},
            "p_merged_mean_after_60": p_merged[after].mean() if steps > 60 else None,
            "p_merged_all_alive_mean_after_60": p_merged_all[after].nanmean() if steps > 60 else None,
            "p_merged_all_alive_min_after_60": p_merged_all[after].min() if steps > 60 else None,
            "merged_structure_first_above_half": merged_at,
            "runs_merged": n_merged,
            "median_merge_detected_step": (sorted(m for m in merged_at if m is not None)[n_merged // 2]
                                           if n_merged else None),
            "first_step_expected_count_above_3_5": detected_at,
            "runs_detected_within_10_steps": sum(d is not None and d <= 10 for d in detected_at),
            "expected_count_step_10_mean": count[min(9, steps - 1)].mean(),
            "expected_count_per_step": ours_count,
            "exists_prob_per_step": res.exists_prob.mean(1),
            "structure_prob_per_step": sp.mean(1),
            "p_merged_all_alive_per_step": p_merged_all,
            "p_all_alive_per_step": ex["all_exist_prob"].mean(1),
            "p_two_pairs_per_step": sp[..., list(PAIRS)].sum(-1).mean(1),
            "p_two_pairs_mean_steps_11_to_45": (sp[10:merge, :, list(PAIRS)].sum(-1).mean()
                                                if merge > 10 and steps > 10 else None),
            "p_merged_mean_last_20": sp[-20:, :, MERGED].mean(),
            "ospa_per_step": o.mean(1), "gospa_per_step": g.mean(1),
            "ospa": o.mean(), "gospa": g.mean(),
            "acceptance": {k: v.nanmean() for k, v in ex.items() if k.startswith("acceptance")},
        }
        if ref is not None:
            payload["reference"] = {"particles": cfg.reference_particles, "seconds": ref["seconds"],
                                    "expected_count_per_step": ref["expected_count"].mean(1),
                                    "ospa_per_step": ref_o.mean(1), "ospa": ref_o.mean(), "gospa": ref_g.mean()}
        if cfg.beyond:
            write_metrics(out, payload, options=options)  # kept if item 4 is interrupted
            payload["beyond"] = _beyond(scn, cfg, gen, options.progress)
        return payload

    def summary(self, payload: dict[str, Any]) -> str:
        """The headline table printed by ``reproduce``: the expected number of targets and the
        merged structure's probability next to the ceiling, the reference and the paper.
        """
        h = payload["headline"]
        cfg = payload["config"]
        cols = [k for k in h if h[k]["ours"] is not None]
        sec = payload["seconds"] + payload.get("reference", {}).get("seconds", 0.0)
        lines = [f"septier-groups: {cfg['runs']} runs x {cfg['steps']} steps, N_p = {cfg['particles']} "
                 f"({cfg['chains']} chains, burn-in {cfg['burn_in']}, thinning {cfg['thinning']}), "
                 + (f"{sec / 60:.1f} min" if sec >= 60 else f"{sec:.0f} s")
                 + (" (quick: small settings)" if cfg.get("quick") else ""),
                 "", "| expected number of targets, step | " + " | ".join(k.split("_")[1] for k in cols) + " |",
                 "| --- |" + " --- |" * len(cols)]
        ceiling = payload["ceiling"]
        rows = [("ceiling (pixel known)", "ceiling"), ("reference (bootstrap PF per target)", "reference"),
                ("group MCMC-PF (ours)", "ours"), ("P(merged)", "p_merged"), ("P(merged | all four alive)",
                                                                              "p_merged_all_alive")]
        for label, key in rows:
            lines.append(f"| {label} | " + " | ".join(cell(h[k][key]) for k in cols) + " |")
        lines += ["", f"ceiling in the long run {cell(ceiling['stationary'])} (P_d,1 = {cell(ceiling['p_d1'])}), "
                  f"{cell(ceiling['stationary_17db'])} at the paper's 17 dB (P_d,1 = {cell(ceiling['p_d1_17db'], 3)}); "
                  "paper: ~4 within ten steps (Fig. 6), [1 1 1 1] ~1 after the merge (Fig. 5)",
                  f"runs with P(merged) > 0.5 after step {payload['merge_step']}: {payload['runs_merged']} of "
                  f"{cfg['runs']}"
                  f"; OSPA {cell(payload['ospa'], 1)} m" + (f" (reference {cell(payload['reference']['ospa'], 1)} m)"
                                                        if "reference" in payload else "")]
        return "\n".join(lines)


STUDY = Groups()
