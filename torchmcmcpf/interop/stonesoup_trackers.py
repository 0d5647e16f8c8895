"""Stone Soup's own multi-target trackers on this library's point frames: the baselines a
user with point detections in clutter would reach for first.

Stone Soup (``stonesoup``, the ``interop`` and ``bench`` extras) is imported when a function
here is called. Two trackers, each built from Stone Soup components as its tutorials build
them, and run one Monte Carlo run at a time (Stone Soup filters one scene at a time):

- **GM-PHD** (Vo and Ma 2006): ``PointProcessMultiTargetTracker`` with a ``PHDUpdater`` over
  a ``KalmanUpdater``, a ``GaussianMixtureHypothesiser`` over a Mahalanobis
  ``DistanceHypothesiser`` (``missed_distance = 3``), a ``GaussianMixtureReducer`` and one
  birth component, as Stone Soup's "Gaussian mixture PHD tutorial"; the set reported at a
  step is the tracker's ``extracted_target_states`` (the components whose weight exceeds
  the extraction threshold).
- **JPDA with EHM** (Maskell, Briers and Wright 2004): ``MultiTargetMixtureTracker`` with
  ``JPDAwithEHM`` over a ``PDAHypothesiser``, a ``MultiMeasurementInitiator`` (a global
  nearest neighbour tracker on the unassociated detections that releases a track after
  ``min_points`` updates) and an ``UpdateTimeStepsDeleter``, as Stone Soup's "Comparing
  EHM with probability associators" example; the set reported at a step is the last state
  of every confirmed track.

Both assume at most one detection per target and frame, while a target of the
:class:`~torchmcmcpf.models.sensors.points.PoissonClutterPoints` sensor gives a
``Poisson(L_x)`` number of points. The front end is the standard one: the points of a frame
are clustered (single linkage with a distance threshold, i.e. DBSCAN with
``min_samples = 1``) and each cluster of ``n`` points becomes one detection at its centroid
with noise covariance ``R / n`` (the covariance of the mean of ``n`` independent points of
one target). GM-PHD can also take the raw points (``cluster=None``); JPDA cannot usefully.

The model Stone Soup gets is the scene's true one (:class:`PointScene`, read off the
library's model objects by :meth:`PointScene.from_models`): constant velocity with the same
``q`` and ``dt``, ``R``, ``P_d = 1 - exp(-L_x)`` (a target yields at least one point, hence
at least one cluster), clutter density ``L_C / V``, survival ``1 - P_D``, and births as the
scene's (a uniform position over the area, moment-matched by one Gaussian, and a
``N(0, s_v^2)`` velocity). The free knobs each tracker leaves to its user (birth weight,
extraction, merge and prune thresholds; clustering distance; initiator and deleter) are the
fields of :class:`GMPHDSettings` and :class:`JPDASettings`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from .._validation import check_positive
from ._layout import optional
from .stonesoup import timestamps

if TYPE_CHECKING:
    from ..models.existence import BirthDeath
    from ..models.motion import ConstantVelocity
    from ..models.sensors.points import PointFrame, PoissonClutterPoints

__all__ = ["PointScene", "GMPHDSettings", "JPDASettings", "cluster_points", "frame_detections", "gmphd_tracker",
           "jpda_tracker", "track_run", "TrackerRun",
           "pad_estimates"]


@dataclass(frozen=True)
class PointScene:
    """The true model of a point-measurement scene, in the terms Stone Soup's trackers take.

    Attributes
    ----------
    dt, q : sampling time [s] and acceleration noise ``sigma^2`` of the constant-velocity
        motion (Stone Soup's ``ConstantVelocity(noise_diff_coeff=q)`` per axis: the same
        ``Q``).
    R : (2, 2) point noise covariance [m^2].
    p_detect : probability that a live target gives at least one point, ``1 - exp(-L_x)``.
    clutter_density : ``L_C / V`` [1 / m^2].
    p_survival : ``1 - P_D``.
    area : ((x_lo, x_hi), (y_lo, y_hi)) [m], where targets are born and clutter falls.
    birth_rate : expected number of births per step at stationarity, ``P_B K (1 - pi)``
        with ``pi = P_B / (P_B + P_D)`` the stationary existence probability of a slot.
    velocity_std : ``s_v`` [m/s] of a newborn's velocity components.
    """

    dt: float
    q: float
    R: np.ndarray
    p_detect: float
    clutter_density: float
    p_survival: float
    area: tuple[tuple[float, float], tuple[float, float]]
    birth_rate: float
    velocity_std: float

    @classmethod
    def from_models(cls, motion: ConstantVelocity, sensor: PoissonClutterPoints, existence: BirthDeath,
                    num_slots: int) -> PointScene:
        """Read the scene off the library's models (those a scenario such as
        :func:`~torchmcmcpf.scenarios.septier.septier` returns) and its ``K`` slots.
        """
        for obj, attrs, what in ((motion, ("dt", "q"), "a ConstantVelocity motion"),
                                 (sensor, ("R", "detection_rate", "clutter_rate", "volume"),
                                  "a PoissonClutterPoints sensor"),
                                 (existence, ("p_birth", "p_death", "area", "velocity_std"), "a BirthDeath model")):
            if not all(hasattr(obj, a) for a in attrs):
                raise ValueError(f"expected {what} with {', '.join(attrs)}, got {type(obj).__name__}")
        if int(num_slots) < 1:
            raise ValueError(f"num_slots must be >= 1, got {num_slots!r}")
        area = existence.area.detach().cpu().double().tolist()
        pi = existence.stationary()
        return cls(dt=float(motion.dt), q=float(motion.q), R=sensor.R.detach().cpu().double().numpy().copy(),
                   p_detect=-math.expm1(-float(sensor.detection_rate)),
                   clutter_density=float(sensor.clutter_rate) / float(sensor.volume),
                   p_survival=1.0 - float(existence.p_death),
                   area=((area[0][0], area[0][1]), (area[1][0], area[1][1])),
                   birth_rate=float(existence.p_birth) * int(num_slots) * (1.0 - pi),
                   velocity_std=float(existence.velocity_std))

    def birth_mean_covar(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean ``(4,)`` and covariance ``(4, 4)`` of a newborn in the layout ``[x, vx, y, vy]``:
        the uniform position moment-matched (centre, ``side^2 / 12``), velocity ``N(0, s_v^2)``.
        """
        (x0, x1), (y0, y1) = self.area
        s2 = self.velocity_std ** 2
        mean = np.array([(x0 + x1) / 2, 0.0, (y0 + y1) / 2, 0.0])
        return mean, np.diag([(x1 - x0) ** 2 / 12, s2, (y1 - y0) ** 2 / 12, s2])


@dataclass(frozen=True)
class GMPHDSettings:
    """The knobs Stone Soup's GM-PHD leaves to its user.

    Attributes
    ----------
    cluster : clustering distance [m] of the front end (:func:`cluster_points`), or ``None``
        for the raw points.
    birth_weight : weight of the birth component (the expected number of births per step
        under the PHD's Poisson birth model; the scene's is :attr:`PointScene.birth_rate`).
    extraction_threshold : a component heavier than this is a reported target.
    merge_threshold : squared Mahalanobis distance under which the reducer merges two
        components.
    prune_threshold : components lighter than this are dropped.
    missed_distance : Mahalanobis gate of the hypothesiser (3 in Stone Soup's tutorial).
    """

    cluster: float | None = 30.0
    birth_weight: float = 0.05
    extraction_threshold: float = 0.5
    merge_threshold: float = 5.0
    prune_threshold: float = 1e-8
    missed_distance: float = 3.0


@dataclass(frozen=True)
class JPDASettings:
    """The knobs of Stone Soup's JPDA tracker with a multi-measurement initiator.

    Attributes
    ----------
    cluster : clustering distance [m] of the front end (:func:`cluster_points`).
    min_points : updates a tentative track needs before the initiator releases it.
    deleter_steps : a track is deleted after this many steps without an update
        (``UpdateTimeStepsDeleter``), tentative ones in the initiator too.
    prob_gate : gate probability of the ``PDAHypothesiser`` (Stone Soup's default 0.95).
    """

    cluster: float = 30.0
    min_points: int = 2
    deleter_steps: int = 3
    prob_gate: float = 0.95


def cluster_points(points: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Single-linkage clusters of one frame's points: two points closer than ``distance``
    share a cluster (DBSCAN with ``min_samples = 1``; ``scipy.cluster.hierarchy``).

    Parameters
    ----------
    points : (M, 2) [m]; distance : > 0 [m].

    Returns
    -------
    centroids (C, 2) and counts (C,) int, in order of each cluster's first point.
    """
    check_positive(distance, "distance")
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[-1] != 2:
        raise ValueError(f"points has shape {pts.shape}, expected (M, 2)")
    if len(pts) < 2:
        return pts.copy(), np.ones(len(pts), dtype=np.int64)
    from scipy.cluster.hierarchy import fcluster, linkage

    labels = fcluster(linkage(pts, method="single"), t=float(distance), criterion="distance")
    _, first, inverse, counts = np.unique(labels, return_index=True, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 2))
    np.add.at(sums, inverse, pts)
    order = np.argsort(first)
    return (sums / counts[:, None])[order], counts[order]


def frame_detections(points: np.ndarray, stamp: Any, R: np.ndarray, *, cluster: float | None,
                     models: dict | None = None) -> set:
    """One frame's points as a set of Stone Soup ``Detection`` s at time ``stamp``.

    Parameters
    ----------
    points : (M, 2) the frame's valid points [m].
    stamp : the frame's ``datetime``.
    R : (2, 2) noise covariance of one point.
    cluster : clustering distance [m] (:func:`cluster_points`; a cluster of ``n`` points is
        one detection at its centroid with noise ``R / n``), or ``None`` for one detection
        per point with noise ``R``.
    models : a dict that caches the measurement model of each cluster size across frames.

    Returns
    -------
    set of ``Detection`` with a ``LinearGaussian`` measurement model on ``(x, y)``.
    """
    optional("stonesoup", "stonesoup")
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.types.detection import Detection

    models = {} if models is None else models
    if cluster is None:
        centres, counts = np.asarray(points, dtype=np.float64), np.ones(len(points), dtype=np.int64)
    else:
        centres, counts = cluster_points(points, cluster)
    out = set()
    for c, n in zip(centres, counts.tolist()):
        if n not in models:
            models[n] = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=np.asarray(R) / n)
        out.add(Detection(c.reshape(2, 1), timestamp=stamp, measurement_model=models[n]))
    return out


def _motion(scene: PointScene) -> Any:
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity

    return CombinedLinearGaussianTransitionModel((ConstantVelocity(scene.q), ConstantVelocity(scene.q)))


def gmphd_tracker(scene: PointScene, settings: GMPHDSettings) -> Any:
    """Stone Soup's GM-PHD tracker for ``scene`` (module docstring), fed through
    ``update_tracker(time, detections)``.
    """
    optional("stonesoup", "stonesoup")
    from stonesoup.hypothesiser.distance import DistanceHypothesiser
    from stonesoup.hypothesiser.gaussianmixture import GaussianMixtureHypothesiser
    from stonesoup.measures import Mahalanobis
    from stonesoup.mixturereducer.gaussianmixture import GaussianMixtureReducer
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.tracker.pointprocess import PointProcessMultiTargetTracker
    from stonesoup.types.state import TaggedWeightedGaussianState
    from stonesoup.updater.kalman import KalmanUpdater
    from stonesoup.updater.pointprocess import PHDUpdater

    predictor = KalmanPredictor(_motion(scene))
    kalman = KalmanUpdater(LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=scene.R))
    updater = PHDUpdater(kalman, clutter_spatial_density=scene.clutter_density, prob_detection=scene.p_detect,
                         prob_survival=scene.p_survival)
    hypothesiser = GaussianMixtureHypothesiser(
        DistanceHypothesiser(predictor, kalman, Mahalanobis(), missed_distance=settings.missed_distance),
        order_by_detection=True)
    reducer = GaussianMixtureReducer(prune_threshold=settings.prune_threshold, pruning=True,
                                     merge_threshold=settings.merge_threshold, merging=True)
    mean, covar = scene.birth_mean_covar()
    birth = TaggedWeightedGaussianState(state_vector=mean.reshape(4, 1), covar=covar, weight=settings.birth_weight,
                                        tag=TaggedWeightedGaussianState.BIRTH, timestamp=timestamps(1)[0])
    return PointProcessMultiTargetTracker(detector=None, hypothesiser=hypothesiser, updater=updater, reducer=reducer,
                                          birth_component=birth, extraction_threshold=settings.extraction_threshold)


def jpda_tracker(scene: PointScene, settings: JPDASettings) -> Any:
    """Stone Soup's JPDA (EHM) tracker for ``scene`` (module docstring), fed through
    ``update_tracker(time, detections)``.
    """
    optional("stonesoup", "stonesoup")
    from stonesoup.dataassociator.neighbour import GlobalNearestNeighbour
    from stonesoup.dataassociator.probability import JPDAwithEHM
    from stonesoup.deleter.time import UpdateTimeStepsDeleter
    from stonesoup.hypothesiser.probability import PDAHypothesiser
    from stonesoup.initiator.simple import MultiMeasurementInitiator
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.tracker.simple import MultiTargetMixtureTracker
    from stonesoup.types.state import GaussianState
    from stonesoup.updater.kalman import KalmanUpdater

    predictor = KalmanPredictor(_motion(scene))
    updater = KalmanUpdater(LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=scene.R))

    def hypothesiser() -> Any:
        return PDAHypothesiser(predictor=predictor, updater=updater, clutter_spatial_density=scene.clutter_density,
                               prob_detect=scene.p_detect, prob_gate=settings.prob_gate)

    deleter = UpdateTimeStepsDeleter(settings.deleter_steps)
    mean, covar = scene.birth_mean_covar()
    # the measured components (x, y) of the prior are replaced by the detection's
    prior = GaussianState(mean.reshape(4, 1), covar, timestamp=timestamps(1)[0])
    initiator = MultiMeasurementInitiator(prior_state=prior, measurement_model=None, deleter=deleter,
                                          data_associator=GlobalNearestNeighbour(hypothesiser()), updater=updater,
                                          min_points=settings.min_points)
    return MultiTargetMixtureTracker(initiator=initiator, deleter=deleter, detector=None,
                                     data_associator=JPDAwithEHM(hypothesiser()), updater=updater)


@dataclass
class TrackerRun:
    """One run of a Stone Soup tracker: ``estimates``, a list of T ``(n_t, 4)`` arrays (the
    states reported at each step, layout ``[x, vx, y, vy]``), and ``step_seconds (T,)``, the
    wall-clock time of each step (front end, tracker and extraction).
    """

    estimates: list
    step_seconds: np.ndarray


def track_run(kind: str, settings: GMPHDSettings | JPDASettings, scene: PointScene, frames: PointFrame,
              run: int) -> TrackerRun:
    """Run Stone Soup's ``kind`` (``"gmphd"`` or ``"jpda"``) tracker on run ``run`` of
    ``frames`` (``PointFrame`` ``z (T, B, M, 2), mask (T, B, M)``) and report every step's
    estimated set. Frame ``t`` is at :func:`~torchmcmcpf.interop.stonesoup.timestamps`
    ``[t]`` with the scene's ``dt``.
    """
    if kind == "gmphd":
        if not isinstance(settings, GMPHDSettings):
            raise ValueError(f"kind 'gmphd' needs GMPHDSettings, got {type(settings).__name__}")
        tracker = gmphd_tracker(scene, settings)
    elif kind == "jpda":
        if not isinstance(settings, JPDASettings):
            raise ValueError(f"kind 'jpda' needs JPDASettings, got {type(settings).__name__}")
        tracker = jpda_tracker(scene, settings)
    else:
        raise ValueError(f"kind must be 'gmphd' or 'jpda', got {kind!r}")
    z, mask = frames
    if z.dim() != 4 or tuple(mask.shape) != tuple(z.shape[:3]) or not 0 <= run < z.shape[1]:
        raise ValueError(f"frames must be z (T, B, M, 2) with mask (T, B, M) and run in [0, B), got "
                         f"{tuple(z.shape)}, {tuple(mask.shape)} and run {run!r}")
    z_np, m_np = z[:, run].detach().cpu().double().numpy(), mask[:, run].cpu().numpy()
    models: dict = {}
    estimates, seconds = [], []
    for t, stamp in enumerate(timestamps(z.shape[0], dt=scene.dt)):
        start = time.perf_counter()
        detections = frame_detections(z_np[t][m_np[t]], stamp, scene.R, cluster=settings.cluster, models=models)
        _, tracks = tracker.update_tracker(stamp, detections)
        states = tracker.extracted_target_states if kind == "gmphd" else [track.state for track in tracks]
        estimates.append(np.array([np.asarray(s.state_vector, dtype=np.float64).ravel() for s in states],
                                  dtype=np.float64).reshape(-1, 4))
        seconds.append(time.perf_counter() - start)
    return TrackerRun(estimates, np.array(seconds))


def pad_estimates(runs: list[list[np.ndarray]], dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor,
                                                                                              torch.Tensor]:
    """Stack the per-step estimate sets of R runs into ``(T, R, W, 4)`` states and a
    ``(T, R, W)`` mask, ``W`` the largest set (at least 1); padding rows are zero.
    """
    t_len = len(runs[0])
    width = max(1, max(len(e) for run in runs for e in run))
    x = torch.zeros((t_len, len(runs), width, 4), dtype=dtype)
    mask = torch.zeros((t_len, len(runs), width), dtype=torch.bool)
    for r, run in enumerate(runs):
        for t, e in enumerate(run):
            x[t, r, :len(e)] = torch.as_tensor(e, dtype=dtype)
            mask[t, r, :len(e)] = True
    return x, mask
