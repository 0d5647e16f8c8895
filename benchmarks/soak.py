"""Soak test: does a long IP-MCMC-PF run hold? (issue 14, item 2)

Two variants, each filtered in chunks of ``--every`` steps (the particle state of one chunk is
the ``init`` of the next, so the run is one uninterrupted filter):

- ``fixed``: the ground-radar TBD scene of paper 000 (``--targets`` targets, IP-MCMC-PF with
  ``--chains`` chains and burn-in ``--burn-in``). Frames are simulated chunk by chunk (the
  whole sequence of 100 runs x 1000 frames would not fit in memory); targets move at
  constant velocity with speeds up to ``--max-speed`` m/s so they stay on the grid for the
  whole run. Reported per chunk: position RMSE (slot labels) and track loss.
- ``birth-death``: the Septier et al. setting with ``--targets`` slots, births and deaths,
  IP-MCMC-PF with an existence chain; reported per chunk: OSPA (c = 100 m, p = 2) and the
  mean cardinality error.

Per chunk both also report: non-finite values in the estimates (must be 0), seconds, and the
resident memory of this process read from ``/proc/self/status`` (``VmRSS`` now, ``VmHWM``
the peak so far). Verdict: no NaN; drift = mean error of the last chunk over the mean of
the chunks after the first (the first holds the start-up transient); RSS growth from the
end of the first chunk to the end.

Full size (hours on a 2-core CPU; a GPU is the place for it)::

    python benchmarks/soak.py --runs 100 --steps 1000 --particles 500 --targets 10 --every 100

Reduced size recorded in benchmarks/README.md::

    python benchmarks/soak.py --runs 5 --steps 100 --particles 500 --targets 10 --every 20

Writes ``--out`` (JSON) with the settings, the per-chunk rows and the verdict.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(ROOT))

from torchmcmcpf import metrics  # noqa: E402
from torchmcmcpf.experiments._common import device_arg, positive_int, provenance, to_jsonable  # noqa: E402
from torchmcmcpf.filters.ipmcmc import IPMCMCFilter  # noqa: E402
from torchmcmcpf.typing import VX, VY, X, Y  # noqa: E402


def rss_mib() -> tuple[float, float]:
    """(current, peak) resident set size of this process [MiB], from /proc/self/status."""
    values = {}
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(("VmRSS:", "VmHWM:")):
                key, kib = line.split(":")
                values[key] = int(kib.split()[0]) / 1024.0
    return values.get("VmRSS", math.nan), values.get("VmHWM", math.nan)


def _fixed_chunks(args, g):
    """Yield (name, filter, chunk measurements, chunk truth) for the ground-radar scene."""
    from torchmcmcpf.scenarios import ground_radar

    # The grid and models come from one run over the full length (so the grid covers every
    # target's travel); the B runs' initial states from the same Table I law.
    geometry = ground_radar(args.targets, args.steps, 1, generator=g, device=args.device,
                            speed_limits=(0.0, args.max_speed))
    scn = ground_radar(args.targets, 1, args.runs, generator=g, device=args.device,
                       speed_limits=(0.0, args.max_speed))
    sensor, motion = geometry.sensor, geometry.motion
    del geometry
    filt = IPMCMCFilter(motion, sensor, num_particles=args.particles, num_chains=args.chains,
                        burn_in=args.burn_in).to(args.device)
    init = scn.initial_particles(args.particles, generator=g)
    x0 = scn.initial  # (B, K, 5); truth[t] = x0 moved t + 1 steps at constant velocity
    for start in range(0, args.steps, args.every):
        t = torch.arange(start + 1, min(start + args.every, args.steps) + 1, device=x0.device, dtype=x0.dtype)
        truth = x0.expand(t.numel(), *x0.shape).clone()
        truth[..., X] = x0[..., X] + scn.dt * t[:, None, None] * x0[..., VX]
        truth[..., Y] = x0[..., Y] + scn.dt * t[:, None, None] * x0[..., VY]
        frames = torch.stack([sensor.simulate(truth[i], generator=g) for i in range(t.numel())])
        yield filt, init, frames, truth
        init = None  # continue from the filter's state


def _score_fixed(res, truth):
    """RMSE and track loss over the chunk with the slot labels, and the RMSE with the labels
    matched per run over the chunk (a label swap between two close targets then costs
    nothing; a lost target still does), and the median over runs of the per-run RMSE (what
    a typical run sees, robust to one lost run)."""
    rmse = metrics.position_rmse(res.mean, truth)
    lost = metrics.track_loss(res.mean, truth).float().mean()
    matched = metrics.position_rmse(res.mean, truth, match=True).overall
    return {"rmse_m": float(rmse.overall), "rmse_matched_m": float(matched),
            "rmse_median_run_m": float(rmse.per_run.median()), "track_loss_rate": float(lost)}


def _birth_death_chunks(args, g):
    from torchmcmcpf.scenarios.septier import septier

    scn = septier(args.runs, args.steps, generator=g, num_slots=args.targets)
    motion, sensor, existence = (m.to(args.device) for m in (scn.motion, scn.sensor, scn.existence))
    filt = IPMCMCFilter(motion, sensor, num_particles=args.particles, num_chains=args.chains,
                        burn_in=args.burn_in, existence=existence).to(args.device)
    init = torch.zeros((args.runs, args.particles, args.targets, 4), dtype=torch.float64, device=args.device)
    z = scn.measurements
    for start in range(0, args.steps, args.every):
        sl = slice(start, min(start + args.every, args.steps))
        chunk = type(z)(*(f[sl].to(args.device) for f in z))
        yield filt, init, chunk, (scn.truth[sl].to(args.device), scn.alive[sl].to(args.device))
        init = None


def _score_birth_death(res, truth):
    truth, alive = truth
    present = res.exists_prob > 0.5
    o = metrics.ospa(res.mean[..., [X, Y]], truth[..., [X, Y]], c=100.0, p=2.0, x_mask=present, y_mask=alive)
    card = metrics.cardinality_error(res.exists_prob.sum(-1), alive.sum(-1))
    return {"ospa_m": float(o.mean()), "cardinality_error": float(card.mean())}


VARIANTS = {"fixed": (_fixed_chunks, _score_fixed, "rmse_m"),
            "birth-death": (_birth_death_chunks, _score_birth_death, "ospa_m")}


def soak(variant: str, args) -> dict:
    chunks, score, error_key = VARIANTS[variant]
    g = torch.Generator(device=args.device).manual_seed(args.seed)
    rows, state, done = [], None, 0
    print(f"\n{variant}: {args.runs} runs x {args.steps} steps, Np = {args.particles}, {args.chains} chains, "
          f"burn-in {args.burn_in}, {args.targets} targets, report every {args.every} steps")
    for filt, init, frames, truth in chunks(args, g):
        t0 = time.perf_counter()
        res = filt(frames, init=state if init is None else init, generator=g, progress=False)
        seconds = time.perf_counter() - t0
        state = res.state
        n = res.mean.shape[0]
        done += n
        bad = int((~torch.isfinite(res.mean)).sum()) + int((~torch.isfinite(state.log_w)).sum())
        rss, peak = rss_mib()
        row = {"steps": done, **score(res, truth), "non_finite": bad, "seconds_per_step": seconds / n,
               "rss_mib": rss, "peak_rss_mib": peak}
        rows.append(row)
        if len(rows) == 1:
            print(" ".join(f"{k:>12}" for k in row), flush=True)
        print(" ".join(f"{v:>12.3f}" if isinstance(v, float) else f"{v:>12}" for v in row.values()), flush=True)
    later = [r[error_key] for r in rows[1:]] or [rows[0][error_key]]
    mean_later = sum(later) / len(later)
    verdict = {
        "non_finite_total": sum(r["non_finite"] for r in rows),
        "error_last_over_mean_after_first_chunk": rows[-1][error_key] / mean_later if mean_later > 0 else None,
        "rss_growth_mib_after_first_chunk": rows[-1]["rss_mib"] - rows[0]["rss_mib"],
        "peak_rss_mib": rows[-1]["peak_rss_mib"],
    }
    print("verdict:", json.dumps(verdict))
    return {"rows": rows, "verdict": verdict}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                epilog="full size: --runs 100 --steps 1000 --particles 500 --targets 10 --every 100")
    p.add_argument("--variant", choices=("fixed", "birth-death", "both"), default="both")
    p.add_argument("--runs", type=positive_int, default=100, help="Monte Carlo runs, one batch (default 100)")
    p.add_argument("--steps", type=positive_int, default=1000, help="time steps (default 1000)")
    p.add_argument("--particles", type=positive_int, default=500, help="Np (default 500)")
    p.add_argument("--targets", type=positive_int, default=10, help="targets / target slots (default 10)")
    p.add_argument("--chains", type=positive_int, default=50, help="IP-MCMC-PF chains (default 50)")
    p.add_argument("--burn-in", type=int, default=100, help="IP-MCMC-PF burn-in (default 100)")
    p.add_argument("--every", type=positive_int, default=100, help="report every this many steps (default 100)")
    p.add_argument("--max-speed", type=float, default=1.0,
                   help="fixed variant: largest target speed [m/s] (default 1; the grid grows with the travel)")
    p.add_argument("--device", type=device_arg, default=torch.device("cpu"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("results") / "soak.json")
    args = p.parse_args(argv)
    if args.particles % args.chains:
        p.error(f"argument --particles: {args.particles} do not divide into --chains {args.chains}")
    started = time.perf_counter()
    variants = ("fixed", "birth-death") if args.variant == "both" else (args.variant,)
    report = {"settings": vars(args), "variants": {v: soak(v, args) for v in variants}}
    args.started, args.command_line = started, " ".join(["python", "benchmarks/soak.py", *(argv or sys.argv[1:])])
    report["provenance"] = provenance(args, args.device)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(to_jsonable(report), indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
