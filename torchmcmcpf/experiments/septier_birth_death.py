"""Unknown, time-varying number of targets: the setting of Septier, Pang, Carmi and Godsill
(paper 001): 5000 x 5000 m, up to 5 targets with random births and deaths, nearly constant
velocity, point measurements in Poisson clutter (:mod:`torchmcmcpf.scenarios.septier`), and
the head-to-head against the trackers a user would pick instead (issue 27).

What runs
---------
Ours, every particle starting with all slots inactive, all with the same birth proposal:

- SIR PF with existence (:class:`~torchmcmcpf.filters.sir.SIRFilter` with a
  :class:`~torchmcmcpf.models.existence.BirthDeath` model, births near the measurements),
- MCMC-PF (:class:`~torchmcmcpf.filters.mcmc.MCMCFilter`, paper 001's adapted algorithm:
  joint draw w.p. 0.75, else a refinement sweep over the slots; ``N / 2`` chains keeping 2
  samples each after ``burn_in`` iterations),
- IP-MCMC-PF (:class:`~torchmcmcpf.filters.ipmcmc.IPMCMCFilter`, exchange moves with the
  existence chain; ``N / 10`` chains, a fixed ``3 burn_in`` iterations of burn-in, no R-hat
  check: below).

Why the IP-MCMC-PF's R-hat rule is a fixed burn-in here
-------------------------------------------------------
Paper 000's rule lengthens the chains of a run while R-hat (eq. 13) is ``>= 1.1``, at most
twice by ``N / C`` iterations. On this scene, with ``2 burn_in`` iterations of burn-in, it
extended 99.8 % of the steps to the maximum and left R-hat below 1.1 in 0.3 % (seeds 1
and 2 of the filter on seed 0's scenes, 10 runs x 60 steps each; mean R-hat 2.9 and 2.5
after the extensions): the chains disagree on which slots exist and on a newborn's
velocity, and an exchange move changes one slot's existence rarely. They do mix, slowly: a
long-chain reference on one step (the study's filter to step 7, then step 8 with
``burn_in`` 40, 160, 640, 2,560) gives a median R-hat over the runs of 2.52, 1.90, 1.40,
1.10. So the rule is a fixed burn-in of ``2 burn_in + 2 N / C`` iterations here, and it is
run as one: ``3 burn_in`` (60 = 40 + 2 x 10 at the full settings) without extensions, the
same iterations without the two extra R-hat reports (each relabels every chain state of
its window): 22-26 % of the step. OSPA with the rule 9.06 / 10.25 m, as a fixed burn-in
9.52 / 10.20 m (the two filter seeds; seed to seed the OSPA moves by 1 m); without the
extra iterations (``2 burn_in``, no extensions) 10.30 / 11.02 m. Since 2026-12-04 it runs
without the check at all (``rhat_method=None``): the one R-hat report left relabelled the
window's chain states for a value never read, 11 % of the step (6.5 of 58 ms per step and run);
the particles, estimates and scores are the same bits.

Stone Soup's (:mod:`torchmcmcpf.interop.stonesoup_trackers`, when Stone Soup is installed;
otherwise the study says so and runs ours alone), on the same frames with the scene's true
model (constant velocity ``q = 1``, ``R = 100 I``, ``P_d = 1 - e^-4``, clutter density
``L_C / V``, survival ``1 - P_D``, births as the scene's), built as Stone Soup's tutorials
build them:

- GM-PHD on the raw points,
- GM-PHD on the points clustered per frame (one detection per cluster, at its centroid
  with noise ``R / n``),
- JPDA with EHM on the clustered points, with a multi-measurement initiator and an
  update-time deleter.

Their free knobs (:data:`STONESOUP`) were tuned by ``reproduce septier-birth-death --tune``:
a grid (:data:`TUNE_GRIDS`) scored by the mean OSPA on scenes of seeds 100-104
(:data:`TUNE_SEEDS`, 2 runs x 60 steps each), never on the reported seed's scenes; it writes
every grid point's scores to ``tuning.json``.

Scores
------
Every tracker reports a set of targets per step: ours the slots with existence probability
> 0.5 at their mean given existence
(:func:`~torchmcmcpf.models.existence.existence_estimate`), GM-PHD the components above the
extraction threshold, JPDA its confirmed tracks. Per step and run: OSPA and GOSPA (c = 100 m,
p = 2, alpha = 2) with GOSPA's localisation, missed and false parts
(:func:`~torchmcmcpf.metrics.gospa_parts`), the number of targets reported and its error
``|reported - true|``; their means over the runs per step, over all steps and per third of
the run; the wall-clock time per step and run (ours: a shard's runs filtered as one batch,
the time divided by its runs; Stone Soup: one run at a time), overall and per third.
Ours also record the expected number of targets (the sum of existence probabilities).

Precision
---------
The scenes are simulated in float64 (Stone Soup's NumPy trackers and the scores read them as
they are); ours filter them in ``--dtype`` (float32 unless asked), their models and frames cast
once (:func:`our_problem`). Float32 resolves 0.5 mm at 5 km, a thousandth of a step's
motion noise; the point sensor forms its Gaussian exponents and its chains' intensities in
float64 whatever the dtype (:func:`~torchmcmcpf.models.sensors.points.gauss_exponents`).
Half the bytes and twice the lanes of every other pass: on seed
0's scenes (2026-12-06, AMD EPYC, one thread, the two in turn) the MCMC-PF step 115 -> 81 ms a
run, the IP-MCMC-PF 38 -> 29 ms. OSPA float64 -> float32, the full study: seed 0 MCMC-PF 9.5
-> 9.9 m, IP-MCMC-PF 10.1 -> 10.0, SIR 30.2 -> 27.5; seed 1 10.4 -> 10.2, 8.8 -> 9.8, 26.9 ->
27.4: within a filter seed's swing (about 1 m). ``--dtype float64`` gives the float64 figures
of the code before bit for bit.

Writes ``metrics.json``, ``tracks.png`` (run 0, one panel per filter of ours),
``cardinality.png`` (every tracker) and ``ospa.png`` (OSPA and GOSPA over time, every
tracker).

The runs are cut into shards of ``--shard-size`` runs (10, quick 1), each from the generator
of ``(seed, shard index)`` (:func:`run_shard`), so ``--workers N`` on Ray writes the same
numbers. Ours filter each third of the run as one call resumed from the previous one's
state (the same numbers as one call), so each third is timed.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import itertools
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .. import metrics
from ..filters.ipmcmc import IPMCMCFilter
from ..filters.mcmc import MCMCFilter
from ..filters.sir import SIRFilter
from ..interop.stonesoup_trackers import GMPHDSettings, JPDASettings, PointScene, pad_estimates, track_run
from ..models.base import MotionModel, SensorModel
from ..models.existence import BirthDeath
from ..scenarios.septier import SeptierScenario, septier
from ..typing import PointFrame, X, Y
from ._figures import np_label, pyplot, save_figure
from ._options import RunOptions
from ._shards import Shards, shard_generator
from ._study import Settings, StepTimer, Study, option

CUTOFF, ORDER = 100.0, 2.0
FILTERS = ("SIR PF", "MCMC-PF", "IP-MCMC-PF")
PARTS = ("ospa", "gospa", "localisation", "missed", "false", "reported", "cardinality_error")

#: Stone Soup's trackers: name -> (kind, settings). Tuned by ``--tune`` (module docstring) on
#: seeds 100-104: each the grid point of :data:`TUNE_GRIDS` with the least mean OSPA there.
STONESOUP: dict[str, tuple[str, GMPHDSettings | JPDASettings]] = {
    "Stone Soup GM-PHD": ("gmphd", GMPHDSettings(cluster=None, birth_weight=0.05, extraction_threshold=0.9,
                                                 merge_threshold=16.0)),
    "Stone Soup GM-PHD, clustered": ("gmphd", GMPHDSettings(cluster=40.0, birth_weight=0.25,
                                                            extraction_threshold=0.7, merge_threshold=16.0)),
    "Stone Soup JPDA (EHM), clustered": ("jpda", JPDASettings(cluster=40.0, min_points=2, deleter_steps=2)),
}
#: the tuning: scenes of these seeds (each ``septier(runs, steps)`` from the generator of
#: ``(seed, 0)``), never the reported seed's
TUNE_SEEDS = (100, 101, 102, 103, 104)
TUNE = dict(runs=2, steps=60)
#: the grid per tracker: every combination of these values (the other fields keep the
#: defaults of :class:`GMPHDSettings`, :class:`JPDASettings`: Stone Soup's tutorial values)
TUNE_GRIDS: dict[str, dict[str, tuple]] = {
    "Stone Soup GM-PHD": dict(cluster=(None,), birth_weight=(0.05, 0.25, 1.0),
                              extraction_threshold=(0.25, 0.5, 0.7, 0.9), merge_threshold=(5.0, 16.0)),
    "Stone Soup GM-PHD, clustered": dict(cluster=(20.0, 40.0), birth_weight=(0.05, 0.25, 1.0),
                                         extraction_threshold=(0.25, 0.5, 0.7, 0.9), merge_threshold=(5.0, 16.0)),
    "Stone Soup JPDA (EHM), clustered": dict(cluster=(20.0, 30.0, 40.0), min_points=(2, 3), deleter_steps=(1, 2, 3)),
}


@dataclass(frozen=True)
class BirthDeathSettings(Settings):
    """The settings of :class:`BirthsAndDeaths` (full values: 10 runs x 60 steps, the runs
    filtered as one batch, the size of issue 27's measurement; the second of each pair:
    ``--quick``).
    """

    runs: int = option(10, 3, help="Monte Carlo runs")
    steps: int = option(60, 25, help="time steps")
    particles: int = option(2000, 300, help="particles Np")
    burn_in: int = option(20, 10, help="MCMC-PF burn-in per step; IP-MCMC-PF uses three times it")
    dtype: str = option("float32", choices=("float32", "float64"),
                        help="our filters' floating dtype (the scenes are simulated in float64, which Stone Soup's "
                             "NumPy trackers keep; module docstring)")
    shard_size: int = option(10, 1, cli=False)
    tune: bool = option(False, record=False,
                        help="instead of the study: tune Stone Soup's trackers on the scenes of seeds "
                             f"{TUNE_SEEDS[0]}-{TUNE_SEEDS[-1]} ({TUNE['runs']} runs x {TUNE['steps']} steps each; "
                             "--quick: 1 run x 10 steps, the first grid points) and write tuning.json")
    #: run Stone Soup's trackers too (``None``: when Stone Soup is installed)
    stonesoup: bool | None = option(None, cli=False)

    def __post_init__(self) -> None:
        if self.stonesoup is None:
            object.__setattr__(self, "stonesoup", importlib.util.find_spec("stonesoup") is not None)

    def record(self) -> dict:
        """The settings as ``metrics.json`` records them under ``"config"`` (Stone Soup's
        trackers with their settings, or ``None``).
        """
        stonesoup = {name: {"kind": kind, **dataclasses.asdict(s)} for name, (kind, s) in STONESOUP.items()}
        return {**super().record(), "stonesoup": stonesoup if self.stonesoup else None}


def _divisor_at_most(n: int, c: int) -> int:
    """The largest divisor of ``n`` that is ``<= c`` (a chain count that divides N)."""
    return max(d for d in range(1, max(1, min(n, c)) + 1) if n % d == 0)


def _masked_positions(x: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """(T, B, K, D) -> (T, B, K, D) with NaN wherever ``keep`` is False (breaks plot lines)."""
    return torch.where(keep.unsqueeze(-1), x, torch.full_like(x, float("nan")))


def thirds(steps: int) -> list[range]:
    """Steps ``0 .. steps - 1`` in three consecutive parts as equal as can be (60 steps:
    1-20, 21-40, 41-60 counted from 1); fewer than 3 steps give empty parts.
    """
    cuts = [round(i * steps / 3) for i in range(4)]
    return [range(a, b) for a, b in zip(cuts, cuts[1:])]


def our_problem(scn: SeptierScenario, cfg: BirthDeathSettings, device: torch.device
                ) -> tuple[MotionModel, SensorModel, BirthDeath, PointFrame]:
    """The scene's models and frames as our filters take them: on ``device``, in
    ``cfg.dtype`` (the scene itself, simulated in float64, is what Stone Soup's trackers and
    the scores read). Returns ``(motion, sensor, existence, frames)``, frames ``(T, B, M, 2)``.
    """
    dtype = getattr(torch, cfg.dtype)
    z = scn.measurements
    return (scn.motion.to(device=device, dtype=dtype), scn.sensor.to(device=device, dtype=dtype),
            scn.existence.to(device=device, dtype=dtype), PointFrame(z.z.to(device=device, dtype=dtype),
                                                                     z.mask.to(device)))


def _filters(cfg: BirthDeathSettings, motion: MotionModel, sensor: SensorModel, existence: BirthDeath) -> dict:
    n, burn_in = cfg.particles, cfg.burn_in
    return {
        "SIR PF": SIRFilter(motion, sensor, num_particles=n, existence=existence),
        "MCMC-PF": MCMCFilter(motion, sensor, num_particles=n, num_chains=_divisor_at_most(n, n // 2),
                              burn_in=burn_in, existence=existence),
        "IP-MCMC-PF": IPMCMCFilter(motion, sensor, num_particles=n, num_chains=max(2, _divisor_at_most(n, n // 10)),
                                   burn_in=3 * burn_in, rhat_method=None, existence=existence),  # module docstring
    }


def set_scores(est: torch.Tensor, present: torch.Tensor, truth: torch.Tensor, alive: torch.Tensor) -> dict:
    """Per step and run, the scores of one tracker's reported sets (:data:`PARTS`).

    Parameters
    ----------
    est : (T, B, W, D) reported states (layout ``[x, vx, y, vy]``); present : (T, B, W) bool,
        which are reported; truth : (T, B, K, D); alive : (T, B, K) bool.

    Returns
    -------
    dict of ``(B, T)`` tensors: ``ospa``, ``gospa`` and its ``localisation`` [m], ``missed``,
    ``false``, ``reported`` (number of targets reported) and ``cardinality_error``
    (``|reported - true|``).
    """
    est_pos, true_pos = est[..., [X, Y]], truth[..., [X, Y]]
    parts = metrics.gospa_parts(est_pos, true_pos, c=CUTOFF, p=ORDER, x_mask=present, y_mask=alive)
    reported = present.sum(-1).to(truth.dtype)
    return {k: v.T for k, v in {
        "ospa": metrics.ospa(est_pos, true_pos, c=CUTOFF, p=ORDER, x_mask=present, y_mask=alive),
        "gospa": parts.total, "localisation": parts.localisation, "missed": parts.missed, "false": parts.false,
        "reported": reported, "cardinality_error": metrics.cardinality_error(reported, alive.sum(-1)),
    }.items()}


def _names(per_run: dict) -> list[str]:
    """The trackers present in ``per_run``: ours, then Stone Soup's."""
    return [n for n in (*FILTERS, *STONESOUP) if f"{n}|ospa" in per_run]


def _third_labels(steps: int) -> str:
    return " / ".join(f"{p.start + 1}-{p.stop}" for p in thirds(steps) if len(p))


# -- tuning Stone Soup's knobs on other seeds -----------------------------------------------


def _grid(name: str, quick: bool) -> list:
    kind, base = STONESOUP[name]
    keys, values = zip(*TUNE_GRIDS[name].items())
    points = [dataclasses.replace(type(base)(), **dict(zip(keys, combo))) for combo in itertools.product(*values)]
    return points[:2] if quick else points


def tuning_scenes(quick: bool = False) -> list:
    """The scenes the tuning scores on: ``septier(runs, steps)`` from the generator of
    ``(seed, 0)`` for each of :data:`TUNE_SEEDS` (:data:`TUNE`; quick: 1 run x 10 steps).
    """
    runs, steps = (1, 10) if quick else (TUNE["runs"], TUNE["steps"])
    return [septier(runs, steps, generator=shard_generator("cpu", s, 0)) for s in TUNE_SEEDS]


def score_settings(kind: str, settings: GMPHDSettings | JPDASettings, scenes: list) -> dict:
    """Mean scores (:func:`set_scores`) and seconds per step and run of one Stone Soup tracker
    setting over every run and step of ``scenes``.
    """
    scores: dict[str, list] = {key: [] for key in PARTS}
    secs, steps = 0.0, 0
    for scn in scenes:
        scene = PointScene.from_models(scn.motion, scn.sensor, scn.existence, scn.alive.shape[-1])
        done = [track_run(kind, settings, scene, scn.measurements, r) for r in range(scn.alive.shape[1])]
        est, present = pad_estimates([d.estimates for d in done])
        for key, value in set_scores(est, present, scn.truth, scn.alive).items():
            scores[key].append(value)
        secs += sum(float(d.step_seconds.sum()) for d in done)
        steps += scn.alive.shape[0] * scn.alive.shape[1]
    return {"settings": dataclasses.asdict(settings),
            **{key: float(torch.cat(v).double().mean()) for key, v in scores.items()},
            "seconds_per_step": secs / steps}


def tune(*, quick: bool = False, progress: bool = False) -> dict:
    """Score every grid point of :data:`TUNE_GRIDS` on :func:`tuning_scenes`.

    Returns
    -------
    dict tracker name -> ``{"grid": [settings and mean ospa, gospa, missed, false, reported,
    seconds per step, best first], "best": the settings with the least mean OSPA}``.
    """
    from tqdm.auto import tqdm

    scenes = tuning_scenes(quick)
    out = {}
    for name, (kind, _) in STONESOUP.items():
        rows = [score_settings(kind, settings, scenes)
                for settings in tqdm(_grid(name, quick), desc=name, disable=not progress)]
        rows.sort(key=lambda r: r["ospa"])
        out[name] = {"grid": rows, "best": rows[0]["settings"]}
    return out


def tuning_summary(tuning: dict, top: int = 5) -> str:
    """The ``top`` grid points per tracker, best first."""
    lines = []
    for name, t in tuning.items():
        keys = list(TUNE_GRIDS[name])
        lines += [f"{name}: best of {len(t['grid'])} grid points (mean over seeds {TUNE_SEEDS[0]}-{TUNE_SEEDS[-1]})",
                  "", "| " + " | ".join(keys) + " | OSPA [m] | GOSPA [m] | missed / false per step | reported |",
                  "|" + "---|" * (len(keys) + 4)]
        for row in t["grid"][:top]:
            lines.append("| " + " | ".join(str(row["settings"][k]) for k in keys) + f" | {row['ospa']:.2f} | "
                         f"{row['gospa']:.2f} | {row['missed']:.3f} / {row['false']:.3f} | {row['reported']:.2f} |")
        lines.append("")
    return "\n".join(lines)


class BirthsAndDeaths(Study[BirthDeathSettings]):
    """Births and deaths in clutter, ours against Stone Soup's (module docstring)."""

    name = "septier-birth-death"
    description = ("Septier et al. setting: up to 5 targets with births/deaths in Poisson clutter; ours against Stone "
                   "Soup's GM-PHD and JPDA (OSPA, GOSPA parts, cardinality, time per step)")
    outputs = ("metrics.json", "tracks.png", "cardinality.png", "ospa.png", "shards", "tuning.json")

    def run_shard(self, cfg: BirthDeathSettings, runs: range, *, generator: torch.Generator, device: torch.device,
                  progress: bool = False) -> tuple[dict, dict]:
        """Simulate the runs ``runs`` and track them with every tracker (ours: one batch).

        Returns
        -------
        ``per_run`` with ``"truth"`` ``(R, T, K, 4)`` (NaN where absent), ``"true_count"``
        ``(R, T)`` and per tracker ``f``: ``"f|<score>"`` ``(R, T)`` for every score of
        :func:`set_scores`; ours also ``"f|count"`` (expected number of targets) and
        ``"f|estimate"`` ``(R, T, K, 4)`` (NaN where the existence probability is <= 0.5).
        ``seconds``: per tracker and third ``i`` of the run, ``"f|i"``, the wall-clock time of
        those steps for all the shard's runs.
        """
        scn = septier(len(runs), cfg.steps, generator=generator)
        scn = scn._replace(truth=scn.truth.to(device))
        motion, sensor, existence, z = our_problem(scn, cfg, device)
        b, k = scn.alive.shape[1:]
        init = torch.zeros((b, cfg.particles, k, 4), dtype=z.z.dtype, device=device)
        per_run = {"truth": _masked_positions(scn.truth, scn.alive).movedim(1, 0),
                   "true_count": scn.true_count.movedim(1, 0)}
        seconds = {}
        parts = [p for p in thirds(cfg.steps) if len(p)]
        for name, filt in _filters(cfg, motion, sensor, existence).items():
            state, means, probs = init, [], []
            for i, part in enumerate(parts):  # each third resumed from the last one's state: timed apart
                zi = type(z)(*(a[part.start:part.stop] for a in z))
                # no gradients: inference mode drops autograd's per-operation work (docs/performance.md)
                with StepTimer(device, len(part)) as timer, torch.inference_mode():
                    res = filt(zi, init=state, generator=generator, progress=progress)
                seconds[f"{name}|{i}"] = timer.seconds
                state = res.state
                means.append(res.mean)
                probs.append(res.exists_prob)
            mean, exists_prob = torch.cat(means).to(scn.truth.dtype), torch.cat(probs).to(scn.truth.dtype)
            present = exists_prob > 0.5  # (T, B, K)
            for key, value in set_scores(mean, present, scn.truth, scn.alive).items():
                per_run[f"{name}|{key}"] = value
            per_run[f"{name}|count"] = exists_prob.sum(-1).T
            per_run[f"{name}|estimate"] = _masked_positions(mean, present).movedim(1, 0)
        if cfg.stonesoup:
            scene = PointScene.from_models(scn.motion, scn.sensor, scn.existence, k)
            for name, (kind, settings) in STONESOUP.items():  # Stone Soup: one run at a time, float64
                done = [track_run(kind, settings, scene, scn.measurements, r) for r in range(b)]
                est, present = pad_estimates([d.estimates for d in done])
                for key, value in set_scores(est.to(device), present.to(device), scn.truth, scn.alive).items():
                    per_run[f"{name}|{key}"] = value
                step_seconds = np.sum([d.step_seconds for d in done], axis=0)
                for i, part in enumerate(parts):
                    seconds[f"{name}|{i}"] = float(step_seconds[part.start:part.stop].sum())
        return per_run, seconds

    @staticmethod
    def aggregate(cfg: BirthDeathSettings, per_run: dict, seconds: dict) -> dict:
        """Per tracker: per-step means over the runs, their time averages overall and per third,
        and the seconds per step and run, overall and per third.
        """
        runs, steps = per_run["true_count"].shape
        parts = [p for p in thirds(steps) if len(p)]
        results = {}
        for name in _names(per_run):
            r: dict = {}
            for key in PARTS:
                v = per_run[f"{name}|{key}"].double()
                r[f"{key}_per_step"] = v.mean(0)
                r[key] = v.mean()
                r[f"{key}_thirds"] = [v[:, p.start:p.stop].mean() for p in parts]
            secs = [seconds[f"{name}|{i}"] for i in range(len(parts))]
            r["seconds_per_step"] = sum(secs) / (steps * runs)
            r["seconds_per_step_thirds"] = [s / (len(p) * runs) for s, p in zip(secs, parts)]
            if f"{name}|count" in per_run:
                r["expected_count_per_step"] = per_run[f"{name}|count"].double().mean(0)
            results[name] = r
        return results

    def summary(self, payload: dict) -> str:
        """Headline tables: every tracker overall, then per third of the run (or, after
        ``--tune``, the best grid points per Stone Soup tracker).
        """
        if "tuning" in payload:
            return tuning_summary(payload["tuning"])
        res, cfg = payload["results"], payload["config"]
        true = float(torch.as_tensor(payload["true_count_per_step"]).double().mean())
        batch = min(cfg["shard_size"], cfg["runs"])

        def f(v, fmt=".1f"):
            return format(float(v), fmt)

        def thirds_of(r, key, fmt=".1f"):
            return " / ".join(f(v, fmt) for v in r[f"{key}_thirds"])

        def ms(name, v):
            return f"{1e3 * v:.0f}" + (f" ({batch} runs batched)" if name in FILTERS and batch > 1 else "")

        lines = [f"| tracker | OSPA [m] | GOSPA [m] | GOSPA localisation [m] | missed / false per step | "
                 f"targets reported (true {true:.2f}) | ms per step per run |", "|---|---|---|---|---|---|---|"]
        for name, r in res.items():
            lines.append(f"| {name} | {f(r['ospa'])} | {f(r['gospa'])} | {f(r['localisation'])} | "
                         f"{f(r['missed'], '.2f')} / {f(r['false'], '.2f')} | {f(r['reported'], '.2f')} | "
                         f"{ms(name, r['seconds_per_step'])} |")
        lines += ["", f"per third of the run (steps {_third_labels(cfg['steps'])}):", "",
                  "| tracker | OSPA [m] | GOSPA [m] | missed per step | false per step | targets reported | "
                  "ms per step per run |", "|---|---|---|---|---|---|---|"]
        for name, r in res.items():
            secs = " / ".join(f"{1e3 * v:.0f}" for v in r["seconds_per_step_thirds"])
            lines.append(f"| {name} | {thirds_of(r, 'ospa')} | {thirds_of(r, 'gospa')} | "
                         f"{thirds_of(r, 'missed', '.2f')} | "
                         f"{thirds_of(r, 'false', '.2f')} | {thirds_of(r, 'reported', '.2f')} | {secs} |")
        if cfg.get("stonesoup") is None:
            lines += ["", "Stone Soup is not installed: its rows are missing (pip install 'torchmcmcpf[bench]')."]
        return "\n".join(lines) + "\n"

    def run(self, settings: BirthDeathSettings, options: RunOptions) -> dict:
        """The study in shards, or with ``settings.tune`` the tuning (``tuning.json`` only)."""
        if not settings.tune:
            return super().run(settings, options)
        if importlib.util.find_spec("stonesoup") is None:
            raise ValueError("--tune needs Stone Soup: pip install 'torchmcmcpf[bench]'")
        start = time.perf_counter()
        tuning = tune(quick=settings.quick, progress=options.progress)
        payload = {"tuning": tuning, "seeds": TUNE_SEEDS, "tune": TUNE, "grids": TUNE_GRIDS,
                   "wall_seconds": time.perf_counter() - start}
        Path(options.out, "tuning.json").write_text(json.dumps(payload, indent=1, default=str))
        return payload

    def summarise(self, cfg: BirthDeathSettings, shards: Shards, out: Path) -> dict:
        """Per tracker results and the three figures (module docstring)."""
        from ..plotting import plot_cardinality, plot_rmse, plot_tracks

        plt = pyplot()
        results = self.aggregate(cfg, shards.per_run, shards.seconds)
        pr, n, quick = shards.per_run, cfg.particles, " (quick)" if cfg.quick else ""
        runs = pr["true_count"].shape[0]
        true_count = pr["true_count"].double().mean(0)

        def label(name):
            return np_label(name, n) if name in FILTERS else name

        fig, axes = plt.subplots(1, len(FILTERS), figsize=(5.5 * len(FILTERS), 5.5), squeeze=False,
                                 layout="constrained")
        for ax, name in zip(axes[0], FILTERS):
            plot_tracks(ax, pr["truth"][0], pr[f"{name}|estimate"][0], estimate_label=np_label(name, n))
            ax.set_title(f"{name} (existence > 0.5)")
        fig.suptitle(f"run 0: true tracks (solid) and estimates (dashed){quick}")
        save_figure(fig, out, "tracks.png", quick=cfg.quick)
        colour = {name: f"C{i}" for i, name in enumerate(results)}  # one colour per tracker in every figure
        fig, ax = plt.subplots(figsize=(8, 4.5))
        curves = {f"{label(name)}: expected number": r["expected_count_per_step"] for name, r in results.items()
                  if "expected_count_per_step" in r}
        curves.update({f"{label(name)}: reported": r["reported_per_step"] for name, r in results.items()})
        styles = {f"{label(name)}: {kind}": {"color": colour[name], "ls": ls, "marker": "o" if ls == "-" else ""}
                  for name in results for kind, ls in (("expected number", "-"), ("reported", "--"))}
        plot_cardinality(ax, true_count, curves, styles=styles)
        ax.legend(fontsize="x-small")
        ax.set_title(f"mean number of targets over {runs} runs{quick}")
        save_figure(fig, out, "cardinality.png", quick=cfg.quick)
        fig, axes = plt.subplots(1, 2, figsize=(13, 4.5), layout="constrained")
        for name in results:
            color, ls = colour[name], "-" if name in FILTERS else "--"
            plot_rmse(axes[0], {label(name): results[name]["ospa_per_step"]}, color=color, ls=ls,
                      ylabel=f"OSPA (c = {CUTOFF:g} m, p = {ORDER:g}) [m]")
            plot_rmse(axes[1], {label(name): results[name]["gospa_per_step"]}, color=color, ls=ls,
                      ylabel=f"GOSPA (c = {CUTOFF:g} m, p = {ORDER:g}, alpha = 2) [m]")
        axes[0].legend(fontsize="x-small")
        fig.suptitle(f"mean over {runs} runs{quick}: ours (solid), Stone Soup (dashed)")
        save_figure(fig, out, "ospa.png", quick=cfg.quick)

        return {"config": cfg.record(), "cutoff": CUTOFF, "order": ORDER, "true_count_per_step": true_count,
                "results": results}


STUDY = BirthsAndDeaths()
