"""Where a births/deaths step goes: the IP-MCMC-PF and the MCMC-PF of
``reproduce septier-birth-death`` (its full settings, B = 10 runs batched, one thread, the
study's first shard of 60 steps), three steps timed and one profiled after 30 steps (half way:
the scene's targets are born over its first steps, and a step at step 2 costs 0.6x a
representative one), split into the parts of issue 49 item 1 by the
profiler's inclusive time of the functions that do each part. Run from the repository root:

    python benchmarks/profile_birth_death.py

Prints, per filter, the unprofiled time per step and run (wall clock and the process's CPU
time, which a busy shared machine inflates less) and each part's share of the profiled step
(profiling inflates the Python-heavy parts a little; the shares are of the profiled total),
then each step's arithmetic floor (:func:`floor`, :func:`floor_mcmc`). Glibc's allocator is tuned as
``python -m torchmcmcpf`` tunes it (large temporaries reuse warm pages), and the filters run
under ``torch.inference_mode()``, as the study runs them.
"""

from __future__ import annotations

import time

import torch
from torch.profiler import profile

from torchmcmcpf.experiments._shards import shard_generator
from torchmcmcpf.experiments.septier_birth_death import BirthDeathSettings, _filters, our_problem
from torchmcmcpf.runtime import tune_cpu_allocator
from torchmcmcpf.scenarios.septier import septier

#: the MCMC-PF's sensor calls: its likelihood part, and inside its bookkeeping's inclusive time
_MCMC_LIKELIHOOD = [("points.py", "log_likelihood"), ("points.py", "amplitude_cache"),
                    ("points.py", "log_likelihood_of_cache"), ("points.py", "log_likelihood_delta_cached")]

#: part -> the functions whose inclusive time it is (file suffix, function name)
PARTS = {
    "IP-MCMC-PF": {
        "likelihood arithmetic": [("points.py", "log_likelihood_delta_cached"), ("points.py", "log_likelihood"),
                                  ("points.py", "amplitude_cache")],
        "move bookkeeping": [("exchange.py", "exchange_iteration"), ("exchange.py", "with_accepted_amplitudes")],
        "noise and proposals": [("ipmcmc.py", "draw"), ("existence.py", "draw_noise")],
        "R-hat": [("ipmcmc.py", "_rhat_report")],
        "relabelling and estimation": [("base.py", "_estimate")],
    },
    "MCMC-PF": {
        "likelihood arithmetic": _MCMC_LIKELIHOOD,
        "move bookkeeping": [("mcmc.py", "mcmc_iteration")],
        "noise and proposals": [("mcmc.py", "draw_iteration_noise"), ("mcmc.py", "relocations")],
        "relabelling and estimation": [("base.py", "_estimate")],
    },
}

#: filter -> the functions whose time the bookkeeping's inclusive time holds but another part counts
INNER = {
    "IP-MCMC-PF": [("points.py", "log_likelihood_delta_cached")],
    "MCMC-PF": _MCMC_LIKELIHOOD,
}


def floor(batch: int = 10, chains: int = 200, iterations: int = 70, points: int = 41,
          dtype: torch.dtype = torch.float32) -> float:
    """The IP-MCMC-PF step's arithmetic floor at the study's settings, per step and run [s]:
    the random numbers its ``iterations`` x ``chains`` exchange moves draw (about 23 each:
    source, slot, motion, accept, birth and relocation draws) and the transcendental
    functions they must evaluate (the moved slot's old and new terms at every point, the
    scored data densities, 0.6 of a draw's ``points`` terms, one ``log`` per point), timed
    as single calls of ``torch.rand``, ``torch.exp`` and ``torch.log`` on that many numbers
    of ``dtype`` (the study's, :class:`BirthDeathSettings`; one thread): what no
    implementation avoids.
    """
    moves = batch * chains * iterations
    return _timed(23 * moves, int(2.6 * points * moves), points * moves, dtype) / batch


def floor_mcmc(batch: int = 10, chains: int = 1000, iterations: int = 22, slots: int = 5, points: int = 41,
               joint: float = 0.75, born: float = 0.25, relocated: float = 0.1, dtype: torch.dtype = torch.float32
               ) -> float:
    """The MCMC-PF step's arithmetic floor at the study's settings (``iterations = burn_in +
    N / C``), per step and run [s], counted as :func:`floor` counts: a joint draw (probability
    ``joint``) draws 2 uniforms and per slot 2 motion normals, the existence uniform, a
    newborn candidate's 4 numbers where the slot can be born (a share ``born``: the proposal's
    0.5 times the half of the slots inactive), the relocation's uniform and its 6 numbers where
    it picks the relocation (a share ``relocated``, ``p_propose``), and evaluates every slot's
    term at every point (``exp``) and one ``log`` per point; a refinement sweep draws per slot
    3 motion and accept numbers and the same birth and relocation ones and evaluates per slot
    its old and new terms at every point and one ``log`` per point.
    """
    draws, sweeps = joint * batch * chains * iterations, (1 - joint) * batch * chains * iterations
    changes = 1 + 4 * born + 1 + 6 * relocated  # per slot: existence, newborn, relocation
    randoms = draws * (2 + (2 + changes) * slots) + sweeps * (3 + changes) * slots
    exps = (draws * slots + sweeps * 2 * slots) * points
    logs = (draws + sweeps * slots) * points
    return _timed(int(randoms), int(exps), int(logs), dtype) / batch


def _timed(randoms: int, exps: int, logs: int, dtype: torch.dtype) -> float:
    """Seconds for single calls of ``torch.rand``, ``torch.exp`` and ``torch.log`` on that
    many numbers of ``dtype`` (best of 5 each, the current thread count; ``log``, not ``log1p``,
    which ATen does not vectorise in float64: 6.7 against 0.9 ns a number), each writing into a
    buffer it wrote before (``out=``): the arithmetic, not the page faults of a fresh 100 MB
    output, which this machine's memory reclaim made vary 1.75x between runs an hour apart
    (2026-12-06).
    """
    g = torch.Generator().manual_seed(0)

    def best(f) -> float:
        times = []
        for _ in range(5):
            start = time.perf_counter()
            f()
            times.append(time.perf_counter() - start)
        return min(times)

    x = torch.rand(exps, generator=g, dtype=dtype)
    y = torch.rand(logs, generator=g, dtype=dtype)
    r, ex, ly = torch.empty(randoms, dtype=dtype), torch.empty_like(x), torch.empty_like(y)
    return best(lambda: torch.rand(randoms, generator=g, dtype=dtype, out=r)) \
        + best(lambda: torch.exp(x, out=ex)) + best(lambda: torch.log(y, out=ly))


def profile_step(filt, frames, init: torch.Tensor, parts: dict, inner: list, warm: int = 30, timed: int = 3
                 ) -> tuple[float, float, float, dict]:
    """One filter's steps after ``warm`` steps (``frames(a, e)`` the frames ``a .. e - 1``,
    ``init`` the initial particles, ``B`` runs): ``timed`` steps timed (wall clock and the
    process's CPU time, ms per step and run), then the next one profiled; ``parts`` and ``inner`` as
    :data:`PARTS` and :data:`INNER` give them for one filter. Returns ``(ms, cpu ms, profiled
    ms of the step, share of each part)``, the rest under "the rest (start, resampling, Python
    and dispatch)". Under ``torch.inference_mode()``, as the studies run their filters.
    """
    b = init.shape[0]
    with torch.inference_mode():
        state = filt(frames(0, warm), init=init, generator=torch.Generator().manual_seed(0)).state
        filt(frames(warm, warm + 1), init=state, generator=torch.Generator().manual_seed(1))  # first-call costs
        start, cpu = time.perf_counter(), time.process_time()
        state = filt(frames(warm, warm + timed), init=state, generator=torch.Generator().manual_seed(1)).state
        plain, cpu = (time.perf_counter() - start) / timed, (time.process_time() - cpu) / timed
        with profile(with_stack=True) as prof:
            filt(frames(warm + timed, warm + timed + 1), init=state, generator=torch.Generator().manual_seed(1))
    totals = {e.key: e.cpu_time_total for e in prof.key_averages() if "torchmcmcpf" in e.key}

    def inclusive(file: str, fn: str) -> float:
        return sum(v for key, v in totals.items() if key.endswith(f"): {fn}") and f"/{file}(" in key)

    total = max(v for key, v in totals.items() if key.endswith("): forward"))
    shares = {part: sum(inclusive(f, fn) for f, fn in where) / total for part, where in parts.items()}
    # the iterations' own sensor calls are inside the bookkeeping's inclusive time
    shares["move bookkeeping"] -= sum(inclusive(f, fn) for f, fn in inner) / total
    shares["the rest (start, resampling, Python and dispatch)"] = 1.0 - sum(shares.values())
    return 1e3 * plain / b, 1e3 * cpu / b, total / 1e3, shares


def report(name: str, ms: float, cpu: float, profiled: float, shares: dict, b: int) -> None:
    """Print one filter's :func:`profile_step`."""
    print(f"\n{name}: {ms:.1f} ms per step and run (B = {b}, unprofiled; CPU time {cpu:.1f} ms); profiled step "
          f"{profiled:.0f} ms")
    for part, v in shares.items():
        print(f"  {part:52s} {100 * v:5.1f} %")


def main() -> None:
    torch.set_num_threads(1)
    tune_cpu_allocator()  # as `python -m torchmcmcpf reproduce` runs the study (torchmcmcpf.runtime)
    cfg = BirthDeathSettings(stonesoup=False)
    scn = septier(10, cfg.steps, generator=shard_generator("cpu", 0, 0))  # the study's first shard
    b, k = scn.alive.shape[1:]
    motion, sensor, existence, z = our_problem(scn, cfg, torch.device("cpu"))  # in the study's dtype
    init = torch.zeros((b, cfg.particles, k, 4), dtype=z.z.dtype)

    def frames(a: int, e: int):
        return type(z)(*(t[a:e] for t in z))

    for name, parts in PARTS.items():
        filt = _filters(cfg, motion, sensor, existence)[name]
        report(name, *profile_step(filt, frames, init, parts, INNER[name]), b)
    dtype = z.z.dtype
    print(f"\nfloors (random numbers and transcendentals in {cfg.dtype}, one thread), ms per step and run: "
          f"IP-MCMC-PF {1e3 * floor(dtype=dtype):.1f}, MCMC-PF {1e3 * floor_mcmc(dtype=dtype):.1f}")


if __name__ == "__main__":
    main()
