"""The crossing scenario, the crossing and soak studies (issue 22), and the relabelled estimate."""

import json
import math

import pytest
import torch

from torchmcmcpf.experiments import crossing as crossing_study
from torchmcmcpf.experiments import soak
from torchmcmcpf.experiments._options import RunOptions
from torchmcmcpf.models.multitarget import Exclusion
from torchmcmcpf.scenarios import crossing, ground_radar
from torchmcmcpf.state import ParticleState, relabel, relabelled_estimate
from torchmcmcpf.typing import VX, VY, X, Y


def test_crossing_geometry():
    g = torch.Generator().manual_seed(0)
    scn = crossing(3, 40, 4, generator=g, speed=0.5, miss_distance=2.0, crossing_step=20, snr_db=(20, 15, 10))
    assert scn.truth.shape == (40, 4, 3, 5) and scn.measurements.shape[:2] == (40, 4)
    pos = scn.truth[..., [X, Y]]
    # at the crossing step neighbouring targets are miss_distance apart (offsets along one line)
    d01 = (pos[20, :, 0] - pos[20, :, 1]).norm(dim=-1)
    torch.testing.assert_close(d01, torch.full_like(d01, 2.0), rtol=0, atol=1e-3)
    # every target moves at the set speed; every radial velocity lies within one doppler cell
    speed = scn.truth[..., [VX, VY]].norm(dim=-1)
    torch.testing.assert_close(speed, torch.full_like(speed, 0.5), rtol=1e-5, atol=1e-5)
    doppler = scn.sensor.measurement_coords(scn.truth)[..., 1]
    assert float(doppler.abs().max()) <= 0.5 + 1e-6
    # amplitudes follow the SNRs (SNR = rho^2 / 2 sigma^2)
    snr = 10 * torch.log10(scn.truth[0, 0, :, 4] ** 2 / 2)
    torch.testing.assert_close(snr, torch.tensor([20.0, 15.0, 10.0]), rtol=0, atol=1e-3)
    with pytest.raises(ValueError, match="snr_db"):
        crossing(2, 5, 1, generator=g, snr_db=(1.0, 2.0, 3.0))
    with pytest.raises(ValueError, match="num_targets"):
        crossing(1, 5, 1, generator=g)


def test_relabel_recovers_swapped_labels(gen):
    # a cloud of two targets where half the particles hold them under swapped labels: the
    # plain slot means both sit between the targets, the relabelled ones on the targets
    n = 400
    a, b = torch.tensor([0.0, 0.0, 0.0, 0.0]), torch.tensor([100.0, 0.0, 50.0, 0.0])
    x = torch.stack([a, b]).expand(1, n, 2, 4) + 2.0 * torch.randn(1, n, 2, 4, generator=gen)
    swap = torch.rand(1, n, generator=gen) < 0.5
    x = torch.where(swap[..., None, None], x.flip(2), x)
    state = ParticleState(x, torch.full((1, n), -math.log(n)))
    plain = state.mean()[0]
    assert float((plain[0, [X, Y]] - a[[X, Y]]).norm()) > 40  # the mixture of labels
    est = relabelled_estimate(state)[0].mean[0]
    assert float((est[0, [X, Y]] - a[[X, Y]]).norm()) < 1.0 or float((est[1, [X, Y]] - a[[X, Y]]).norm()) < 1.0
    assert float((est[0, [X, Y]] - est[1, [X, Y]]).norm()) > 100
    # against a reference the labels follow the reference
    ref = torch.stack([b, a]).unsqueeze(0)
    xr, _ = relabel(x, ref)
    assert float((xr[0, :, 0, [X, Y]] - b[[X, Y]]).norm(dim=-1).max()) < 20
    # with existence: a dead slot takes the absent reference label
    exists = torch.ones(1, n, 2, dtype=torch.bool)
    exists[0, :, 1] = False
    xs = torch.stack([a, torch.zeros(4)]).expand(1, n, 2, 4).clone()
    xs[0, ::2] = xs[0, ::2].flip(0)  # alternate particles hold the target in slot 1
    es = exists.clone()
    es[0, ::2] = es[0, ::2].flip(-1)
    est, _ = relabelled_estimate(ParticleState(xs, torch.full((1, n), -math.log(n)), es))
    assert sorted(est.exists_prob[0].tolist()) == pytest.approx([0.0, 1.0])


def _run_quick(module, tmp_path):
    return module.STUDY.run(module.STUDY.settings(quick=True), RunOptions(out=tmp_path))


def _cloud(points, gen, n=400, noise=3.0):
    """Particles ``(1, n, K, 4)`` whose live slots hold ``points[i]`` (positions ``(x, y)`` or
    None for a dead slot) in a random slot order per particle, with ``noise`` m of spread."""
    k = len(points[0])
    x = torch.zeros(1, n, k, 4, dtype=torch.float64)
    exists = torch.zeros(1, n, k, dtype=torch.bool)
    for i in range(n):
        row = points[i % len(points)]
        perm = torch.randperm(k, generator=gen)
        for j, p in enumerate(row):
            if p is not None:
                x[0, i, perm[j], X], x[0, i, perm[j], Y] = p
                exists[0, i, perm[j]] = True
    x[..., [X, Y]] += noise * torch.randn(x[..., [X, Y]].shape, generator=gen, dtype=torch.float64) * exists[..., None]
    return ParticleState(x, torch.zeros(1, n, dtype=torch.float64), exists)


def test_relabelled_estimate_keeps_stray_slots_out_of_a_target(gen):
    # A at (0, 0), B at (1000, 0); one particle in ten holds two slots on A and none on B: B's
    # estimate stays on B (not 100 m towards A), with existence 0.9
    a, b = (0.0, 0.0), (1000.0, 0.0)
    rows = [(a, b, None)] * 9 + [(a, (20.0, 10.0), None)]
    state = _cloud(rows, gen)
    ref = torch.zeros(1, 3, 4, dtype=torch.float64)
    ref[0, 0, X], ref[0, 1, X] = 0.0, 1000.0
    est, relabelled = relabelled_estimate(state, ref, reference_exists=torch.tensor([[True, True, False]]))
    assert est.present.tolist() == [[True, True, False]]
    assert abs(float(est.mean[0, 1, X]) - 1000.0) < 5.0 and abs(float(est.mean[0, 0, X])) < 5.0
    assert float(est.exists_prob[0, 1]) == pytest.approx(0.9, abs=1e-9)
    assert float(est.expected_count[0]) == pytest.approx(2.0, abs=1e-9)  # the live slots, all of them
    assert relabelled.exists.sum() <= state.exists.sum()


def test_relabelled_estimate_founds_one_label_for_a_new_target(gen):
    # the reference knows A; most particles also hold a new target C (in any slot), a few a
    # stray slot elsewhere: C gets one label, on C, and the stray slots found none
    a, c = (0.0, 0.0), (3000.0, 2000.0)
    rows = [(a, c, None)] * 8 + [(a, (-2500.0, 4000.0), None), (a, None, None)]
    state = _cloud(rows, gen)
    ref = torch.zeros(1, 3, 4, dtype=torch.float64)
    est, _ = relabelled_estimate(state, ref, reference_exists=torch.tensor([[True, False, False]]))
    present = est.present[0]
    assert int(present.sum()) == 2 and bool(present[0])
    new = est.mean[0, present][1]
    assert abs(float(new[X]) - 3000.0) < 5.0 and abs(float(new[Y]) - 2000.0) < 5.0
    assert float(est.exists_prob[0, present][1]) == pytest.approx(0.8, abs=1e-9)


def test_crossing_study_quick(tmp_path):
    payload = _run_quick(crossing_study, tmp_path)
    for name in ("metrics.json", "crossing.png", "coalescence.png", "tracks.png"):
        assert (tmp_path / name).exists()
    stored = json.loads((tmp_path / "metrics.json").read_text())
    assert set(stored["results"]) == set(crossing_study.FILTERS) | {crossing_study.CLAIRVOYANT}
    reference = payload["results"][crossing_study.CLAIRVOYANT]
    assert reference["recaptured_share"] is None
    assert "| clairvoyant reference |" in crossing_study.STUDY.summary(payload)
    # quick counts after the targets separate, as the full study: the reference holds both (issue 52)
    assert reference["runs_shared_late"] == 0 and reference["runs_uncovered_late"] == 0
    r = payload["results"]["IP-MCMC-PF"]
    assert 0 <= r["runs_uncovered_late"] <= r["runs"] and float(r["matched_rmse"]) >= 0
    assert "| IP-MCMC-PF |" in crossing_study.STUDY.summary(payload)
    # a row that re-captured in no run has no median step: "0% (-)", live (NaN) or stored (null)
    for median in (torch.tensor(float("nan"), dtype=torch.float64), None):
        row = dict(r, recaptured_share=torch.tensor(0.0, dtype=torch.float64), recapture_step_median=median)
        text = crossing_study.STUDY.summary({"config": payload["config"], "results": {"IP-MCMC-PF": row}})
        assert "| 0% (-) |" in text and "nan" not in text


def test_soak_study_quick(tmp_path):
    payload = _run_quick(soak, tmp_path)
    assert (tmp_path / "soak.png").exists() and (tmp_path / "metrics.json").exists()
    # the partitioned PF's row and the clairvoyant reference's
    assert set(payload["results"]["fixed"]) == set(soak.FIXED_FILTERS) | {soak.CLAIRVOYANT}
    assert set(payload["results"]["birth-death"]) == set(soak.FILTERS)
    for fixed in payload["results"]["fixed"].values():
        assert fixed["non_finite"] == 0 and len(fixed["matched_rmse_per_chunk"]) == 2
    bd = payload["results"]["birth-death"]["IP-MCMC-PF"]
    for total, loc, card in bd["ospa_per_chunk"]:  # per step OSPA^2 = loc^2 + card^2, so for the means:
        assert max(loc, card) - 1e-6 <= total <= loc + card + 1e-6
    floor = payload["results"]["fixed_floor"]
    assert floor["per_run"].shape == (1,) and 0 < floor["all"] < 20  # metres, 3 targets, quick
    assert "birth-death" in soak.STUDY.summary(payload) and "PCRB" in soak.STUDY.summary(payload)
    assert "filters' q = 1," in soak.STUDY.summary(payload)


def test_soak_q_sets_the_filters_motion_and_refuses_a_bad_value(gen):
    """--q is the filters' acceleration noise on the fixed scene (the truth stays noise-free)."""
    scn = ground_radar(2, 3, 1, generator=gen, q=0.01)
    assert scn.motion.q == 0.01
    same = ground_radar(2, 3, 1, generator=torch.Generator().manual_seed(0))
    again = ground_radar(2, 3, 1, generator=torch.Generator().manual_seed(0), q=0.01)
    torch.testing.assert_close(same.truth, again.truth, rtol=0, atol=0)  # the truth does not depend on q
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="argument --q"):
            soak.STUDY.settings(q=bad)


@pytest.mark.parametrize("moved_share", [0.3, 0.7])
def test_relabelled_estimate_follows_a_recaptured_slot(gen, moved_share):
    # Without existence: the reference has both labels on target A (two slots had coalesced
    # there) and a share of the particles has re-captured target B, 150 m away, with slot 1.
    # A minority beyond the cutoff stays out of label 1's mean (it remains on A); a majority
    # takes the label with it (its mean on B, from those particles only).
    n = 1000
    a, b = torch.tensor([0.0, 0.0, 0.0, 0.0]), torch.tensor([150.0, 0.0, 0.0, 0.0])
    x = a.expand(1, n, 2, 4) + 1.0 * torch.randn(1, n, 2, 4, generator=gen)
    moved = torch.arange(n) < int(moved_share * n)
    x[0, moved, 1] += b
    state = ParticleState(x, torch.full((1, n), -math.log(n)))
    ref = a.expand(1, 2, 4).clone()
    est = relabelled_estimate(state, ref)[0].mean[0]
    assert float(est[0, X].abs()) < 1.0  # label 0 stays on A
    expected = 150.0 if moved_share > 0.5 else 0.0
    assert abs(float(est[1, X]) - expected) < 1.0


def test_streams_are_independent_of_each_other_and_of_the_names_asked_for():
    from torchmcmcpf.experiments._shards import streams

    def draws(names, name, before=None):
        s = streams(torch.Generator().manual_seed(3), names)
        if before is not None:  # another consumer draws first
            torch.randn(100, generator=s[before])
        return torch.randn(5, generator=s[name])

    ref = draws(("frames", "a", "b"), "a")
    torch.testing.assert_close(draws(("a",), "a"), ref, rtol=0, atol=0)  # the set of names does not matter
    torch.testing.assert_close(draws(("frames", "a", "b"), "a", before="b"), ref, rtol=0, atol=0)
    assert not torch.equal(draws(("frames", "a", "b"), "b"), ref)  # distinct names, distinct streams
    assert not torch.equal(draws(("a",), "a"), torch.randn(5, generator=torch.Generator().manual_seed(3)))


def test_soak_rows_are_the_same_bits_whichever_rows_and_scenes_run():
    """``--filters`` / ``--scenes``: one filter on one scene gives that row's bits of the full
    study (the scenes are drawn either way, every row has a stream of its own), and the
    summary shows only what ran; asking for nothing is refused by name.
    """
    dev, runs = torch.device("cpu"), range(1)
    full, _ = soak.STUDY.run_shard(soak.STUDY.settings(quick=True), runs, generator=torch.Generator().manual_seed(5),
                                   device=dev)
    for scene, key in (("fixed", "fixed|IP-MCMC-PF|matched_error"), ("birth-death", "birth-death|IP-MCMC-PF|ospa")):
        cfg = soak.STUDY.settings(quick=True, filters=("IP-MCMC-PF",), scenes=(scene,))
        one, seconds = soak.STUDY.run_shard(cfg, runs, generator=torch.Generator().manual_seed(5), device=dev)
        assert {k.split("|")[1] for k in one if k != "fixed|floor"} == {"IP-MCMC-PF"}
        assert all(k.startswith(scene) for k in one)
        torch.testing.assert_close(one[key], full[key], rtol=0, atol=0)
        payload = {"config": {"q": cfg.q}, "results": soak.STUDY.aggregate(cfg, one, seconds)}
        text = soak.STUDY.summary(payload)
        assert "| IP-MCMC-PF |" in text and "partitioned" not in text and ("PCRB" in text) == (scene == "fixed")
    for bad in ({"filters": ()}, {"scenes": ()}):
        with pytest.raises(ValueError, match="--filters and --scenes"):
            soak.STUDY.settings(**bad)


def test_crossing_rows_are_the_same_bits_whichever_rows_run():
    """``--filters``: the IP-MCMC-PFs alone (without the MCMC-PF, the partitioned PF and the
    reference) see the same scenes and draw from the same streams, so their figures are the
    same bits as in the whole study (on one shared stream the filters before them would move
    their draws); the summary shows only what ran, and asking for nothing is refused."""
    def run(cfg):
        return crossing_study.STUDY.run_shard(cfg, range(1), generator=torch.Generator().manual_seed(4),
                                              device=torch.device("cpu"))

    full, _ = run(crossing_study.STUDY.settings(quick=True))
    keep = ("IP-MCMC-PF (paper)", "IP-MCMC-PF")
    cfg = crossing_study.STUDY.settings(quick=True, filters=keep)
    fewer, seconds = run(cfg)
    assert {k.split("|")[0] for k in fewer if k != "truth"} == set(keep)
    for name in keep:
        for what in ("matched_error", "recaptured", "estimate"):
            torch.testing.assert_close(fewer[f"{name}|{what}"], full[f"{name}|{what}"], rtol=0, atol=0)
    text = crossing_study.STUDY.summary({"config": {"from_step": cfg.from_step, "coalesce_steps": cfg.coalesce_steps},
                                         "results": crossing_study.STUDY.aggregate(cfg, fewer, seconds)})
    assert "| IP-MCMC-PF |" in text and "MCMC-PF |" not in text.replace("IP-MCMC-PF |", "")
    assert "clairvoyant" not in text
    with pytest.raises(ValueError, match="--filters"):
        crossing_study.STUDY.settings(filters=())


def _displaced(scn, moves):
    """The truth ``(T, B, K, D)`` with slot ``k`` of run ``b`` moved ``metres`` across the line
    of sight at every frame, for each ``(b, k, metres)`` of ``moves``."""
    mean = scn.truth.clone()
    for run, slot, metres in moves:
        p = scn.truth[:, run, slot, [X, Y]]
        across = torch.stack([-p[:, 1], p[:, 0]], -1) / p.norm(dim=-1, keepdim=True)
        mean[:, run, slot, X] += metres * across[:, 0]
        mean[:, run, slot, Y] += metres * across[:, 1]
    return mean


def test_late_check_tells_the_filters_gap_from_the_models(gen):
    """Whose gap (the crossing study's ``_late_check``, quick: 100 L-BFGS iterations), on
    hand-made estimates over 6 frames of two resolved targets 150 m apart. Both at 25 dB:
    run 0's estimate is the truth (no gap: NaN, not covered); in run 1 a slot is 25 m off
    across the line of sight, inside its target's point spread, where the posterior has no
    mode: the maximum found from it returns to the target (the filter's gap). One at -20 dB:
    its slot 100 m off stays off (its data say nothing), about as probable as the truth
    (the model's gap). The check maximises the defaults' posterior, exclusion included."""
    cfg = crossing_study.STUDY.settings(quick=True, from_step=0)
    excl = Exclusion()
    name = "IP-MCMC-PF"
    clear = crossing(2, 6, 2, generator=gen, miss_distance=150.0, crossing_step=3, snr_db=(25.0, 25.0))
    out = crossing_study._late_check(cfg, name, _displaced(clear, [(1, 0, 25.0)]), clear, excl)
    odds, covers = out[f"{name}|gap_log_odds"], out[f"{name}|gap_map_covers"]
    assert math.isnan(float(odds[0])) and not bool(covers[0])
    assert bool(covers[1]) and abs(float(odds[1])) < 1.0  # back on the target: the same maximum
    buried = crossing(2, 6, 1, generator=gen, miss_distance=150.0, crossing_step=3, snr_db=(25.0, -20.0))
    mean = _displaced(buried, [(0, 1, 100.0)])
    out = crossing_study._late_check(cfg, name, mean, buried, excl)
    assert not bool(out[f"{name}|gap_map_covers"][0])
    assert float(out[f"{name}|gap_log_odds"][0]) <= crossing_study.GAP_ODDS
    per_run = {**crossing_study._scores(name, mean, buried.truth), **out}
    r = crossing_study.STUDY.aggregate(cfg, per_run, {name: 1.0})[name]
    assert (r["runs_uncovered_late"], r["late_gaps_the_filters"], r["late_gaps_the_models"]) == (1, 0, 1)
