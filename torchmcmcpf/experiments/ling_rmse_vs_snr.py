"""Fig. 3 (and Fig. 2) of Ling (2016), paper 002: position RMSE of the MCMC-based PF-TBD
versus SNR on the three-target scenario (:func:`~torchmcmcpf.scenarios.ling.ling`).

Writes ``metrics.json`` (RMSE per SNR and kernel, eq. 16, whether it is below the 10 m range
resolution, acceptance rates, seconds), ``rmse_vs_snr.png`` (Fig. 3) and ``tracks.png``
(Fig. 2: the tracks of one run at 10 dB, or the SNR closest to it).

Mapping of the paper's settings
-------------------------------
Paper 002 runs, at each frame, one Markov chain of ``B + M N`` iterations and keeps every
M-th state after the first B: ``B = 500`` (burn-in), ``M = 10`` (thinning), ``N = 100``
(samples), 1500 iterations. That is :class:`~torchmcmcpf.filters.mcmc.MCMCFilter` with
``num_chains=1``, ``burn_in=500``, ``thinning=10``, ``num_particles=100``; the chain starts
from a previous sample moved by the prior (the paper's step 1, what ``MCMCFilter`` does).

Kernels
-------
- ``"random_walk"`` (the paper's): Gaussian random walk on the joint state, eq. 13, with
  the acceptance ratio of eq. 14 (mixture prior over all N previous samples). Paper 002 does
  not give the covariance S; we use ``S = diag(s^2)`` with :data:`RW_SCALE` (0.4 m and
  0.4 m/s per position and velocity component, 1e-3 on the known power), chosen in a pilot
  run (4 runs, 12 frames, 10 dB) for an acceptance rate near the 0.234 of Roberts, Gelman and
  Gilks (1997): measured 0.25 (s = 0.2 gave 0.08, and the chain barely moved), not for the
  RMSE. Over 35 frames (4 runs per SNR, 0-12 dB) the acceptance fell to 0.074 and the
  chains lost the targets (RMSE 16-68 m); a diagonal S cannot follow the strong
  position-velocity correlation of the transition (eq. 2), whose narrow direction has a
  standard deviation of 0.26 sqrt(q).
- ``"adaptive_random_walk"``: the same random walk (eqs. 13-14) with a proposal covariance
  that fits the posterior, ``rw_scale="adaptive"`` of
  :class:`~torchmcmcpf.filters.mcmc.MCMCFilter`: per target, ``S_k = 2.38^2 / (K D) *
  Sigma_k`` with ``Sigma_k`` the prior mixture's covariance at the start of the frame, then
  the chain's history during the burn-in (Haario et al.'s adaptive Metropolis, re-fitted
  every tenth of the burn-in), frozen for the kept samples.
- ``"mixture"`` (reference, the library's default): joint draw from the prior mixture with
  probability 0.75, else a per-target refinement sweep (paper 004), same B, M, N.

All SNRs and runs are one batch (``B_runs = runs x len(snr)``, per-run SNR); the RMSE of an
SNR is eq. 16 over its runs, all frames and the three targets, with the slot labels the
filter was initialised with (the paper's definition); ``rmse_matched`` relabels each run by
the whole-track optimal assignment (a swap of targets 2 and 3 is then not counted).

``reproduce`` runs the study in shards of ``--shard-size`` runs per SNR (5, quick 1), each
from the generator of ``(seed, shard index)`` (:func:`run_shard`, :func:`aggregate`), so
``--workers N`` on Ray writes the same numbers; :func:`run_study` filters all runs as one
batch (the notebook's entry point).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from .. import metrics
from ..filters.mcmc import MCMCFilter
from ..scenarios.ling import LingScenario, ling
from ._figures import np_label, pyplot, save_figure
from ._options import nonnegative_int
from ._shards import Shards
from ._study import Settings, StepTimer, Study, generator, option

#: random-walk step per state component ``[x, vx, y, vy, P]`` (see the module docstring)
RW_SCALE = (0.4, 0.4, 0.4, 0.4, 1e-3)
MOVES = ("random_walk", "adaptive_random_walk", "mixture")


@dataclass(frozen=True)
class LingSettings(Settings):
    """The settings of :class:`RMSEvsSNR` (full values; the second of each pair: ``--quick``)."""

    runs: int = option(100, 2, help="Monte Carlo runs per SNR")
    snr: tuple[float, ...] = option((0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0), (4.0, 10.0), help="SNR values [dB]")
    steps: int = option(35, 6, help="frames")
    burn_in: int = option(500, 20, help="burn-in, iterations discarded per frame", type=nonnegative_int)
    thinning: int = option(10, 2, help="M, keep every M-th state")
    particles: int = option(100, 10, help="Np, samples kept per frame")
    moves: tuple[str, ...] = option(MOVES, ("random_walk", "mixture"), help="kernels to run", choices=MOVES)
    shard_size: int = option(5, 1, cli=False)

    def __post_init__(self) -> None:
        if self.burn_in < 0:
            raise ValueError(f"--burn-in must be >= 0, got {self.burn_in}")


def run_study(cfg: LingSettings, *, device: torch.device, seed: int, progress: bool = False) -> dict:
    """Simulate the scenario for every SNR, filter it with each kernel, score eq. 16.

    Returns
    -------
    dict with ``"results"`` (kernel -> metrics per SNR), ``"scenario"`` (the LingScenario,
    runs of SNR ``i`` at ``i * runs .. (i + 1) * runs - 1``) and ``"estimates"`` (kernel ->
    ``(T, B, 3, 5)`` filter means).
    """
    g = generator(device, seed)
    snr = torch.tensor(cfg.snr, dtype=torch.float32)
    runs = cfg.runs
    scn = ling(snr.repeat_interleave(runs), runs * snr.numel(), generator=g, num_steps=cfg.steps, device=device)
    x0 = scn.initial_particles(cfg.particles, generator=g)
    results, estimates = {}, {}
    for moves in cfg.moves:
        filt = _filter(cfg, scn, moves, device)
        with StepTimer(device, steps=cfg.steps) as timer:
            res = filt(scn.measurements, init=x0, generator=g, progress=progress)
        est = res.mean
        per_snr = []
        for i, value in enumerate(cfg.snr):  # a handful of SNR values, not a loop over runs
            sl = slice(i * runs, (i + 1) * runs)
            rmse = metrics.position_rmse(est[:, sl], scn.truth[:, sl])
            matched = metrics.position_rmse(est[:, sl], scn.truth[:, sl], match=True)
            per_target = metrics.position_error(est[:, sl], scn.truth[:, sl]).square().mean((0, 1)).sqrt()
            per_snr.append({
                "snr_db": value,
                "rmse": rmse.overall,
                "rmse_matched": matched.overall,
                "rmse_per_target": per_target,
                "rmse_per_step": rmse.per_step,
                "below_range_resolution": bool(rmse.overall < scn.range_resolution),
                "acceptance": {k.removeprefix("acceptance_"): v[:, sl].nanmean() for k, v in res.info.extras.items()},
            })
        results[moves] = {"per_snr": per_snr, "seconds_per_step": timer.seconds_per_step,
                          "seconds_total": timer.seconds}
        estimates[moves] = est
    return {"results": results, "scenario": scn, "estimates": estimates}


def _filter(cfg: LingSettings, scn: LingScenario, moves: str, device: str | torch.device) -> MCMCFilter:
    return MCMCFilter(scn.motion, scn.sensor, num_particles=cfg.particles, num_chains=1, burn_in=cfg.burn_in,
                      thinning=cfg.thinning, moves="random_walk" if moves == "adaptive_random_walk" else moves,
                      rw_scale=torch.tensor(RW_SCALE, device=device) if moves == "random_walk" else
                      "adaptive" if moves == "adaptive_random_walk" else None).to(device)


class RMSEvsSNR(Study[LingSettings]):
    """Fig. 3 of paper 002 (module docstring)."""

    name = "ling-rmse-vs-snr"
    description = ("Ling 2016 Fig. 3: MCMC-based PF-TBD position RMSE vs SNR, 3 targets, 35 frames "
                   "(B=500, M=10, N=100)")
    outputs = ("metrics.json", "rmse_vs_snr.png", "tracks.png", "shards")

    def run_shard(self, cfg: LingSettings, runs: range, *, generator: torch.Generator, device: torch.device,
                  progress: bool = False) -> tuple[dict, dict]:
        """The runs ``runs`` at every SNR (one batch of ``len(runs) x S`` problems).

        Returns
        -------
        ``per_run`` with ``"truth"`` ``(R, S, T, 3, 5)`` and, per kernel ``m``, ``"m|estimate"``
        (same), ``"m|se"`` and ``"m|se_matched"`` ``(R, S, T, 3)`` squared position errors
        (slot labels; labels matched per run), ``"m|acceptance|<move>"`` ``(R, S)`` (mean over
        the frames); ``seconds`` per kernel.
        """
        r, s = len(runs), len(cfg.snr)
        snr = torch.tensor(cfg.snr, dtype=torch.float32)
        scn = ling(snr.repeat_interleave(r), r * s, generator=generator, num_steps=cfg.steps, device=device)
        x0 = scn.initial_particles(cfg.particles, generator=generator)

        def per_run_first(x):  # (T, S * R, ...) -> (R, S, T, ...)
            return x.unflatten(1, (s, r)).movedim(0, 2).movedim(1, 0)

        per_run, seconds = {"truth": per_run_first(scn.truth)}, {}
        for moves in cfg.moves:
            with StepTimer(device, steps=cfg.steps) as timer:
                res = _filter(cfg, scn, moves, device)(scn.measurements, init=x0, generator=generator,
                                                       progress=progress)
            seconds[moves] = timer.seconds
            matched, _ = metrics.match_tracks(res.mean, scn.truth)
            per_run[f"{moves}|estimate"] = per_run_first(res.mean)
            per_run[f"{moves}|se"] = per_run_first(metrics.position_error(res.mean, scn.truth).square())
            per_run[f"{moves}|se_matched"] = per_run_first(metrics.position_error(matched, scn.truth).square())
            for name, v in res.info.extras.items():  # v: (T, S * R)
                if name.startswith("acceptance_"):
                    move = name.removeprefix("acceptance_")
                    per_run[f"{moves}|acceptance|{move}"] = v.nanmean(0).unflatten(0, (s, r)).T
        return per_run, seconds

    @staticmethod
    def aggregate(cfg: LingSettings, per_run: dict, seconds: dict, range_resolution: float) -> dict:
        """Eq. 16 per SNR and kernel from the per-run arrays of every shard (see
        :func:`run_study` for the fields; acceptance: mean over runs of the per-run mean).
        """
        results = {}
        for moves in cfg.moves:
            se, sem = per_run[f"{moves}|se"], per_run[f"{moves}|se_matched"]  # (R, S, T, K)
            per_snr = []
            for i, value in enumerate(cfg.snr):  # a handful of SNR values, not a loop over runs
                rmse = se[:, i].mean().sqrt()
                per_snr.append({
                    "snr_db": value,
                    "rmse": rmse,
                    "rmse_matched": sem[:, i].mean().sqrt(),
                    "rmse_per_target": se[:, i].mean((0, 1)).sqrt(),
                    "rmse_per_step": se[:, i].mean((0, 2)).sqrt(),
                    "below_range_resolution": bool(rmse < range_resolution),
                    "acceptance": {k.rsplit("|", 1)[1]: v[:, i].nanmean() for k, v in per_run.items()
                                   if k.startswith(f"{moves}|acceptance|")},
                })
            results[moves] = {"per_snr": per_snr, "seconds_per_step": seconds[moves] / cfg.steps,
                              "seconds_total": seconds[moves]}
        return results

    def summary(self, payload: dict) -> str:
        """Headline table: RMSE [m] per SNR and kernel."""
        snr = payload["config"]["snr"]
        lines = ["| kernel | " + " | ".join(f"{v:g} dB" for v in snr) + " |", "|---" * (len(snr) + 1) + "|"]
        for moves, r in payload["results"].items():
            lines.append(f"| {moves} | " + " | ".join(f"{float(p['rmse']):.2f}" for p in r["per_snr"]) + " |")
        return "position RMSE [m] (eq. 16) per SNR\n\n" + "\n".join(lines) + "\n"

    def summarise(self, cfg: LingSettings, shards: Shards, out: Path) -> dict:
        """Eq. 16 per SNR and kernel, ``rmse_vs_snr.png`` and ``tracks.png`` (module docstring)."""
        from ..plotting import plot_tracks
        from ..scenarios.ling import ling as _ling

        plt = pyplot()
        probe = _ling(10.0, 1, generator=generator("cpu", 0), num_steps=1)  # the geometry (no randomness used)
        res_m = probe.range_resolution
        results = self.aggregate(cfg, shards.per_run, shards.seconds, res_m)
        quick = " (quick)" if cfg.quick else ""

        fig, ax = plt.subplots(figsize=(6, 4))
        for moves, r in results.items():
            ax.plot(cfg.snr, [float(p["rmse"]) for p in r["per_snr"]], "o-",
                    label=np_label(f"MCMC-PF, {moves}", cfg.particles))
        ax.axhline(res_m, color="k", ls=":", lw=1, label=f"range resolution ({res_m:g} m)")
        ax.set_xlabel("SNR [dB]")
        ax.set_ylabel("position RMSE [m] (eq. 16)")
        ax.set_yscale("log")
        ax.set_title(f"{cfg.runs} runs, {cfg.steps} frames, burn-in {cfg.burn_in}, thinning {cfg.thinning}, "
                     f"Np = {cfg.particles}{quick}")
        ax.legend(fontsize="small")
        save_figure(fig, out, "rmse_vs_snr.png", quick=cfg.quick)

        i = min(range(len(cfg.snr)), key=lambda j: abs(cfg.snr[j] - 10.0))
        moves_all = list(results)
        fig, axes = plt.subplots(1, len(moves_all), figsize=(5.5 * len(moves_all), 4.5), squeeze=False)
        truth = shards.per_run["truth"][0, i]  # (T, K, D) run 0 at SNR i
        for ax, moves in zip(axes[0], moves_all):
            plot_tracks(ax, truth, shards.per_run[f"{moves}|estimate"][0, i],
                        estimate_label=np_label(f"MCMC-PF, {moves}", cfg.particles))
            ax.set_title(f"{moves}, SNR {cfg.snr[i]:g} dB (run 0){quick}")
        save_figure(fig, out, "tracks.png", quick=cfg.quick)

        payload = {
            "config": {**asdict(cfg), "rw_scale": RW_SCALE, "num_chains": 1},
            "grid": list(probe.sensor.frame_shape),
            "range_resolution_m": res_m,
            "results": results,
        }
        return payload


STUDY = RMSEvsSNR()
#: the notebook's entry point: an argparse-style namespace in, read once
settings = STUDY.settings_from
