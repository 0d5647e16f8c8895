"""An IP-MCMC-PF segment's exchange iterations in C calls (paper 000 Alg. 2 on the radar's CPU
path): :func:`exchange_run` runs a segment's ``L`` iterations of :func:`~.exchange.exchange_iteration`
with their noise and proposals drawn before it, each run of one-slot moves between the
two-slot ones in one call and each two-slot move in one after its source term, on buffers
made once for the segment (``torchmcmcpf/_native/exchange.c``, :mod:`._exchange_native`),
where :func:`run_serves`. The same chains, decisions, cache and trace as the tensor path to
the bit (tests/kernels/test_exchange_caches.py); the filter's fallback is the iteration loop
(:mod:`torchmcmcpf.filters.ipmcmc`).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .._native import RowsLoop
from ..models.base import SensorModel
from ..models.existence import TargetDynamics
from ..models.multitarget import LOG_PHI_FLOOR, Exclusion, exclusion_on, log_q_ratio
from ..typing import Measurement, Tensor
from . import _exchange_native
from .exchange import ExchangeChains, ExchangeNoise, _in_c, _move_fields, _source_term

__all__ = ["exchange_run", "run_serves"]


class _Run(NamedTuple):
    """What :func:`exchange_run` hands the C loop: the chain fields with their rows (leading
    ``L``) in :func:`~.exchange._one_call`'s order, the chains' ``log r`` conversion to the move's
    ``epsilon`` (by kind; None: none) and the pair's source term's ``rho`` (0: none).
    """

    fields: dict[str, tuple[Tensor, Tensor]]
    conv: Tensor | None
    rho: float


def _run_fields(chains: ExchangeChains, noise: ExchangeNoise, sensor: SensorModel, exclusion: Exclusion | None,
                dynamics: TargetDynamics) -> _Run | None:
    """:func:`exchange_run`'s plan where it serves these chains and noise (:func:`run_serves`),
    else None.
    """
    log_lik, log_r, kind, src, lw, cache, coords, terms = (chains.log_lik, chains.log_r, chains.kind, chains.source,
                                                           chains.log_w_source, chains.amplitude, chains.coords,
                                                           chains.terms)
    proposal, m = noise.proposal, noise.slot.shape[-1]
    if (not _in_c(chains) or proposal is None or noise.partner is not None or proposal.exists is not None
            or terms is None or cache is None or not cache.is_contiguous() or dynamics.existence is not None):
        return None
    r_new, coords_new = proposal.log_r, proposal.coords
    on = exclusion_on(exclusion, sensor)
    kept = on and coords is not None and coords_new is not None
    if (on and not kept) or proposal.terms is None:
        return None
    # exchange_iteration's epsilon and rho (one slot: the chains' epsilon, no source term)
    recapture = dynamics.recapture
    base = None if recapture is None else recapture.p_propose
    eps_k = None if recapture is None else (base if m == 1 else recapture.p_propose_pair)
    rho = 0.0 if recapture is None or m == 1 else recapture.p_same_source
    if rho > 0 and (src is None or lw is None):
        return None
    fields = _move_fields(chains, proposal, noise.source, noise.log_w_source, kept, base, eps_k)
    conv = None
    if "log_r" in fields and m > 1 and kind is not None and base is not None and eps_k is not None \
            and base != eps_k:
        conv = log_q_ratio(torch.arange(3, dtype=torch.int8), base, eps_k).to(fields["log_r"][0].dtype)
    # a recorded field that would not change (no rows): the tensor path then records it as it is
    if any(t is not None and name not in fields for name, t in (("log_r", log_r), ("kind", kind), ("source", src))):
        return None
    if not _exchange_native.applies(log_lik, noise.u, cache, log_r, r_new, coords, coords_new):
        return None
    return _Run(fields, conv, rho)


def run_serves(chains: ExchangeChains, z: Measurement, noise: ExchangeNoise, *, dynamics: TargetDynamics,
               sensor: SensorModel, exclusion: Exclusion | None = None, pairs: ExchangeNoise | None = None) -> bool:
    """Whether :func:`exchange_run` serves a segment of these chains on this noise (leading
    ``L``; ``pairs`` its two-slot moves): the conditions of the one C call
    (:func:`~.exchange.one_call_serves`: move terms, an amplitude cache, no existence flags, eager
    float32 CPU), the segment's proposals made, no joint pairs, and a sensor with a C entry
    for its change (:meth:`~torchmcmcpf.models.base.SensorModel.delta_rows_loop`).
    """
    return _plan(chains, z, noise, pairs, dynamics, sensor, exclusion) is not None


def _plan(chains: ExchangeChains, z: Measurement, noise: ExchangeNoise, pairs: ExchangeNoise | None,
          dynamics: TargetDynamics, sensor: SensorModel, exclusion: Exclusion | None
          ) -> tuple[_Run, _Run | None, RowsLoop] | None:
    """:func:`exchange_run`'s plans of its one- and two-slot moves and the sensor's entry, or
    None where it does not serve them.
    """
    single = _run_fields(chains, noise, sensor, exclusion, dynamics)
    double = None if pairs is None else _run_fields(chains, pairs, sensor, exclusion, dynamics)
    if single is None or noise.slot.shape[-1] != 1 or chains.terms is None or (
            pairs is not None and (double is None or list(double.fields) != list(single.fields))):
        return None
    loop = sensor.delta_rows_loop(chains.terms, z)
    return None if loop is None else (single, double, loop)


def exchange_run(chains: ExchangeChains, z: Measurement, noise: ExchangeNoise, *, dynamics: TargetDynamics,
                 sensor: SensorModel, exclusion: Exclusion | None = None, pairs: ExchangeNoise | None = None,
                 at_pairs: tuple[int, ...] = (), record_from: int = 0
                 ) -> tuple[ExchangeChains, Tensor, ExchangeChains]:
    """A segment's ``L`` iterations of :func:`~.exchange.exchange_iteration` (each followed by the cache's
    advance, :func:`~.exchange.with_accepted_amplitudes`) in C calls (:func:`._exchange_native.segment`):
    each run of one-slot iterations between the two-slot ones in one call, chain by chain
    through every iteration of the run (the sensor's change of each chain's move by its C
    entry, then the rest of the move), each two-slot iteration in one after its source term
    (``p_same_source > 0``: read from the chains by ATen's ``softplus``, whose vector and
    scalar loops round by position); the buffers made once for the segment. The same chains,
    decisions and cache to the bit, with no Python between a run's iterations. Where
    :func:`run_serves`.

    Parameters
    ----------
    chains : :class:`~.exchange.ExchangeChains` ``(B, C, ...)`` with their amplitude cache (advanced in
        place) and move terms; z : the frame.
    noise : :class:`~.exchange.ExchangeNoise` of the ``L`` iterations' one-slot moves (leading ``(L, B,
        C)``) with the segment's proposals; pairs : that of the two-slot moves (leading
        ``(len(at_pairs), B, C)``), made at the iterations ``at_pairs`` (whose ``noise`` is
        unread), or None.
    dynamics, sensor, exclusion : as :func:`~.exchange.exchange_iteration`'s.
    record_from : the first iteration whose chains are recorded.

    Returns
    -------
    chains : after the ``L`` iterations (the cache the same tensor); accepted : (B, C) float32,
        the acceptances per chain; trace : :class:`~.exchange.ExchangeChains` of the chains after
        iterations ``record_from .. L - 1`` (leading ``L - record_from``: ``y``, ``log_lik``,
        ``log_r``, ``kind``, ``source``; the rest None), as the iterations' loop records them.
    """
    plan = _plan(chains, z, noise, pairs, dynamics, sensor, exclusion)
    cache = chains.amplitude
    if plan is None or cache is None or (pairs is None) != (not at_pairs) or (
            pairs is not None and pairs.u.shape[0] != len(at_pairs)):
        raise ValueError("exchange_run does not serve these chains and noise (run_serves), or pairs and at_pairs "
                         f"disagree (at_pairs {at_pairs})")
    single, double, loop = plan
    names = list(single.fields)
    at: dict[str, int] = {name: names.index(name) for name in ("terms", "coords", "log_r", "kind") if name in names}

    def moves(noise_: ExchangeNoise, run: _Run) -> _exchange_native.Moves:
        assert noise_.proposal is not None
        return _exchange_native.Moves(noise_.u, noise_.valid, noise_.slot, [rows for _, rows in run.fields.values()],
                                      noise_.proposal.coords if "coords" in at else None,
                                      noise_.proposal.log_r if "log_r" in at else None, run.conv)

    def source_term(own: list[Tensor], i: int) -> Tensor | None:
        if pairs is None or double is None or double.rho <= 0 or "source" not in names:
            return None
        assert pairs.source is not None and pairs.log_w_source is not None
        first = pairs._replace(source=pairs.source[i].contiguous(), log_w_source=pairs.log_w_source[i].contiguous(),
                               slot=pairs.slot[i].contiguous())
        term = _source_term(first, own[names.index("source")], own[names.index("log_w_source")], double.rho)
        return None if term is None else term.to(chains.log_lik.dtype)

    ll, own, traces, ll_trace, count = _exchange_native.segment(
        chains.log_lik, [field for field, _ in single.fields.values()], at, cache, loop,
        1.0 if exclusion is None else exclusion.scale, LOG_PHI_FLOOR, moves(noise, single),
        None if pairs is None or double is None else moves(pairs, double), at_pairs, record_from,
        [name in ("y", "log_r", "kind", "source") for name in names], source_term)
    new, trace = dict(zip(names, own)), dict(zip(names, traces))
    assert trace["y"] is not None
    out = ExchangeChains(new["y"], ll, None, new.get("log_r", chains.log_r), new.get("kind", chains.kind),
                         new.get("source", chains.source), new.get("log_w_source", chains.log_w_source), cache,
                         new.get("coords"), new["terms"])
    return out, count, ExchangeChains(trace["y"], ll_trace, None, trace.get("log_r"), trace.get("kind"),
                                      trace.get("source"))
