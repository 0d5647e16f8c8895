"""Why our SIR PF loses the 10-target runs of Table II (paper 000) where the paper's holds:
an ablation of the joint SIR filter on the ground-radar scenario (issue 13, item 2).

The paper reports SIR 6.74 m / 6% track loss at Np = 500 and 6.23 m / 3% at Np = 5000 with
10 targets. Ours (``bocquel-table2``) loses every run. This study varies, one factor at a
time around the Table II setting (10 targets, Np = 500, initial spread 5 m / 1 m/s / 10 %,
point spread read as standard deviations, ``SNR = rho^2 / (2 sigma^2)``):

- the number of targets K in ``--targets`` (1, 2, 3, 5, 10);
- Np in ``--particles`` (500, 5000, 50000) at K = 10;
- the initial spread, scaled by each factor in ``--spreads`` (0: every particle on the true
  initial state; 1: the default; 2: twice as wide), at K = 10, Np = 500;
- the reading of eq. 20 and the SNR convention, every combination at K = 10, Np = 500:
  ``R, D, B`` as standard deviations equal to the cell sizes (``std``, ours) or as variances
  as the formula writes them (``variance``: 3.16 m, 1.41 m/s, 7.6 deg standard deviations,
  see :func:`~torchmcmcpf.scenarios.ground_radar.ground_radar`), and ``SNR = rho^2 /
  (2 sigma^2)`` (``half``, ours: peak power over the mean noise power ``2 sigma^2`` of a
  cell) or ``SNR = rho^2 / sigma^2`` (``full``: the same dB values give amplitudes
  ``1/sqrt 2`` as large, i.e. the scenario's SNR range shifted down by 3.01 dB in our
  convention).

Each setting simulates its own scenario (the data follow the reading the filter uses), runs
an :class:`~torchmcmcpf.filters.sir.SIRFilter` resampling every step, and reports RMSE, TLR
(20 m, slot labels as in Table II), the mean ESS and seconds per step. Writes
``ablation.md``, ``metrics.json`` and ``ablation.png`` (RMSE and mean ESS against the number
of targets at the base Np, with the paper's 10-target SIR row).

Shards: ``--shard-size`` runs per shard (default 5, quick 1), each with the generator of
``(seed, shard index)`` (:func:`~torchmcmcpf.experiments._shards.run_shards`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from .. import metrics
from ..filters.sir import SIRFilter
from ..scenarios.ground_radar import ground_radar
from ._figures import pyplot, save_figure
from ._shards import Shards
from ._study import Settings, StepTimer, Study, option

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: the paper's SIR rows (10 targets): Np -> (RMSE [m], TLR)
PAPER = {500: (6.74, 0.06), 5000: (6.23, 0.03)}
#: the default initial spread (position std [m], velocity std [m/s], relative amplitude std)
SPREAD = (5.0, 1.0, 0.1)
#: SNR conventions -> dB added to the scenario's SNR range in our convention rho^2 / (2 sigma^2)
SNR_SHIFT = {"half": 0.0, "full": -10.0 * math.log10(2.0)}


@dataclass(frozen=True)
class AblationSettings(Settings):
    """The settings of :class:`SIRAblation` (full values; the second of each pair: ``--quick``)."""

    runs: int = option(20, 1, help="Monte Carlo runs per setting")
    steps: int = option(20, 3, help="time steps")
    targets: tuple[int, ...] = option((1, 2, 3, 5, 10), (1, 3), help="numbers of targets")
    particles: tuple[int, ...] = option((500, 5000, 50000), (50, 100), help="Np values (at the base K)")
    spreads: tuple[float, ...] = option((0.0, 1.0, 2.0), (0.0, 1.0), help="initial-spread scale factors")
    base_targets: int = option(10, 3, help="K of the base setting")
    base_particles: int = option(500, 50, help="Np of the base setting")
    shard_size: int = option(5, 1, cli=False)

    def __post_init__(self) -> None:
        if any(s < 0 or not math.isfinite(s) for s in self.spreads):
            raise ValueError(f"--spreads must be finite and >= 0, got {self.spreads}")


def cells(cfg: AblationSettings) -> list[dict]:
    """Every setting the study runs (one factor at a time around the base), each a dict
    ``targets, particles, spread, point_spread, snr`` with its ``key``; duplicates dropped.
    """
    base = dict(targets=cfg.base_targets, particles=cfg.base_particles, spread=1.0, point_spread="std",
                snr="half")
    out = [dict(base, targets=k) for k in cfg.targets]
    out += [dict(base, particles=n) for n in cfg.particles]
    out += [dict(base, spread=s) for s in cfg.spreads]
    out += [dict(base, point_spread=p, snr=c) for p in ("std", "variance") for c in SNR_SHIFT]
    seen, unique = set(), []
    for c in out:
        key = f"K={c['targets']}|Np={c['particles']}|spread={c['spread']:g}|psf={c['point_spread']}|snr={c['snr']}"
        if key not in seen:
            seen.add(key)
            unique.append({**c, "key": key})
    return unique


def table_markdown(rows: dict) -> str:
    """The ablation rows as a markdown table, with the paper's SIR figures beside them."""
    lines = ["| K | Np | initial spread | eq. 20 R, D, B as | SNR | RMSE [m] | TLR | mean ESS | s / step (batch) |"
             " paper RMSE | paper TLR |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows.values():
        paper = PAPER.get(r["particles"]) if r["targets"] == 10 and r["spread"] == 1.0 else None
        lines.append(
            f"| {r['targets']} | {r['particles']} | x{r['spread']:g} | "
            f"{'std = cell' if r['point_spread'] == 'std' else 'variance'} | "
            f"{'rho^2/(2 sigma^2)' if r['snr'] == 'half' else 'rho^2/sigma^2'} | {float(r['rmse']):.2f} | "
            f"{100 * float(r['tlr']):.0f}% | {float(r['ess']):.1f} | {r['seconds_per_step']:.3f} | "
            + ("- | - |" if paper is None else f"{paper[0]:.2f} | {100 * paper[1]:.0f}% |"))
    return "\n".join(lines) + "\n"


def targets_figure(rows: dict, cfg: AblationSettings) -> Figure:
    """RMSE and mean ESS against the number of targets K (the base setting otherwise: Np =
    ``base_particles``, spread x1, std reading, ``rho^2 / (2 sigma^2)``), with the paper's SIR
    figure at K = 10 where the base Np is one of its rows.
    """
    plt = pyplot()
    line = sorted((r for r in rows.values() if r["particles"] == cfg.base_particles and r["spread"] == 1.0
                   and r["point_spread"] == "std" and r["snr"] == "half"), key=lambda r: r["targets"])
    k = [r["targets"] for r in line]
    fig, (ax_rmse, ax_ess) = plt.subplots(1, 2, figsize=(10, 4), layout="constrained")
    ax_rmse.plot(k, [float(r["rmse"]) for r in line], "o-", label=f"SIR PF, Np = {cfg.base_particles}")
    ax_rmse.axhline(20.0, color="grey", ls=":", lw=1, label="track-loss threshold (20 m)")
    if cfg.base_particles in PAPER:
        ax_rmse.plot([10], [PAPER[cfg.base_particles][0]], "k*", ms=10, label="paper, SIR, 10 targets")
    ax_rmse.set_xlabel("number of targets K")
    ax_rmse.set_ylabel("position RMSE [m]")
    ax_rmse.legend(fontsize="small")
    ax_ess.semilogy(k, [float(r["ess"]) for r in line], "o-")
    ax_ess.set_xlabel("number of targets K")
    ax_ess.set_ylabel(f"mean ESS (of Np = {cfg.base_particles})")
    for ax in (ax_rmse, ax_ess):
        ax.set_xticks(k)
        ax.grid(alpha=0.3)
    fig.suptitle(f"joint SIR on the ground radar: {cfg.runs} run(s) per point, {cfg.steps} steps")
    return fig


class SIRAblation(Study[AblationSettings]):
    """The SIR row of Table II, one factor at a time (module docstring)."""

    name = "bocquel-sir-ablation"
    description = ("Bocquel et al. 2012 Table II SIR row: SIR RMSE/TLR vs targets, Np, initial spread, "
                   "eq. 20 reading and SNR convention")
    outputs = ("metrics.json", "ablation.md", "ablation.png", "shards")

    def run_shard(self, cfg: AblationSettings, runs: range, *, generator: torch.Generator, device: torch.device,
                  progress: bool = False) -> tuple[dict, dict]:
        """Every setting of :func:`cells` for the runs ``runs``.

        Returns
        -------
        ``per_run`` with, per setting key: ``|se`` ``(B, T)`` squared position error averaged
        over the targets, ``|lost`` ``(B,)`` track loss (20 m), ``|ess`` ``(B,)`` mean ESS;
        ``seconds`` per key.
        """
        g = generator
        per_run, seconds = {}, {}
        scenarios = {}
        for c in cells(cfg):
            sk = (c["targets"], c["point_spread"], c["snr"])
            if sk not in scenarios:  # one scenario per (K, reading, SNR convention), shared by the settings
                lo, hi = 9.0 + SNR_SHIFT[c["snr"]], 20.0 + SNR_SHIFT[c["snr"]]
                scenarios[sk] = ground_radar(c["targets"], cfg.steps, len(runs), generator=g, device=device,
                                             snr_db=(lo, hi), point_spread=c["point_spread"])
            scn = scenarios[sk]
            x0 = scn.initial_particles(c["particles"], generator=g, spread=tuple(c["spread"] * s for s in SPREAD))
            with StepTimer(device, steps=cfg.steps) as timer:
                res = SIRFilter(scn.motion, scn.sensor, c["particles"])(scn.measurements, init=x0, generator=g,
                                                                        progress=progress)
            key = c["key"]
            seconds[key] = timer.seconds
            per_run[f"{key}|se"] = metrics.position_error(res.mean, scn.truth).square().mean(-1).T
            per_run[f"{key}|lost"] = metrics.track_loss(res.mean, scn.truth)
            per_run[f"{key}|ess"] = res.info.ess.mean(0)
        return per_run, seconds

    @staticmethod
    def aggregate(cfg: AblationSettings, per_run: dict, seconds: dict) -> dict:
        """One row per setting: ``key -> {targets, particles, spread, point_spread, snr, rmse,
        tlr, ess, seconds_per_step}``.
        """
        rows = {}
        for c in cells(cfg):
            key = c["key"]
            rows[key] = {**{k: v for k, v in c.items() if k != "key"},
                         "rmse": per_run[f"{key}|se"].mean().sqrt(),
                         "tlr": per_run[f"{key}|lost"].float().mean(),
                         "ess": per_run[f"{key}|ess"].mean(),
                         "seconds_per_step": seconds[key] / cfg.steps}
        return rows

    def summary(self, payload: dict) -> str:
        """The headline table printed by ``reproduce``."""
        return table_markdown(payload["results"])

    def summarise(self, cfg: AblationSettings, shards: Shards, out: Path) -> dict:
        """The rows, ``ablation.md`` and ``ablation.png`` (RMSE and ESS against K)."""
        rows = self.aggregate(cfg, shards.per_run, shards.seconds)
        md = ["# SIR ablation on the ground radar of Bocquel et al. (2012)", "",
              f"{cfg.runs} Monte Carlo runs per setting, {cfg.steps} steps, SIR resampling every step; "
              "device: see metrics.json" + (" (QUICK mode: small settings)" if cfg.quick else ""), "",
              table_markdown(rows)]
        (out / "ablation.md").write_text("\n".join(md))
        save_figure(targets_figure(rows, cfg), out, "ablation.png", quick=cfg.quick)
        return {"config": asdict(cfg), "results": rows}


STUDY = SIRAblation()
