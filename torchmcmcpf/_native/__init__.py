"""The library's C loops: built once per machine, loaded through ``ctypes``.

Loops in plain C beside the tensor paths, each the same values (to round-off for the sums):

- ``rician_window.c``: the radar's windowed Rician likelihood and its moves
  (:mod:`torchmcmcpf.models.sensors.grid.native`);
- ``points.c``: the point sensor's Gaussian sums, its intensities, cached moves and
  data-driven densities (:mod:`torchmcmcpf.models.sensors._points_native`);
- ``exclusion.c``: the exclusion factor and its change when a slot moves
  (:meth:`torchmcmcpf.models.multitarget.Exclusion.log_factor`, ``log_change``);
- ``exchange.c``: the exchange move's iteration after its likelihood change (the MH decision,
  the chains' fields and cache written) in one call, and a segment's iterations with the
  sensor's change (a :class:`RowsLoop`) in one call per run of one-slot moves or two-slot move
  (:mod:`torchmcmcpf.kernels._exchange_native`, :mod:`torchmcmcpf.kernels.exchange_segment`);
- ``select.c``: ``torch.where`` and the read-back of a packed block in one pass
  (:mod:`torchmcmcpf._native.select`), which every move makes dozens of times an iteration.

The sources (with ``split.h``, the samples' split over threads, ``vecmath.h``, the
vectorisable ``exp`` and ``log``, and ``exclusion.h``, the exclusion's loops that two sources
share) are compiled together by the host's C compiler (``$CC``, else ``cc``; ``-O3
-march=native``, OpenMP where it has it, else serial) into one library in a cache folder (``$TORCHMCMCPF_CACHE``, else
``~/.cache/torchmcmcpf``), keyed by the sources, the compiler, its flags and the CPU, on the
first :func:`available` call. The calls split their samples evenly over
``torch.get_num_threads()`` of torch's own OpenMP threads (the wheel's ``libgomp.so.1``,
already loaded, is the one the library links to), so each sample's result is the same at any
thread count. Without a compiler, or with ``TORCHMCMCPF_NATIVE=0``, every path runs on
tensors; :func:`tensor_path` does the same within a block (an A/B in one process).
"""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

import torch

from .. import runtime

__all__ = ["available", "applies", "library", "tensor_path", "FLAGS", "RowsLoop"]

_FOLDER = Path(__file__).parent
#: the sources, compiled together into one library (the headers are part of the key)
SOURCES = ("rician_window.c", "points.c", "exclusion.c", "exchange.c", "select.c")
#: compiler flags: vectorised selects need ``-fno-trapping-math``, inlined ``sqrtf``
#: ``-fno-math-errno``; neither changes a finite result (no fast-math reassociation). Loops
#: stay loops (``-fno-tree-loop-distribute-patterns``: a box row's copy of 7 floats was a
#: ``memcpy`` call). ``-fopenmp`` first: the loops then run on torch's own OpenMP threads; a
#: compiler without OpenMP builds them serial (``-fopenmp-simd``: the vector loops only)
FLAGS = ("-O3", "-march=native", "-fno-math-errno", "-fno-trapping-math", "-fno-tree-loop-distribute-patterns",
         "-shared", "-fPIC")
_THREADING = ("-fopenmp", "-fopenmp-simd")

_i64, _ptr, _f64, _int = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double, ctypes.c_int
#: every exported call: (return type, argument types)
SIGNATURES: dict[str, tuple[Any, list[Any]]] = {
    "rician_window_loglik": (_int, [_i64] * 4 + [_ptr] * 6 + [_i64, _f64, _ptr]),
    "rician_delta_cached": (_int, [_i64] * 4 + [_ptr] * 6 + [_i64, _f64] + [_ptr] * 3),
    "rician_delta_rows": (_int, [_i64] * 5 + [_ptr] * 7 + [_i64, _f64] + [_ptr] * 3),
    "rician_move": (_int, [_i64] * 4 + [_ptr] * 9 + [_i64, _f64, _ptr]),
    "rician_floor": (_f64, [_i64] * 3 + [_ptr] * 3 + [_f64]),
    "points_intensity": (_int, [_i64] * 5 + [_ptr] * 3 + [_f64, _ptr]),
    "points_delta": (_int, [_i64] * 5 + [_ptr] * 7),
    "points_near": (_int, [_i64] * 4 + [_ptr] * 3 + [_f64, _ptr]),
    "points_log_sum": (_int, [_i64] * 4 + [_ptr] * 3),
    "points_exp": (None, [_i64, _ptr, _ptr]),
    "points_log": (None, [_i64, _ptr, _ptr]),
    "exclusion_change": (_int, [_i64] * 4 + [_ptr] * 5 + [_f64, _f64, _ptr]),
    "exclusion_factor": (_int, [_i64] * 4 + [_ptr] * 2 + [_f64, _f64, _ptr]),
    "exclusion_log_phi": (None, [_i64, _ptr, _f64, _f64, _ptr]),
    "exchange_commit": (_int, [_i64] * 4 + [_ptr] * 8 + [_i64, _f64, _f64] + [_ptr] * 3 + [_i64] + [_ptr] * 7
                        + [_i64] + [_ptr] * 2),
    "exchange_segment": (_int, [_i64] * 5 + [_ptr] * 7 + [_i64, _f64, _f64] + [_ptr] * 5 + [_i64] + [_ptr] * 8
                         + [_i64] + [_ptr] * 4 + [_i64] + [_ptr] * 3),
    "rician_rows_context_size": (_i64, []),
    "rician_rows_context": (_int, [_ptr, _i64, _ptr, _ptr, _ptr, _i64, _f64]),
    "rician_rows_one": (ctypes.c_float, [_ptr, _i64, _i64] + [_ptr] * 6),
    "select_rows": (_int, [_i64] * 4 + [_ptr] * 2 + [_i64, _ptr, _i64, _ptr]),
    "unpack_rows": (_int, [_i64] * 6 + [_ptr] * 4 + [_i64, _ptr]),
}

_state: dict[str, Any] = {}


class RowsLoop(NamedTuple):
    """A sensor's change of one sample's move read from its rows, as a C entry that another C
    loop calls sample by sample (:meth:`~torchmcmcpf.models.base.SensorModel.delta_rows_loop`;
    the exchange segment's loop, ``exchange.c``): ``fn`` the entry's address (``float fn(ctx,
    q, M, terms_q, slot_q, terms_new_q, cache, cells_q, change_q)``, ``exchange.c``'s
    ``rows_delta``), ``context`` its argument (a buffer the entry reads), ``cells`` the cells a
    moved slot's box holds (a move of ``M`` slots writes ``2 M cells`` cells and changes), and
    ``keep`` the tensors the context points into (held while the loop lives).
    """

    fn: int
    context: Any
    cells: int
    keep: tuple


def _cpu_key() -> str:
    """What ``-march=native`` depends on: the CPU's model and flags."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        return "".join(sorted({ln for ln in lines if ln.startswith(("model name", "flags"))}))
    except OSError:
        return platform.processor() + platform.machine()


def _warn(message: str) -> None:
    warnings.warn(f"torchmcmcpf: {message}; the tensor paths are used", RuntimeWarning, stacklevel=4)


def _build() -> ctypes.CDLL | None:
    """Compile (once per machine and sources) and load the C loops; ``None`` with a warning
    when no compiler is found or the build fails.
    """
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        _warn("no C compiler found for the C loops")
        return None
    sources = [_FOLDER / name for name in SOURCES]
    try:
        version = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=60).stdout
    except (OSError, subprocess.SubprocessError):
        version = ""
    parts = [p.read_bytes() for p in sources + sorted(_FOLDER.glob("*.h"))]
    key = hashlib.sha256(b"\0".join(parts + [cc.encode(), version.encode(), " ".join(FLAGS + _THREADING).encode(),
                                             _cpu_key().encode()])).hexdigest()[:16]
    folder = Path(os.environ.get("TORCHMCMCPF_CACHE") or Path.home() / ".cache" / "torchmcmcpf")
    target = folder / f"torchmcmcpf-{key}.so"
    if not target.exists():
        errors = []
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            errors.append(f"cannot make {folder}: {err}")
        for threading in _THREADING if not errors else ():
            try:
                with tempfile.TemporaryDirectory(dir=folder) as tmp:
                    built = Path(tmp) / target.name
                    subprocess.run([cc, *FLAGS, threading, *map(str, sources), "-o", str(built), "-lm"], check=True,
                                   capture_output=True, text=True, timeout=300)
                    os.replace(built, target)  # atomic: concurrent builders leave one whole file
                break
            except (OSError, subprocess.SubprocessError) as err:
                errors.append((getattr(err, "stderr", "") or str(err)).strip()[:300])
        else:
            _warn(f"building the C loops failed ({' / '.join(errors)})")
            return None
    try:
        lib = ctypes.CDLL(str(target))
    except OSError as err:  # a file another machine's build left, or a damaged one
        _warn(f"loading the C loops {target} failed ({err})")
        return None
    for name, (restype, argtypes) in SIGNATURES.items():
        fn = getattr(lib, name, None)
        if fn is None:  # a library of other sources under this key: not ours to use
            _warn(f"{target} has no {name}")
            return None
        fn.restype, fn.argtypes = restype, argtypes
    return lib


def available() -> bool:
    """Whether the C loops are built and loaded (building them on the first call; ``False``
    with ``TORCHMCMCPF_NATIVE=0``). Called eagerly when a sensor with a loop is made, so
    that compiled code reads a settled answer.
    """
    if "lib" not in _state:
        _state["lib"] = None if os.environ.get("TORCHMCMCPF_NATIVE", "1") == "0" else _build()
    return _state["lib"] is not None


def library() -> Any:
    """The loaded library (its functions typed as :data:`SIGNATURES`), or ``None``: not built,
    not wanted, or inside :func:`tensor_path`.
    """
    return _state.get("lib")


def applies(x: torch.Tensor) -> bool:
    """Whether a float64 C loop serves a call on ``x``: a float32 or float64 CPU tensor, no
    gradient to record, no ``torch.func`` transform, the loops built (the point sensor's and
    the exclusion factor's; the radar's has its own rule).
    """
    return (x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64)
            and not (x.requires_grad and torch.is_grad_enabled()) and not runtime.in_function_transform()
            and library() is not None)


@contextlib.contextmanager
def tensor_path() -> Iterator[None]:
    """Within the block, every path runs on tensors, as on a machine without a compiler (an
    A/B of the two forms in one process: benchmarks/bench_likelihood.py, the tests).
    Compiled code guards on the switch, so a compiled call made inside the block recompiles
    once outside it.
    """
    available()
    lib = _state.get("lib")
    _state["lib"] = None
    try:
        yield
    finally:
        _state["lib"] = lib
