"""Paper-003 scenario (Maroulas and Stinis 2010) and the quick reproduction end to end."""

import json
import math

import pytest
import torch

from torchmcmcpf.experiments import maroulas_hmc
from torchmcmcpf.scenarios import maroulas as M


def test_target_counts_follow_the_paper():
    assert M.target_counts(8) == [2, 2, 1, 2, 3, 4, 4, 4, 4]
    assert M.target_counts(200)[-1] == 4 and len(M.target_counts(200)) == 201


def test_motion_is_eq_11_12(gen):
    m = M.WhiteAccelerationMotion(dt=2.0, sigma=3.0)
    A = torch.tensor([[1.0, 2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]])
    Bm = torch.tensor([[2.0, 0], [2, 0], [0, 2], [0, 2]])  # T^2/2, T
    torch.testing.assert_close(m.A, A)
    torch.testing.assert_close(m.G, 3.0 * Bm)
    x, u = torch.randn(5, 3, 4, generator=gen), torch.randn(5, 3, 2, generator=gen)
    torch.testing.assert_close(m.propagate(x, u), x @ A.T + 3.0 * u @ Bm.T)
    with pytest.raises(ValueError, match="sigma"):
        M.WhiteAccelerationMotion(sigma=-1.0)


@pytest.mark.parametrize("obs", M.OBSERVATIONS)
def test_simulate(obs, gen):
    sensor = M.paper_sensor(obs)
    data = M.simulate(3, 10, sensor=sensor, generator=gen)
    assert data.x.shape == (11, 3, 4, 4) and data.alive.shape == (11, 3, 4)
    assert data.frames.z.shape == (11, 3, 4, 2) and data.z_slot.shape == (11, 3, 4, 2)
    assert data.frames.mask.sum(-1)[:, 0].tolist() == M.target_counts(10)
    # newborns: positions in [-100, 100]^2, velocities in [-1, 1]^2
    born = data.alive[1:] & ~data.alive[:-1]
    xb = data.x[1:][born]
    assert xb[:, [0, 2]].abs().max() <= 100 and xb[:, [1, 3]].abs().max() <= 1
    # the shuffled frame holds the same measurements as the slot-ordered one
    t = 7
    a = data.frames.z[t][data.frames.mask[t]].reshape(3, -1, 2)
    b = data.z_slot[t][data.alive[t]].reshape(3, -1, 2)
    torch.testing.assert_close(a.sort(1).values, b.sort(1).values)
    with pytest.raises(ValueError, match="observation"):
        M.paper_sensor("range_only")


def test_birth_density_is_centred_on_the_measurement(gen):
    # per particle: xy position of z + N(0, s^2); linear sensor: mean z, std 1 per axis.
    # 4000 draws: SE of the mean = 1 / sqrt(4000) = 0.016; 4.5 SE = 0.07.
    sensor = M.paper_sensor("linear")
    z = torch.tensor([[[10.0, -20.0]]], dtype=torch.float64)
    p = M.birth_particles(sensor, z, 4000, generator=gen)
    assert p.shape == (1, 4000, 1, 4)
    torch.testing.assert_close(p[0, :, 0, [0, 2]].mean(0), z[0, 0], atol=0.07, rtol=0)
    assert p[..., [1, 3]].abs().max() <= 1


def test_rmse_is_eq_31():
    mean = torch.zeros(1, 1, 3, 4)
    truth = torch.zeros(1, 1, 3, 4)
    truth[..., 0, :] = torch.tensor([3.0, 0, 4, 0])  # error 5
    truth[..., 1, :] = torch.tensor([1.0, 1, 1, 1])  # error 2
    truth[..., 2, :] = 100.0  # dead slot: ignored
    alive = torch.tensor([[[True, True, False]]])
    torch.testing.assert_close(M.rmse_per_target(mean, truth, alive), torch.tensor([[math.sqrt((25 + 4) / 2)]]))


def test_quick_reproduction_end_to_end(tmp_path):
    from torchmcmcpf.experiments._options import RunOptions

    metrics = maroulas_hmc.STUDY.run(maroulas_hmc.STUDY.settings(quick=True), RunOptions(out=tmp_path))
    written = json.loads((tmp_path / "metrics.json").read_text())
    for obs in M.OBSERVATIONS:
        for name in ("improved", "generic", "generic_equal_time"):
            entry = written[obs][name]
            assert entry["rmse_time_average"] is not None and entry["rmse_time_average"] > 0
            assert 0 < entry["ess_percent"] <= 100
        for fig in ("rmse", "ess", "tracks"):
            assert (tmp_path / f"{fig}_{obs}.png").stat().st_size > 0
    assert metrics["linear"]["improved"]["hmc_acceptance"] > 0.5
    # the improved filter tracks (paper: RMSE ~2.5 per target throughout; measurement std 1)
    assert metrics["linear"]["improved"]["rmse_time_average"] < 6
