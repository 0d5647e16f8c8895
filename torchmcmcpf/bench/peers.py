"""The point-measurement problem of ``bench``, its peers (Stone Soup, ``particles``) with the
exact Kalman log-evidence, and the arithmetic floors of the point and radar figures.
"""

from __future__ import annotations

import datetime
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch

if TYPE_CHECKING:
    from ..filters.base import Filter


# -- point measurements: ours against Stone Soup and particles ----------------------------------
#: the point problem: one target, constant velocity (dt, q), its position measured with unit noise
POINT_MODEL = dict(dt=1.0, q=0.1, noise_std=1.0)
#: mean of the initial cloud ``N(m0, I)`` (every library starts from it)
POINT_M0 = (0.0, 1.0, 0.0, 1.0)
#: Stone Soup's documented ways of giving the particles' weights (all timed; the fastest is kept)
STONESOUP_WEIGHTS = ("weight", "log_weight", "Probability")


def _point_track(b: int, steps: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Constant-velocity truth ``(steps, B, 4)`` and its noisy position measurements
    ``(steps, B, 2)`` (float64, CPU; every library filters the same numbers).
    """
    from ..models import ConstantVelocity

    g = torch.Generator().manual_seed(seed)
    motion = ConstantVelocity(POINT_MODEL["dt"], POINT_MODEL["q"]).double()
    x = torch.tensor(POINT_M0, dtype=torch.float64).expand(b, 1, 4)
    truth, z = [], []
    for _ in range(steps):
        x = motion.sample(x, generator=g)
        truth.append(x[:, 0])
        z.append(x[:, 0, ::2] + POINT_MODEL["noise_std"] * torch.randn(b, 2, generator=g, dtype=torch.float64))
    return torch.stack(truth), torch.stack(z)


def point_filter(n: int, b: int, steps: int, device: torch.device, dtype: torch.dtype = torch.float32, *,
                 compile_step: bool = False, seed: int = 0) -> tuple[Filter, torch.Tensor, torch.Tensor]:
    """Our SIR filter on the point problem (systematic resampling at every step), the
    measurements ``(T, B, K = 1, 2)`` and an initial cloud ``(B, N, 1, 4)`` drawn from
    ``N(m0, I)``: ``(filt, z, x0)``.
    """
    from ..filters import SIRFilter
    from ..models import ConstantVelocity, LinearGaussian

    _, z = _point_track(b, steps, seed)
    z = z.to(device=device, dtype=dtype).unsqueeze(2)
    motion = ConstantVelocity(POINT_MODEL["dt"], POINT_MODEL["q"])
    filt = SIRFilter(motion, LinearGaussian.position(POINT_MODEL["noise_std"]), n, resample_method="systematic",
                     compile_step=compile_step).to(device=device, dtype=dtype)
    g = torch.Generator(device).manual_seed(seed + 1)
    x0 = torch.tensor(POINT_M0, device=device, dtype=dtype) + torch.randn(b, n, 1, 4, generator=g, device=device,
                                                                          dtype=dtype)
    return filt, z, x0


def point_sir_forward(n: int, b: int, steps: int, device: torch.device, dtype: torch.dtype = torch.float32, *,
                      compile_step: bool = False) -> Callable[[], object]:
    """Each call filters the whole sequence of ``steps`` frames through the public
    ``filt(z, init=x0, generator=g)`` (divide its time by ``steps`` for a time per step).
    """
    filt, z, x0 = point_filter(n, b, steps, device, dtype, compile_step=compile_step)
    g = torch.Generator(device).manual_seed(2)
    return lambda: filt(z, init=x0, generator=g)


def point_sir_step(n: int, b: int, steps: int, device: torch.device, dtype: torch.dtype = torch.float32, *,
                   compile_step: bool = False, public: bool = True) -> Callable[[], object]:
    """Each call filters the next frame (B runs at once) from the state the previous call
    returned: through the public ``filt.step`` (``public``), or through
    :func:`~torchmcmcpf.filters.sir_bound_step` on the filter's bound object, which checks
    nothing (the cost of the step itself, to measure what ``step``'s checks add).
    """
    from ..filters import sir_bound_step

    filt, z, x0 = point_filter(n, b, steps, device, dtype, compile_step=compile_step)
    g = torch.Generator(device).manual_seed(2)
    state: list[Any] = [filt.init(x0), 0]

    def step():
        s, t = state
        if public:
            state[0], _ = filt.step(s, z[t % steps], generator=g)
        else:
            state[0], _ = sir_bound_step(s, z[t % steps], filt.bound, generator=g)
        state[1] = t + 1
        return state[0]

    return step


def point_floor(n: int, b: int, device: torch.device, dtype: torch.dtype = torch.float32) -> Callable[[], object]:
    """The floor of one point SIR step (B runs, N particles, K = 1, D = 4): what no
    implementation of the step can avoid with torch's generator. The random numbers it must
    draw (4 normals per particle, one uniform per run) and one pass over the memory it must
    touch (read the cloud and the noise, write the new cloud; read and write the weights).
    """
    g = torch.Generator(device).manual_seed(0)
    x = torch.randn(b, n, 1, 4, generator=g, device=device, dtype=dtype)
    eps, out = torch.empty_like(x), torch.empty_like(x)
    log_w = torch.randn(b, n, generator=g, device=device, dtype=dtype)

    def step():
        torch.randn(x.shape, generator=g, out=eps)
        torch.rand(b, 1, generator=g, device=device, dtype=torch.float64)
        torch.add(x, eps, out=out)
        return log_w.neg_()

    return step


def radar_floor(terms: int, sensor: Any, device: torch.device, dtype: torch.dtype = torch.float32,
                compiled: bool = True) -> Callable[[], object]:
    """The arithmetic floor of a windowed radar step that evaluates ``terms`` cell terms: what
    no implementation of the windowed likelihood can avoid, one amplitude per (sample, target,
    box cell), the product of the target's amplitude and its profile values (per axis, the
    last two merged as the library lays a box out), and the sensor's Rician log ratio there
    (:meth:`RangeDopplerBearingTBD.cell_log_ratio`), summed; compiled (``compiled=True``)
    into one loop over the terms, built from inputs of a few KB (no memory traffic but the
    loop's own). Lower than any real step: no neighbours' amplitudes summed into a cell, no
    ownership of cells shared by two boxes, no gathers of the frame.

    ``terms``: ``N K V`` for the SIR step (every particle's K boxes of ``V =
    prod(geometry.window_sizes)`` cells, 7^3 for the radar); ``B (burn_in + N / C) C x 2 boxes x 2 x V`` for the
    IP-MCMC-PF's one-slot moves (the old and the new box, the cells' log ratio before and
    after the move).

    On the CPU in float32 with the radar's C loop built
    (:mod:`~torchmcmcpf.models.sensors.grid.native`), the same arithmetic in that loop's
    code (:func:`~torchmcmcpf.models.sensors.grid.native.ratio_floor`: one ``log`` a cell
    where the compiled tensor loop evaluates both branches' three; 2.7x faster than it on
    2026-12-07's AMD EPYC), the lower of the two.
    """
    from ..models.sensors.grid import native

    geometry = sensor.geometry
    box = math.prod(geometry.window_sizes)
    g = torch.Generator(device).manual_seed(0)
    if (device.type == "cpu" and dtype == torch.float32 and compiled and native.available()
            and (ratio := sensor.native_ratio()) is not None):
        boxes = max(terms // box, 1)
        amp_c = 1.0 + torch.rand(boxes, generator=g, dtype=dtype)
        prof_c = torch.rand(box, generator=g, dtype=dtype)
        zc_c = 3.0 * torch.rand(box, generator=g, dtype=dtype)
        return lambda: native.ratio_floor(amp_c, prof_c, zc_c, ratio[1])
    # the boxes' cells in the library's layout (GridGeometry.box_cells: the last two axes merged,
    # an innermost loop of 49, which vectorises; one of 7 does not): amp * p_first * p_merged
    layout = tuple(geometry.box_cells)
    amp = 1.0 + torch.rand((max(terms // box, 1),) + (1,) * len(layout), generator=g, device=device, dtype=dtype)
    profiles = [torch.rand((1,) + tuple(w if i == a else 1 for i in range(len(layout))), generator=g, device=device,
                           dtype=dtype) for a, w in enumerate(layout)]
    zc = 3.0 * torch.rand((1,) + layout, generator=g, device=device, dtype=dtype)

    def kernel(amp: torch.Tensor, zc: torch.Tensor, *profiles: torch.Tensor) -> torch.Tensor:
        a = amp
        for p in profiles:
            a = a * p
        return sensor.cell_log_ratio(a, zc).sum()

    fn = torch.compile(kernel, fullgraph=True) if compiled else kernel
    return lambda: fn(amp, zc, *profiles)


def stonesoup_step(n: int, b: int, steps: int, weights: str = "weight") -> Callable[[], object]:
    """Stone Soup's particle filter on the same problem: ``ParticlePredictor`` +
    ``ParticleUpdater`` with a ``SystematicResampler`` (resampling at every update), a
    Python loop over the B runs; each call filters the next measurement of every run.

    ``weights``: how the initial ``ParticleState`` gets its weights, one of
    :data:`STONESOUP_WEIGHTS`: ``"weight"`` (a float array), ``"log_weight"`` (a float
    array of logs), ``"Probability"`` (an array of Stone Soup ``Probability``, as in its
    particle filter tutorial). Stone Soup draws from NumPy's global generator.
    """
    import numpy as np
    from stonesoup.models.measurement.linear import LinearGaussian as SSLinearGaussian
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel
    from stonesoup.models.transition.linear import ConstantVelocity as SSConstantVelocity
    from stonesoup.predictor.particle import ParticlePredictor
    from stonesoup.resampler.particle import SystematicResampler
    from stonesoup.types.array import StateVectors
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.numeric import Probability
    from stonesoup.types.state import ParticleState as SSParticleState
    from stonesoup.updater.particle import ParticleUpdater

    if weights not in STONESOUP_WEIGHTS:
        raise ValueError(f"weights must be one of {STONESOUP_WEIGHTS}, got {weights!r}")
    z = _point_track(b, steps)[1].numpy()
    q, r = POINT_MODEL["q"], POINT_MODEL["noise_std"] ** 2
    transition = CombinedLinearGaussianTransitionModel([SSConstantVelocity(q), SSConstantVelocity(q)])
    sensor = SSLinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=np.diag([r, r]))
    predictor = ParticlePredictor(transition)
    updater = ParticleUpdater(sensor, resampler=SystematicResampler())
    start = datetime.datetime(2026, 1, 1)
    dt = datetime.timedelta(seconds=POINT_MODEL["dt"])
    rng = np.random.default_rng(1)

    def prior():
        sv = StateVectors(np.array(POINT_M0).reshape(4, 1) + rng.standard_normal((4, n)))
        if weights == "weight":
            return SSParticleState(sv, weight=np.full(n, 1.0 / n), timestamp=start)
        if weights == "log_weight":
            return SSParticleState(sv, log_weight=np.full(n, -math.log(n)), timestamp=start)
        return SSParticleState(sv, weight=np.array([Probability(1.0 / n)] * n), timestamp=start)

    priors = [prior() for _ in range(b)]
    t = [0]

    def step():
        k = t[0] % steps
        for i in range(b):  # Stone Soup filters one run at a time
            prediction = predictor.predict(priors[i], timestamp=priors[i].timestamp + dt)
            detection = Detection(z[k, i].reshape(2, 1), timestamp=prediction.timestamp, measurement_model=sensor)
            priors[i] = updater.update(SingleHypothesis(prediction, detection))
        t[0] += 1
        return priors

    return step


def kalman_log_evidence(z: torch.Tensor) -> torch.Tensor:
    """Exact ``log p(z_1:T)`` of the point problem for each run (Kalman filter, float64):
    ``z (T, B, 2) -> (B,)``. The state starts from ``N(m0, I)`` and is predicted once before
    each measurement, as :meth:`~torchmcmcpf.filters.base.Filter.forward` runs.
    """
    from ..models.motion import cv_matrices

    z = z.to(torch.float64)
    F, Q = cv_matrices(POINT_MODEL["dt"], POINT_MODEL["q"], dtype=torch.float64)
    H = torch.zeros(2, 4, dtype=torch.float64)
    H[0, 0] = H[1, 2] = 1.0
    R = POINT_MODEL["noise_std"] ** 2 * torch.eye(2, dtype=torch.float64)
    m = torch.tensor(POINT_M0, dtype=torch.float64).expand(z.shape[1], 4)
    P = torch.eye(4, dtype=torch.float64)  # the same for every run: it does not depend on the data
    total = torch.zeros(z.shape[1], dtype=torch.float64)
    for zt in z:
        m, P = m @ F.mT, F @ P @ F.mT + Q
        S = H @ P @ H.mT + R
        v = zt - m @ H.mT  # (B, 2) innovations
        total += -0.5 * (2 * math.log(2 * math.pi) + torch.logdet(S) + (v @ torch.linalg.inv(S) * v).sum(-1))
        G = P @ H.mT @ torch.linalg.inv(S)
        m = m + v @ G.mT
        P = (torch.eye(4, dtype=torch.float64) - G @ H) @ P
    return total


def particles_runs(n: int, b: int, steps: int, seed: int = 0) -> Callable[[], torch.Tensor]:
    """``particles`` (Chopin's SMC library) on the point problem, one run at a time: each
    call runs a bootstrap filter (``ssm.Bootstrap`` on ``kalman.MVLinearGauss``,
    ``SMC(resampling="systematic", ESSrmin=1.0, store_history=False, collect="off")``,
    i.e. systematic resampling at every step, nothing recorded) over the ``steps`` frames
    of each of the B runs and returns their log-evidence ``(B,)``. One short run is made
    here, before the first call, so that numba's compilation is not timed. Its initial law is the
    predicted one, ``N(F m0, F F' + Q)``, so that its first weighting matches ours.
    """
    import numpy as np
    import particles
    from particles import kalman
    from particles import state_space_models as ssm

    from ..models.motion import cv_matrices

    F, Q = (a.numpy() for a in cv_matrices(POINT_MODEL["dt"], POINT_MODEL["q"], dtype=torch.float64))
    H = np.zeros((2, 4))
    H[0, 0] = H[1, 2] = 1.0
    model = kalman.MVLinearGauss(F=F, G=H, covX=Q, covY=POINT_MODEL["noise_std"] ** 2 * np.eye(2),
                                 mu0=F @ np.array(POINT_M0), cov0=F @ F.T + Q)
    z = _point_track(b, steps, seed)[1].numpy()
    # warm-up: particles compiles its resampling with numba on first use (seconds)
    particles.SMC(fk=ssm.Bootstrap(ssm=model, data=list(z[:2, 0])), N=n, resampling="systematic", ESSrmin=1.0,
                  store_history=False, collect="off", verbose=False).run()

    def runs():
        np.random.seed(seed + 3)  # particles draws from NumPy's global generator
        out = np.empty(b)
        for i in range(b):  # particles filters one run at a time
            pf = particles.SMC(fk=ssm.Bootstrap(ssm=model, data=list(z[:, i])), N=n, resampling="systematic",
                               ESSrmin=1.0, store_history=False, collect="off", verbose=False)
            pf.run()
            out[i] = pf.logLt
        return torch.from_numpy(out)

    return runs


def evidence_errors(log_z: torch.Tensor, exact: torch.Tensor) -> dict:
    """Median and inter-quartile range of ``log_z - exact`` over runs (the check that a
    library filters the model it is timed on: a wrong model is off by tens of nats).
    """
    err = (log_z.to(torch.float64) - exact).cpu()
    q = torch.quantile(err, torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64))
    return dict(median=float(q[1]), iqr=float(q[2] - q[0]))


# -- the run -------------------------------------------------------------------------------------
