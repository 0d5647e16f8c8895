"""The library's select (``torchmcmcpf._native.select``): ``where`` gives ``torch.where``'s
bits, dtype and shape in every layout the C loop serves and falls back to ATen in every other;
``unpacked`` equals a gather and a select. The loop is checked to run where it should (its
calls counted), so an equality cannot pass because the fallback ran.
"""

from __future__ import annotations

import pytest
import torch

from torchmcmcpf import _native
from torchmcmcpf._native.select import MIN_ELEMENTS, packed_places, unpacked, where

pytestmark = pytest.mark.skipif(not _native.available(), reason="the C loops are not built on this machine")

G = torch.Generator().manual_seed(0)
B, C, K, D = 4, 600, 5, 4  # B * C * K * D = 48,000 elements: above MIN_ELEMENTS


def _bits(t: torch.Tensor) -> torch.Tensor:
    return t if t.dtype == torch.bool else t.contiguous().view(torch.uint8)


def _same(got: torch.Tensor, want: torch.Tensor) -> bool:
    """The same dtype, shape and bits."""
    return got.dtype == want.dtype and got.shape == want.shape and torch.equal(_bits(got), _bits(want))


def _state(dtype=torch.float32) -> torch.Tensor:
    x = torch.randn(B, C, K, D, generator=G).to(dtype)
    if dtype.is_floating_point:  # special values travel as bits
        x[0, 0, 0, :3] = torch.tensor([float("nan"), -0.0, float("inf")]).to(dtype)
    return x


def _layouts():
    """(name, condition, input, other): the selects of the moves, each above MIN_ELEMENTS."""
    x, y = _state(), _state()
    row = torch.rand(B, C, generator=G) < 0.5
    slot = torch.rand(B, C, K, generator=G) < 0.5
    x0, y0 = x[..., 0].contiguous(), y[..., 0].contiguous()
    return [
        ("accept over (K, D)", row[:, :, None, None], x, y),
        ("accept over D", slot.unsqueeze(-1), x, y),
        ("fill row", slot.unsqueeze(-1), x, torch.randn(D, generator=G)),
        ("row first", slot.unsqueeze(-1), torch.randn(D, generator=G), x),
        ("flat", slot, x0, y0),
        ("scalar other", slot, x0, 0.0),
        ("scalar input int", slot, 1, x0),
        ("0-dim float64", slot, torch.tensor(0.25, dtype=torch.float64), torch.tensor(0.75, dtype=torch.float64)),
        ("bool", slot, slot, ~slot),
        ("bool scalar", slot, True, slot),
        ("float64", slot, x0.double(), y0.double()),
        ("int64", slot, x0.long(), 3),
        ("float16", row[:, :, None, None], x.half(), y.half()),
        ("strided operands", slot, x[..., 1], y[..., 2]),
        ("transposed", slot.unsqueeze(-1), x.transpose(0, 1).contiguous().transpose(0, 1), y),
        ("condition with leading 1s", slot.reshape(1, B * C, K), x0.reshape(1, B * C, K), y0.reshape(B * C, K)),
        ("fewer dims", slot[0].unsqueeze(-1), x[0], y[0]),
        ("expanded row", slot.unsqueeze(-1), x, torch.randn(D, generator=G).expand(B, C, K, D)),
        ("expanded over the chains", row[:, :, None, None], torch.randn(B, 1, K, D, generator=G).expand(B, C, K, D), y),
    ]


def _where_by(c, a, b, count_native_calls) -> list[str]:
    """``where(c, a, b)`` checked against ``torch.where``; the C loop's calls it made."""
    want = torch.where(c, a, b)
    calls = count_native_calls()
    assert _same(where(c, a, b), want)
    return calls


@pytest.mark.parametrize("case", range(len(_layouts())), ids=[name for name, *_ in _layouts()])
def test_where_is_torch_where_by_the_loop(case, count_native_calls):
    assert _where_by(*_layouts()[case][1:], count_native_calls) == ["select_rows"]


@pytest.mark.parametrize("threads", [1, 2])
def test_where_same_bits_at_any_thread_count(threads, at_threads, count_native_calls):
    x, y = torch.randn(40, 4000, 2, generator=G), torch.randn(40, 4000, 2, generator=G)  # above the threaded size
    c = torch.rand(40, 4000, 1, generator=G) < 0.3
    want = torch.where(c, x, y)
    calls = count_native_calls()
    assert _same(at_threads(lambda: where(c, x, y), threads), want)
    assert calls == ["select_rows"]


def _fallbacks():
    x = torch.randn(B, C, K, generator=G)
    c = torch.rand(B, C, K, generator=G) < 0.5
    small = torch.rand(3, 5, generator=G) < 0.5
    return [
        ("small", small, torch.randn(3, 5, generator=G), 0.0),
        ("mixed dtypes", c, x, x.double()),
        ("float scalar into int", c, x.long(), 0.5),
        ("condition broadcast in its rows", c[:, :1], x, -x),
        ("operand broadcast inside the rows", c.unsqueeze(-1), x.unsqueeze(-1), torch.zeros(B, 1, 1, 3)),
        ("0-dim other of another dtype", c, x, torch.tensor(1.0, dtype=torch.float64)),
        ("complex", c, x.to(torch.complex128), 0.0),
    ]


@pytest.mark.parametrize("case", range(len(_fallbacks())), ids=[name for name, *_ in _fallbacks()])
def test_where_falls_back_to_aten(case, count_native_calls):
    assert _where_by(*_fallbacks()[case][1:], count_native_calls) == []


def test_where_of_nothing_is_aten_at_any_threshold(monkeypatch, count_native_calls):
    from torchmcmcpf._native import select

    monkeypatch.setattr(select, "MIN_ELEMENTS", 1)
    c = torch.rand(3, 0, 4, generator=G) < 0.5
    assert _where_by(c, torch.zeros(3, 0, 4), torch.tensor(1.0), count_native_calls) == []


def test_where_records_gradients_by_aten(count_native_calls):
    x = torch.randn(B, C, K, generator=G, requires_grad=True)
    c = torch.rand(B, C, K, generator=G) < 0.5
    calls = count_native_calls()
    out = where(c, x, 0.0)
    assert calls == [] and out.requires_grad
    out.sum().backward()
    assert torch.equal(x.grad, c.to(x.dtype))
    with torch.no_grad():
        where(c, x, 0.0)
    assert calls == ["select_rows"]


def test_where_under_vmap_and_compile(count_native_calls):
    x = torch.randn(B, C, K, generator=G)
    c = torch.rand(B, C, K, generator=G) < 0.5
    calls = count_native_calls()
    got = torch.vmap(lambda ci, xi: where(ci, xi, -xi))(c, x)
    compiled = torch.compile(lambda ci, xi: where(ci, xi, -xi), fullgraph=True, backend="eager")(c, x)
    assert calls == []
    assert _same(got, torch.where(c, x, -x))
    assert _same(compiled, torch.where(c, x, -x))


def test_where_without_the_loops_is_aten(count_native_calls):
    c, a, b = _layouts()[1][1:]
    calls = count_native_calls()
    with _native.tensor_path():
        got = where(c, a, b)
    assert calls == []
    assert _same(got, torch.where(c, a, b))


def test_the_first_large_select_loads_the_loops(monkeypatch):
    monkeypatch.delitem(_native._state, "lib")
    c = torch.rand(2, MIN_ELEMENTS, generator=G) < 0.5
    where(c[:, :10], torch.zeros(2, 10), 1.0)
    assert "lib" not in _native._state  # a small select does not build
    assert _same(where(c, torch.zeros(2, MIN_ELEMENTS), 1.0), torch.where(c, torch.zeros(2, MIN_ELEMENTS), 1.0))
    assert _native._state["lib"] is not None


def test_min_elements_counts_the_largest_tensor(count_native_calls):
    n = MIN_ELEMENTS
    c = torch.rand(n, generator=G) < 0.5
    calls = count_native_calls()
    where(c[:-1], torch.zeros(n - 1), 1.0)
    assert calls == []
    assert _same(where(c, torch.zeros(n), 1.0), torch.where(c, torch.zeros(n), 1.0))
    assert calls == ["select_rows"]


def _packed(dims: tuple[int, ...], dtype=torch.float32):
    flags = torch.rand(B, C * K, generator=G) < 0.4
    flags[1] = False  # a run with no entry flagged
    width, place = packed_places(flags)
    block = torch.randn((B, width) + dims, generator=G).to(dtype)
    return flags, place, block


def _reference(block, place, flags, fill):
    index = place.reshape(place.shape + (1,) * (block.dim() - 2))
    gathered = torch.gather(block, 1, index.expand((-1, -1) + tuple(block.shape[2:])))
    return torch.where(flags.reshape(index.shape), gathered, fill)


@pytest.mark.parametrize("dims,fill", [((), 0.0), ((), "full"), ((4,), "row"), ((4,), "full"), ((3,), 0.0),
                                       ((2, 3), "row")], ids=["scalar", "full", "row of 4", "full of 4",
                                                              "scalar over 3", "row of 2x3"])
@pytest.mark.parametrize("threads", [1, 2])
def test_unpacked_is_a_gather_and_a_select(dims, fill, threads, at_threads, count_native_calls):
    flags, place, block = _packed(dims)
    if fill == "full":
        fill = torch.randn((B, C * K) + dims, generator=G)
    elif fill == "row":
        fill = torch.randn(dims, generator=G).expand((B, C * K) + dims)
    want = _reference(block, place, flags, fill)
    calls = count_native_calls()
    got = at_threads(lambda: unpacked(block, place, flags, fill), threads)
    assert calls == ["unpack_rows"]
    assert _same(got, want)


def test_unpacked_falls_back_with_gradients(count_native_calls):
    flags, place, block = _packed((2,))
    block.requires_grad_(True)
    calls = count_native_calls()
    got = unpacked(block, place, flags, 0.0)
    assert calls == [] and got.requires_grad
    assert _same(got.detach(), _reference(block.detach(), place, flags, 0.0))


def test_packed_places_order():
    flags = torch.tensor([[False, True, True, False, True], [True, False, False, False, False]])
    width, place = packed_places(flags)
    assert width == 3
    assert place.tolist() == [[0, 0, 1, 1, 2], [0, 0, 0, 0, 0]]


def test_library_code_selects_with_the_library_select():
    """models, kernels, filters, state, resampling and diagnostics call ``where`` of
    ``torchmcmcpf._native.select`` (docs/design.md, "One select"), never ``torch.where``."""
    from pathlib import Path

    root = Path(_native.__file__).resolve().parents[1]
    files = [p for d in ("models", "kernels", "filters") for p in (root / d).rglob("*.py")]
    files += [root / f for f in ("state.py", "resampling.py", "diagnostics.py")]
    offenders = [str(p.relative_to(root)) for p in files if "torch.where(" in p.read_text()]
    assert offenders == []
