"""Table II (and Figs. 3, 5, 6) of Bocquel, Driessen and Bagchi (2012), paper 000.

SIR PF, PMMH and IP-MCMC-PF with Np in {500, 5000} (and, as an extra row, the
independent-partition PF of the paper's refs. [3], [6]) on the ground-radar scenario of Table I,
with one target (Figs. 1-3) and ten targets (Figs. 4-6, Table II), Monte Carlo runs batched.
Writes ``table2.md`` (our table next to the paper's), ``metrics.json`` (RMSE, TLR, seconds
per time step, the device), ``rmse_1_target.png``, ``rmse_10_targets.png`` and
``tracks.png`` (the IP-MCMC-PF tracks of the first run, Fig. 5). ``--algorithms`` picks the
rows (default all four); ``--compile`` compiles each filter's step (same numbers, faster).

What runs
---------
- SIR PF: :class:`~torchmcmcpf.filters.sir.SIRFilter`, resampling every step.
- IP-MCMC-PF: :class:`~torchmcmcpf.filters.ipmcmc.IPMCMCFilter`, 50 chains, burn-in 100,
  R-hat threshold 1.1, at most ``--max-extensions`` extensions.
- PMMH: :class:`~torchmcmcpf.filters.pmmh.PMMHFilter`, sequential PMMH (particle
  independent MH) on ``theta = log q``, the log-scale of the filters' process noise (true
  value 0, prior N(0, 1)): ``--pmmh-candidates`` L prior draws of theta (the chain length,
  no burn-in), each with its own SIR filter of Np particles (L * Np in all); the track at
  each step is the chain average of the candidates' filtering means (see
  :mod:`torchmcmcpf.filters.pmmh`). Its seconds per step are those of the whole filter.
  The shard's runs go through it in batches of at most :data:`PMMH_BATCH_PARTICLES`
  particles (2 runs at Np = 5000): L * Np particles per run would otherwise hold 250,000
  particles per shard of 10 runs (5.4 GiB peak, and a compiled graph of 39 unrolled
  likelihood chunks that took about 6 min to compile).
- Partitioned PF (extra row, not in the paper's table):
  :class:`~torchmcmcpf.filters.partitioned.PartitionedSIRFilter`, Np particles, each
  target's partition weighted with the others at their predicted estimates and resampled
  on its own (Orton and Fitzgerald; Kreucher et al.), with exclusion and re-capture
  (``--factorised``: without either).

Every filter starts from ``Scenario.initial_particles`` (5 m / 1 m/s / 10 % around the
truth one step before frame 0, labels kept); RMSE and TLR (20 m) use the slot labels.

Shards
------
The runs are cut into shards of ``--shard-size`` runs (10, quick 1); each shard simulates
its own runs of both scenarios and filters them with every algorithm, from the generator of
``(seed, shard index)`` (:func:`~torchmcmcpf.experiments._shards.run_shards`), so
``--workers N`` on Ray gives the same numbers as the default in-process loop. Each row's
filter is built once per process and reused by its later shards, so ``--compile`` compiles
each row once per process, not once per shard (:func:`_reused_filter`). Seconds per step are
the filter times summed over the shards (the first shard's compilation included), over T.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TypeVar

import torch

from .. import metrics
from ..filters.ipmcmc import IPMCMCFilter
from ..filters.partitioned import PartitionedSIRFilter
from ..filters.pmmh import PMMHFilter
from ..filters.sir import SIRFilter
from ..scenarios._common import Scenario
from ..scenarios.ground_radar import ground_radar
from ._figures import np_label, pyplot, save_figure
from ._options import nonnegative_int
from ._shards import Shards
from ._study import Settings, StepTimer, Study, models_key, option, reused

#: paper 000 Table II (10 targets): (algorithm, Np) -> (RMSE [m], TLR, CPU s per step)
PAPER = {
    ("SIR PF", 500): (6.74, 0.06, 0.5), ("SIR PF", 5000): (6.23, 0.03, 3.8),
    ("PMMH", 500): (5.42, 0.01, 0.6), ("PMMH", 5000): (4.65, 0.00, 2.7),
    ("IP-MCMC-PF", 500): (4.84, 0.00, 0.4), ("IP-MCMC-PF", 5000): (4.61, 0.00, 0.69),
}
ALGORITHMS = ("SIR PF", "Partitioned PF", "PMMH", "IP-MCMC-PF")
#: particles of one PMMH batch (runs x L x Np): the SIR row's at Np = 5000 for a shard of 10
PMMH_BATCH_PARTICLES = 50_000
F = TypeVar("F")


@dataclass(frozen=True)
class Table2Settings(Settings):
    """The settings of :class:`Table2` (full values; the second of each pair: ``--quick``)."""

    runs: int = option(100, 2, help="Monte Carlo runs")
    steps: int = option(20, 3, help="time steps")
    particles: tuple[int, ...] = option((500, 5000), (40, 80), help="Np values")
    chains: int = option(50, 10, cli=False)
    burn_in: int = option(100, 10, cli=False)
    targets: tuple[int, ...] = option((1, 10), cli=False)
    max_extensions: int = option(2, 1, help="IP-MCMC-PF R-hat extensions", type=nonnegative_int)
    pmmh_candidates: int = option(5, 2, help="PMMH candidates L (chain length; L SIR filters of Np particles)")
    shard_size: int = option(10, 1, cli=False)
    algorithms: tuple[str, ...] = option(
        ALGORITHMS, choices=ALGORITHMS, metavar="NAME",
        help=f"the rows to run, among {', '.join(repr(a) for a in ALGORITHMS)} (default all)")
    compile: bool = option(True, False, help="compile each filter's step (compile_step=True; PMMH: its candidates' SIR "
                                             "kernel): the same numbers, about 2x faster once compiled (about 5 min "
                                             "of compilation, once per process); --no-compile runs eager")
    factorised: bool = option(False, help="the paper's factorised targets: no exclusion between slots, and the "
                                          "IP-MCMC-PF's plain exchange move (exclusion=None, recapture=None; "
                                          "default: the library's defaults)")

    def __post_init__(self) -> None:
        object.__setattr__(self, "algorithms", tuple(a for a in ALGORITHMS if a in self.algorithms))
        if self.pmmh_candidates < 2:
            raise ValueError(f"--pmmh-candidates must be >= 2, got {self.pmmh_candidates}")
        if any(n % self.chains for n in self.particles):
            raise ValueError(f"--particles {self.particles} must be multiples of {self.chains} chains")


def _run_pmmh(scn: Scenario, n: int, cfg: Table2Settings, g: torch.Generator, progress: bool) -> tuple:
    """The PMMH row: :class:`PMMHFilter` with L = ``pmmh_candidates`` candidates of Np
    particles each (module docstring).
    """
    lc = cfg.pmmh_candidates
    filt = _reused_filter(cfg, scn, "PMMH", n, lambda: PMMHFilter(scn.motion, scn.sensor, lc * n, num_candidates=lc,
                                                                    compile_step=cfg.compile))
    init = scn.initial_particles(lc * n, generator=g)  # (B, L * Np, K, D)
    per = max(1, PMMH_BATCH_PARTICLES // (lc * n))
    out = []
    for b0 in range(0, init.shape[0], per):  # batches of runs: memory and compiled graph bounded
        res = filt(scn.measurements[:, b0:b0 + per], init=init[b0:b0 + per], generator=g, progress=progress)
        out.append((res.mean, res.info.acceptance.mean(0), res.info.extras["theta_mean"][-1]))
    mean, acceptance, theta = (torch.cat(parts, dim) for parts, dim in zip(zip(*out), (1, 0, 0)))
    return mean, {"acceptance": acceptance, "theta_mean": theta}


def _make_filter(name: str, scn: Scenario, n: int,
                 cfg: Table2Settings) -> SIRFilter | PartitionedSIRFilter | IPMCMCFilter:
    """The row ``name``'s filter with Np = ``n`` (``cfg.compile``: ``compile_step=True``)."""
    c = cfg.compile
    plain: dict = dict(exclusion=None) if cfg.factorised else {}
    if name == "SIR PF":
        return SIRFilter(scn.motion, scn.sensor, num_particles=n, compile_step=c, **plain)
    if plain:
        plain["recapture"] = None
    if name == "Partitioned PF":
        return PartitionedSIRFilter(scn.motion, scn.sensor, num_particles=n, compile_step=c, **plain)
    return IPMCMCFilter(scn.motion, scn.sensor, num_particles=n, num_chains=cfg.chains, burn_in=cfg.burn_in,
                        max_extensions=cfg.max_extensions, compile_step=c, **plain)


def _reused_filter(cfg: Table2Settings, scn: Scenario, name: str, n: int, build: Callable[[], F]) -> F:
    """The row's filter, built once per process (:func:`~torchmcmcpf.experiments._study.reused`:
    each shard's compilations would otherwise be paid again), for the settings, the row and
    the scenario's models (equal in every shard: they depend on the number of steps, the
    device and the dtype, not on the random numbers).
    """
    return reused(("bocquel-table2", cfg, scn.num_targets, name, n, models_key(scn.motion, scn.sensor)), build)


def _key(num_targets: int, name: str, n: int) -> str:
    return f"{num_targets}|{name}|{n}"


def table_markdown(results: dict, num_targets: int, with_paper: bool) -> str:
    """Table II for ``num_targets`` targets as markdown (with the paper's figures when ``with_paper``)."""
    head = "| Algorithm | Np | RMSE [m] | TLR | s / step |"
    sep = "|---|---|---|---|---|"
    if with_paper:
        head += " paper RMSE [m] | paper TLR | paper CPU s |"
        sep += "---|---|---|"
    lines = [f"**{num_targets} target{'s' if num_targets > 1 else ''}**", "", head, sep]
    for r in results.values():
        row = (f"| {r['algorithm']} | {r['num_particles']} | {float(r['rmse']):.2f} | "
               f"{100 * float(r['tlr']):.0f}% | {r['seconds_per_step']:.3f} |")
        if with_paper:
            p = PAPER.get((r["algorithm"], r["num_particles"]))
            row += " - | - | - |" if p is None else f" {p[0]:.2f} | {100 * p[1]:.0f}% | {p[2]} |"
        lines.append(row)
    return "\n".join(lines) + "\n"


class Table2(Study[Table2Settings]):
    """Table II of paper 000 (module docstring)."""

    name = "bocquel-table2"
    description = "Bocquel et al. 2012 Table II: SIR PF vs PMMH vs IP-MCMC-PF on the ground radar (RMSE, TLR, s/step)"
    outputs = ("metrics.json", "table2.md", "rmse_1_target.png", "rmse_10_targets.png", "tracks.png", "shards")

    def run_shard(self, cfg: Table2Settings, runs: range, *, generator: torch.Generator, device: torch.device,
                  progress: bool = False) -> tuple[dict, dict]:
        """Both scenarios, every algorithm and Np, for the runs ``runs`` (one batch).

        Returns
        -------
        ``per_run`` with, per ``"<K>|<algorithm>|<Np>"``: ``|se`` ``(B, T)`` squared position
        error averaged over the targets, ``|lost`` ``(B,)`` track loss (20 m), the per-run
        diagnostics (``|rhat_mean``, ``|extensions_mean``, ``|acceptance``, ``|theta_mean``),
        and for the largest K ``"<K>|truth"`` and the IP-MCMC-PF estimates of the largest Np
        ``(B, T, K, D)`` (the tracks figure); ``seconds`` per key.
        """
        g = generator
        per_run, seconds = {}, {}
        for k in cfg.targets:
            scn = ground_radar(k, cfg.steps, len(runs), generator=g, device=device)
            for n in cfg.particles:
                x0 = scn.initial_particles(n, generator=g)
                for name in cfg.algorithms:
                    key = _key(k, name, n)
                    with StepTimer(device, steps=cfg.steps) as timer:
                        if name == "PMMH":
                            est, extra = _run_pmmh(scn, n, cfg, g, progress)
                        else:
                            filt = _reused_filter(cfg, scn, name, n, lambda: _make_filter(name, scn, n, cfg))
                            res = filt(scn.measurements, init=x0, generator=g, progress=progress)
                            est, extra = res.mean, {}
                            if name == "IP-MCMC-PF":
                                extra = {"rhat_mean": res.info.extras["rhat"].mean(0),
                                         "extensions_mean": res.info.extras["extensions"].float().mean(0),
                                         "extended_share": (res.info.extras["extensions"] > 0).float().mean(0),
                                         "acceptance": res.info.acceptance.mean(0)}
                    seconds[key] = timer.seconds
                    per_run[f"{key}|se"] = metrics.position_error(est, scn.truth).square().mean(-1).T
                    per_run[f"{key}|lost"] = metrics.track_loss(est, scn.truth)
                    per_run.update({f"{key}|{e}": v for e, v in extra.items()})
                    if k == max(cfg.targets) and name == "IP-MCMC-PF" and n == max(cfg.particles):
                        per_run[f"{key}|estimate"] = est.movedim(1, 0)
            if k == max(cfg.targets):
                per_run[f"{k}|truth"] = scn.truth.movedim(1, 0)
        return per_run, seconds

    @staticmethod
    def aggregate(cfg: Table2Settings, per_run: dict, seconds: dict) -> dict:
        """Table II from the per-run arrays of every shard: ``"<K> targets" -> "<algorithm> |
        <Np>" -> {rmse, rmse_per_step, tlr, seconds_per_step, diagnostics}``.
        """
        results = {}
        for k in cfg.targets:
            rows = {}
            for n in cfg.particles:
                for name in cfg.algorithms:
                    key = _key(k, name, n)
                    se = per_run[f"{key}|se"]  # (B, T)
                    extra = {e: per_run[f"{key}|{e}"].mean()
                             for e in ("rhat_mean", "extensions_mean", "extended_share", "acceptance", "theta_mean")
                             if f"{key}|{e}" in per_run}
                    rows[f"{name} | {n}"] = {
                        "algorithm": name, "num_particles": n,
                        "rmse": se.mean().sqrt(), "rmse_per_step": se.mean(0).sqrt(),
                        "tlr": per_run[f"{key}|lost"].float().mean(),
                        "seconds_per_step": seconds[key] / cfg.steps, **extra,
                    }
            results[f"{k} targets"] = rows
        return results

    def summary(self, payload: dict) -> str:
        """The headline table printed by ``reproduce``: the 10-target rows next to the paper's."""
        k = max(payload["config"]["targets"])
        return table_markdown(payload["results"][f"{k} targets"], k, with_paper=(k == 10))

    def summarise(self, cfg: Table2Settings, shards: Shards, out: Path) -> dict:
        """Table II, ``table2.md`` and the figures (module docstring)."""
        from ..plotting import plot_rmse, plot_tracks

        plt = pyplot()
        all_results = self.aggregate(cfg, shards.per_run, shards.seconds)
        quick = " (quick)" if cfg.quick else ""
        md = ["# Table II of Bocquel et al. (2012), regenerated", "",
              f"{cfg.runs} Monte Carlo runs, {cfg.steps} steps, device: see metrics.json"
              + (" (QUICK mode: small settings, not comparable with the paper)" if cfg.quick else ""), ""]
        for k in cfg.targets:
            rows = all_results[f"{k} targets"]
            md.append(table_markdown(rows, k, with_paper=(k == 10)))
            fig, ax = plt.subplots(figsize=(6, 4))
            plot_rmse(ax, {np_label(r["algorithm"], r["num_particles"]): r["rmse_per_step"] for r in rows.values()})
            ax.set_title(f"Position RMSE, {k} target{'s' if k > 1 else ''}, {cfg.runs} runs{quick}")
            save_figure(fig, out, f"rmse_{k}_target{'s' if k > 1 else ''}.png", quick=cfg.quick)
        k, n = max(cfg.targets), max(cfg.particles)
        estimate = shards.per_run.get(f"{_key(k, 'IP-MCMC-PF', n)}|estimate")
        if estimate is not None:  # the IP-MCMC-PF row ran (--algorithms)
            fig, ax = plt.subplots(figsize=(6, 5))
            plot_tracks(ax, shards.per_run[f"{k}|truth"].movedim(0, 1), estimate.movedim(0, 1), run=0,
                        estimate_label=f"IP-MCMC-PF, Np = {n}")
            ax.set_title(f"IP-MCMC-PF tracks, {k} targets (run 0){quick}")
            save_figure(fig, out, "tracks.png", quick=cfg.quick)
        md += ["**Paper 000, Table II** (10 targets, 100 runs; MATLAB R2011b on an Intel Core i7 920)", "",
               "| Algorithm | Np | RMSE [m] | TLR | CPU s / step |", "|---|---|---|---|---|"]
        md += [f"| {a} | {n} | {p[0]:.2f} | {100 * p[1]:.0f}% | {p[2]} |" for (a, n), p in PAPER.items()]
        (out / "table2.md").write_text("\n".join(md) + "\n")
        return {"config": asdict(cfg), "results": all_results}


STUDY = Table2()
#: the notebook's entry points: an argparse-style namespace in, read once
NAME, settings, run = STUDY.name, STUDY.settings_from, STUDY.run_namespace
