"""The quick reproduction of Table II (paper 000) runs end to end and writes its outputs."""

import argparse
import json

import pytest
import torch

from torchmcmcpf.experiments import _study
from torchmcmcpf.experiments import bocquel_table2 as exp
from torchmcmcpf.experiments._options import RunOptions


def test_quick_reproduction_end_to_end(tmp_path):
    payload = exp.STUDY.run(exp.STUDY.settings(quick=True, steps=3, pmmh_candidates=2), RunOptions(out=tmp_path))
    for f in ("table2.md", "metrics.json", "rmse_1_target.png", "rmse_10_targets.png", "tracks.png"):
        assert (tmp_path / f).stat().st_size > 0, f
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["device"].startswith("cpu")
    for scenario in ("1 targets", "10 targets"):
        rows = saved["results"][scenario]
        assert {r["algorithm"] for r in rows.values()} == {"SIR PF", "Partitioned PF", "PMMH", "IP-MCMC-PF"}
        for r in rows.values():
            assert 0 < r["rmse"] < 100  # finite, and the filters track (initialised on the truth)
            assert 0 <= r["tlr"] <= 1 and r["seconds_per_step"] > 0
            assert len(r["rmse_per_step"]) == 3
    table = (tmp_path / "table2.md").read_text()
    assert "IP-MCMC-PF" in table and "4.84" in table  # our rows next to the paper's
    assert payload["config"]["quick"]


def test_settings_validate_particles():
    with pytest.raises(ValueError, match="particles"):
        exp.STUDY.settings(quick=True, particles=[45])
    # the notebook's entry point reads an argparse namespace the same way
    args = argparse.Namespace(quick=True, particles=[45], runs=None, steps=None, max_extensions=None,
                              pmmh_candidates=None)
    with pytest.raises(ValueError, match="particles"):
        exp.settings(args)


def test_algorithms_pick_the_rows(tmp_path):
    """``--algorithms`` runs only the rows named (in the table's order); without the
    IP-MCMC-PF row there is no tracks figure."""
    args = argparse.Namespace(name=exp.NAME, quick=True, out=tmp_path, device=torch.device("cpu"), seed=0,
                              progress=False, runs=None, steps=2, particles=None, max_extensions=None,
                              pmmh_candidates=None, algorithms=["SIR PF"], compile=False)
    payload = exp.run(args)  # the notebook's entry point: a namespace in
    assert payload["config"]["algorithms"] == ("SIR PF",)
    for rows in payload["results"].values():
        assert {r["algorithm"] for r in rows.values()} == {"SIR PF"}
    assert not (tmp_path / "tracks.png").exists()
    assert "SIR PF" in (tmp_path / "table2.md").read_text()


def test_compile_reaches_every_row(monkeypatch):
    """``--compile`` compiles the kernel of every row's filter, PMMH's candidates included
    (it once reached only SIR, partitioned and IP-MCMC-PF: PMMH ran eager, 3.4x slower)."""
    from types import SimpleNamespace

    from torchmcmcpf import ConstantVelocity, LinearGaussian

    scn = SimpleNamespace(motion=ConstantVelocity(1.0, 1.0), sensor=LinearGaussian.position(1.0), num_targets=1)
    monkeypatch.setattr(_study, "_REUSED", {})  # a fresh process: no filter kept from another test
    for compile_ in (True, False):
        cfg = exp.STUDY.settings(compile=compile_, chains=5, particles=(10,), burn_in=2, max_extensions=0,
                                 pmmh_candidates=2)
        for name in ("SIR PF", "Partitioned PF", "IP-MCMC-PF"):
            assert exp._make_filter(name, scn, 10, cfg).compile_step is compile_, name
        seen = []

        class Built(Exception):
            pass

        class Spy(exp.PMMHFilter):
            def __init__(self, *args, **kwargs):
                super().__init__(*args, **kwargs)
                seen.append(self.compile_step)
                raise Built

        monkeypatch.setattr(exp, "PMMHFilter", Spy)
        try:
            exp._run_pmmh(scn, 10, cfg, torch.Generator(), False)
        except Built:
            pass
        assert seen == [compile_]


def test_pmmh_runs_in_batches_of_bounded_particles(monkeypatch):
    """PMMH's L * Np particles per run go through the filter in batches of at most
    ``PMMH_BATCH_PARTICLES`` (at least one run each); the batches' outputs are the shard's,
    run by run, in order."""
    from torchmcmcpf.scenarios.ground_radar import ground_radar

    scn = ground_radar(2, 2, 3, generator=torch.Generator().manual_seed(0))
    calls = []

    class Spy(exp.PMMHFilter):
        def forward(self, measurements, **kwargs):
            calls.append(measurements.shape[1])
            return super().forward(measurements, **kwargs)

    monkeypatch.setattr(exp, "PMMHFilter", Spy)
    monkeypatch.setattr(_study, "_REUSED", {})  # the spy is built here and kept from no other test
    cfg = exp.STUDY.settings(pmmh_candidates=2, compile=False)
    for budget, batches in ((1, [1, 1, 1]), (2 * 20 * 2, [2, 1]), (10**9, [3])):
        monkeypatch.setattr(exp, "PMMH_BATCH_PARTICLES", budget)
        calls.clear()
        mean, extra = exp._run_pmmh(scn, 20, cfg, torch.Generator().manual_seed(1), False)
        assert calls == batches
        assert mean.shape == (2, 3, 2, 5) and torch.isfinite(mean).all()
        assert extra["acceptance"].shape == extra["theta_mean"].shape == (3,)


def test_shards_reuse_each_rows_filter(monkeypatch):
    """Each row's filter is built once per process and reused by the later shards (a compiled
    filter would otherwise compile again in every shard: torch.cond graphs skip Inductor's
    cache), with the same results as a filter built for the shard alone."""
    monkeypatch.setattr(_study, "_REUSED", {})
    cfg = exp.STUDY.settings(quick=True, steps=2, algorithms=("SIR PF", "PMMH", "IP-MCMC-PF"), pmmh_candidates=2)
    device = torch.device("cpu")

    def shard(index):
        return exp.STUDY.run_shard(cfg, range(index, index + 1), generator=torch.Generator().manual_seed(index),
                                   device=device)[0]

    shard(0)
    built = dict(_study._REUSED)
    assert len(built) == len(cfg.targets) * len(cfg.particles) * len(cfg.algorithms)
    reused = shard(1)
    assert all(_study._REUSED[key] is filt for key, filt in built.items())  # no filter built again
    monkeypatch.setattr(_study, "_REUSED", {})
    fresh = shard(1)
    assert len(_study._REUSED) == len(built)
    assert reused.keys() == fresh.keys()
    for key in fresh:
        torch.testing.assert_close(reused[key], fresh[key], rtol=0, atol=0, msg=key)


def test_reused_keeps_the_newest(monkeypatch):
    monkeypatch.setattr(_study, "_REUSED", {})
    monkeypatch.setattr(_study, "REUSED_MAX", 2)
    made = []

    def build(key):
        return lambda: made.append(key) or object()

    a = _study.reused("a", build("a"))
    _study.reused("b", build("b"))
    assert _study.reused("a", build("a")) is a  # kept: built once
    _study.reused("c", build("c"))  # drops "b", the least recently used
    assert list(_study._REUSED) == ["a", "c"] and made == ["a", "b", "c"]


def test_models_key_tells_models_apart():
    """Scenarios drawn from other random numbers share their models' key (their filters are
    reused); another grid (more steps widen it), noise level or dtype does not."""
    from torchmcmcpf.scenarios.ground_radar import ground_radar

    def key(steps=20, seed=0, **kw):
        scn = ground_radar(3, steps, 2, generator=torch.Generator().manual_seed(seed), **kw)
        return _study.models_key(scn.motion, scn.sensor)

    assert key() == key(seed=5)
    hash(key())
    assert key() != key(steps=21)
    assert key() != key(noise_std=2.0)
    assert key() != key(q=0.5)
    assert key() != key(dtype=torch.float64)
