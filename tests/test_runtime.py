"""``torchmcmcpf.runtime.tune_cpu_allocator``: glibc keeps large freed blocks in the heap."""

import ctypes
import ctypes.util
import sys

import pytest
import torch

from torchmcmcpf.runtime import tune_cpu_allocator


def _mmapped_bytes() -> int | None:
    """glibc's ``mallinfo2().hblkhd``: bytes currently held in mmapped blocks (None without it)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.mallinfo2
    except (OSError, AttributeError):
        return None

    class Mallinfo2(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in
                    ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
                     "fordblks", "keepcost")]

    fn.restype = Mallinfo2
    return int(fn().hblkhd)


@pytest.mark.parametrize("bad", [0, -1, 1.5, True])
def test_bad_max_block(bad):
    with pytest.raises(ValueError, match="max_block"):
        tune_cpu_allocator(bad)


@pytest.mark.skipif(not sys.platform.startswith("linux") or _mmapped_bytes() is None, reason="glibc only")
def test_large_tensor_comes_from_the_heap():
    """After the call a 64 MB tensor is not an mmapped block (it was before: glibc's default
    threshold is at most 32 MB)."""
    assert tune_cpu_allocator() is True
    before = _mmapped_bytes()
    t = torch.empty(16 * 2**20)  # 64 MB
    assert _mmapped_bytes() - before < 2**20
    del t


def test_programs_of_one_def_have_their_own_compile_cache():
    # nine filters of one class bind their models in the same nested def: dynamo counts
    # recompilations per code object (limit 8), so each Program copies the code object
    import functools

    from torchmcmcpf.runtime import compile_program

    def bind(scale):
        def body(x):
            return x * scale
        return body

    x = torch.ones(3)
    programs = [compile_program(bind(float(s))) for s in range(9)]
    programs.append(compile_program(functools.partial(torch.mul, other=2.0)))  # any callable
    assert [float(p(x)[0]) for p in programs] == [float(s) for s in range(9)] + [2.0]


@pytest.mark.compile
def test_repeating_program_skips_guards_only_for_signatures_it_has_run():
    # inside runtime.repeating a repeated signature skips Dynamo's guards; a new one (another
    # shape, another tuple layout) still runs them and compiles, so every result is right
    from torchmcmcpf import runtime
    from torchmcmcpf.runtime import compile_program

    def body(x, pair):
        return x * pair[0] + pair[1].sum()

    prog = compile_program(body)
    inputs = [(torch.full((3,), float(i)), (torch.tensor(2.0), torch.arange(float(i + 2)))) for i in range(3)]
    inputs.append((torch.ones(5), (torch.tensor(3.0), torch.ones(4))))  # another shape
    with runtime.repeating():
        inside = [prog(x, pair) for x, pair in inputs + inputs]
        with runtime.repeating():  # a nested loop starts afresh
            inside += [prog(x, pair) for x, pair in reversed(inputs)]
            assert len(prog._seen[1]) == len(inputs)
        inside += [prog(*inputs[0])]
    assert runtime._repeating[0] == 0  # left the loops
    for (x, pair), got in zip(inputs + inputs + inputs[::-1] + inputs[:1], inside):
        torch.testing.assert_close(got, body(x, pair), rtol=0, atol=0)


@pytest.mark.compile
def test_program_runs_eagerly_where_eager_when_says():
    """A Program's ``eager_when(*args)``: a CPU call for which it is true runs the function
    eagerly (nothing traced), any other call the compiled program."""
    from torchmcmcpf.runtime import compile_program

    traced = []

    def body(x):
        traced.append(torch.compiler.is_compiling())
        return x + 1.0

    prog = compile_program(body)
    prog.eager_when = lambda x: bool(x.shape[0] == 2)
    assert torch.equal(prog(torch.zeros(2)), torch.ones(2)) and traced == [False]
    assert torch.equal(prog(torch.zeros(3)), torch.ones(3)) and traced[1:] == [True]  # compiled (its side effect)
    assert torch.equal(prog(torch.zeros(2)), torch.ones(2)) and traced[2:] == [False]


@pytest.mark.parametrize("t_shape, i_shape, dim", [
    ((3, 7, 5, 4), (3, 7, 1, 1), 2),    # a slot's row of each chain, broadcast over the state
    ((3, 7, 5), (3, 7, 5), -1),         # a permutation of each particle's slots
    ((1, 7, 5), (3, 2, 5), 1),          # the input broadcast over the batch
    ((6, 4), (1, 9), 1),                # more picks than entries
])
def test_take_along_equals_take_along_dim(t_shape, i_shape, dim):
    """runtime.take_along gives torch.take_along_dim's values and gradient for non-negative
    indices, with either side broadcast outside ``dim``; a dims mismatch is a ValueError."""
    from torchmcmcpf.runtime import take_along

    g = torch.Generator().manual_seed(0)
    t = torch.randn(t_shape, generator=g, dtype=torch.float64, requires_grad=True)
    index = torch.randint(t_shape[dim], i_shape, generator=g)
    want = torch.take_along_dim(t, index, dim)
    got = take_along(t, index, dim)
    assert got.shape == want.shape and torch.equal(got, want)
    w = torch.randn(want.shape, generator=g, dtype=torch.float64)
    (grad_want,) = torch.autograd.grad((want * w).sum(), t)
    (grad_got,) = torch.autograd.grad((got * w).sum(), t)
    assert torch.equal(grad_got, grad_want)
    with pytest.raises(ValueError, match="same number"):
        take_along(t, index.flatten(), dim)


def test_flagged_first_puts_the_flagged_entries_first_in_order():
    from torchmcmcpf.runtime import flagged_first

    flags = torch.tensor([[False, True, False, True, True], [False] * 5, [True] * 5])
    assert flagged_first(flags).tolist() == [[1, 3, 4, 0, 2], [0, 1, 2, 3, 4], [0, 1, 2, 3, 4]]


@pytest.mark.parametrize("shapes", [
    ((3, 1, 5), (7, 1)), ((1,), (4, 2)), ((), (2, 3)), ((2, 0), (1,)), ((5, 1, 1), (1, 4, 1), (1, 1, 3)), ((4,),),
])
def test_broadcast_shapes_equals_torch(shapes):
    """runtime.broadcast_shapes gives torch.broadcast_shapes' shape, eager and traced."""
    from torchmcmcpf.runtime import broadcast_or_none, broadcast_shapes

    want = tuple(torch.broadcast_shapes(*shapes))
    assert broadcast_shapes(*shapes) == want and broadcast_or_none(*shapes) == want
    assert torch.compile(lambda x: x.new_zeros(broadcast_shapes(*shapes)), backend="eager")(torch.ones(1)).shape == want


def test_broadcast_shapes_raises_torch_error():
    from torchmcmcpf.runtime import broadcast_or_none, broadcast_shapes

    assert broadcast_or_none((3, 2), (4, 2)) is None
    with pytest.raises(RuntimeError, match="broadcast"):
        torch.broadcast_shapes((3, 2), (4, 2))
    with pytest.raises(RuntimeError, match="broadcast"):
        broadcast_shapes((3, 2), (4, 2))


def test_eager_op_calls_its_function_eager_and_its_op_traced():
    """runtime.custom_op: an eager call runs the function itself (no dispatcher), a traced
    call the registered op (a compiled graph holds it, the fake function gives its shape)."""
    from torchmcmcpf.runtime import custom_op

    calls = []

    @custom_op("torchmcmcpf_test::doubled")
    def doubled(x: torch.Tensor) -> torch.Tensor:
        calls.append(torch.compiler.is_compiling())
        return x * 2

    @doubled.register_fake
    def _(x):
        return torch.empty_like(x)

    x = torch.arange(4.0)
    assert torch.equal(doubled(x), x * 2) and calls == [False]
    assert torch.equal(doubled.op(x), x * 2) and len(calls) == 2  # the op itself runs the same function
    gm = []

    def backend(g, inputs):
        gm.append(g)
        return g.forward

    assert torch.equal(torch.compile(lambda t: doubled(t) + 1, backend=backend, fullgraph=True)(x), x * 2 + 1)
    assert any("torchmcmcpf_test.doubled" in str(node.target) for node in gm[0].graph.nodes)
    # a fake tensor (shape propagation outside torch.compile) takes the op's fake function
    from torch._subclasses.fake_tensor import FakeTensorMode

    before = len(calls)
    with FakeTensorMode() as mode:
        out = doubled(mode.from_tensor(x))
    assert out.shape == x.shape and len(calls) == before
