"""Long runs: do the tracks hold? (issue 22; replaces benchmarks/soak.py of issue 14).

Two scenes, each filtered in chunks of ``--every`` steps (the particle state of one chunk is
the ``init`` of the next, so a run is one uninterrupted filter; frames are simulated chunk by
chunk, so memory does not grow with the length):

- ``fixed``: the ground-radar TBD scene of paper 000 with ``--targets`` targets (10) at
  speeds up to ``--max-speed`` (1 m/s, so that they stay on the grid for hundreds of steps;
  slow targets stay close together for long, which is where tracks coalesce). The truth is
  noise-free constant velocity; the filters' motion model has ``q = --q``: 1 by default
  (paper 000's, the setting of Table II), more process noise than the truth needs (a truth
  with that much noise would leave the grid within tens of steps); ``--q 0.01`` is the
  filter matched to the truth (as near to its ``q = 0`` as a particle cloud can keep).
  Scored per chunk by the per-step assignment RMSE (labels matched at every step: a label
  swap costs nothing, a lost target does), and over the run by the longest stretch a
  target has no slot estimate within 20 m and the identity switches. Next to them two
  references: the posterior Cramer-Rao bound of each target alone with its amplitude known
  (:func:`~torchmcmcpf.metrics.pcrb_position_rmse` at the mid-run truth; a bound for
  trajectories that move as the filters' model says, which the noise-free truth does not, so
  a filter may go below it), and the *clairvoyant reference* on the same frames: each
  target's own particle filter (``Np`` particles, the filters' count) weighted with every
  other target at its true state, what the data allow a tracker that never confuses the
  targets. A target this reference holds and a filter loses is lost to the association, not
  to the SNR or ``q``.
- ``birth-death``: the Septier et al. scene (:func:`~torchmcmcpf.scenarios.septier`) with
  ``--targets`` slots, births and deaths in clutter; scored per chunk by OSPA (c = 100 m,
  p = 2) split into its localisation and cardinality parts.

Filters: the IP-MCMC-PF with the library's defaults (exclusion and re-capture) and as in
paper 000 (``exclusion=None, recapture=None``), Np particles in ``Np / 10`` chains, burn-in
``--burn-in``; the MCMC-PF with its defaults (joint draws from the previous cloud, no
factorised prior), Np particles in ``Np / 2`` chains after half that burn-in, as the
crossing study runs it; on the fixed scene also the partitioned PF (Orton and Fitzgerald 2002, with
exclusion and re-capture; :class:`~torchmcmcpf.filters.partitioned.PartitionedSIRFilter`) with the same Np,
a reference of another kind on the same frames (it has no births and deaths), and the
IP-MCMC-PF with joint pairs (``joint_pairs=1.5``, as the crossing study runs it). Also: seconds
per step and the non-finite values in the estimates (must be 0).

Writes ``metrics.json`` and ``soak.png`` (error per chunk for each filter and scene). Shards
of ``--shard-size`` runs, each with the generator of ``(seed, shard index)``; within a shard
the scenes are drawn from it, then the frames and each filter get a stream of their own
(:func:`~torchmcmcpf.experiments._shards.streams`), so that every filter sees the same frames
and no filter's figures depend on which filters ran before it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch

from .. import metrics
from ..filters.ipmcmc import IPMCMCFilter
from ..filters.mcmc import MCMCFilter
from ..filters.partitioned import PartitionedSIRFilter, clairvoyant_partitions
from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath
from ..typing import VX, VY, X, Y
from ._figures import np_label, pyplot, save_figure
from ._shards import Shards, streams
from ._study import Settings, StepTimer, Study, in_order, option, rows_option
from .crossing import JOINT_PAIRS

FILTERS = ("IP-MCMC-PF", "IP-MCMC-PF (paper)", "MCMC-PF")
JOINT = "IP-MCMC-PF (joint pairs)"  # known number of targets only
FIXED_FILTERS = FILTERS + ("partitioned PF", JOINT)  # the fixed scene's: known number of targets only
CLAIRVOYANT = "clairvoyant reference"  # each target's own PF (Np particles) with the others known
SCENES = ("fixed", "birth-death")
ROWS = FIXED_FILTERS + (CLAIRVOYANT,)  # every row (the fixed scene's; the births/deaths scene has FILTERS)
COVER, CUTOFF, ORDER = 20.0, 100.0, 2.0
FLOOR_FRAMES, FLOOR_SEED = 200, 0  # frames per target of the floor's Fisher information, their seed


@dataclass(frozen=True)
class SoakSettings(Settings):
    """The settings of :class:`Soak` (full values; the second of each pair: ``--quick``)."""

    runs: int = option(5, 1, help="Monte Carlo runs of each scene")
    steps: int = option(200, 10, help="time steps")
    every: int = option(20, 5, help="steps per chunk (the reporting period)")
    particles: int = option(500, 100, help="particles Np (a multiple of 10)")
    burn_in: int = option(100, 20, help="IP-MCMC-PF burn-in (the MCMC-PF's: half)")
    targets: int = option(10, 3, help="targets (fixed) / slots (birth-death)")
    max_speed: float = option(1.0, 1.0, help="fixed scene: largest target speed [m/s]")
    q: float = option(1.0, 1.0, help="fixed scene: the filters' acceleration noise q [m^2 s^-3] (1: paper 000's; the "
                                     "truth has none, so a small q is the filter matched to it)")
    shard_size: int = option(5, 1, cli=False)
    filters: tuple[str, ...] = rows_option(ROWS)
    scenes: tuple[str, ...] = option(SCENES, choices=SCENES, metavar="SCENE",
                                     help="the scenes to run, among 'fixed', 'birth-death' (default both)")

    def __post_init__(self) -> None:
        object.__setattr__(self, "filters", in_order(ROWS, self.filters))
        object.__setattr__(self, "scenes", in_order(SCENES, self.scenes))
        if not self.filters or not self.scenes:
            raise ValueError(f"arguments --filters and --scenes: expected at least one of each, got "
                             f"{list(self.filters)} and {list(self.scenes)}")
        if self.particles % 10:
            raise ValueError(f"argument --particles: {self.particles} is not a multiple of 10 (the IP-MCMC-PF's "
                             "chains)")
        if not (math.isfinite(self.max_speed) and self.max_speed > 0):
            raise ValueError(f"argument --max-speed: expected a speed > 0, got {self.max_speed}")
        if not (math.isfinite(self.q) and self.q > 0):
            raise ValueError(f"argument --q: expected a noise level > 0, got {self.q}")


def _filters(cfg: SoakSettings, motion: MotionModel, sensor: SensorModel, existence: BirthDeath | None = None) -> dict:
    n = cfg.particles
    kw: dict[str, Any] = dict(num_chains=n // 10, burn_in=cfg.burn_in, existence=existence)
    filters: dict[str, Any] = {"IP-MCMC-PF": IPMCMCFilter(motion, sensor, n, **kw),
                               "IP-MCMC-PF (paper)": IPMCMCFilter(motion, sensor, n, exclusion=None, recapture=None,
                                                                  **kw),
                               "MCMC-PF": MCMCFilter(motion, sensor, n, num_chains=n // 2, burn_in=cfg.burn_in // 2,
                                                     existence=existence)}
    if existence is None:
        filters["partitioned PF"] = PartitionedSIRFilter(motion, sensor, n)
        filters[JOINT] = IPMCMCFilter(motion, sensor, n, joint_pairs=JOINT_PAIRS, **kw)
    return filters


def _chunks(steps: int, every: int) -> list[slice]:
    return [slice(a, min(a + every, steps)) for a in range(0, steps, every)]


def _fixed(cfg: SoakSettings, b: int, generator: torch.Generator, device: torch.device,
           progress: bool) -> tuple[dict, dict, tuple | None]:
    from ..scenarios import ground_radar

    # the grid and models from one run over the whole length (so the grid covers every
    # target's travel), the B runs' initial states from the same Table I law
    geometry = ground_radar(cfg.targets, cfg.steps, 1, generator=generator, device=device,
                            speed_limits=(0.0, cfg.max_speed), q=cfg.q)
    scn = ground_radar(cfg.targets, 1, b, generator=generator, device=device,
                       speed_limits=(0.0, cfg.max_speed))
    sensor, motion, x0 = geometry.sensor, geometry.motion, scn.initial
    init = scn.initial_particles(cfg.particles, generator=generator)
    names = tuple(r for r in ROWS if r in cfg.filters and "fixed" in cfg.scenes)
    filters = {k: f for k, f in _filters(cfg, motion, sensor).items() if k in names}
    gens = streams(generator, ("frames",) + names)  # every filter sees the same frames
    states: dict = {name: None for name in filters}
    states[CLAIRVOYANT] = init
    means: dict = {name: [] for name in names}
    seconds: dict = {}
    truths = []
    for part in _chunks(cfg.steps, cfg.every) if names else ():  # the scene is drawn either way
        t = torch.arange(part.start + 1, part.stop + 1, device=device, dtype=x0.dtype)
        truth = x0.expand(t.numel(), *x0.shape).clone()  # truth[t] = x0 moved t + 1 steps
        truth[..., X] = x0[..., X] + t[:, None, None] * x0[..., VX]
        truth[..., Y] = x0[..., Y] + t[:, None, None] * x0[..., VY]
        truths.append(truth)
        frames = torch.stack([sensor.simulate(truth[i], generator=gens["frames"]) for i in range(t.numel())])
        for name, filt in filters.items():
            with StepTimer(device, t.numel()) as timer:
                res = filt(frames, init=init if states[name] is None else states[name], generator=gens[name],
                           progress=progress)
            seconds[f"fixed|{name}"] = seconds.get(f"fixed|{name}", 0.0) + timer.seconds
            states[name] = res.state
            means[name].append(res.mean)
        if CLAIRVOYANT in names:
            with StepTimer(device, t.numel()) as timer:
                states[CLAIRVOYANT], mean = clairvoyant_partitions(frames, truth, states[CLAIRVOYANT], motion=motion,
                                                                   sensor=sensor, generator=gens[CLAIRVOYANT])
            seconds[f"fixed|{CLAIRVOYANT}"] = seconds.get(f"fixed|{CLAIRVOYANT}", 0.0) + timer.seconds
            means[CLAIRVOYANT].append(mean)
    if not names:
        return {}, {}, None
    truth = torch.cat(truths)
    out: dict = {}
    for name in names:
        mean = torch.cat(means[name])  # (T, B, K, D)
        matched, _ = metrics.match_tracks(mean, truth, per_step=True)
        out[f"fixed|{name}|matched_error"] = metrics.position_error(matched, truth).square().mean(-1).sqrt().T
        cover = metrics.slot_coverage(mean, truth, radius=COVER)
        out[f"fixed|{name}|longest_uncovered"] = metrics.longest_run(cover == 0).amax(-1)  # (B,)
        out[f"fixed|{name}|switches"] = metrics.identity_switches(mean, truth)
        out[f"fixed|{name}|non_finite"] = (~torch.isfinite(mean)).sum((0, 2, 3))
    # the floor's inputs: the models and the truth at mid-run
    return out, seconds, (sensor, motion, truth[truth.shape[0] // 2])


def _birth_death(cfg: SoakSettings, b: int, generator: torch.Generator, device: torch.device,
                 progress: bool) -> tuple[dict, dict]:
    from ..scenarios.septier import septier

    if "birth-death" not in cfg.scenes or not set(FILTERS) & set(cfg.filters):
        return {}, {}
    scn = septier(b, cfg.steps, generator=generator, num_slots=cfg.targets)
    motion, sensor, existence = scn.motion.to(device), scn.sensor.to(device), scn.existence.to(device)
    init = torch.zeros((b, cfg.particles, cfg.targets, 4), dtype=torch.float64, device=device)
    out: dict = {}
    seconds: dict = {}
    gens = streams(generator, FILTERS)
    for name, filt in ((k, f) for k, f in _filters(cfg, motion, sensor, existence).items() if k in cfg.filters):
        state, parts, counts = None, [], []
        for part in _chunks(cfg.steps, cfg.every):
            z = type(scn.measurements)(*(f[part].to(device) for f in scn.measurements))
            with StepTimer(device, part.stop - part.start) as timer:
                res = filt(z, init=init if state is None else state, generator=gens[name], progress=progress)
            seconds[name] = seconds.get(name, 0.0) + timer.seconds
            state = res.state
            present = res.exists_prob > 0.5
            truth, alive = scn.truth[part].to(device), scn.alive[part].to(device)
            o = metrics.ospa_parts(res.mean[..., [X, Y]], truth[..., [X, Y]], c=CUTOFF, p=ORDER, x_mask=present,
                                   y_mask=alive)
            parts.append(torch.stack(list(o), -1))  # (t, B, 3): total, localisation, cardinality
            counts.append(metrics.cardinality_error(res.exists_prob.sum(-1), alive.sum(-1)))
        out[f"birth-death|{name}|ospa"] = torch.cat(parts).movedim(1, 0)  # (B, T, 3)
        out[f"birth-death|{name}|cardinality_error"] = torch.cat(counts).T  # (B, T)
    return out, {f"birth-death|{k}": v for k, v in seconds.items()}


class Soak(Study[SoakSettings]):
    """Long runs: do the tracks hold? (module docstring)."""

    name = "soak"
    description = ("long runs (issue 22): per-step assignment RMSE and uncovered targets over 200 steps of 10 slow "
                   "radar targets, OSPA over a births/deaths scene, with and without exclusion and re-capture")
    outputs = ("metrics.json", "soak.png", "shards")

    def run_shard(self, cfg: SoakSettings, runs: range, *, generator: torch.Generator, device: torch.device,
                  progress: bool = False) -> tuple[dict, dict]:
        """Both scenes for the runs ``runs`` (module docstring).

        Returns
        -------
        ``per_run``: ``"fixed|f|matched_error"`` ``(R, T)``, ``"fixed|f|longest_uncovered"``,
        ``"fixed|f|switches"``, ``"fixed|f|non_finite"`` ``(R,)``, ``"birth-death|f|ospa"``
        ``(R, T, 3)`` (total, localisation, cardinality), ``"birth-death|f|cardinality_error"``
        ``(R, T)``, ``"fixed|floor"`` ``(R, J)`` each target's floor
        (:func:`~torchmcmcpf.metrics.pcrb_position_rmse` at mid-run); ``seconds`` per scene
        and filter.
        """
        fixed, s1, models = _fixed(cfg, len(runs), generator, device, progress)
        bd, s2 = _birth_death(cfg, len(runs), generator, device, progress)
        if models is not None:  # a property of the scene, not of a run: its frames from a generator of their own
            sensor, motion, mid = models
            fixed["fixed|floor"] = metrics.pcrb_position_rmse(sensor, motion, mid, num_frames=FLOOR_FRAMES,
                                                              generator=torch.Generator(device).manual_seed(FLOOR_SEED))
        return {**fixed, **bd}, {**s1, **s2}

    @staticmethod
    def aggregate(cfg: SoakSettings, per_run: dict, seconds: dict) -> dict:
        """Per scene and filter: chunk rows and the acceptance figures of issue 22."""
        chunks = _chunks(cfg.steps, cfg.every)
        results: dict = {"fixed": {}, "birth-death": {}}
        if "fixed|floor" in per_run:
            floor = per_run["fixed|floor"]  # (R, J)
            results["fixed_floor"] = {"per_run": floor.square().mean(-1).sqrt(),
                                      "all": float(floor.square().mean().sqrt())}
        for name in (r for r in ROWS if f"fixed|{r}|matched_error" in per_run):  # the rows that ran
            err = per_run[f"fixed|{name}|matched_error"]  # (R, T)
            rows = [float(err[:, c].square().mean().sqrt()) for c in chunks]
            results["fixed"][name] = {
                "chunks": [f"{c.start + 1}-{c.stop}" for c in chunks],
                "matched_rmse_per_chunk": rows,
                "matched_rmse_per_step": err.square().mean(0).sqrt(),
                "longest_uncovered_per_run": per_run[f"fixed|{name}|longest_uncovered"],
                "identity_switches_per_run": per_run[f"fixed|{name}|switches"],
                "non_finite": int(per_run[f"fixed|{name}|non_finite"].sum()),
                "last_over_second_chunk": rows[-1] / rows[1] if len(rows) > 1 and rows[1] > 0 else None,
                "seconds_per_step": seconds[f"fixed|{name}"] / cfg.steps,
            }
        for name in (r for r in FILTERS if f"birth-death|{r}|ospa" in per_run):
            o = per_run[f"birth-death|{name}|ospa"]  # (R, T, 3)
            results["birth-death"][name] = {
                "chunks": [f"{c.start + 1}-{c.stop}" for c in chunks],
                "ospa_per_chunk": [[float(v) for v in o[:, c].mean((0, 1))] for c in chunks],
                "ospa_per_step": o[..., 0].mean(0),
                "cardinality_error": per_run[f"birth-death|{name}|cardinality_error"].mean(),
                "seconds_per_step": seconds[f"birth-death|{name}"] / cfg.steps,
            }
        return results

    def summary(self, payload: dict) -> str:
        """Headline tables: per-step assignment RMSE per chunk (fixed), OSPA parts per chunk
        (birth-death).
        """
        fixed, bd = payload["results"]["fixed"], payload["results"]["birth-death"]
        q = payload["config"]["q"]
        lines: list[str] = []
        if fixed:
            chunks = next(iter(fixed.values()))["chunks"]
            lines += [f"fixed (filters' q = {q:g}, noise-free truth): per-step assignment RMSE [m] per chunk; longest "
                      "uncovered stretch (steps, worst run); identity switches per run",
                      "| filter | " + " | ".join(chunks) + " | longest uncovered | switches / run | s / step |",
                      "|---" * (len(chunks) + 4) + "|"]
            for name, r in fixed.items():
                lines.append(f"| {name} | " + " | ".join(f"{v:.2f}" for v in r["matched_rmse_per_chunk"])
                             + f" | {int(r['longest_uncovered_per_run'].max())} | "
                             f"{float(r['identity_switches_per_run'].double().mean()):.1f} | "
                             f"{r['seconds_per_step']:.2f} |")
            floor = payload["results"]["fixed_floor"]["all"]
            lines.append(f"PCRB (each target alone, on trajectories with the filters' q; metrics.pcrb_position_rmse): "
                         f"{floor:.2f} m; the noise-free truth can be tracked below it (the clairvoyant reference)")
        if bd:
            chunks = next(iter(bd.values()))["chunks"]
            lines += ["", "birth-death: OSPA [m] per chunk, total (localisation / cardinality)",
                      "| filter | " + " | ".join(chunks) + " | s / step |", "|---" * (len(chunks) + 2) + "|"]
            for name, r in bd.items():
                parts = " | ".join(f"{t:.1f} ({lo:.1f} / {c:.1f})" for t, lo, c in r["ospa_per_chunk"])
                lines.append(f"| {name} | " + parts + f" | {r['seconds_per_step']:.2f} |")
        return "\n".join(lines) + "\n"

    def summarise(self, cfg: SoakSettings, shards: Shards, out: Path) -> dict:
        """Per scene and filter results, and ``soak.png`` (module docstring)."""
        from ..plotting import plot_rmse

        plt = pyplot()
        results = self.aggregate(cfg, shards.per_run, shards.seconds)
        n, quick = cfg.particles, " (quick)" if cfg.quick else ""
        runs = next(iter(shards.per_run.values())).shape[0]
        panels = [scene for scene in SCENES if results[scene]]  # one panel per scene that ran
        fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4.5), layout="constrained", squeeze=False)
        for ax, scene in zip(axes[0], panels):
            if scene == "fixed":
                plot_rmse(ax, {np_label(k, n): r["matched_rmse_per_step"] for k, r in results["fixed"].items()},
                          ylabel="per-step assignment RMSE [m]")
                ax.axhline(results["fixed_floor"]["all"], color="0.4", linestyle="--",
                           label="PCRB (trajectories with the filters' q)")
                ax.legend()
                ax.set_title(f"fixed: {cfg.targets} radar targets, filters' q = {cfg.q:g}, {runs} runs")
            else:
                plot_rmse(ax, {np_label(k, n): r["ospa_per_step"] for k, r in results["birth-death"].items()},
                          ylabel=f"OSPA (c = {CUTOFF:g} m, p = {ORDER:g}) [m]")
                ax.set_title(f"birth-death: {cfg.targets} slots, {runs} runs")
        fig.suptitle(f"soak: {cfg.steps} steps{quick}")
        save_figure(fig, out, "soak.png", quick=cfg.quick)
        return {"config": asdict(cfg), "results": results}


STUDY = Soak()
