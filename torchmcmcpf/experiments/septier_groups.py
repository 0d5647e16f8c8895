"""Septier, Pang, Godsill and Carmi (2009, paper 004) sec. 5, Figs. 4-6: the marginalised
MCMC-based particle filter (:class:`~torchmcmcpf.filters.group.GroupMCMCFilter`) detects four
targets from an all-inactive start and infers that two groups of two (structure
``[1 1 2 2]``) merge into one (``[1 1 1 1]``) at step 46 (the scenario of
:mod:`torchmcmcpf.scenarios.group_merge`).

Paper settings (defaults): ``P_NC = 0.6``, ``P_Q = 0.05``, ``P_B = 0.2``, ``P_D = 0.05``,
``P_a = 0.5``, ``P_I = 0.01``, ``xi = 0.75``, burn-in 1000, ``N_p = 4000`` kept with thinning
6, 40 runs, 110 steps. The paper runs one chain; here the ``N_p`` kept samples are shared
by ``C`` chains (``--chains``), each with its own burn-in, so a step costs
``burn_in + thinning N_p / C`` iterations of ``B C`` chains.

Writes ``metrics.json`` and

- ``tracks.png`` (Fig. 4): run 0's true and estimated tracks (slots with existence > 0.5)
  and, every 15 steps, an ellipse around each group of the modal structure labelled with
  its number of detected members;
- ``structures.png`` (Fig. 5): the probability of each of the 15 structures over time, run 0
  and the mean over runs;
- ``existence.png`` (Fig. 6): the mean existence of each slot and the expected number of
  targets, averaged over the runs;
- ``ospa.png``: OSPA and GOSPA (c = 100 m, p = 2) over time, mean over runs.

``metrics.json`` holds per-step curves, the step at which the merged structure first exceeds
probability 0.5 in each run (after the true merge), the probability of two groups of two
(any of the three slot pairings: slots are exchangeable), the first step with more than 3.5
expected targets in each run, and the wall time. ``--beyond`` adds issue 11's item 4 at the
sizes given by ``--beyond-*``: (a) the same filter without marginalisation at equal
iterations (about equal time: same kernels) -- OSPA per run (a position error) and its
spread over the runs; (b) the same sample budget on ``C`` chains vs one long chain.
"""

from __future__ import annotations

import argparse
import time
from typing import TYPE_CHECKING, Any

import torch

from .. import metrics
from ..filters.group import GroupMCMCFilter
from ..models.group import group_structures
from ..scenarios.group_merge import GroupMergeScenario, group_merge
from ..state import FilterResult
from ..typing import Tensor
from ._common import generator, positive_int, save_figure, write_metrics

if TYPE_CHECKING:
    from matplotlib.axes import Axes

NAME = "septier-groups"
DESCRIPTION = "Septier et al. 2009 Figs. 4-6: marginalised MCMC-PF detects 4 targets and infers two groups merging"

FULL = dict(runs=40, steps=110, particles=4000, chains=20, burn_in=1000, thinning=6)
QUICK = dict(runs=2, steps=8, particles=40, chains=10, burn_in=10, thinning=2)
BEYOND_FULL = dict(beyond_runs=10, beyond_steps=30, beyond_particles=400, beyond_burn_in=100)
BEYOND_QUICK = dict(beyond_runs=2, beyond_steps=4, beyond_particles=20, beyond_burn_in=5)
CUTOFF, ORDER = 100.0, 2.0
MERGED = 0  # row of [0, 0, 0, 0] in group_structures(4): the paper's [1 1 1 1]
#: rows of the two-groups-of-two structures [1 1 2 2], [1 2 1 2], [1 2 2 1]: slots are
#: exchangeable (a target is born into whichever slot), so "two groups of two" is any of them
PAIRS = (3, 6, 8)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add this study's options (runs, steps, particles, chains, burn-in, thinning, ``--beyond``
    and its sizes) to ``parser``; each help text shows the full and the ``--quick`` default.
    """
    parser.add_argument("--runs", type=positive_int, help="Monte Carlo runs (default 40, quick 2)")
    parser.add_argument("--steps", type=positive_int, help="time steps (default 110, quick 8)")
    parser.add_argument("--particles", type=positive_int, help="kept samples N_p (default 4000, quick 40)")
    parser.add_argument("--chains", type=positive_int, help="chains C sharing N_p (default 20, quick 10)")
    parser.add_argument("--burn-in", dest="burn_in", type=int, help="burn-in per chain (default 1000, quick 10)")
    parser.add_argument("--thinning", type=positive_int, help="thinning (default 6, quick 2)")
    parser.add_argument("--compile", action="store_true",
                        help="compile the two moves (GroupMCMCFilter(compile_step=True)): about 2.4x faster "
                             "per iteration, about 3 min to compile")
    parser.add_argument("--beyond", action="store_true", help="also run issue 11 item 4 (a) and (b)")
    for key in BEYOND_FULL:
        parser.add_argument("--" + key.replace("_", "-"), dest=key, type=positive_int)


def _config(args: argparse.Namespace) -> dict[str, int]:
    cfg = dict(QUICK if args.quick else FULL)
    cfg.update(BEYOND_QUICK if args.quick else BEYOND_FULL)
    for key in cfg:
        if getattr(args, key, None) is not None:
            cfg[key] = getattr(args, key)
    cfg["chains"] = max(d for d in range(1, min(cfg["chains"], cfg["particles"]) + 1) if cfg["particles"] % d == 0)
    return cfg


def _filter(scn: GroupMergeScenario, cfg: dict[str, int], *, particles: int | None = None, chains: int | None = None,
            burn_in: int | None = None, marginalise: bool = True, compile_step: bool = False) -> GroupMCMCFilter:
    return GroupMCMCFilter(scn.motion, scn.sensor, particles or cfg["particles"], existence=scn.existence,
                           structure_prior=scn.structure_prior, num_chains=chains or cfg["chains"],
                           burn_in=cfg["burn_in"] if burn_in is None else burn_in, thinning=cfg["thinning"],
                           xi=0.75, p_a=0.5, p_i=0.01, marginalise=marginalise, compile_step=compile_step)


def _errors(res: FilterResult, scn: GroupMergeScenario, steps: int) -> tuple[Tensor, Tensor]:
    if res.exists_prob is None:
        raise ValueError("res must carry exists_prob (a GroupMCMCFilter result), got None")
    present = res.exists_prob > 0.5
    est, true = res.mean[..., 0::2], scn.truth[:steps, ..., 0::2]
    o = metrics.ospa(est, true, c=CUTOFF, p=ORDER, x_mask=present, y_mask=scn.exists[:steps])
    g = metrics.gospa(est, true, c=CUTOFF, p=ORDER, x_mask=present, y_mask=scn.exists[:steps])
    return o, g  # (T, B)


def _run(filt: GroupMCMCFilter, scn: GroupMergeScenario, steps: int, gen: torch.Generator,
         progress: bool | None) -> tuple[FilterResult, float]:
    t0 = time.perf_counter()
    res = filt(scn.frames[:steps], init=filt.init_inactive(scn.frames.shape[1], scn.truth.shape[2]),
               generator=gen, progress=progress)
    return res, time.perf_counter() - t0


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
            span = (p.amax(0) - p.amin(0)) if p.shape[0] > 1 else torch.zeros(2)
            ax.add_patch(Ellipse((float(centre[0]), float(centre[1])), float(span[0]) + 250, float(span[1]) + 250,
                                 fill=False, color="k", lw=1))
            ax.annotate(str(int(members.sum())), (float(centre[0]), float(centre[1]) + span[1] / 2 + 150),
                        ha="center", fontsize=9)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def run(args: argparse.Namespace) -> dict:
    """Run the study (module docstring); writes into ``args.out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfg = _config(args)
    device = args.device
    gen = generator(device, args.seed)
    steps = cfg["steps"]
    scn = group_merge(cfg["runs"], generator=gen, num_steps=max(steps, 2), merge_step=min(46, max(steps, 2)))
    scn = scn._replace(motion=scn.motion.to(device), sensor=scn.sensor.to(device),
                       existence=scn.existence.to(device), structure_prior=scn.structure_prior)
    filt = _filter(scn, cfg, compile_step=bool(getattr(args, "compile", False)))
    res, seconds = _run(filt, scn, steps, gen, args.progress)
    if res.exists_prob is None:
        raise ValueError("the filter result carries no exists_prob (expected a GroupMCMCFilter result)")
    sp = res.info.extras["structure_prob"]  # (T, B, 15)
    count = res.info.extras["expected_count"]  # (T, B)
    o, g = _errors(res, scn, steps)
    merge = scn.merge_step
    merged_at = first_step_above(sp[..., MERGED], 0.5, start=merge)
    detected_at = first_step_above(count, 3.5)
    table = group_structures(4)

    # -- figures
    fig, ax = plt.subplots(figsize=(7, 7))
    modal = table[sp[:, 0].argmax(-1)]
    plot_groups(ax, scn.positions[:steps, 0, :4].cpu(), res.mean[:, 0, :, 0::2].cpu(),
                (res.exists_prob[:, 0] > 0.5).cpu(), modal)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title("run 0: tracks and the modal group structure (Fig. 4)")
    save_figure(fig, args.out, "tracks.png")

    fig, axes = plt.subplots(1, 2, figsize=(13, 4.5), sharey=True)
    steps_axis = torch.arange(1, steps + 1)
    cmap = plt.get_cmap("tab20")
    for ax, probs, title in ((axes[0], sp[:, 0], "run 0"), (axes[1], sp.mean(1), f"mean over {cfg['runs']} runs")):
        for s in range(table.shape[0]):
            lab = "[" + " ".join(str(int(v) + 1) for v in table[s]) + "]"
            ax.plot(steps_axis, probs[:, s].cpu(), color=cmap(s), lw=2.5 if s in (MERGED,) + PAIRS else 1, label=lab)
        ax.plot(steps_axis, probs[:, list(PAIRS)].sum(-1).cpu(), "k--", lw=1.5, label="two groups of two (sum)")
        ax.axvline(merge + 1, color="k", ls=":", lw=1)
        ax.set_xlabel("time step")
        ax.set_title(f"group structure probability, {title} (Fig. 5)")
    axes[0].set_ylabel("probability")
    axes[1].legend(fontsize=7, ncol=3, loc="center right")
    save_figure(fig, args.out, "structures.png")

    fig, ax = plt.subplots(figsize=(7, 4))
    ep = res.exists_prob.mean(1).cpu()  # (T, K)
    for i in range(ep.shape[1]):
        ax.plot(steps_axis, ep[:, i], lw=1, label=f"slot {i}")
    ax.plot(steps_axis, count.mean(1).cpu(), "k", lw=2, label="expected number of targets")
    ax.axhline(4, color="0.5", ls=":")
    ax.set_xlabel("time step")
    ax.set_title(f"mean existence over {cfg['runs']} runs (Fig. 6)")
    ax.legend(fontsize=8)
    save_figure(fig, args.out, "existence.png")

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    axes[0].plot(steps_axis, o.mean(1).cpu())
    axes[0].set_ylabel(f"OSPA (c = {CUTOFF:g} m, p = {ORDER:g}) [m]")
    axes[1].plot(steps_axis, g.mean(1).cpu())
    axes[1].set_ylabel(f"GOSPA (c = {CUTOFF:g} m, p = {ORDER:g}) [m]")
    for ax in axes:
        ax.set_xlabel("time step")
    save_figure(fig, args.out, "ospa.png")

    n_merged = sum(m is not None for m in merged_at)
    payload = {
        "config": cfg,
        "iterations_per_step": cfg["burn_in"] + cfg["thinning"] * cfg["particles"] // cfg["chains"],
        "seconds": seconds,
        "seconds_per_step": seconds / steps,
        "merge_step": merge + 1,
        "merged_structure_first_above_half": merged_at,
        "runs_merged": n_merged,
        "median_merge_detected_step": (sorted(m for m in merged_at if m is not None)[n_merged // 2]
                                       if n_merged else None),
        "first_step_expected_count_above_3_5": detected_at,
        "runs_detected_within_10_steps": sum(d is not None and d <= 10 for d in detected_at),
        "expected_count_step_10_mean": count[min(9, steps - 1)].mean(),
        "expected_count_per_step": count.mean(1),
        "exists_prob_per_step": res.exists_prob.mean(1),
        "structure_prob_per_step": sp.mean(1),
        "p_two_pairs_per_step": sp[..., list(PAIRS)].sum(-1).mean(1),
        "p_two_pairs_mean_steps_11_to_45": (sp[10:merge, :, list(PAIRS)].sum(-1).mean()
                                            if merge > 10 and steps > 10 else None),
        "p_merged_mean_last_20": sp[-20:, :, MERGED].mean(),
        "ospa_per_step": o.mean(1), "gospa_per_step": g.mean(1),
        "ospa": o.mean(), "gospa": g.mean(),
        "acceptance": {k: v.nanmean() for k, v in res.info.extras.items() if k.startswith("acceptance")},
    }
    write_metrics(args.out, payload, args=args, device=device)  # kept if item 4 is interrupted
    if getattr(args, "beyond", False):
        payload["beyond"] = _beyond(scn, cfg, gen, args.progress)
        write_metrics(args.out, payload, args=args, device=device)
    return payload


def _beyond(scn: GroupMergeScenario, cfg: dict[str, int], gen: torch.Generator, progress: bool | None
            ) -> dict[str, Any]:
    """Issue 11 item 4 on the first ``beyond_runs`` runs and ``beyond_steps`` steps."""
    r, steps, n, burn = cfg["beyond_runs"], cfg["beyond_steps"], cfg["beyond_particles"], cfg["beyond_burn_in"]
    sub = scn._replace(truth=scn.truth[:, :r], exists=scn.exists[:, :r], frames=scn.frames[:, :r])
    chains = max(d for d in range(1, min(cfg["chains"], n) + 1) if n % d == 0)
    out: dict[str, Any] = {"runs": r, "steps": steps, "particles": n, "burn_in": burn, "chains": chains,
                           "thinning": cfg["thinning"]}
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
    total = chains * burn + cfg["thinning"] * n
    for name, c, b in (("C_chains", chains, burn), ("one_chain", 1, total - cfg["thinning"] * n)):
        res, sec = _run(_filter(sub, cfg, particles=n, chains=c, burn_in=b), sub, steps, gen, progress)
        o, _ = _errors(res, sub, steps)
        per_run = o[start:].mean(0)
        out[name] = {"chains": c, "burn_in": b, "seconds": sec, "ospa_mean": per_run.mean(),
                     "ospa_std_over_runs": per_run.std(), "expected_count_final": res.info.extras["expected_count"][-1]}
    return out
