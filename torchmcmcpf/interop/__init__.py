"""Results out of torchmcmcpf and into the tools around it: Stone Soup, xarray and ArviZ.

Optional packages, imported only when a function here is called (``pip install
'torchmcmcpf[interop]'``; the ``dev`` extra includes them):

- :func:`tracks_to_stonesoup` (``FilterResult.to_stonesoup``) and :func:`truth_to_stonesoup`:
  Stone Soup ``Track`` s of ``GaussianState`` s or ``ParticleState`` s and ``GroundTruthPath`` s,
  with timestamps, one per target slot and stretch of existence, so Stone Soup's metric
  generators (OSPA, GOSPA, SIAP) and plotters work on them;
- :func:`result_to_xarray` (``FilterResult.to_xarray``): an ``xarray.Dataset`` on dims
  ``time, run, target, component``;
- :func:`chains_to_arviz` and :func:`result_to_arviz` (``FilterResult.to_arviz``): the kept
  samples of an MCMC filter's chains at one step as ArviZ ``InferenceData`` (``chain``,
  ``draw``), for ``az.rhat``, ``az.ess``, ``az.plot_trace``;
- :mod:`torchmcmcpf.interop.stonesoup_trackers`: the other way round, Stone Soup's own GM-PHD
  and JPDA trackers run on the library's point frames with the scene's true model (the
  baselines of the ``septier-birth-death`` study).

The guide "Use torchmcmcpf inside a Stone Soup workflow" (``docs/guides/stonesoup.md``) shows
them at work. State components are named from the layout of :mod:`torchmcmcpf.typing`:
``x, vx, y, vy`` and ``rho`` (amplitude or power) last.
"""

from __future__ import annotations

from ._layout import component_names
from .arviz import chains_to_arviz, result_to_arviz, result_to_xarray
from .stonesoup import tracks_to_stonesoup, truth_to_stonesoup

__all__ = ["component_names", "tracks_to_stonesoup", "truth_to_stonesoup", "result_to_xarray", "chains_to_arviz",
           "result_to_arviz"]
