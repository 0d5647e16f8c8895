"""OSPA (Schuhmacher et al. 2008), GOSPA (Rahmathullah et al. 2017, alpha = 2) and the
cardinality error, against brute-force enumeration of the definitions."""

import itertools
import math

import pytest
import torch

from torchmcmcpf.metrics import cardinality_error, gospa, gospa_parts, ospa


def ospa_brute(X, Y, c, p):
    m, n = len(X), len(Y)
    if m == 0 and n == 0:
        return 0.0
    if m > n:
        X, Y, m, n = Y, X, n, m
    best = min((sum(min(c, math.dist(X[i], Y[pi[i]])) ** p for i in range(m))
                for pi in itertools.permutations(range(n), m)), default=0.0)
    return ((best + c**p * (n - m)) / n) ** (1 / p)


def gospa_brute(X, Y, c, p):
    """The definition with explicit partial assignments gamma (pairs may stay unassigned):
    min_gamma sum_{(i,j) in gamma} d^p + c^p/2 (|X| + |Y| - 2 |gamma|)."""
    m, n = len(X), len(Y)
    best = c**p / 2 * (m + n)
    for size in range(1, min(m, n) + 1):
        for rows in itertools.combinations(range(m), size):
            for cols in itertools.permutations(range(n), size):
                cost = sum(math.dist(X[i], Y[j]) ** p for i, j in zip(rows, cols))
                best = min(best, cost + c**p / 2 * (m + n - 2 * size))
    return best ** (1 / p)


def padded(points, size, gen):
    """Pad a list of points to (size, 2) with random junk rows, masked out."""
    x = torch.randn(size, 2, generator=gen, dtype=torch.float64) * 1e3
    mask = torch.zeros(size, dtype=torch.bool)
    idx = torch.randperm(size, generator=gen)[: len(points)]
    if points:
        x[idx] = torch.tensor(points, dtype=torch.float64)
    mask[idx] = True
    return x, mask


@pytest.mark.parametrize("p", [1.0, 2.0, 3.0])
@pytest.mark.parametrize("c", [0.5, 3.0, 100.0])
def test_against_brute_force(gen, p, c):
    xs, xm, ys, ym, ref_o, ref_g = [], [], [], [], [], []
    for _ in range(30):
        m, n = torch.randint(0, 5, (2,), generator=gen).tolist()
        X = (torch.rand(m, 2, generator=gen, dtype=torch.float64) * 6).tolist()
        Y = (torch.rand(n, 2, generator=gen, dtype=torch.float64) * 6).tolist()
        a, am = padded(X, 5, gen)
        b, bm = padded(Y, 4, gen)
        xs.append(a), xm.append(am), ys.append(b), ym.append(bm)
        ref_o.append(ospa_brute(X, Y, c, p))
        ref_g.append(gospa_brute(X, Y, c, p))
    x, y = torch.stack(xs).reshape(5, 6, 5, 2), torch.stack(ys).reshape(5, 6, 4, 2)
    mx, my = torch.stack(xm).reshape(5, 6, 5), torch.stack(ym).reshape(5, 6, 4)
    o = ospa(x, y, c=c, p=p, x_mask=mx, y_mask=my)
    g = gospa(x, y, c=c, p=p, x_mask=mx, y_mask=my)
    assert o.shape == (5, 6) and g.shape == (5, 6)
    assert torch.allclose(o.reshape(-1), torch.tensor(ref_o, dtype=torch.float64), atol=1e-10)
    assert torch.allclose(g.reshape(-1), torch.tensor(ref_g, dtype=torch.float64), atol=1e-10)
    # symmetric
    assert torch.allclose(ospa(y, x, c=c, p=p, x_mask=my, y_mask=mx), o)
    assert torch.allclose(gospa(y, x, c=c, p=p, x_mask=my, y_mask=mx), g)


def gospa_parts_brute(X, Y, c, p):
    """The minimiser of :func:`gospa_brute` split: (sum of d^p over its pairs, missed, false)."""
    m, n = len(X), len(Y)
    best = (c**p / 2 * (m + n), 0.0, n, m)
    for size in range(1, min(m, n) + 1):
        for rows in itertools.combinations(range(m), size):
            for cols in itertools.permutations(range(n), size):
                loc = sum(math.dist(X[i], Y[j]) ** p for i, j in zip(rows, cols))
                if loc + c**p / 2 * (m + n - 2 * size) < best[0]:
                    best = (loc + c**p / 2 * (m + n - 2 * size), loc, n - size, m - size)
    return best[1:]


@pytest.mark.parametrize("p", [1.0, 2.0])
@pytest.mark.parametrize("c", [0.5, 3.0])
def test_gospa_parts_against_brute_force(gen, p, c):
    xs, xm, ys, ym, ref = [], [], [], [], []
    for _ in range(40):
        m, n = torch.randint(0, 5, (2,), generator=gen).tolist()
        X = (torch.rand(m, 2, generator=gen, dtype=torch.float64) * 6).tolist()
        Y = (torch.rand(n, 2, generator=gen, dtype=torch.float64) * 6).tolist()
        a, am = padded(X, 5, gen)
        b, bm = padded(Y, 4, gen)
        xs.append(a), xm.append(am), ys.append(b), ym.append(bm)
        ref.append(gospa_parts_brute(X, Y, c, p))
    x, y, mx, my = torch.stack(xs), torch.stack(ys), torch.stack(xm), torch.stack(ym)
    parts = gospa_parts(x, y, c=c, p=p, x_mask=mx, y_mask=my)
    loc, missed, false = (torch.tensor(r, dtype=torch.float64) for r in zip(*ref))
    assert torch.allclose(parts.localisation.pow(p), loc, atol=1e-10)
    assert torch.equal(parts.missed, missed) and torch.equal(parts.false, false)
    # consistent with gospa: total^p = localisation^p + c^p / 2 (missed + false)
    assert torch.allclose(parts.total, gospa(x, y, c=c, p=p, x_mask=mx, y_mask=my), atol=1e-12)
    assert torch.allclose(parts.total.pow(p), loc + c**p / 2 * (missed + false), atol=1e-10)


def test_gospa_parts_hand_made():
    est = torch.tensor([[0.0, 0.0], [3.0, 4.0], [100.0, 0.0], [0.0, 90.0]], dtype=torch.float64)
    truth = torch.tensor([[0.0, 1.0], [3.0, 4.0], [60.0, 60.0]], dtype=torch.float64)
    # c = 10: pairs at 1 and 0 are localised; the truth at (60, 60) is missed, the estimates at
    # (100, 0) and (0, 90) are false: GOSPA^2 = 1 + 0 + 50 (1 + 2)
    parts = gospa_parts(est, truth, c=10.0, p=2)
    assert parts.localisation.item() == pytest.approx(1.0)
    assert (parts.missed.item(), parts.false.item()) == (1.0, 2.0)
    assert parts.total.item() == pytest.approx(math.sqrt(151.0))
    # a pair farther than c is one missed and one false point, not a localised pair
    far = gospa_parts(est[:1], est[:1] + 30.0, c=10.0, p=2)
    assert (far.localisation.item(), far.missed.item(), far.false.item()) == (0.0, 1.0, 1.0)
    # empty sets and masks
    none = torch.zeros(0, 2)
    assert tuple(v.item() for v in gospa_parts(none, none, c=5.0)) == (0.0, 0.0, 0.0, 0.0)
    only_truth = gospa_parts(est, truth, c=10.0, x_mask=torch.zeros(4, dtype=torch.bool))
    assert (only_truth.missed.item(), only_truth.false.item(), only_truth.localisation.item()) == (3.0, 0.0, 0.0)


def test_gospa_parts_agree_with_stonesoup(gen):
    pytest.importorskip("stonesoup")
    from datetime import datetime

    from stonesoup.measures import Euclidean
    from stonesoup.metricgenerator.ospametric import GOSPAMetric
    from stonesoup.types.state import State

    c, p = 3.0, 2.0
    metric = GOSPAMetric(c=c, p=p, measure=Euclidean())
    stamp = datetime(2000, 1, 1)
    for _ in range(20):
        m, n = torch.randint(1, 6, (2,), generator=gen).tolist()
        x = torch.rand(m, 2, generator=gen, dtype=torch.float64) * 6
        y = torch.rand(n, 2, generator=gen, dtype=torch.float64) * 6
        single, _ = metric.compute_gospa_metric([State(v.numpy()[:, None], timestamp=stamp) for v in x],
                                                [State(v.numpy()[:, None], timestamp=stamp) for v in y])
        theirs = single.value
        ours = gospa_parts(x, y, c=c, p=p)
        assert ours.total.item() == pytest.approx(theirs["distance"])
        assert ours.localisation.item() ** p == pytest.approx(theirs["localisation"], abs=1e-12)
        assert ours.missed.item() * c**p / 2 == pytest.approx(theirs["missed"])
        assert ours.false.item() * c**p / 2 == pytest.approx(theirs["false"])


def test_hand_made_sets():
    X = torch.tensor([[0.0, 0.0], [10.0, 0.0]])
    Y = torch.tensor([[1.0, 0.0]])
    # one pair at distance 1, one point unmatched: OSPA_1 = (1 + 5) / 2, GOSPA_1 = 1 + 5/2
    assert ospa(X, Y, c=5.0, p=1).item() == pytest.approx(3.0)
    assert gospa(X, Y, c=5.0, p=1).item() == pytest.approx(3.5)
    # p = 2: OSPA = sqrt((1 + 25) / 2), GOSPA = sqrt(1 + 25 / 2)
    assert ospa(X, Y, c=5.0, p=2).item() == pytest.approx(math.sqrt(13.0))
    assert gospa(X, Y, c=5.0, p=2).item() == pytest.approx(math.sqrt(13.5))
    # identical sets: 0; a cut-off below every distance: OSPA = c
    assert ospa(X, X, c=1.0).item() == 0.0 and gospa(X, X, c=1.0).item() == 0.0
    assert ospa(X, X + 3.0, c=0.5, p=1).item() == pytest.approx(0.5)


def test_empty_sets():
    X = torch.tensor([[0.0, 0.0], [10.0, 0.0]])
    none = torch.zeros(0, 2)
    assert ospa(none, none, c=5.0).item() == 0.0
    assert gospa(none, none, c=5.0).item() == 0.0
    assert ospa(X, none, c=5.0).item() == pytest.approx(5.0)
    assert gospa(X, none, c=5.0, p=2).item() == pytest.approx(math.sqrt(2 * 25 / 2))
    # all masked out: the same as empty
    mask = torch.zeros(2, dtype=torch.bool)
    assert ospa(X, X, c=5.0, x_mask=mask, y_mask=mask).item() == 0.0
    assert ospa(X, X, c=5.0, x_mask=mask).item() == pytest.approx(5.0)


def test_cardinality_error():
    est = torch.tensor([[0.5, 2.0], [3.0, 0.0]])
    true = torch.tensor([[0, 2], [1, 1]])
    assert torch.equal(cardinality_error(est, true), torch.tensor([[0.5, 0.0], [2.0, 1.0]]))
    with pytest.raises(ValueError, match="estimated_count"):
        cardinality_error(est, true[0])


@pytest.mark.parametrize("kw, match", [
    (dict(c=0.0), "c"), (dict(c=1.0, p=0.5), "p"), (dict(c=1.0, x_mask=torch.ones(3, dtype=torch.bool)), "x_mask"),
])
def test_bad_input_raises(kw, match):
    with pytest.raises(ValueError, match=match):
        ospa(torch.zeros(2, 2), torch.zeros(1, 2), **kw)
    with pytest.raises(ValueError, match="shape"):
        gospa(torch.zeros(2, 2), torch.zeros(1, 3), c=1.0)
    nan = torch.zeros(1, 2)
    nan[0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        ospa(torch.zeros(2, 2), nan, c=1.0)
