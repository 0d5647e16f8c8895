"""Labelled arrays: a filter result as an ``xarray.Dataset``, an MCMC filter's chains as ArviZ
``InferenceData``.

xarray and ArviZ are imported when a function here is called.

Dataset layout (:func:`result_to_xarray`)
-----------------------------------------
Dimensions ``time`` (the T steps, coordinate: step index; ``seconds`` alongside when the
motion model has a sampling time), ``run`` (B), ``target`` (K slots), ``component`` (D,
coordinate: ``x, vx, y, vy(, rho)``), and for the final cloud ``particle`` (N).

- ``mean (time, run, target, component)``; ``cov (time, run, target, component,
  component_2)``; ``exists_prob (time, run, target)`` with births and deaths;
- the info fields: ``ess``, ``log_evidence``, ``acceptance`` ``(time, run)`` and every
  extra under its own name, ``(time, run, <name>_dim_2, ...)`` for extras with more dims
  (a name already taken gets the prefix ``info_``); ``log_evidence_total (run)``;
- the final state: ``final_x (run, particle, target, component)``, ``final_log_w (run,
  particle)`` and ``final_exists (run, particle, target)``;
- attributes: the filter, its particle count, models and sampling time, the settings
  (``settings``, a JSON string, and one ``settings.<name>`` attribute per scalar setting),
  the versions (``torchmcmcpf_version``, ``torch_version``) and ``created_utc``: plain
  strings and numbers, so ``ds.to_netcdf(path)`` writes it as is.

Chains (:func:`chains_to_arviz`)
--------------------------------
The MCMC filters (``MCMCFilter``, ``IPMCMCFilter``) return their ``N = C S`` kept samples in
chain-major order: particle ``c S + s`` is draw ``s`` of chain ``c`` (in the order the chain
visited them). ``x (B, N, K, D)`` of run ``b`` becomes one posterior variable per component,
``(chain, draw, target)``, plus ``exists`` (as 0/1) with births and deaths; ArviZ's
``rhat``, ``ess`` and ``plot_trace`` then work per target and component. ArviZ's
``rhat(method="identity")`` is the classic Gelman-Rubin PSRF,
:func:`torchmcmcpf.diagnostics.psrf`, and ``method="split"`` is
:func:`torchmcmcpf.diagnostics.split_rhat` (tested equal on the same samples).
"""

from __future__ import annotations

import json
import platform
import time
import warnings
from types import ModuleType
from typing import Any, NamedTuple

import numpy as np
import torch

from .._validation import check_positive_int
from .._version import __version__
from ._layout import Cloud, Result, check_index, component_names, optional

__all__ = ["result_to_xarray", "chains_to_arviz", "result_to_arviz"]


class _Step(NamedTuple):
    """Step ``t`` of a result's history, as :func:`chains_to_arviz` reads it (a :class:`Cloud`)."""

    x: torch.Tensor
    log_w: torch.Tensor
    exists: torch.Tensor | None


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy()


def _attrs(meta: dict | None) -> dict[str, Any]:
    """A result's ``meta`` as netCDF-safe attributes (strings and numbers)."""
    meta = meta or {}
    out: dict[str, Any] = {}
    for key in ("filter", "num_particles", "motion", "sensor", "existence", "dt", "compile_step"):
        value = meta.get(key)
        if value is not None:
            out[key] = int(value) if isinstance(value, bool) else value
    settings = meta.get("settings")
    if settings is not None:
        out["settings"] = json.dumps(settings)
        for key, value in settings.items():
            if isinstance(value, (bool, int, float, str)):
                out[f"settings.{key}"] = int(value) if isinstance(value, bool) else value
    versions = {"torchmcmcpf": __version__, "torch": torch.__version__, **(meta.get("versions") or {})}
    for key, value in versions.items():
        out[f"{key}_version"] = str(value)
    out["python_version"] = platform.python_version()
    out["created_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    return out


def result_to_xarray(result: Result) -> Any:
    """A filter result as an ``xarray.Dataset`` (layout in the module docstring).

    Parameters
    ----------
    result : :class:`~torchmcmcpf.state.FilterResult` (any filter).

    Returns
    -------
    ``xarray.Dataset``; NumPy copies of the tensors (moved to the CPU).
    """
    xr = optional("xarray", "xarray")
    t_len, b, k, d = result.mean.shape
    names = component_names(d)
    coords: dict[str, Any] = {"time": np.arange(t_len), "run": np.arange(b), "target": np.arange(k),
                              "component": names, "component_2": names}
    dt = (result.meta or {}).get("dt")
    if dt is not None:
        coords["seconds"] = ("time", np.arange(t_len) * float(dt))
    data: dict[str, Any] = {"mean": (("time", "run", "target", "component"), _np(result.mean))}
    if result.cov is not None:
        data["cov"] = (("time", "run", "target", "component", "component_2"), _np(result.cov))
    if result.exists_prob is not None:
        data["exists_prob"] = (("time", "run", "target"), _np(result.exists_prob))
    info = result.info
    fields = {"ess": info.ess, "log_evidence": info.log_evidence, "acceptance": info.acceptance, **info.extras}
    for name, value in fields.items():
        if not torch.is_tensor(value):
            continue
        key = f"info_{name}" if name in data else name
        extra_dims = tuple(f"{name}_dim_{i}" for i in range(2, value.dim()))
        data[key] = (("time", "run", *extra_dims)[: value.dim()], _np(value))
    data["log_evidence_total"] = (("run",), _np(result.log_evidence))
    state = result.state  # a ParticleState, or a filter's own state with the same x, log_w, exists
    x, log_w, exists = (getattr(state, f, None) for f in ("x", "log_w", "exists"))
    if torch.is_tensor(x) and x.dim() == 4 and torch.is_tensor(log_w):
        data["final_x"] = (("run", "particle", "target", "component"), _np(x))
        data["final_log_w"] = (("run", "particle"), _np(log_w))
        if torch.is_tensor(exists):
            data["final_exists"] = (("run", "particle", "target"), _np(exists))
    ds = xr.Dataset(data, coords=coords, attrs=_attrs(result.meta))
    ds["component"].attrs["long_name"] = "state component, layout of torchmcmcpf.typing"
    ds["time"].attrs["long_name"] = "time step (0-based frame index)"
    return ds


def _arviz() -> ModuleType:
    with warnings.catch_warnings():  # ArviZ 0.2x announces its 1.0 refactor on import
        warnings.simplefilter("ignore", FutureWarning)
        return optional("arviz", "arviz")


def chains_to_arviz(state: Cloud, *, num_chains: int, run: int = 0, attrs: dict | None = None) -> Any:
    """The kept samples of an MCMC filter's chains at one step as ArviZ ``InferenceData``.

    Parameters
    ----------
    state : the ``ParticleState`` an MCMC filter returned for that step (``x (B, N, K, D)``,
        chain-major: module docstring), e.g. from ``filt.step`` or ``result.state``.
    num_chains : C, the filter's ``settings.num_chains``; it must divide N.
    run : which of the B runs.
    attrs : extra attributes of the posterior group (e.g. the filter's settings).

    Returns
    -------
    ``arviz.InferenceData`` whose ``posterior`` has one variable per state component
    (``x``, ``vx``, ...) on ``(chain, draw, target)``, and ``exists`` with births and deaths.
    """
    az = _arviz()
    b, n, k, d = state.x.shape
    c = check_positive_int(num_chains, "num_chains")
    if n % c:
        raise ValueError(f"num_chains={c} must divide the state's N = {n} particles (x has shape "
                         f"{tuple(state.x.shape)})")
    r = check_index(run, "run", b, f"B = {b} runs")
    x = _np(state.x[r]).reshape(c, n // c, k, d)  # (chain, draw, target, component)
    posterior = {name: x[..., i] for i, name in enumerate(component_names(d))}
    exists = state.exists
    if exists is not None:
        posterior["exists"] = _np(exists[r]).reshape(c, n // c, k).astype(np.float64)
    with warnings.catch_warnings():
        # ArviZ guesses that an array with more chains than draws was passed as (draw, chain)
        # and warns "More chains (C) than draws (S)"; ours is (chain, draw) by construction
        # (module docstring), and an IP-MCMC-PF keeps few draws of many chains (C = 50, S = 20
        # in paper 000), so the guess is wrong here: that one warning is silenced
        warnings.filterwarnings("ignore", message=r"More chains \(\d+\) than draws", category=UserWarning)
        return az.from_dict(posterior=posterior, dims={name: ["target"] for name in posterior},
                            coords={"target": np.arange(k)}, posterior_attrs=dict(attrs or {}))


def result_to_arviz(result: Result, *, step: int = -1, run: int = 0) -> Any:
    """:func:`chains_to_arviz` of a result's step ``step`` (the last by default; an earlier
    one needs ``result.history``), with the filter's ``num_chains`` read from ``result.meta``.
    """
    meta = result.meta or {}
    num_chains = (meta.get("settings") or {}).get("num_chains")
    if num_chains is None:
        raise ValueError(f"to_arviz needs the kept chain samples of an MCMC filter (settings.num_chains); this "
                         f"result is from {meta.get('filter', 'a filter without chains')}")
    t_len = result.mean.shape[0]
    t = check_index(step, "step", t_len, f"T = {t_len} steps")
    if t == t_len - 1:
        state = result.state
    elif result.history is None:
        raise ValueError(f"step={step} is not the last step and result.history is None; run the filter with "
                         "forward(..., history=True) to keep every step's chains")
    else:
        h = result.history
        state = _Step(h.x[t], h.log_w[t], None if h.exists is None else h.exists[t])
    attrs = {k: v for k, v in _attrs(meta).items() if k != "created_utc"}
    return chains_to_arviz(state, num_chains=num_chains, run=run, attrs={**attrs, "step": t})
