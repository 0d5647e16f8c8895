"""The triggered pair-path move (issue 50): conditional SMC with ancestor sampling leaves the
pair's conditional path posterior invariant (module docstring of
:mod:`torchmcmcpf.kernels.pair_path`, eq. 2).

Oracles on slots on a line (``tests/_line.py``: state ``[u]``, labelled Gaussian measurements,
resolution 1) with a Gaussian random walk: without exclusion the pair's window is a Gaussian
whose conditional mean and covariance are exact (Gaussian conditioning, what a Kalman smoother
gives); with exclusion the oracle is importance sampling from that Gaussian, weighted by the
exclusion factors. The references are drawn from the oracle, one kernel is applied, and the
output's moments are compared with the oracle's within the Monte Carlo error of P independent
kernels (fixed seeds).
"""

import io
import math

import pytest
import torch
from _line import DT, LineSensor, R

from torchmcmcpf.kernels.pair_path import PairPath, conditional_smc, pair_path_update, window_bytes
from torchmcmcpf.models.motion import LinearGaussianMotion
from torchmcmcpf.models.multitarget import Exclusion

W, Q, K = 4, 1.0, 3
MOTION = LinearGaussianMotion(torch.ones(1, 1, dtype=DT), torch.full((1, 1), Q, dtype=DT))


def _conditional(u0, z):
    """Exact conditional of one slot's path ``u_1..u_W`` given ``u_0`` and ``z_1..z_W``
    (random walk, Gaussian measurements): mean (W,), covariance (W, W)."""
    s = torch.arange(1, W + 1, dtype=DT)
    prior = Q * torch.minimum(s[:, None], s[None, :])
    gain = prior @ torch.linalg.inv(prior + R * torch.eye(W, dtype=DT))
    return u0 + gain @ (z - u0), prior - gain @ prior


def _scene():
    """Two runs, pairs (0, 2) and (1, 2); every slot starts at its own point; frames near it."""
    start = torch.tensor([[-1.0, 5.0, 0.0], [6.0, -0.5, 0.5]], dtype=DT)  # (B, K)
    z = torch.stack([start + 0.3 * (t + 1) * torch.tensor([1.0, -1.0, 0.5], dtype=DT) for t in range(W)])  # (W, B, K)
    pair = torch.tensor([[0, 2], [1, 2]])
    return start, z, pair


def _exact_paths(start, z, pair, p, g):
    """(B, P, W + 1, K, 1): the pair's slots drawn from the exact conditional (no exclusion),
    the others on a fixed path; and the exact means, variances (B, 2, W)."""
    b = start.shape[0]
    path = start.reshape(b, 1, 1, K, 1).expand(b, p, W + 1, K, 1).clone()
    path[:, :, 1:] += 0.1 * torch.arange(1, W + 1, dtype=DT).reshape(1, 1, W, 1, 1)  # the others' fixed path
    means, variances = torch.zeros(b, 2, W, dtype=DT), torch.zeros(b, 2, W, dtype=DT)
    for r in range(b):  # loops over two runs and two slots of a test oracle
        for j in range(2):
            k = int(pair[r, j])
            mean, cov = _conditional(start[r, k], z[:, r, k])
            draw = mean + torch.randn(p, W, generator=g, dtype=DT) @ torch.linalg.cholesky(cov).T
            path[r, :, 1:, k, 0] = draw
            means[r, j], variances[r, j] = mean, cov.diagonal()
    return path, means, variances


def _pair_of(path, pair):
    return torch.stack([path[r, :, 1:, pair[r], 0] for r in range(path.shape[0])])  # (B, P, W, 2)


def _moment_scores(x, means, variances):
    """``x (B, P, W, 2)`` against exact ``means, variances (B, 2, W)``: the largest |z| of the
    sample means and of the sample variances (their Monte Carlo standard errors)."""
    p = x.shape[1]
    m, v = x.mean(1).transpose(-1, -2), x.var(1).transpose(-1, -2)
    z_mean = (m - means) / (variances / p).sqrt()
    z_var = (v - variances) / (variances * math.sqrt(2.0 / (p - 1)))
    return float(z_mean.abs().max()), float(z_var.abs().max())


def _check_moments(x, means, variances, z_max=4.5):
    z_mean, z_var = _moment_scores(x, means, variances)
    assert z_mean < z_max, z_mean
    assert z_var < z_max, z_var


@pytest.mark.parametrize("m", [2, 8])
def test_invariant_for_the_gaussian_conditional(m):
    g = torch.Generator().manual_seed(0)
    start, z, pair = _scene()
    frames = z.unsqueeze(-1)  # (W, B, K, 1)
    path, means, variances = _exact_paths(start, z, pair, 4000, g)
    new, moved = conditional_smc(path, frames, pair, motion=MOTION, sensor=LineSensor(), num_particles=m, generator=g)
    _check_moments(_pair_of(new, pair), means, variances)
    assert 0.2 < moved.double().mean() < 1.0  # it moves
    others = torch.ones(2, K, dtype=torch.bool)
    others[torch.arange(2)[:, None], pair] = False
    assert torch.equal(new[..., 0][others.reshape(2, 1, 1, K).expand(2, 4000, W + 1, K)],
                       path[..., 0][others.reshape(2, 1, 1, K).expand(2, 4000, W + 1, K)])  # the others untouched
    assert torch.equal(new[:, :, 0], path[:, :, 0])  # the window's start held


def test_converges_from_a_ghost():
    """References on a wrong path (the pair swapped after the first frame): a few kernels
    reach the conditional (ancestor sampling leaves the reference's early part)."""
    g = torch.Generator().manual_seed(1)
    start, z, pair = _scene()
    path, means, variances = _exact_paths(start, z, pair, 3000, g)
    ghost = path.clone()
    for r in range(2):
        a, b = pair[r]
        ghost[r, :, 1:, a], ghost[r, :, 1:, b] = path[r, :, 1:, b] + 3.0, path[r, :, 1:, a] - 3.0
    for _ in range(8):
        ghost, _ = conditional_smc(ghost, z.unsqueeze(-1), pair, motion=MOTION, sensor=LineSensor(), num_particles=16,
                                   generator=g)
    z_mean, z_var = _moment_scores(_pair_of(ghost, pair), means, variances)
    assert z_mean < 4.5 and z_var < 4.5, (z_mean, z_var)


def test_invariant_with_exclusion():
    """Exclusion between the pair and against the third slot: importance-sampling oracle."""
    g = torch.Generator().manual_seed(2)
    start = torch.tensor([[0.0, 3.0, 0.4]], dtype=DT)
    z = torch.stack([torch.tensor([0.1, 3.0, 0.3], dtype=DT) * (1 + 0.2 * t) for t in range(W)]).unsqueeze(1)
    pair = torch.tensor([[0, 2]])
    exclusion, sensor = Exclusion(scale=1.0), LineSensor()
    big, p = 400_000, 4000
    draws, _, _ = _exact_paths(start, z, pair, big, g)  # (1, big, W + 1, K, 1), the Gaussian part
    u = draws[..., 0]  # (1, big, W + 1, K)
    log_w = exclusion.log_factor(sensor.resolution_coords(draws[:, :, 1:]))[0].sum(-1)  # (big,)
    w = torch.softmax(log_w, 0)
    pair_u = u[0, :, 1:][:, :, pair[0]]  # (big, W, 2)
    means = (w[:, None, None] * pair_u).sum(0).T.unsqueeze(0)  # (1, 2, W)
    variances = (w[:, None, None] * (pair_u - means[0].T).square()).sum(0).T.unsqueeze(0)
    assert 1.0 / w.square().sum() > 20_000  # the oracle's own error is small beside the kernel's
    pick = torch.multinomial(w, p, replacement=True, generator=g)
    path = draws[:, pick]
    new, _ = conditional_smc(path, z.unsqueeze(-1), pair, motion=MOTION, sensor=sensor, exclusion=exclusion,
                             num_particles=4, generator=g)
    _check_moments(_pair_of(new, pair), means, variances)
    # the exclusion matters here: the Gaussian part alone is off by many standard errors
    plain, _ = conditional_smc(path, z.unsqueeze(-1), pair, motion=MOTION, sensor=sensor, num_particles=4,
                               generator=g)
    x = _pair_of(plain, pair)
    assert ((x.mean(1).transpose(-1, -2) - means) / (variances / p).sqrt()).abs().max() > 6


def test_same_seed_same_bits_and_bad_input():
    start, z, pair = _scene()
    path, _, _ = _exact_paths(start, z, pair, 10, torch.Generator().manual_seed(3))
    a = conditional_smc(path, z.unsqueeze(-1), pair, motion=MOTION, sensor=LineSensor(),
                        generator=torch.Generator().manual_seed(4))[0]
    b = conditional_smc(path, z.unsqueeze(-1), pair, motion=MOTION, sensor=LineSensor(),
                        generator=torch.Generator().manual_seed(4))[0]
    assert torch.equal(a, b)
    with pytest.raises(ValueError, match="pair must be"):
        conditional_smc(path, z.unsqueeze(-1), torch.tensor([[0, 0], [1, 2]]), motion=MOTION, sensor=LineSensor(),
                        generator=torch.Generator())
    with pytest.raises(ValueError, match="frames must be"):
        conditional_smc(path, z.unsqueeze(-1)[1:], pair, motion=MOTION, sensor=LineSensor(),
                        generator=torch.Generator())
    with pytest.raises(ValueError, match="path has shape"):
        conditional_smc(path[0], z.unsqueeze(-1), pair, motion=MOTION, sensor=LineSensor(), generator=torch.Generator())
    with pytest.raises(ValueError, match="lag"):
        PairPath(lag=0)


def test_window_genealogy_and_trigger():
    """Each new slot continues its source's path; the move fires for close pairs only, every
    ``every`` steps, and moves the chosen particles only."""
    g = torch.Generator().manual_seed(5)
    b, n, lag = 2, 6, 3
    settings = PairPath(lag=lag, every=2, num_paths=3, num_particles=4, distance=1.5)
    x = torch.zeros(b, n, K, 1, dtype=DT)
    x[..., 0] = torch.tensor([0.0, 10.0, 20.0], dtype=DT)
    centre = x[:, 0].clone()
    centre[0, 1, 0] = 1.0  # run 0: slots 0 and 1 close; run 1: none
    extras, fired = None, []
    for t in range(4):
        x_new = x + 0.01 * (t + 1) + 0.001 * torch.arange(n, dtype=DT).reshape(1, n, 1, 1)
        source = torch.randint(n, (b, n, K), generator=g)
        z = x_new[:, 0, :, :].clone()  # (B, K, 1), labelled frames
        prev_paths = None if extras is None else extras.x
        out, extras, report = pair_path_update(extras, x, centre, x_new, source, z, motion=MOTION, sensor=LineSensor(),
                                               exclusion=None, settings=settings, generator=g)
        fired.append(report["pair_path_fired"].tolist())
        if prev_paths is not None and not bool(report["pair_path_fired"][0]):
            want = torch.take_along_dim(prev_paths[:, :, 1:].permute(0, 3, 1, 2, 4), source.permute(0, 2, 1)[..., None,
                                        None], 2).permute(0, 2, 3, 1, 4)
            assert torch.equal(extras.x[:, :, :-1], want)
        assert torch.equal(out[1], x_new[1])  # run 1 never fires
        assert torch.equal(extras.x[:, :, -1], out)
        x = out
    assert fired == [[1.0, 0.0], [0.0, 0.0], [1.0, 0.0], [0.0, 0.0]]
    assert extras.frames.tolist() == [3, 3]
    assert window_bytes(n, K, 1, 0, lag, 8) == 8 * n * (lag + 1) * K


def test_in_the_ipmcmc_filter():
    """``IPMCMCSettings.pair_path``: the window travels in the state (a resumed run is the
    same bits), the move fires while the two crossing targets are close, and it reports."""
    import torchmcmcpf as tp
    from torchmcmcpf.scenarios.crossing import crossing

    g = torch.Generator().manual_seed(6)
    scn = crossing(2, 6, 2, generator=g, crossing_step=2)
    init = scn.initial_particles(40, generator=g)
    settings = PairPath(lag=4, every=2, num_paths=4, num_particles=4)
    filt = tp.IPMCMCFilter(scn.motion, scn.sensor, 40, num_chains=4, burn_in=5, pair_path=settings)
    whole = filt(scn.measurements, init=init, generator=torch.Generator().manual_seed(7))
    fired = whole.info.extras["pair_path_fired"]
    assert fired.tolist() == [[1.0, 1.0], [0.0, 0.0]] * 3  # close from the start: every second step
    window = whole.state.extras["pair_path"]  # a typed carry (PairPathWindow)
    assert window.x.shape == (2, 40, 5, 2, 5)
    assert torch.equal(window.x[:, :, -1], whole.state.x)
    gen = torch.Generator().manual_seed(7)
    first = filt(scn.measurements[:3], init=init, generator=gen)
    gen_state = gen.get_state()
    rest = filt(scn.measurements[3:], init=first.state, generator=gen)
    assert torch.equal(rest.mean, whole.mean[3:])
    buf = io.BytesIO()  # saved and loaded weights_only, the window resumes bit for bit
    torch.save(first.state, buf)
    buf.seek(0)
    loaded = torch.load(buf, weights_only=True)
    again = filt(scn.measurements[3:], init=loaded, generator=torch.Generator().manual_seed(7).set_state(gen_state))
    assert torch.equal(again.mean, rest.mean)
    bad = loaded._replace(extras={**loaded.extras, "pair_path": window._replace(since=window.since[:1])})
    wrong = r"state.extras\['pair_path'\].since has shape \(1, 2, 2\), expected \(2, 2, 2\)"
    with pytest.raises(ValueError, match=wrong):
        filt(scn.measurements[3:], init=bad, generator=torch.Generator())
    with pytest.raises(ValueError, match="pair_path"):  # a plain IP-MCMC-PF does not take a state with a window
        tp.IPMCMCFilter(scn.motion, scn.sensor, 40, num_chains=4, burn_in=5)(scn.measurements[3:], init=first.state,
                                                                              generator=torch.Generator())
    plain = tp.IPMCMCFilter(scn.motion, scn.sensor, 40, num_chains=4, burn_in=5)
    assert "pair_path_fired" not in plain(scn.measurements, init=init, generator=g).info.extras
    with pytest.raises(ValueError, match="pair_path must be"):
        tp.IPMCMCFilter(scn.motion, scn.sensor, 40, num_chains=4, pair_path=3)
