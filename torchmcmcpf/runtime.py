"""The runtime: every choice that depends on where and how the code runs, in one module.

Models, moves and filters compute the same mathematics on every device; *how* a piece of it
is best evaluated depends on the device (CPU or CUDA), on whether ``torch.compile`` is
tracing it, and on whether a ``torch.func`` transform is active. Those questions are asked
here, by name, and each answer is written down once with its reason:

- :func:`on_cuda`, :func:`compiling`, :func:`in_function_transform`: the facts;
- :func:`neighbour_count`: how the windowed grid likelihood sizes its neighbour slots
  (dense on a GPU, one host read eager on a CPU, ``torch.cond`` compiled);
- :func:`broadcast_sums`: a sum of products as one broadcast reduction (GPU) or as
  products and a batched matrix product (CPU);
- :func:`compiled_for_cpu`: Inductor-on-CPU layout choices (a buffer of its own, a matmul
  for an outer product);
- :func:`blocked_linear_map`: the block-diagonal product of the small per-target maps (CPU);
- :func:`squared_norm`, :func:`pairwise_squared_distances`: sums of squares over a short last
  dim as explicit additions (CPU);
- :func:`guided_search`: categorical draws by a guide table (CPU, eager) or ``searchsorted``;
- :func:`fused_elementwise`, :func:`generated_reductions`: what compiling changes in the
  numerics (a polynomial fuses; a reduction must keep eager's bits);
- :class:`Program` and :func:`compile_program`: ``torch.compile(fullgraph=True)`` of a pure
  function, with CUDA graphs on a GPU (per call, or a whole loop captured as one graph);
- :func:`memory_budget`: the bytes of temporaries a grid sensor may hold at once, a
  process-wide default (``--memory-budget`` on the command line, at least 1 MiB);
- :func:`check_allocation`: a large allocation (initial particles, a filter's working
  memory) estimated and refused beyond :func:`allocation_budget` (default: the memory
  available on the device; :func:`set_allocation_budget` overrides it);
- :func:`tune_cpu_allocator`: glibc's allocator kept from returning large blocks.

Vocabulary (one word, one meaning): a **move** is one Metropolis-Hastings transition of every
chain of one kind (joint draw, refinement, random walk, exchange, HMC); an **iteration** is
one MCMC iteration of every chain (the move picked for it, applied); a **program** is a pure
function compiled here (an iteration, a move, the body of an SIR step).

Nothing here imports a model or a filter: the models and the filters ask.

CPU allocator
-------------
The windowed TBD likelihood of a batched step holds per-cell temporaries of tens of MB (at
N = 5000 particles and K = 10 targets, ``(N * K, 7, 49)`` float32 blocks of 68-98 MB). glibc's
``malloc`` serves blocks above its mmap threshold (128 KiB to 32 MiB, adaptive) with fresh
``mmap`` pages and returns them to the system when they are freed, so every call faults in and
zeroes its temporaries again. Measured on the 2-core CPU of benchmarks/README.md, compiled
windowed log-likelihood of the ground radar (N = 5000, K = 10): 190 ms per call by default,
89 ms after :func:`tune_cpu_allocator`; the fused ``log I0`` over 1.7e7 cells alone: 32 -> 12
ms. The command line (``python -m torchmcmcpf ...``) and the benchmarks call it; a library user
calls it once at start-up, or starts Python with ``THP_MEM_ALLOC_ENABLE=1`` (torch's own
switch: transparent huge pages for its CPU allocations, most of the same gain; it must be set
before torch allocates anything).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import inspect
import sys
import types
from collections.abc import Callable, Iterator
from typing import Any

import torch
from torch.utils._pytree import tree_flatten, tree_map, tree_unflatten

from ._validation import check_positive_int

__all__ = ["on_cuda", "compiling", "in_function_transform", "neighbour_count", "broadcast_sums", "compiled_for_cpu",
           "broadcast_shapes", "broadcast_or_none", "custom_op", "EagerOp", "take_along", "flagged_first",
           "blocked_linear_map", "fused_elementwise", "generated_reductions", "Program", "compile_program",
           "memory_budget", "set_memory_budget", "check_memory_budget", "MIN_MEMORY_BUDGET", "available_memory",
           "allocation_budget", "set_allocation_budget", "check_allocation", "tune_cpu_allocator"]


# ----------------------------------------------------------------------------- the facts
def on_cuda(t: torch.Tensor) -> bool:
    """Whether ``t`` lives on a CUDA device."""
    return t.device.type == "cuda"


def compiling() -> bool:
    """Whether ``torch.compile`` is tracing the caller."""
    return torch.compiler.is_compiling()


def in_function_transform() -> bool:
    """Whether a ``torch.func`` transform (``grad``, ``vmap``) is active around the caller
    (torch's only way to ask is a private call; it is made here and nowhere else).
    """
    return bool(torch._C._are_functorch_transforms_active())


# ----------------------------------------------------------------------------- the decisions
def neighbour_count(t: torch.Tensor) -> str:
    """How the windowed grid likelihood sizes the neighbour slots of a box
    (:meth:`~torchmcmcpf.models.sensors.grid.SeparableGridSensor.log_likelihood_window`) for
    a call whose tensors live where ``t`` does.

    - ``"dense"`` on a GPU: every target in every box, no device sync for the count and no
      branch, so that a compiled kernel is captured whole in a CUDA graph
      (:meth:`Program.capture`); also under a ``torch.func`` transform while compiling
      (``torch.cond`` cannot be traced inside ``torch.func.grad``: the compiled HMC move);
    - ``"count"`` eager on a CPU: the most targets overlapping one box, read from the device
      (one host read, cheap there);
    - ``"cond"`` compiled on a CPU: ``torch.cond`` between the fixed small count and the dense
      form (both branches compiled; the graph stays whole and its shapes static).

    All three are exact: they differ in how many zero terms a box sums.
    """
    if on_cuda(t):
        return "dense"
    if not compiling():
        return "count"
    return "dense" if in_function_transform() else "cond"


def broadcast_sums(t: torch.Tensor) -> bool:
    """Whether a sum of products over a short dim is best one broadcast product summed
    (True, on a GPU: fused by ``torch.compile``; a batched matrix product there would be tens
    of thousands of tiny matrices, which cuBLAS runs at a few percent of the card: its gemms
    were 70 % of the IP-MCMC-PF's GPU time on an H200, benchmarks/README.md) or outer
    products and one batched matrix product / term-by-term sums (False, on a CPU).
    """
    return on_cuda(t)


def compiled_for_cpu(t: torch.Tensor) -> bool:
    """Whether Inductor is compiling the caller for the CPU. There a cheap pointwise tensor
    inlined into a vectorised per-cell loop whose index needs a division falls back to
    scalar code, and an outer product fuses better as a matmul with inner size 1 (measured,
    benchmarks/bench_likelihood.py), so the grid sensor gives such tensors buffers of their
    own; eager, or on a GPU, the plain forms are faster.
    """
    return compiling() and t.device.type == "cpu"


def blocked_linear_map(x: torch.Tensor) -> bool:
    """Whether :func:`~torchmcmcpf.models.base.linear_map` multiplies groups of rows by a
    block-diagonal matrix (on the CPU, where BLAS is slow on tall products with 2-5 columns;
    eager and compiled alike, so the two give the same bits) rather than ``x @ M.mT``.
    """
    return x.device.type == "cpu"


def broadcast_shapes(*shapes: tuple[int, ...]) -> tuple[int, ...]:
    """``torch.broadcast_shapes(*shapes)`` for static shapes: the same shape, or its
    RuntimeError where they do not broadcast, without its checks of symbolic sizes (12 us a
    call in eager code, 2-4 calls in every MCMC iteration). A traced call takes torch's.
    """
    out = broadcast_or_none(*shapes) if not compiling() else None
    return torch.broadcast_shapes(*shapes) if out is None else out


def broadcast_or_none(*shapes: tuple[int, ...]) -> tuple[int, ...] | None:
    """The shapes broadcast together, or None where they do not."""
    out = [1] * max((len(s) for s in shapes), default=0)
    for s in shapes:
        offset = len(out) - len(s)
        for i, d in enumerate(s):
            if d != 1:
                if out[offset + i] == 1:
                    out[offset + i] = d
                elif out[offset + i] != d:
                    return None
    return tuple(out)


def take_along(t: torch.Tensor, index: torch.Tensor, dim: int) -> torch.Tensor:
    """``torch.take_along_dim(t, index, dim)`` for a non-negative ``index`` (the same values
    and gradient): one ``gather`` of the two broadcast against each other outside ``dim``.
    ``take_along_dim`` also wraps negative indices, a ``remainder`` pass over the index (one
    CPU thread: 48 -> 38 us for a chain's slot row ``(10, 200, 1, 1)`` of ``(10, 200, 5, 4)``,
    558 -> 131 us for a permutation of ``(10, 2000, 5)``). ``t`` and ``index`` have the same
    number of dims; a negative index is an error (``gather``'s bounds check), not wrapped.
    """
    if t.dim() != index.dim():
        raise ValueError(f"index has {index.dim()} dims and t {t.dim()}: expected the same number")
    d = dim % t.dim()
    shape_t = list(broadcast_shapes(t.shape[:d] + (1,) + t.shape[d + 1:], index.shape[:d] + (1,) + index.shape[d + 1:]))
    shape_i = list(shape_t)
    shape_t[d], shape_i[d] = t.shape[d], index.shape[d]
    return torch.gather(t.expand(shape_t), d, index.expand(shape_i))



def flagged_first(flags: torch.Tensor) -> torch.Tensor:
    """The indices of the last dim with the flagged entries first, each part in order (a stable
    sort of the flags): ``flags (..., P)`` bool -> ``(..., P)`` int64. Cut at a row's count, the
    flagged entries alone (a frame's valid points, a cloud's live candidate slots).
    """
    return torch.argsort((~flags).to(torch.uint8), dim=-1, stable=True)


def squared_norm(v: torch.Tensor) -> torch.Tensor:
    """``v.square().sum(-1)`` for a short last dim (2-4 coordinates: a whitened residual, a
    position, resolution coordinates): ``(..., r) -> (...)``, as explicit additions
    ``((v_0^2 + v_1^2) + v_2^2) ...``, the order in which ATen reduces up to 4 elements, so the
    same bits as ``.square().sum(-1)`` there (tested), eager and compiled.

    ATen's CPU sum reduces a float64 last dim of 2 or 3 elements row by row: 0.56-0.7 ms for
    40,000 rows on one core (the exclusion factors of 2,000 chains), against 0.05 ms for the
    additions; 1.5 ms for ``(100, 5000, 1, 2)`` float32 against 0.34 (the point SIR step).
    Differentiable.
    """
    out = v[..., 0].square()
    for i in range(1, v.shape[-1]):  # over the coordinates of one point
        out = out + v[..., i].square()
    return out


def pairwise_squared_distances(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``|a_i - b_j|^2`` for ``a (*S, I, r)`` and ``b (*S, J, r)`` -> ``(*S, I, J)``, coordinate
    by coordinate: the values of ``squared_norm(a[..., :, None, :] - b[..., None, :, :])``
    (each coordinate's difference squared, added in order), without a difference broadcast
    over an inner dim of ``r = 2-3`` coordinates, which costs 3x the time on the CPU (the
    exclusion factors of 10,000 MCMC-PF chains). Each coordinate is made contiguous first: the
    broadcast difference of two contiguous operands runs ATen's vectorised loop, of two
    stride-``r`` ones not (0.84 against 1.55 ms for ``(10, 1000, 2, 2)`` against ``(10, 1000,
    5, 2)``, one thread; the same values).
    """
    out = None
    for c in range(a.shape[-1]):  # over the coordinates
        sq = (a[..., c].contiguous().unsqueeze(-1) - b[..., c].contiguous().unsqueeze(-2)).square()
        out = sq if out is None else out + sq
    if out is None:
        raise ValueError(f"a has shape {tuple(a.shape)}: expected at least one coordinate")
    return out


def guided_search(cdf: torch.Tensor, u: torch.Tensor) -> bool:
    """Whether :func:`~torchmcmcpf.resampling.inverse_cdf` inverts the points ``u (..., M)``
    with a guide table over ``cdf (..., N)`` (its host reads: eager on a CPU only) rather than
    ``searchsorted``: where ``M >= 4 N``, so the table (``N`` points of its own) pays.
    """
    return host_reads(u) and u.shape[-1] >= 4 * cdf.shape[-1]


def in_place(x: torch.Tensor) -> bool:
    """Whether arithmetic on ``x`` may update its own fresh temporaries in place (the same
    operations, the same bits, fewer buffers: a chain of elementwise passes then stays in the
    cache): eager code with no gradient to record and no ``torch.func`` transform (the point
    sensor's intensities, the radar's ``log I0``).
    """
    return not (x.requires_grad and torch.is_grad_enabled()) and not in_function_transform() and not compiling()


def host_reads(t: torch.Tensor) -> bool:
    """Whether code on ``t`` may read the device to pick the entries that need work
    (``nonzero``, a count): eager on a CPU, where such a read is cheap; never compiled, under
    a ``torch.func`` transform or on a GPU (no sync: a captured CUDA graph). Used where the
    work skipped is larger than the read: a chain cache's scatter-add of the accepted moves
    only (:meth:`~torchmcmcpf.models.base.SensorModel.update_amplitude_cache`: 1.40 against
    0.26 ms at 30 % accepted, a cache of 245 MB bound by its misses), the radar's ``log I0``
    tail on its large arguments only (:func:`~torchmcmcpf.models.sensors.radar.log_i0_approx`),
    the guide table of the source draws (:func:`guided_search`).
    """
    return not on_cuda(t) and not compiling() and not in_function_transform()


def fused_elementwise() -> bool:
    """Whether chains of elementwise operations run fused into one loop (while compiling): a
    polynomial of a few dozen operations then costs about one pass over memory, less than a
    special function's own kernel (the radar's ``log I0``: about 1.5 ns per element compiled
    against 15 for ``i0e``, :func:`~torchmcmcpf.models.sensors.radar.log_i0`); eager, each
    operation is a pass of its own.
    """
    return compiling()


def generated_reductions() -> bool:
    """Whether Inductor generates the reductions of the caller (while compiling): its ``exp``
    and its summation order differ from ATen's in the last bit, so a reduction whose bits
    must equal eager code's (``compile_step=True`` equals eager) goes through an op the
    compiler cannot see into (the point sensors' ``logsumexp``).
    """
    return compiling()


# ----------------------------------------------------------------------------- programs
def _first_on_cuda(args: tuple) -> bool:
    """Whether the first tensor among ``args`` (and the tuples in them, one level down; a
    program's first argument is a tensor or a chain tuple) is on a CUDA device. Cheaper than
    flattening the arguments: it runs once per MH iteration.
    """
    for a in args:
        for t in (a if isinstance(a, tuple) else (a,)):
            if torch.is_tensor(t):
                return on_cuda(t)
    return False


def _signature(args: tuple) -> tuple:
    """The properties of ``args`` that a compiled program's graph depends on, as far as
    :func:`repeating` checks them: shape, dtype and device of each tensor argument
    and of the tensors in tuple arguments, one level down; scalars by value, anything else
    (deeper tuples) by its type.
    """
    def one(a: Any) -> Any:
        if torch.is_tensor(a):
            return (a.shape, a.dtype, a.device)
        return a if isinstance(a, (int, float, bool, str, type(None))) else type(a)

    return tuple(tuple(one(t) for t in a) if isinstance(a, tuple) else one(a) for a in args)


def _own_code(fn: Callable) -> Callable:
    """``fn`` as a Python function with a code object of its own.

    Dynamo keeps its compiled graphs, and counts recompilations against its limit (8), per
    code object. Every filter of one class binds its models in the same nested ``def`` (and
    ``torch.compile`` wraps a ``functools.partial`` or any other callable in one shared code
    object), so without a copy the programs of a process's ninth filter would fail with
    ``fullgraph=True``; with it, each program has its own cache.
    """
    if not inspect.isfunction(fn):
        inner = fn

        def fn(*args: Any) -> Any:
            return inner(*args)
    own = types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)
    own.__kwdefaults__, own.__qualname__ = fn.__kwdefaults__, fn.__qualname__
    return own


class Program:
    """A pure function compiled with ``torch.compile(fn, fullgraph=True, dynamic=False)``,
    with CUDA graphs on a GPU (:func:`compile_program` builds it).

    Called on CPU tensors it is the compiled ``fn``. Called on CUDA tensors (the first tensor
    argument decides) it is ``fn`` compiled with ``mode="reduce-overhead"``: each call
    replays one CUDA graph instead of launching the graph's kernels one by one. The MCMC
    filters call their iteration hundreds of times per step, and on a GPU those launches
    were the step's cost (benchmarks/README.md, H200: about 1 ms per iteration). A replay
    writes its outputs into the graph's static buffers, which the next replay overwrites,
    and the filters keep every iteration's chain state (the R-hat trace, the kept samples),
    so the outputs are cloned before they are returned. That mode is a second compilation
    of ``fn``, whose reductions may round differently from the plain one (float32 rounding:
    4e-6 relative on the SIR step's mean, H200).

    :meth:`capture` goes further: a whole loop of calls (a segment of MH iterations)
    captured as one CUDA graph of the plain compiled program (bit for bit its results), so
    that a GPU step costs the kernels' own time, not a graph launch and its Python per
    iteration: the IP-MCMC-PF step at Np = 5000 went from 73 to 16 ms on an H200.
    """

    def __init__(self, fn: Callable):
        fn = _own_code(fn)
        self._fn = fn
        #: a CPU call for which ``eager_when(*args)`` is true runs ``fn`` eagerly (:meth:`__call__`)
        self.eager_when: Callable[..., bool] | None = None
        self._plain = torch.compile(fn, fullgraph=True, dynamic=False)
        self._graphed: Callable | None = None
        self._inside = False  # warming up or capturing a loop: the plain program, no nested graphs
        self._loops: dict = {}
        self._seen: tuple[int, set] = (0, set())  # (loop of repeating(), the signatures called in it)

    def __call__(self, *args: Any) -> Any:
        """``fn(*args)``, compiled; on CUDA tensors one CUDA graph replay (class docstring).
        Inside :func:`repeating` a CPU call of a signature called before in the same loop
        skips Dynamo's guard evaluation. A CPU call for which ``eager_when(*args)`` is true
        runs ``fn`` eagerly: where its eager form is the faster (the IP-MCMC-PF's iteration
        in two C calls, :mod:`torchmcmcpf.kernels._exchange_native`).
        """
        if self._inside or not _first_on_cuda(args):
            if self.eager_when is not None and not self._inside and self.eager_when(*args):
                return self._fn(*args)
            loop = _repeating[0]
            if loop:
                if self._seen[0] != loop:
                    self._seen = (loop, set())
                key = _signature(args)
                if key in self._seen[1]:  # Dynamo's guards passed for it in this loop
                    with torch.compiler.set_stance("default", skip_guard_eval_unsafe=True):
                        return self._plain(*args)
                self._seen[1].add(key)
            return self._plain(*args)
        if self._graphed is None:
            self._graphed = torch.compile(self._fn, fullgraph=True, dynamic=False, mode="reduce-overhead")
        torch.compiler.cudagraph_mark_step_begin()
        return tree_map(lambda a: a.clone() if torch.is_tensor(a) else a, self._graphed(*args))

    def capture(self, loop: Callable, *args: Any) -> Any:
        """``loop(self, *args)``; on CUDA tensors as one CUDA graph.

        ``loop`` calls this program (any number of times) and must read tensors only through
        ``args`` (pytrees of tensors, ``None`` and hashable constants) and never wait for the
        device (no ``.item()``, no data-dependent Python branch). On CUDA the first call for a
        given ``loop`` and signature (shapes, dtypes, devices, constants) warms up on a side
        stream, then captures ``loop`` on static copies of the tensor arguments; every call
        copies the arguments in, replays the graph and returns clones of its outputs (so an
        earlier result survives the next replay). Same kernels, same results as the loop
        called eagerly with this program, which is what it is on the CPU (inside
        :func:`repeating`). Each signature's graph and its memory pool are kept for the
        program's life (the filter's).
        """
        leaves, spec = tree_flatten(args)
        tensors = [a for a in leaves if torch.is_tensor(a)]
        if not tensors or not on_cuda(tensors[0]):
            with repeating():
                return loop(self, *args)
        key = (loop, spec, tuple((a.shape, a.dtype, a.device) if torch.is_tensor(a) else a for a in leaves))
        entry = self._loops.get(key)
        if entry is None:
            static = [a.clone() if torch.is_tensor(a) else a for a in leaves]
            static_args = tree_unflatten(static, spec)
            side = torch.cuda.Stream(tensors[0].device)
            side.wait_stream(torch.cuda.current_stream(tensors[0].device))
            graph = torch.cuda.CUDAGraph()
            self._inside = True
            try:
                with torch.cuda.stream(side):  # warm-up: compilation, library handles
                    loop(self, *static_args)
                torch.cuda.current_stream(tensors[0].device).wait_stream(side)
                with torch.cuda.graph(graph):
                    outputs = loop(self, *static_args)
            finally:
                self._inside = False
            entry = self._loops[key] = (graph, static, outputs)
        graph, static, outputs = entry
        for dst, src in zip(static, leaves):
            if torch.is_tensor(src):
                dst.copy_(src)
        graph.replay()
        return tree_map(lambda a: a.clone() if torch.is_tensor(a) else a, outputs)


#: ``[loop]``: the current :func:`repeating` loop's number (0: none), ``[count]``: loops so far
_repeating = [0]
_loops_started = [0]


@contextlib.contextmanager
def repeating() -> Iterator[None]:
    """A loop that calls compiled programs (:class:`Program`) many times with arguments of a
    few fixed signatures (MH iterations fed their own outputs): inside it, a CPU call of a
    program with a signature (shapes, dtypes and devices of its tensors and of those in its
    tuples, one level down; :func:`_signature`) that the program already ran in this loop
    skips Dynamo's guard evaluation (``torch.compiler.set_stance(skip_guard_eval_unsafe=
    True)``: only the guards that tell the program's cached graphs apart run). The guards
    had cost about 0.25 ms per call, 5-12 % of a compiled IP-MCMC-PF step (radar, Np =
    5000, one CPU thread; the same bits). Safe because the first call of each signature in
    the loop runs the full guards (and compiles if it must), a repeat's tensors have the
    same properties, and Inductor's code still asserts every input's sizes and strides.
    Loops nest (the inner one starts afresh). Eager code is unaffected.
    """
    previous = _repeating[0]
    _loops_started[0] += 1
    _repeating[0] = _loops_started[0]
    try:
        yield
    finally:
        _repeating[0] = previous


class EagerOp:
    """A ``torch.library`` custom op whose eager calls run its function directly: the
    dispatcher's pass through the op (autograd and device keys, the schema's checks) costs
    about 8 us a call, which an MCMC iteration of a few hundred chains pays two or three
    times. A traced call (:func:`compiling`) or one on a tensor subclass (fake tensors) takes
    the op, so a compiled or exported graph holds it.
    Only for ops with no autograd formula, called where nothing needs one (the C loops'
    ``applies``: no gradient to record, no ``torch.func`` transform).

    Example
    -------
    >>> import torch
    >>> from torchmcmcpf.runtime import custom_op
    >>> @custom_op("torchmcmcpf_doc::plus_one")
    ... def plus_one(x: torch.Tensor) -> torch.Tensor:
    ...     return x + 1
    >>> plus_one(torch.zeros(2))  # eager: the function itself
    tensor([1., 1.])
    >>> plus_one.op(torch.zeros(2))  # the registered op, which a traced call takes
    tensor([1., 1.])
    """

    def __init__(self, fn: Callable, op: Any) -> None:
        self._fn, self.op = fn, op

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        """The function's result: directly on plain tensors when eager, through the op when
        traced or on a tensor subclass (a fake tensor of ``torch.export``, a user's subclass).
        """
        if compiling() or any(isinstance(a, torch.Tensor) and type(a) is not torch.Tensor for a in args):
            return self.op(*args, **kwargs)
        return self._fn(*args, **kwargs)

    def register_fake(self, fn: Callable) -> Callable:
        """The op's fake (meta) function, as ``CustomOpDef.register_fake``."""
        return self.op.register_fake(fn)


def custom_op(name: str) -> Callable[[Callable], EagerOp]:
    """``torch.library.custom_op(name, mutates_args=())`` as an :class:`EagerOp` (decorator)."""
    def wrap(fn: Callable) -> EagerOp:
        return EagerOp(fn, torch.library.custom_op(name, mutates_args=())(fn))
    return wrap


def compile_program(fn: Callable) -> Program:
    """``fn`` compiled as a filter's program: :class:`Program`."""
    return Program(fn)


# ----------------------------------------------------------------------------- memory
#: the process-wide default of :func:`memory_budget` (bytes); :func:`set_memory_budget` sets it
_memory_budget = [2**30]


def memory_budget() -> int:
    """Bytes of temporaries a grid sensor's likelihood may hold at once when the sensor was
    built without its own ``memory_budget`` (default 1 GiB; the grid sensors chunk their
    samples to stay within it, :mod:`torchmcmcpf.models.sensors.grid`).
    """
    return _memory_budget[0]


#: the smallest :func:`memory_budget` accepted (1 MiB): below it a grid sensor's blocks hold a
#: handful of samples each and a step runs thousands of tiny blocks (a budget in bytes given as,
#: say, megabytes: ``--memory-budget 10``)
MIN_MEMORY_BUDGET = 2**20


def check_memory_budget(num_bytes: object, name: str = "memory_budget") -> int:
    """``num_bytes`` as an ``int >= MIN_MEMORY_BUDGET`` (1 MiB); a ``ValueError`` naming
    ``name`` otherwise.
    """
    return check_positive_int(num_bytes, f"{name} (bytes)", minimum=MIN_MEMORY_BUDGET)


def set_memory_budget(num_bytes: int) -> int:
    """Set the process-wide :func:`memory_budget` (``--memory-budget`` on the command line);
    returns the previous value. Below :data:`MIN_MEMORY_BUDGET` (1 MiB) it is refused.
    """
    old = _memory_budget[0]
    _memory_budget[0] = check_memory_budget(num_bytes)
    return old


# ----------------------------------------------------------------------------- allocation guard
#: the process-wide :func:`allocation_budget` set by :func:`set_allocation_budget` (bytes), or
#: ``None``: the memory available on the device at the time of the check
_allocation_budget: list[int | None] = [None]


def available_memory(device: torch.device | str | None = None) -> int | None:
    """Bytes free on ``device`` now: ``torch.cuda.mem_get_info`` on a GPU, ``MemAvailable`` of
    ``/proc/meminfo`` (Linux) or the free physical pages (other POSIX) on the CPU; ``None``
    where the platform does not say.
    """
    device = torch.device("cpu" if device is None else device)
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    if device.type != "cpu":
        return None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        import os

        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def allocation_budget(device: torch.device | str | None = None) -> int | None:
    """The most bytes one large allocation of the library (a cloud of initial particles, a
    filter's working memory, :func:`check_allocation`) may take on ``device``: the value of
    :func:`set_allocation_budget` when one is set, else the memory available on the device
    now (:func:`available_memory`; ``None``: unknown, nothing is refused).
    """
    return _allocation_budget[0] if _allocation_budget[0] is not None else available_memory(device)


def set_allocation_budget(num_bytes: int | None) -> int | None:
    """Set the process-wide :func:`allocation_budget` in bytes (``None``: back to the memory
    available at each check); returns the previous setting. Raise it to let a problem through
    that the estimate refuses (the estimates are lower bounds, so a refused one would not have
    fitted), lower it to keep a process small.
    """
    old = _allocation_budget[0]
    _allocation_budget[0] = None if num_bytes is None else check_positive_int(num_bytes, "allocation_budget")
    return old


def _size(num_bytes: float) -> str:
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if num_bytes >= scale:
            return f"{num_bytes / scale:.3g} {unit}"
    return f"{num_bytes:.0f} bytes"


def check_allocation(num_bytes: float, what: str, device: torch.device | str | None = None, *,
                     hint: str = "") -> None:
    """Refuse, before anything is allocated, ``what`` (e.g. ``"initial_particles(num_particles=
    100000000)"``) whose estimated size ``num_bytes`` exceeds :func:`allocation_budget` on
    ``device``: a ``ValueError`` naming the estimate, the budget and how to change it, instead
    of torch's allocator error or minutes of swapping. ``hint`` ends the message (what to make
    smaller).
    """
    budget = allocation_budget(device)
    if budget is None or num_bytes <= budget:
        return
    source = ("runtime.set_allocation_budget" if _allocation_budget[0] is not None
              else f"the memory available on {torch.device('cpu' if device is None else device)}")
    raise ValueError(f"{what} needs an estimated {_size(num_bytes)} ({int(num_bytes):,} bytes), above the allocation "
                     f"budget of {_size(budget)} ({source}); {hint + '; ' if hint else ''}"
                     "torchmcmcpf.runtime.set_allocation_budget(bytes) changes the budget")


# ----------------------------------------------------------------------------- the allocator

#: glibc ``mallopt`` parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def tune_cpu_allocator(max_block: int = 2**30) -> bool:
    """Keep freed CPU memory in the process for reuse (glibc's ``malloc`` only).

    Sets glibc's mmap threshold and trim threshold to ``max_block`` bytes with ``mallopt``:
    blocks up to that size come from the heap and freed memory stays there, so the next step
    reuses warm pages instead of faulting in new ones. The process's resident memory then
    stays near its peak instead of shrinking between steps, and the peak can grow by heap
    fragmentation: measured +19% (1.04 -> 1.24 GB) over ten eager radar SIR steps at N = 5000
    followed by three IP-MCMC-PF steps at B = 10 in one process. Affects the whole process,
    from the call on; call it once.

    Parameters
    ----------
    max_block : int > 0
        Largest block served from the heap, in bytes (default 1 GiB).

    Returns
    -------
    bool: True when applied; False on a platform without glibc's ``mallopt`` (macOS, musl,
    Windows), where nothing changes.
    """
    max_block = check_positive_int(max_block, "max_block")
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    value = min(max_block, 2**31 - 1)
    return bool(mallopt(_M_MMAP_THRESHOLD, value)) and bool(mallopt(_M_TRIM_THRESHOLD, value))
