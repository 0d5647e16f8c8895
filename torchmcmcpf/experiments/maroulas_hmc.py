"""Figs. 3, 4, 7, 8 of Maroulas and Stinis (2010), paper 003: the particle filter with an
HMC move against the generic particle filter, linear and bearing-range observations.

What runs (per observation model, Monte Carlo runs batched):

- improved PF: :class:`~torchmcmcpf.filters.resample_move.ResampleMoveFilter`, exact
  association, 100 HMC accept/reject rounds of one leapfrog step of 0.1 (paper sec.
  2.1.2), N = 100 (linear) or 200 (bearing-range);
- generic PF: the same step without the move (``num_hmc_steps=0``: predict, weight,
  resample), N = 120 or 220 as in the paper;
- generic PF at equal time: the generic PF with N scaled by the measured time ratio
  (capped), since here the move costs far more than the paper's "few percent".

Outputs: ``metrics.json`` (RMSE per target, eq. 31, averaged over time and runs; ESS in %
of N, sec. 1.3; HMC acceptance; seconds per step; the paper's numbers), ``rmse_<obs>.png``
(Figs. 3, 7), ``ess_<obs>.png`` (Figs. 4, 8; ``ess_percent`` is the ESS of the predicted
particles' weights, ``ess_after_move_percent`` that of ``g`` over the returned particles,
the reading that matches the paper's "about 25 %", see
:mod:`torchmcmcpf.filters.resample_move`) and ``tracks_<obs>.png`` (Figs. 1, 5).
Paper 003 gives no units; the figures read positions in metres and the unit time step
(``T = 1``) in seconds.

Not sharded (no ``--workers``): the equal-time particle count comes from a measured time
ratio, so it is not a function of the seed.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, NamedTuple

import torch

from .._validation import check_generator
from ..filters.base import Filter
from ..filters.resample_move import ResampleMoveFilter
from ..models.sensors.association import AssociationSensor, PointFrame
from ..scenarios import maroulas as scenario
from ..state import ParticleState
from ..typing import Tensor
from ._figures import np_label, save_figure
from ._options import RunOptions
from ._study import Settings, StepTimer, Study, cell, generator, option

#: paper 003 sec. 2.2-2.3: observation -> (N improved, N generic, RMSE improved (mean, std
#: over time), RMSE generic (mean, std), ESS improved [% of N])
PAPER: dict[str, dict[str, Any]] = {
    "linear": dict(particles=(100, 120), rmse_improved=(2.5, 0.5), rmse_generic=(800.0, 760.0), ess_improved=25.0),
    "bearing_range": dict(particles=(200, 220), rmse_improved=(22.0, 21.0), rmse_generic=(760.0, 770.0),
                          ess_improved=25.0),
}


@dataclass(frozen=True)
class MaroulasSettings(Settings):
    """The settings of :class:`HMCvsGeneric` (full values; the second of each pair: ``--quick``)."""

    runs: int = option(10, 2, help="Monte Carlo runs")
    steps: int = option(200, 12, help="time steps after t=0")
    hmc_steps: int = option(100, 50, help="HMC accept/reject rounds")
    max_equal_time_particles: int = option(20000, 2000, cli=False)


class TrackResult(NamedTuple):
    """What :func:`track` returns.

    Attributes
    ----------
    mean : (T+1, B, K, 4) estimates (time 0: the mean of the initial cloud).
    ess : (T, B) effective sample size of each step's weights.
    acceptance : (T, B) HMC acceptance, or None for filters without a move.
    ess_after_move : (T, B) ESS of ``g`` over the particles each step returns (paper 003
        sec. 1.3's reading; ``info.extras["ess_after_move"]``), or None for a filter
        without it.
    """

    mean: Tensor
    ess: Tensor
    acceptance: Tensor | None
    ess_after_move: Tensor | None = None


def track(filt: Filter, data: scenario.MaroulasData, *, generator: torch.Generator,
          progress: bool = False) -> TrackResult:
    """Run ``filt`` over a simulated scenario with the scenario's births and deaths: before each
    step the slots that died are switched off; after it, the newborn slots get particles from
    the birth density (:func:`~torchmcmcpf.scenarios.maroulas.birth_particles`). It runs a
    filter, so it lives here, not in :mod:`torchmcmcpf.scenarios` (which never imports filters).

    Parameters
    ----------
    filt : a Filter whose sensor is an AssociationSensor (e.g. ResampleMoveFilter, or
        SIRFilter).
    data : from :func:`torchmcmcpf.scenarios.maroulas.simulate`.
    generator : source of randomness.
    progress : tqdm bar over time.

    Returns
    -------
    :class:`TrackResult`.
    """
    check_generator(generator)
    n = filt.num_particles
    alive = data.alive
    sensor = filt.sensor
    if not isinstance(sensor, AssociationSensor):
        raise ValueError(f"filt.sensor must be an AssociationSensor (births are drawn around its measurements), "
                         f"got {type(sensor).__name__}")
    x0 = scenario.birth_particles(sensor, data.z_slot[0], n, generator=generator)
    x0 = torch.where(alive[0].unsqueeze(1).unsqueeze(-1), x0, torch.zeros_like(x0))
    state = filt.init(x0, alive[0].unsqueeze(1).expand(-1, n, -1))
    means, esss, accs, after = [state.mean()], [], [], []
    steps = range(1, alive.shape[0])
    if progress:
        from tqdm.auto import tqdm

        steps = tqdm(steps, desc=type(filt).__name__, leave=False)
    for t in steps:
        state = state._replace(exists=_flags(state) & alive[t].unsqueeze(1))  # deaths
        frame = PointFrame(data.frames.z[t], data.frames.mask[t])
        state, info = filt.step(state, frame, generator=generator)
        born = alive[t] & ~alive[t - 1]  # (B, K), the same for every run
        if bool(born.any()):
            xb = scenario.birth_particles(sensor, data.z_slot[t], n, generator=generator)
            bn = born.unsqueeze(1)
            state = ParticleState(torch.where(bn.unsqueeze(-1), xb, state.x), state.log_w, _flags(state) | bn)
        means.append(filt.estimate(state))
        esss.append(info.ess)
        accs.append(info.acceptance)
        after.append(info.extras.get("ess_after_move"))
    acc = torch.stack(accs)
    return TrackResult(torch.stack(means), torch.stack(esss), None if bool(torch.isnan(acc).all()) else acc,
                       None if any(a is None for a in after) else torch.stack([a for a in after if a is not None]))


def _flags(state: ParticleState) -> Tensor:
    """``state.exists (B, N, K)``; a ValueError if the filter returned a state without flags."""
    if state.exists is None:
        raise ValueError("the filter returned a state with exists=None; track needs existence flags")
    return state.exists


@contextlib.contextmanager
def _one_thread(device: torch.device) -> Iterator[None]:
    """Small tensors: on the CPU one intra-op thread is faster (no oversubscription)."""
    old = torch.get_num_threads()
    if device.type == "cpu":
        torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def _summary(result: TrackResult, data: scenario.MaroulasData, n: int, seconds: float) -> dict:
    rmse = scenario.rmse_per_target(result.mean, data.x, data.alive)[1:]  # (T, B), t = 1..T
    per_run = rmse.mean(0)  # time average of each run
    curve = rmse.mean(1)
    ess_pct = 100.0 * result.ess / n
    after_pct = None if result.ess_after_move is None else 100.0 * result.ess_after_move / n
    return dict(
        particles=n,
        rmse_time_average=per_run.mean(), rmse_time_average_runs_std=per_run.std() if per_run.numel() > 1 else 0.0,
        rmse_time_std=rmse.std(0).mean(), rmse_median=rmse.median(),
        ess_percent=ess_pct.mean(),
        ess_after_move_percent=None if after_pct is None else after_pct.mean(),
        hmc_acceptance=None if result.acceptance is None else result.acceptance.mean(),
        seconds_per_step=seconds / rmse.shape[0],
        rmse_curve=curve, ess_percent_curve=ess_pct.mean(1),
        ess_after_move_percent_curve=None if after_pct is None else after_pct.mean(1),
    )


def _figures(out: str | Path, obs: str, results: dict, data: scenario.MaroulasData, sensor: AssociationSensor,
             quick: bool = False) -> None:
    import matplotlib.pyplot as plt

    from ..plotting import plot_rmse

    q = " (quick)" if quick else ""
    labels = {k: np_label(k, v["particles"]) for k, v in results.items()}
    fig, ax = plt.subplots(figsize=(6, 3.5))
    plot_rmse(ax, {labels[k]: v["rmse_curve"] for k, v in results.items()}, ylabel="RMSE per target (eq. 31) [m]")
    ax.set_yscale("log")
    ax.set_title(f"{obs}: RMSE per target, mean over {data.x.shape[1]} runs{q}")
    save_figure(fig, out, f"rmse_{obs}.png", quick=quick)

    fig, ax = plt.subplots(figsize=(6, 3.5))
    curves = {labels[k]: v["ess_percent_curve"] for k, v in results.items()}
    curves.update({f"{labels[k]}, after move": v["ess_after_move_percent_curve"] for k, v in results.items()
                   if v.get("ess_after_move_percent_curve") is not None and k == "improved"})
    plot_rmse(ax, curves, ylabel="ESS [% of Np]")
    ax.set_title(f"{obs}: effective sample size{q}")
    save_figure(fig, out, f"ess_{obs}.png", quick=quick)

    fig, ax = plt.subplots(figsize=(5, 5))
    alive = data.alive[:, 0].unsqueeze(-1)
    nan = torch.tensor(float("nan"), dtype=data.x.dtype, device=data.x.device)
    xy = torch.where(alive, data.x[:, 0][..., [0, 2]], nan)  # NaN breaks the line of a reused slot
    zxy = torch.where(alive, sensor.to_position(data.z_slot[:, 0]), nan)
    est = torch.where(alive, results["improved"]["track_mean"][..., [0, 2]], nan)[::5]
    for k in range(xy.shape[1]):
        ax.plot(xy[:, k, 0], xy[:, k, 1], "-", lw=1, color=f"C{k}", label="truth" if k == 0 else None)
        ax.plot(zxy[:, k, 0], zxy[:, k, 1], "x", ms=3, color="gray", label="observations" if k == 0 else None)
        ax.plot(est[:, k, 0], est[:, k, 1], ".", color=f"C{k}", mec="k", mew=0.3,
                label=labels["improved"] if k == 0 else None)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(fontsize="small")
    ax.set_title(f"{obs}: run 0 (estimates every 5 steps){q}")
    save_figure(fig, out, f"tracks_{obs}.png", quick=quick)


class HMCvsGeneric(Study[MaroulasSettings]):
    """Figs. 3, 4, 7, 8 of paper 003 (module docstring); not sharded."""

    name = "maroulas-hmc"
    description = "Maroulas & Stinis 2010 Figs. 3, 4, 7, 8: PF with an HMC move vs the generic PF (RMSE, ESS)"
    outputs = tuple(f"{kind}_{obs}.png" for obs in scenario.OBSERVATIONS for kind in ("rmse", "ess", "tracks")) \
        + ("metrics.json",)

    def compute(self, settings: MaroulasSettings, options: RunOptions) -> dict:
        """Run the study (module docstring); writes the PNGs into ``options.out``."""
        cfg, device = asdict(settings), options.device
        g = generator(device, options.seed)
        motion = scenario.WhiteAccelerationMotion().to(device)
        metrics: dict[str, Any] = {"config": cfg, "paper": PAPER}
        with _one_thread(device):
            for obs in scenario.OBSERVATIONS:
                sensor = scenario.paper_sensor(obs).to(device)
                data = scenario.simulate(cfg["runs"], cfg["steps"], sensor=sensor, generator=g, motion=motion,
                                         device=device)
                n_rm, n_gen = PAPER[obs]["particles"]
                filters = {
                    "improved": ResampleMoveFilter(motion, sensor, num_particles=n_rm, num_hmc_steps=cfg["hmc_steps"]),
                    "generic": ResampleMoveFilter(motion, sensor, num_particles=n_gen, num_hmc_steps=0),
                }
                results: dict[str, Any] = {}
                times: dict[str, float] = {}
                for name, filt in filters.items():
                    with StepTimer(device, cfg["steps"]) as timer:
                        res = track(filt, data, generator=g, progress=options.progress)
                    times[name] = timer.seconds
                    results[name] = _summary(res, data, filt.num_particles, timer.seconds)
                    results[name]["track_mean"] = res.mean[:, 0]
                ratio = times["improved"] / times["generic"]
                n_eq = min(int(n_gen * ratio), cfg["max_equal_time_particles"])
                filt = ResampleMoveFilter(motion, sensor, num_particles=n_eq, num_hmc_steps=0)
                with StepTimer(device, cfg["steps"]) as timer:
                    res = track(filt, data, generator=g, progress=options.progress)
                results["generic_equal_time"] = _summary(res, data, n_eq, timer.seconds)
                _figures(options.out, obs, results, data, sensor, quick=settings.quick)
                for v in results.values():
                    v.pop("track_mean", None)
                results["time_ratio_improved_over_generic"] = ratio
                metrics[obs] = results
        return metrics

    def summary(self, payload: dict) -> str:
        """Headline table: time-averaged RMSE per target and ESS per observation model and filter."""
        lines = ["| observation | filter | Np | RMSE per target [m] | ESS before move [% of Np] | ESS after move "
                 "[% of Np] | s / step |", "|---|---|---|---|---|---|---|"]
        for obs in scenario.OBSERVATIONS:
            for name, r in payload[obs].items():
                if isinstance(r, dict):
                    lines.append(f"| {obs} | {name} | {r['particles']} | {float(r['rmse_time_average']):.2f} | "
                                 f"{float(r['ess_percent']):.1f} | {cell(r.get('ess_after_move_percent'), 1)} | "
                                 f"{r['seconds_per_step']:.3f} |")
        return "\n".join(lines) + "\n"


STUDY = HMCvsGeneric()
