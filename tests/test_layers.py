"""The package's imports run one way: no import circle between modules, no back-arrow.

Every ``import`` of the package's own modules is read with :mod:`ast` from the source: at
module level, inside functions and under ``if TYPE_CHECKING:`` alike (a deferred import is
still an arrow). ``from .x import name`` is an arrow to module ``x`` (to the package's
``__init__`` when ``x`` is a package), ``from . import y`` to submodule ``y``.

The layers, bottom to top; a module imports only its own layer and the layers below:

0. foundations: ``_version``, ``typing``, ``_validation``, ``runtime``, ``_native`` (the C loops);
1. exporters: ``interop`` (``_layout``, ``arviz``, ``stonesoup``): they read a result
   through the protocols of ``interop._layout``, so that ``state`` can offer
   ``FilterResult.to_xarray`` / ``to_arviz`` / ``to_stonesoup`` without a circle;
2. containers and weights: ``state``, ``resampling``, ``diagnostics``;
3. ``models`` (motion, existence, group, sensors);
4. ``kernels``, ``metrics``, ``scenarios``: simulators draw from the models and never run a
   filter (a function that runs one lives in ``filters`` or ``experiments``, e.g.
   ``experiments.maroulas_hmc.track``);
5. ``filters``, ``plotting``, ``interop.stonesoup_trackers`` (Stone Soup's trackers as
   baselines);
6. ``experiments``, ``bench``;
7. the public facade ``torchmcmcpf/__init__`` and ``__main__``: nothing inside the package
   imports the facade (the version lives in ``_version``).

Within a layer any direction is allowed, but no circle, also inside a package (the grid
sensor's evaluation paths read the sensor through ``grid._protocol.GridSensorLike``, so
``grid.sensor`` imports them and not the other way). A new top-level module or package must
be placed in :data:`LAYERS`.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "torchmcmcpf"
PACKAGE = "torchmcmcpf"

#: module (or package prefix) -> layer; the longest matching prefix wins (module docstring)
LAYERS: dict[str, int] = {
    "_version": 0, "typing": 0, "_validation": 0, "runtime": 0, "_native": 0,
    "interop": 1,
    "state": 2, "resampling": 2, "diagnostics": 2,
    "models": 3,
    "kernels": 4, "kernels.pair_path": 4, "metrics": 4, "scenarios": 4,
    "filters": 5, "plotting": 5, "interop.stonesoup_trackers": 5,
    "experiments": 6, "bench": 6,
    "": 7, "__main__": 7,  # "": the facade torchmcmcpf/__init__ itself (exact match only)
}


def modules(root: Path = ROOT, package: str = PACKAGE) -> dict[str, tuple[Path, bool]]:
    """Dotted name -> (source path, is a package ``__init__``) of every module under ``root``."""
    found = {}
    for path in sorted(root.rglob("*.py")):
        parts = [package, *path.relative_to(root).with_suffix("").parts]
        is_package = parts[-1] == "__init__"
        found[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    return found


def _targets(node: ast.Import | ast.ImportFrom, name: str, is_package: bool, known: set[str]) -> list[str]:
    """The package's modules that one import statement of module ``name`` reads."""
    if isinstance(node, ast.Import):
        wanted = [alias.name for alias in node.names]
    else:
        if node.level:
            base = name.split(".") if is_package else name.split(".")[:-1]
            base = base[: len(base) - (node.level - 1)]
            source = ".".join(base + ([node.module] if node.module else []))
        else:
            source = node.module or ""
        wanted = [f"{source}.{alias.name}" if f"{source}.{alias.name}" in known else source for alias in node.names]
    out = []
    for target in wanted:
        while target and target not in known:  # ``import torchmcmcpf.x.y`` reads module x.y; a name -> its module
            target = target.rpartition(".")[0]
        if target:
            out.append(target)
    return out


def import_graph(root: Path = ROOT, package: str = PACKAGE) -> dict[str, dict[str, int]]:
    """Module -> {imported module of the package: line of the first such import}."""
    found = modules(root, package)
    known = set(found)
    graph: dict[str, dict[str, int]] = {name: {} for name in found}
    for name, (path, is_package) in found.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for target in _targets(node, name, is_package, known):
                    if target != name:
                        graph[name].setdefault(target, node.lineno)
    return graph


def cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def layer(module: str) -> int | None:
    """The layer of ``module`` (longest prefix of :data:`LAYERS`), or None if it has none."""
    rel = module.removeprefix(PACKAGE).removeprefix(".")
    if rel == "":
        return LAYERS[""]
    matches = [p for p in LAYERS if p and (rel == p or rel.startswith(p + "."))]
    return LAYERS[max(matches, key=len)] if matches else None


GRAPH = import_graph()


def test_the_graph_is_read():
    """A few arrows known to exist, so that the checks below are not vacuous."""
    assert "torchmcmcpf.state" in GRAPH["torchmcmcpf.filters.base"]
    assert "torchmcmcpf.models.sensors.grid.whole" in GRAPH["torchmcmcpf.models.sensors.grid.delta"]  # from . import
    assert "torchmcmcpf.experiments.maroulas_hmc" in GRAPH  # a module with no package __init__ edge still listed


def test_cycles_are_found():
    assert cycles({"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}, "d": {"a": 1}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b": 1}, "b": {}}) == []


def test_no_import_cycle():
    found = cycles(GRAPH)
    detail = [f"{a} -> {b} (line {GRAPH[a][b]})" for c in found for a in c for b in GRAPH[a] if b in c]
    assert not found, f"import circles: {found}; arrows inside them: {detail}"


def test_every_module_has_a_layer():
    missing = [m for m in GRAPH if layer(m) is None]
    assert not missing, f"place these modules in tests/test_layers.py LAYERS: {missing}"


def test_no_back_arrows():
    back = [f"{a} (layer {layer(a)}) -> {b} (layer {layer(b)}), line {line}"
            for a, targets in GRAPH.items() for b, line in targets.items()
            if layer(a) is not None and layer(b) is not None and layer(b) > layer(a)]  # type: ignore[operator]
    assert not back, "imports up the layers (module docstring):\n" + "\n".join(back)


@pytest.mark.parametrize("lower, upper", [("scenarios", "filters"), ("scenarios", "experiments")])
def test_scenarios_do_not_import_filters(lower, upper):
    bad = [f"{a} -> {b}" for a, targets in GRAPH.items() if a.startswith(f"{PACKAGE}.{lower}")
           for b in targets if b.startswith(f"{PACKAGE}.{upper}")]
    assert not bad, f"{lower} must not import {upper}: {bad}"
