"""Tracks that hold through an unresolved crossing, and re-capture after coalescence (issue 22).

Two scenes of the range-doppler-bearing radar of paper 000 (:func:`~torchmcmcpf.scenarios.crossing`):

- **crossing**: two targets (18.9 and 13.5 dB) pass each other 2 m apart at step 20, slowly
  (0.5 m/s), within one doppler cell, so they stay unresolved in range, doppler and bearing
  for tens of steps; the filters' motion model has ``q = 1`` (far more process noise than
  the noise-free truth needs: velocity cannot carry a slot's identity through the crossing).
  Scored per run: whether some target has no slot estimate within 20 m at a step ``>= 50``
  (*uncovered*: lost, whatever the labels), whether two slot estimates sit within 10 m of
  one target at a step ``>= 50`` (*shared*: both slots on one target), the per-step
  assignment RMSE (a label swap costs nothing) and the identity switches.
- **whose gap**: for each run with a target uncovered at a step ``>= from_step``, the maximum
  of the model's own posterior over those frames (:func:`~torchmcmcpf.metrics.map_trajectory`,
  the filters' motion model and the radar's likelihood, no particles) is found from the
  filter's estimate and from the truth. The gap is *the model's* when the maximum found from
  the estimate still leaves a target uncovered and its log posterior is within ``GAP_ODDS`` (3
  nats) of the truth's (the data and the model support the estimate about as well as the
  truth: an exact filter could hold it too); otherwise *the filter's* (the estimate lies on
  no mode, or on one far less probable than the truth's).
- **coalescence** (staged): the same two targets 150 m apart (always resolved), every
  particle starting with *both* slots on the strong target; scored by whether a slot comes
  within 10 m of the weak target within ``coalesce_steps`` steps, and when. A filter whose
  proposals only come from each slot's own prediction cannot do it (the weak target lies
  hundreds of standard deviations outside that prediction); the data-driven re-capture of
  :mod:`torchmcmcpf.models.multitarget` can.

Filters (every one with ``Np`` particles): the IP-MCMC-PF with the library's defaults
(exclusion and re-capture), the IP-MCMC-PF of paper 000 (``exclusion=None, recapture=None``:
the factorised target and the plain exchange move), the MCMC-PF with its defaults, the
independent-partition PF (with exclusion and re-capture), the IP-MCMC-PF with the
triggered pair-path move (:mod:`torchmcmcpf.kernels.pair_path`, ``PairPath()``; issue 50),
and the IP-MCMC-PF whose close pairs keep their joint prediction (``joint_pairs=1.5``;
:mod:`torchmcmcpf.filters.ipmcmc`, "Joint pairs").
A second table gives per filter the late-gap runs with their 95 % Clopper-Pearson interval,
the uncovered target-steps at ``t >= from_step``, the longest gap, an exact McNemar test of
the late-gap runs against the defaults on the same scenes, the pair-path move's firing
rate and the share of its re-drawn paths that changed, and the share of late steps with the
slots on each other's targets (:func:`~torchmcmcpf.metrics.amplitude_swapped`: the slot of the
largest amplitude nearest another target) in the late-gap runs and in the others. Next to
them, on the crossing scene, the *clairvoyant reference*
(:func:`~torchmcmcpf.filters.partitioned.clairvoyant_partitions`): each target's own PF
weighted with the other at its true state, what the data allow a tracker that knows the
association (it has no coalescence column: it reads the truth and has no data-driven move).

Writes ``metrics.json``, ``crossing.png`` (uncovered runs and per-step assignment RMSE over
time per filter), ``coalescence.png`` (share of runs that have re-captured the weak target
against the step) and ``tracks.png`` (run 0 of the crossing). Shards of ``--shard-size``
runs (5, quick 1), each with the generator of ``(seed, shard index)``; the scenes are drawn
from it, then each filter (and the reference) gets a stream of its own for both scenes
(:func:`~torchmcmcpf.experiments._shards.streams`), so that no filter's figures depend on
which filters ran before it, and ``--filters`` runs some rows only, each the same bits as in
the whole study.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from .. import metrics
from ..filters.ipmcmc import IPMCMCFilter
from ..filters.mcmc import MCMCFilter
from ..filters.partitioned import PartitionedSIRFilter, clairvoyant_partitions
from ..kernels.pair_path import PairPath
from ..models.base import MotionModel, SensorModel
from ..models.multitarget import Exclusion
from ..scenarios._common import Scenario
from ..scenarios.crossing import crossing
from ..typing import Tensor
from ._figures import np_label, pyplot, save_figure
from ._shards import Shards, streams
from ._study import Settings, StepTimer, Study, cell, in_order, option, rows_option

FILTERS = ("IP-MCMC-PF", "IP-MCMC-PF (paper)", "MCMC-PF", "partitioned PF", "IP-MCMC-PF (pair path)",
           "IP-MCMC-PF (joint pairs)")
JOINT_PAIRS = 1.5  # [resolution cells] the joint-pairs rows (docs/tracks.md: 1.5 and 3 hold the same runs)
CLAIRVOYANT = "clairvoyant reference"  # each target's PF with the other at its true state (crossing scene only)
ROWS = FILTERS + (CLAIRVOYANT,)
COVER, SHARE, RECAPTURE = 20.0, 10.0, 10.0  # [m]: "uncovered", "shared" and "re-captured" radii
GAP_ODDS = 3.0  # [nats] a late gap is the model's when its posterior maximum is within this of the truth's


def _binomial_cdf(k: int, n: int, p: float) -> float:
    """``P(X <= k)`` for ``X ~ Binomial(n, p)`` (exact sum, small ``n``)."""
    return sum(math.comb(n, i) * p ** i * (1.0 - p) ** (n - i) for i in range(0, k + 1)) if k >= 0 else 0.0


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """The exact (Clopper and Pearson 1934) interval of a binomial rate from ``k`` of ``n``:
    ``(lower, upper)`` with ``P(X >= k | lower) = P(X <= k | upper) = (1 - level) / 2``,
    by bisection on the exact binomial tail.

    >>> [round(v, 3) for v in clopper_pearson(15, 60)]
    [0.147, 0.379]
    """
    alpha = (1.0 - level) / 2.0

    def solve(f, target):  # f increasing in p on [0, 1]
        lo, hi = 0.0, 1.0
        for _ in range(60):
            mid = (lo + hi) / 2.0
            lo, hi = (mid, hi) if f(mid) < target else (lo, mid)
        return (lo + hi) / 2.0

    lower = 0.0 if k == 0 else solve(lambda p: 1.0 - _binomial_cdf(k - 1, n, p), alpha)
    upper = 1.0 if k == n else solve(lambda p: -_binomial_cdf(k, n, p), -alpha)
    return lower, upper


def mcnemar_exact(only_first: int, only_second: int) -> float:
    """Two-sided exact McNemar test of paired binary outcomes: the discordant pairs
    (``only_first`` runs with the event under the first filter only, ``only_second`` under
    the second only) against ``Binomial(b + c, 1/2)``; returns the p-value.

    >>> round(mcnemar_exact(6, 0), 4), mcnemar_exact(2, 2)
    (0.0312, 1.0)
    """
    n = only_first + only_second
    return min(1.0, 2.0 * _binomial_cdf(min(only_first, only_second), n, 0.5)) if n else 1.0


@dataclass(frozen=True)
class CrossingSettings(Settings):
    """The settings of :class:`Crossing` (full values; the second of each pair: ``--quick``)."""

    runs: int = option(20, 2, help="Monte Carlo runs of each scene")
    steps: int = option(80, 60, help="time steps of the crossing")
    particles: int = option(500, 100, help="particles Np (a multiple of 10)")
    burn_in: int = option(100, 20, help="MCMC burn-in per step")
    shard_size: int = option(5, 1, cli=False)
    coalesce_steps: int = option(20, 8, help="time steps of the coalescence scene")
    # the targets cross at step 20 and stay unresolved until about step 45: a count from the
    # crossing itself (the quick value was 20) sees two slots on one target in every filter
    from_step: int = option(50, help="first step at which uncovered and shared targets count")
    map_iterations: int = option(1000, 100, cli=False)  # L-BFGS iterations of a late gap's check
    filters: tuple[str, ...] = rows_option(ROWS)

    def __post_init__(self) -> None:
        object.__setattr__(self, "filters", in_order(ROWS, self.filters))
        if not self.filters:
            raise ValueError("argument --filters: expected at least one row, got none")
        if self.particles % 10:
            raise ValueError(f"argument --particles: {self.particles} is not a multiple of 10 (the IP-MCMC-PF's "
                             "chains)")


def _filters(cfg: CrossingSettings, motion: MotionModel, sensor: SensorModel) -> dict:
    n, burn_in = cfg.particles, cfg.burn_in
    chains = n // 10
    return {
        "IP-MCMC-PF": IPMCMCFilter(motion, sensor, n, num_chains=chains, burn_in=burn_in),
        "IP-MCMC-PF (paper)": IPMCMCFilter(motion, sensor, n, num_chains=chains, burn_in=burn_in, exclusion=None,
                                           recapture=None),
        "MCMC-PF": MCMCFilter(motion, sensor, n, num_chains=n // 2, burn_in=burn_in // 2),
        "partitioned PF": PartitionedSIRFilter(motion, sensor, n),
        "IP-MCMC-PF (pair path)": IPMCMCFilter(motion, sensor, n, num_chains=chains, burn_in=burn_in,
                                               pair_path=PairPath()),
        "IP-MCMC-PF (joint pairs)": IPMCMCFilter(motion, sensor, n, num_chains=chains, burn_in=burn_in,
                                                 joint_pairs=JOINT_PAIRS),
    }


def _late_check(cfg: CrossingSettings, name: str, mean: Tensor, scn: Scenario, exclusion: Exclusion | None
                ) -> dict:
    """Whose is a late gap: for each run with a target uncovered at a step ``>= from_step``,
    the maximum of the model's own posterior over frames ``from_step ..`` (
    :func:`~torchmcmcpf.metrics.map_trajectory`, with the filter's ``exclusion`` factor) found
    from the filter's estimate and from the truth. ``"f|gap_log_odds"`` ``(R,)``: the second's
    log posterior minus the first's (NaN for a run without a late gap); ``"f|gap_map_covers"``
    ``(R,)`` bool: the maximum found from the estimate has a slot within 20 m of every target at
    every late step (the estimate lies on no mode of the posterior: the gap is the filter's).
    """
    late = slice(cfg.from_step, None)
    gap = (metrics.slot_coverage(mean[late], scn.truth[late], radius=COVER) == 0).any(-1).any(0)  # (R,)
    odds = torch.full(gap.shape, float("nan"), dtype=torch.float64)
    covers = torch.zeros(gap.shape, dtype=torch.bool)
    runs = gap.nonzero().squeeze(1)
    if runs.numel():  # both starts in one batch of 2 r runs
        start = torch.cat([mean[late][:, runs], scn.truth[late][:, runs]], 1).double()
        z = scn.measurements[late][:, torch.cat([runs, runs])]
        found = metrics.map_trajectory(scn.sensor, scn.motion, z, start, exclusion=exclusion,
                                       max_iter=cfg.map_iterations)
        r = runs.numel()
        odds[runs.cpu()] = (found.log_posterior[r:] - found.log_posterior[:r]).cpu()  # odds, covers: CPU results
        cover = metrics.slot_coverage(found.x[:, :r], scn.truth[late][:, runs].double(), radius=COVER)
        covers[runs.cpu()] = (cover > 0).all(-1).all(0).cpu()
    return {f"{name}|gap_log_odds": odds, f"{name}|gap_map_covers": covers}


def _share(flags: Tensor, runs: Tensor) -> float:
    """The mean of ``flags (R, T)`` over the runs where ``runs (R,)`` (NaN for none)."""
    return float(flags[runs].double().mean()) if bool(runs.any()) else math.nan


def _scores(name: str, mean: Tensor, truth: Tensor) -> dict:
    """The crossing scene's per-run figures of one estimate ``mean (T, B, K, D)`` against
    ``truth (T, B, K, D)`` (keys ``"name|coverage"`` ... of :meth:`Crossing.run_shard`).
    """
    matched, _ = metrics.match_tracks(mean, truth, per_step=True)
    return {f"{name}|coverage": metrics.slot_coverage(mean, truth, radius=COVER).movedim(1, 0),
            f"{name}|shared": metrics.slot_coverage(mean, truth, radius=SHARE).movedim(1, 0),
            f"{name}|matched_error": metrics.position_error(matched, truth).square().mean(-1).sqrt().T,
            f"{name}|switches": metrics.identity_switches(mean, truth),
            f"{name}|estimate": mean.movedim(1, 0)}


class Crossing(Study[CrossingSettings]):
    """Two targets crossing unresolved, and re-capture after coalescence (module docstring)."""

    name = "crossing"
    description = ("targets crossing unresolved and re-capture after coalescence: uncovered and shared targets, "
                   "per-step assignment RMSE, identity switches, with and without exclusion and re-capture")
    outputs = ("metrics.json", "crossing.png", "coalescence.png", "tracks.png", "shards")

    def run_shard(self, cfg: CrossingSettings, runs: range, *, generator: torch.Generator, device: torch.device,
                  progress: bool = False) -> tuple[dict, dict]:
        """Simulate both scenes for the runs ``runs`` and filter them with every filter.

        Returns
        -------
        ``per_run`` with ``"truth"`` ``(R, T, 2, 5)`` and per filter ``f``: ``"f|coverage"``
        ``(R, T, 2)`` (slots within 20 m of each target), ``"f|shared"`` ``(R, T, 2)`` (within
        10 m), ``"f|matched_error"`` ``(R, T)`` (per-step assignment position RMSE over the two
        targets), ``"f|switches"`` ``(R,)``, ``"f|estimate"`` ``(R, T, 2, 5)``,
        ``"f|gap_log_odds"`` and ``"f|gap_map_covers"`` ``(R,)`` (:func:`_late_check`) and
        ``"f|recaptured"`` ``(R, T_c)`` (a slot within 10 m of the weak target in the
        coalescence scene); ``seconds`` per filter (crossing scene).
        """
        b = len(runs)
        scn = crossing(2, cfg.steps, b, generator=generator, device=device)
        init = scn.initial_particles(cfg.particles, generator=generator)
        far = crossing(2, cfg.coalesce_steps, b, generator=generator, device=device, miss_distance=150.0,
                       crossing_step=cfg.coalesce_steps // 2)
        coalesced = far.initial_particles(cfg.particles, generator=generator)
        coalesced[:, :, 1] = coalesced[:, :, 0]  # both slots on the strong target, the weak one uncovered
        per_run: dict = {"truth": scn.truth.movedim(1, 0)}
        seconds = {}
        on_far = _filters(cfg, far.motion, far.sensor)  # the coalescence scene has its own grid
        filters = {k: f for k, f in _filters(cfg, scn.motion, scn.sensor).items() if k in cfg.filters}
        gens = streams(generator, ROWS)  # no filter's figures depend on the others
        for name, filt in filters.items():
            with StepTimer(device, cfg.steps) as timer:
                res = filt(scn.measurements, init=init, generator=gens[name], progress=progress)
            seconds[name] = timer.seconds
            per_run.update(_scores(name, res.mean, scn.truth))
            if "pair_path_fired" in res.info.extras:  # (T, B): the move's trigger and its effect
                per_run[f"{name}|pair_path_fired"] = res.info.extras["pair_path_fired"].T
                per_run[f"{name}|pair_path_moved"] = res.info.extras["pair_path_moved"].T
            per_run.update(_late_check(cfg, name, res.mean, scn, filt.settings.exclusion))
            res = on_far[name](far.measurements, init=coalesced, generator=gens[name])
            weak = far.truth[:, :, 1:]  # (T, B, 1, D)
            per_run[f"{name}|recaptured"] = (metrics.slot_coverage(res.mean, weak, radius=RECAPTURE)[..., 0] > 0).T
        if CLAIRVOYANT not in cfg.filters:
            return per_run, seconds
        with StepTimer(device, cfg.steps) as timer:  # what the data allow with the association known
            _, mean = clairvoyant_partitions(scn.measurements, scn.truth, init, motion=scn.motion, sensor=scn.sensor,
                                             generator=gens[CLAIRVOYANT])
        seconds[CLAIRVOYANT] = timer.seconds
        per_run.update(_scores(CLAIRVOYANT, mean, scn.truth))
        per_run.update(_late_check(cfg, CLAIRVOYANT, mean, scn, None))  # each target filtered alone
        return per_run, seconds

    @staticmethod
    def aggregate(cfg: CrossingSettings, per_run: dict, seconds: dict) -> dict:
        """Per filter: run counts, per-step curves and means (module docstring)."""
        results = {}
        late = slice(cfg.from_step, None)
        for name in (r for r in ROWS if f"{r}|coverage" in per_run):  # the rows that ran
            cov, shared = per_run[f"{name}|coverage"], per_run[f"{name}|shared"]
            err = per_run[f"{name}|matched_error"]
            uncovered = cov == 0  # (R, T, 2)
            gap = uncovered[:, late].any(-1).any(-1)  # (R,)
            odds, covers = per_run[f"{name}|gap_log_odds"], per_run[f"{name}|gap_map_covers"]
            model = gap & ~covers & (odds <= GAP_ODDS)  # the estimate's maximum about as likely as the truth's
            fired = per_run.get(f"{name}|pair_path_fired")  # (R, T) with the pair-path move
            truth = per_run.get("truth")  # (R, T, 2, D); the slots on each other's targets (R, T)
            swapped = None if truth is None else metrics.amplitude_swapped(
                per_run[f"{name}|estimate"].movedim(1, 0), truth.movedim(1, 0)).T
            results[name] = {
                "runs": int(cov.shape[0]),
                "runs_uncovered_late": int(gap.sum()),
                "runs_uncovered_late_interval": clopper_pearson(int(gap.sum()), int(cov.shape[0])),
                "gap_per_run": gap,
                "uncovered_target_steps_late": int(uncovered[:, late].sum()),
                "pair_path_fire_rate": None if fired is None else fired.double().mean(),
                "pair_path_moved": None if fired is None else (
                    (per_run[f"{name}|pair_path_moved"] * fired).sum() / fired.sum().clamp(min=1)).double(),
                "late_gaps_the_filters": int((gap & ~model).sum()),
                "late_gaps_the_models": int(model.sum()),
                "late_gap_log_odds": odds[gap],
                "runs_shared_late": int((shared[:, late] >= 2).any(-1).any(-1).sum()),
                # the share of late steps with the slots on each other's targets, gap runs / others
                "amplitude_swapped_late": (math.nan, math.nan) if swapped is None else
                tuple(_share(swapped[:, late], runs) for runs in (gap, ~gap)),
                "longest_uncovered": metrics.longest_run(uncovered.movedim(1, 0)).amax(-1),
                "uncovered_per_step": uncovered.any(-1).double().mean(0),
                "matched_rmse_per_step": err.square().mean(0).sqrt(),
                "matched_rmse": err.square().mean().sqrt(),
                "identity_switches_per_run": per_run[f"{name}|switches"].double().mean(),
                "seconds_per_step": seconds[name] / cfg.steps,
            }
            # the reference has no coalescence column (it reads the truth and has no data-driven move)
            rec = per_run.get(f"{name}|recaptured")  # (R, T_c)
            first = None if rec is None else torch.where(rec.any(1), rec.to(torch.int64).argmax(1).double(),
                                                         float("nan"))  # (R,)
            results[name].update({
                "recaptured_per_step": None if rec is None else rec.double().mean(0),
                "recaptured_share": None if rec is None else rec.any(1).double().mean(),
                "recapture_step_median": None if first is None else first.nanmedian(),
            })
        base = results.get("IP-MCMC-PF")
        for name, r in results.items():  # paired with the defaults on the same scenes (exact McNemar)
            if base is not None and name != "IP-MCMC-PF":
                g0, g1 = base["gap_per_run"], r["gap_per_run"]
                r["mcnemar_vs_defaults"] = {"only_defaults": int((g0 & ~g1).sum()), "only_this": int((~g0 & g1).sum()),
                                            "p": mcnemar_exact(int((g0 & ~g1).sum()), int((~g0 & g1).sum()))}
        return results

    def summary(self, payload: dict) -> str:
        """Headline table: the acceptance figures of issue 22 per filter."""
        cfg = payload["config"]
        lines = [f"| filter | runs with a target uncovered at t >= {cfg['from_step']} (the filter's / the model's) "
                 f"| runs with two slots on one "
                 f"target at t >= {cfg['from_step']} | per-step assignment RMSE [m] | identity switches / run | "
                 f"coalescence: runs re-captured within {cfg['coalesce_steps']} steps (median step) | s / step |",
                 "|---|---|---|---|---|---|---|"]
        for name, r in payload["results"].items():
            recaptured = ("-" if r["recaptured_share"] is None  # the clairvoyant reference
                          else f"{float(r['recaptured_share']):.0%} ({cell(r['recapture_step_median'], 0)})")
            lines.append(f"| {name} | {r['runs_uncovered_late']} / {r['runs']} ({r['late_gaps_the_filters']} / "
                         f"{r['late_gaps_the_models']}) | "
                         f"{r['runs_shared_late']} / {r['runs']} | "
                         f"{float(r['matched_rmse']):.2f} | {float(r['identity_switches_per_run']):.2f} | "
                         f"{recaptured} | {r['seconds_per_step']:.3f} |")
        lines += ["", f"| filter | runs uncovered at t >= {cfg['from_step']} (95 % Clopper-Pearson) | uncovered "
                      "target-steps | longest gap (steps) | McNemar vs the defaults (only the defaults / only this, "
                      "p) | pair-path trigger: steps fired (share) | moved paths (share) | late steps on each other's "
                      "targets (gap runs / others) |",
                  "|---|---|---|---|---|---|---|---|"]
        for name, r in payload["results"].items():
            lo, hi = r["runs_uncovered_late_interval"]
            mc = r.get("mcnemar_vs_defaults")
            test = "-" if mc is None else f"{mc['only_defaults']} / {mc['only_this']}, p = {mc['p']:.3g}"
            lines.append(f"| {name} | {r['runs_uncovered_late']} / {r['runs']} ({100 * lo:.0f}-{100 * hi:.0f} %) | "
                         f"{r['uncovered_target_steps_late']} | {int(max(r['longest_uncovered']))} | {test} | "
                         f"{cell(r['pair_path_fire_rate'])} | {cell(r['pair_path_moved'])} | "
                         f"{' / '.join(cell(v) for v in r['amplitude_swapped_late'])} |")
        return "\n".join(lines) + "\n"

    def summarise(self, cfg: CrossingSettings, shards: Shards, out: Path) -> dict:
        """Per-filter results and the three figures (module docstring)."""
        from ..plotting import plot_rmse, plot_tracks

        plt = pyplot()
        results = self.aggregate(cfg, shards.per_run, shards.seconds)
        pr, n, quick = shards.per_run, cfg.particles, " (quick)" if cfg.quick else ""
        runs = pr["truth"].shape[0]

        fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), layout="constrained")
        plot_rmse(axes[0], {np_label(k, n): r["uncovered_per_step"] for k, r in results.items()},
                  ylabel=f"share of runs with a target uncovered ({COVER:g} m)")
        plot_rmse(axes[1], {np_label(k, n): r["matched_rmse_per_step"] for k, r in results.items()},
                  ylabel="per-step assignment RMSE [m]")
        for ax in axes:
            ax.axvline(20, color="0.6", lw=0.8, ls=":")
        fig.suptitle(f"two targets crossing unresolved at step 20, {runs} runs{quick}")
        save_figure(fig, out, "crossing.png", quick=cfg.quick)

        fig, ax = plt.subplots(figsize=(7, 4.5), layout="constrained")  # title, label and legend apart
        plot_rmse(ax, {np_label(k, n): r["recaptured_per_step"] for k, r in results.items()
                       if r["recaptured_per_step"] is not None},
                  ylabel=f"runs with a slot within {RECAPTURE:g} m\nof the weak target (share)")
        ax.set_title(f"staged coalescence: both slots start on the strong target\n{runs} runs{quick}")
        save_figure(fig, out, "coalescence.png", quick=cfg.quick)

        shown = [name for name in FILTERS if name in results]
        fig, axes = plt.subplots(1, max(len(shown), 1), figsize=(4.5 * max(len(shown), 1), 4.5), squeeze=False,
                                 layout="constrained")
        for ax, name in zip(axes[0], shown):
            plot_tracks(ax, pr["truth"][0], pr[f"{name}|estimate"][0], estimate_label=np_label(name, n))
            ax.set_title(name)
        fig.suptitle(f"crossing, run 0: true tracks (solid) and slot estimates (dashed){quick}")
        save_figure(fig, out, "tracks.png", quick=cfg.quick)

        return {"config": asdict(cfg), "radii_m": {"uncovered": COVER, "shared": SHARE, "recaptured": RECAPTURE},
                "results": results}


STUDY = Crossing()
