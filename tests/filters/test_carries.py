"""Typed carries (torchmcmcpf.filters._carry): each filter's state beyond the weighted cloud is
one typed value under one key of ``extras``, checked by its type, saved and loaded with
``torch.load(weights_only=True)``, and states saved with the open keys of before still resume
with the same bits.
"""

from __future__ import annotations

import pytest
import torch

import torchmcmcpf as tp
from torchmcmcpf.filters._carry import carry_type, typed_extras
from torchmcmcpf.filters.base import CarriedEstimate
from torchmcmcpf.filters.pmmh import PMMHState, pmmh_bound_step


def _pmmh():
    motion, sensor = tp.ConstantVelocity(dt=1.0, q=1.0), tp.LinearGaussian.position(noise_std=1.0)
    g = torch.Generator().manual_seed(0)
    z, x = torch.randn(5, 2, 2, 2, generator=g), torch.randn(2, 40, 2, 4, generator=g)
    return tp.PMMHFilter(motion, sensor, 40, num_candidates=4), z, x


def _open_keys(state: tp.ParticleState) -> tp.ParticleState:
    """The state as older versions saved it: every field of a carry an open key of ``extras``."""
    pm, est = state.extras["pmmh"], state.extras["estimate"]
    return state._replace(extras={"theta": pm.theta, "log_evidence": pm.log_evidence, "log_w_candidate":
                                  pm.log_w_candidate, "estimate": est.mean, "estimate_present": est.present})


def _same(a: tp.FilterResult, b: tp.FilterResult) -> None:
    for f in ("mean", "cov", "log_evidence"):
        assert torch.equal(getattr(a, f), getattr(b, f)), f
    assert torch.equal(a.state.x, b.state.x) and torch.equal(a.state.log_w, b.state.log_w)
    for u, v in zip(a.state.extras["pmmh"], b.state.extras["pmmh"]):
        assert torch.equal(u, v)


def test_the_carries_are_registered_under_their_keys():
    assert carry_type("pmmh") is PMMHState and carry_type("estimate") is CarriedEstimate
    assert carry_type("group") is tp.filters.group.GroupState and carry_type("theta") is None


def test_pmmh_state_is_typed_and_resumes_bit_for_bit(tmp_path):
    filt, z, x = _pmmh()
    full = filt(z, init=x, generator=torch.Generator().manual_seed(1))
    assert set(full.state.extras) == {"pmmh", "estimate"}
    pm = full.state.extras["pmmh"]
    assert isinstance(pm, PMMHState) and pm.theta.shape == (2, 4) and pm.log_w_candidate.shape == (2, 40)
    g = torch.Generator().manual_seed(1)
    half = filt(z[:3], init=x, generator=g)
    torch.save({"result": half, "generator": g.get_state()}, tmp_path / "half.pt")
    ckpt = torch.load(tmp_path / "half.pt", weights_only=True)
    assert isinstance(ckpt["result"].state.extras["pmmh"], PMMHState)
    for state in (ckpt["result"].state, _open_keys(ckpt["result"].state)):  # typed, and as older states held it
        g2 = torch.Generator()
        g2.set_state(ckpt["generator"])
        rest = filt(z[3:], init=state, generator=g2)
        _same(rest, full._replace(mean=full.mean[3:], cov=full.cov[3:], log_evidence=rest.log_evidence))
        assert torch.equal(rest.log_evidence, full.info.log_evidence[3:].sum(0))
    g3, g4 = torch.Generator().manual_seed(2), torch.Generator().manual_seed(2)  # step() converts too
    a, _ = filt.step(half.state, z[3], generator=g3)
    b, _ = filt.step(_open_keys(half.state), z[3], generator=g4)
    assert torch.equal(a.x, b.x) and all(torch.equal(u, v) for u, v in zip(a.extras["pmmh"], b.extras["pmmh"]))


def test_pmmh_state_errors_name_the_field_and_shapes():
    filt, z, x = _pmmh()
    state = filt(z[:2], init=x, generator=torch.Generator()).state
    pm = state.extras["pmmh"]
    g = torch.Generator()
    bad = state._replace(extras={**state.extras, "pmmh": pm._replace(theta=pm.theta[:, :3])})
    with pytest.raises(ValueError, match=r"state.extras\['pmmh'\].theta has shape \(2, 3\), expected \(2, 4\)"):
        filt.step(bad, z[0], generator=g)
    bad = state._replace(extras={**state.extras, "pmmh": pm._replace(log_w_candidate=pm.log_w_candidate[:, :20])})
    with pytest.raises(ValueError, match=r"log_w_candidate has shape \(2, 20\), expected \(2, 40\)"):
        filt(z, init=bad, generator=g)
    bad = state._replace(extras={**state.extras, "pmmh": pm._replace(log_evidence=pm.log_evidence.double())})
    with pytest.raises(ValueError, match=r"log_evidence is torch.float64 on cpu, expected torch.float32"):
        filt.step(bad, z[0], generator=g)
    bad = state._replace(extras={**state.extras, "pmmh": dict(pm._asdict())})
    with pytest.raises(ValueError, match=r"state.extras\['pmmh'\] must be a PMMHState, got dict"):
        filt.step(bad, z[0], generator=g)
    with pytest.raises(ValueError, match=r"must be a PMMHState, got dict"):  # the pure step function checks too
        pmmh_bound_step(bad, z[0], filt.bound, generator=g)


def test_carried_estimate_is_typed_and_old_states_resume():
    from torchmcmcpf.scenarios import ground_radar

    scn = ground_radar(2, 5, 2, generator=torch.Generator().manual_seed(3))
    filt = tp.IPMCMCFilter(scn.motion, scn.sensor, 40, num_chains=4, burn_in=2)  # relabels: the estimate matters
    x = scn.initial_particles(40, generator=torch.Generator().manual_seed(4))
    full = filt(scn.measurements, init=x, generator=torch.Generator().manual_seed(5))
    est = full.state.extras["estimate"]
    assert isinstance(est, CarriedEstimate) and est.mean.shape == (2, 2, 5) and est.present.dtype == torch.bool
    g = torch.Generator().manual_seed(5)
    half = filt(scn.measurements[:3], init=x, generator=g)
    e = half.state.extras["estimate"]
    old = half.state._replace(extras={"estimate": e.mean, "estimate_present": e.present})
    assert all(u is v for u, v in zip(typed_extras(old.extras)["estimate"], e))
    rest = filt(scn.measurements[3:], init=old, generator=g)
    assert torch.equal(rest.mean, full.mean[3:]) and torch.equal(rest.state.x, full.state.x)
    bad = half.state._replace(extras={"estimate": e._replace(mean=e.mean[:, :1])})
    message = r"state.extras\['estimate'\].mean has shape \(2, 1, 5\), expected \(2, 2, 5\)"
    with pytest.raises(ValueError, match=message):
        filt(scn.measurements, init=bad, generator=g)
    with pytest.raises(ValueError, match=r"state.extras\['estimate'\] must be a CarriedEstimate, got Tensor"):
        filt(scn.measurements, init=half.state._replace(extras={"estimate": e.mean}), generator=g)
    hist = filt(scn.measurements[:2], init=x, generator=g, history=True).history  # stacks field by field
    assert isinstance(hist.extras["estimate"], CarriedEstimate) and hist.extras["estimate"].mean.shape == (2, 2, 2, 5)
