"""Where a ``septier-groups`` iteration goes: the group filter (paper 004's marginalised
MCMC-PF, :class:`~torchmcmcpf.filters.group.GroupMCMCFilter`) with the study's sampler and
chains (40 runs x 20 chains, lag 2, the study's move mixture), one step profiled on the
study's frames after 20 warm steps, split into the parts of issue 49 item 1 by the profiler's
inclusive time of the functions that do each part. Run from the repository root:

    python benchmarks/profile_groups.py             # eager: the parts (about 2 minutes)
    python benchmarks/profile_groups.py --compiled  # also the compiled step (compiles 5-6 minutes)

A step here runs ``30 + 6 x 10 = 90`` iterations (burn-in 30, 200 kept samples): an
iteration costs what it costs at the paper's budget (1000 + 6 x 200 iterations a step, 4000
kept samples), whose step is 2200 iterations. Prints the time per iteration (eager, and
compiled with ``--compiled``, the study's default) and each part's share of the profiled
eager step, and the study's time that the compiled iteration implies (110 steps x 2200
iterations). One thread, under ``torch.inference_mode()``, glibc's allocator tuned as
``python -m torchmcmcpf`` tunes it.
"""

from __future__ import annotations

import dataclasses
import sys
import time

import torch
from torch.profiler import profile

from torchmcmcpf.experiments.septier_groups import GroupsSettings, _filter
from torchmcmcpf.runtime import tune_cpu_allocator
from torchmcmcpf.scenarios import group_merge

#: part -> the functions whose inclusive time it is (file suffix, function name); the
#: transition's and the Kalman filter's calls are inside the moves' proposals, counted here
PARTS = {
    "configuration's transition (eqs. 27, 42; Psi, Q, r)": [("motion.py", "transition")],
    "pairwise Kalman predict and update (eqs. 47-58)": [("kalman.py", "pairwise_kalman_predict"),
                                                         ("kalman.py", "pairwise_kalman_update")],
    "thresholded-pixel likelihood (eq. 40)": [("pixels.py", "log_likelihood")],
    "structure prior (eq. 19)": [("structures.py", "log_probs")],
    "positions' Gaussian and birth densities (eqs. 44, 64)": [("moves.py", "_log_px"), ("moves.py", "_birth_ratio")],
    "MH selects and chain gathers": [("mh.py", "select"), ("moves.py", "_gather")],
    "noise draws": [("noise.py", "_draw_fields")],
}

#: the study's steps and iterations per step at the paper's budget
STUDY_STEPS, STUDY_ITERATIONS = 110, 2200
WARM, BURN_IN, KEPT = 20, 30, 200


def main() -> None:
    compiled = "--compiled" in sys.argv[1:]
    torch.set_num_threads(1)
    tune_cpu_allocator()
    cfg = dataclasses.replace(GroupsSettings(), burn_in=BURN_IN, particles=KEPT)
    scn = group_merge(GroupsSettings.runs, generator=torch.Generator().manual_seed(0), num_steps=STUDY_STEPS,
                      merge_step=46)
    frames = scn.frames
    iterations = BURN_IN + cfg.thinning * KEPT // cfg.chains
    for mode in ("eager", "compiled") if compiled else ("eager",):
        filt = _filter(scn, cfg, compile_step=mode == "compiled")
        with torch.inference_mode():  # as the study runs its filter
            state = filt(frames[:WARM], init=filt.init_inactive(frames.shape[1], scn.truth.shape[2]),
                         generator=torch.Generator().manual_seed(1)).state
            times = []
            for _ in range(3):
                start = time.perf_counter()
                filt(frames[WARM:WARM + 1], init=state, generator=torch.Generator().manual_seed(2))
                times.append(time.perf_counter() - start)
            per = min(times) / iterations
            print(f"{mode}: {1e3 * per:.1f} ms an iteration (B = {frames.shape[1]} runs x C = {cfg.chains} chains; "
                  f"best of 3 steps of {iterations} iterations); the study's {STUDY_STEPS} x {STUDY_ITERATIONS} "
                  f"iterations: {STUDY_STEPS * STUDY_ITERATIONS * per / 60:.0f} min")
            if mode != "eager":
                continue
            with profile(with_stack=True) as prof:
                filt(frames[WARM:WARM + 1], init=state, generator=torch.Generator().manual_seed(2))
        totals = {e.key: e.cpu_time_total for e in prof.key_averages() if "torchmcmcpf" in e.key}

        def inclusive(file: str, fn: str) -> float:
            return sum(v for key, v in totals.items() if key.endswith(f"): {fn}") and f"/{file}(" in key)

        total = max(v for key, v in totals.items() if key.endswith("): forward"))
        shares = {part: sum(inclusive(f, fn) for f, fn in where) for part, where in PARTS.items()}
        # the likelihood and structure prior inside the Kalman-based path terms are counted once
        shares["the rest (moves' own arithmetic, proposals, Python and dispatch)"] = total - sum(shares.values())
        print(f"  eager step profiled: {total / 1e6:.2f} s")
        for part, t in shares.items():
            print(f"  {100 * t / total:5.1f} %  {part}")


if __name__ == "__main__":
    main()
