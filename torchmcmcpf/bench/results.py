"""``bench``'s result files and the guard against regressions: a run compared with a stored
one (``bench --compare``, ``--save``; issue 49 item 8).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

#: the layout of ``bench.json`` (its ``schema`` field); :func:`load_result` refuses another
SCHEMA = "torchmcmcpf.bench/1"
#: :func:`compare` flags a figure of ours whose time now / stored exceeds this (and below 1 / this as faster)
SLOWER = 1.10
#: the kinds of :class:`Figure`
KINDS = ("ours", "floor", "peer")


# -- the guard against regressions: a run compared with a stored one (issue 49) -------------------
def reference_path(device_type: str = "cpu") -> Path:
    """The stored reference run of ``bench --compare`` / ``bench --save`` without a FILE:
    ``benchmarks/reference-<device type>.json`` in the repository.
    """
    return Path(__file__).resolve().parents[2] / "benchmarks" / f"reference-{device_type}.json"


def figure_kind(fig: dict) -> str:
    """A figure's ``kind`` (:class:`Figure`); read from its name in files written before kinds were."""
    if fig.get("kind") in KINDS:
        return fig["kind"]
    name = fig["name"]
    if name.endswith("-floor") or name.startswith("point-floor-"):
        return "floor"
    if name.startswith("stonesoup-") or (name.startswith("particles-") and not name.startswith("particles-ours")):
        return "peer"
    return "ours"


def check_result(result: object, what: str = "the result") -> dict:
    """``result`` checked as a ``bench.json`` dictionary and returned with a ``machine`` record
    (built from the top-level ``device``, ``torch`` and ``threads`` of a file written before
    the record was); a ``ValueError`` that starts with ``what`` otherwise: not a JSON object,
    another ``schema``, no ``figures`` or none, a figure without a ``name`` or a positive,
    finite ``seconds``, two figures of one name.
    """
    if not isinstance(result, dict):
        raise ValueError(f"{what} is not a bench result: expected a JSON object with 'figures', got "
                         f"{type(result).__name__}")
    if "schema" in result and result["schema"] != SCHEMA:
        raise ValueError(f"{what} has schema {result['schema']!r}, expected {SCHEMA!r}")
    figures = result.get("figures")
    if not isinstance(figures, list):
        raise ValueError(f"{what} is not a bench result: expected a list 'figures', got "
                         f"{type(figures).__name__ if 'figures' in result else 'none'}")
    if not figures:
        raise ValueError(f"{what} holds no figures")
    seen = set()
    for i, fig in enumerate(figures):
        name = fig.get("name") if isinstance(fig, dict) else None
        if not isinstance(name, str) or not name:
            raise ValueError(f"{what}: figures[{i}] has no 'name'")
        secs = fig.get("seconds")
        if isinstance(secs, bool) or not isinstance(secs, (int, float)) or not 0 < secs < math.inf:
            raise ValueError(f"{what}: figure {name!r} has seconds {secs!r}, expected a positive number")
        if name in seen:
            raise ValueError(f"{what}: figure {name!r} appears twice")
        seen.add(name)
    record = result.get("machine")
    if record is not None and not isinstance(record, dict):
        raise ValueError(f"{what}: 'machine' is {type(record).__name__}, expected an object")
    if record is None:
        record = {key: result[key] for key in ("device_type", "torch", "threads") if key in result}
        if "device" in result:
            record["name"] = result["device"]
    return {**result, "machine": record}


def load_result(path: str | Path) -> dict:
    """Read a stored run (``bench.json``, or ``benchmarks/reference-cpu.json``), checked by
    :func:`check_result`. Raises a ``ValueError`` that names ``path``: missing, unreadable,
    not JSON, or not a bench result.
    """
    what = repr(str(path))
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValueError(f"{what} does not exist (write a stored run with: python -m torchmcmcpf bench "
                         f"--save {path})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{what} is not JSON (not UTF-8 text)") from None
    except OSError as err:
        raise ValueError(f"{what} cannot be read ({err.strerror})") from None
    try:
        result = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{what} is not JSON ({err.msg} at line {err.lineno})") from None
    return check_result(result, what)


def _machine_text(record: dict) -> str:
    """``name`` (torch, threads), with the host CPU for a GPU."""
    host = f", host {record['cpu']}" if record.get("device_type") == "cuda" and record.get("cpu") else ""
    return (f"{record.get('name', 'an unnamed machine')}{host} (torch {record.get('torch', '?')}, "
            f"{record.get('threads', '?')} threads)")


def _machine_warnings(now: dict, stored: dict) -> list[str]:
    """What differs between the two runs' conditions, besides the code: the machine, torch,
    threads, sizes (``--quick``), the CPU allocator's tuning.
    """
    a, b = stored["machine"], now["machine"]
    warnings = []
    if "name" not in a:
        warnings.append("the stored run names no machine: its ratios may mix the code's change with the machines'")
    elif (a.get("name"), a.get("cpu", b.get("cpu"))) != (b.get("name"), b.get("cpu", a.get("cpu"))):
        warnings.append(f"the machines differ: stored on {_machine_text(a)}, now on {_machine_text(b)}; the ratios "
                        "mix the code's change with the machines' difference (the x-floor column divides the "
                        "machine's arithmetic speed out)")
    for key, label in (("torch", "torch versions"), ("threads", "thread counts")):
        if key in a and a.get(key) != b.get(key):
            warnings.append(f"{label} differ: stored {a[key]}, now {b.get(key)}")
    if "quick" in stored and bool(stored["quick"]) != bool(now.get("quick")):
        size = {True: "--quick sizes", False: "full sizes"}
        warnings.append(f"sizes differ: stored at {size[bool(stored['quick'])]}, now at {size[bool(now.get('quick'))]}")
    if "cpu_allocator_tuned" in stored and stored["cpu_allocator_tuned"] != now.get("cpu_allocator_tuned"):
        warnings.append(f"the CPU allocator's tuning differs: stored {stored['cpu_allocator_tuned']}, "
                        f"now {now.get('cpu_allocator_tuned')}")
    return warnings


def compare(now: dict, stored: dict, *, threshold: float = SLOWER, source: str = "the stored run") -> dict:
    """A run (``now``) against a stored one, figure by figure: the guard against regressions.

    For every figure in both (by name), ``ratio = now / stored`` of its ``seconds`` per step;
    where both have a floor, ``floor_multiple_ratio``, the ratio of the figure's multiples of
    its floor (its ratio divided by the floor's: what is left once the machine's arithmetic
    speed is divided out). A figure of ours whose ratio exceeds ``threshold`` is flagged
    ``"slower"``, below ``1 / threshold`` ``"faster"``; floors and peers are shown but never
    flagged (they measure the machine); a figure whose settings (``params``) changed is marked
    ``"settings differ"`` instead (its ratio is no regression). Warns when the machines,
    torch, the thread counts or the sizes differ, and when the floors themselves moved by
    more than ``threshold`` (the machine is busier or faster than when stored).

    Returns a JSON-able dictionary: ``source``, ``threshold``, ``stored_machine``,
    ``now_machine``, ``warnings``, ``rows`` (``name``, ``kind``, ``stored_s``, ``now_s``,
    ``ratio``, ``floor_multiple_ratio``, ``settings`` ``{param: [stored, now]}``, ``flag``),
    ``only_stored`` and ``only_now`` (figure names), ``slower`` and ``faster`` (names).
    Raises ``ValueError`` when either is not a bench result (:func:`check_result`) or
    ``threshold <= 1``.
    """
    if not threshold > 1:
        raise ValueError(f"threshold must be a ratio above 1, got {threshold!r}")
    now, stored = check_result(now, "this run"), check_result(stored, source)
    before = {f["name"]: f for f in stored["figures"]}
    after = {f["name"]: f for f in now["figures"]}
    rows = []
    for name, fig in after.items():
        if name not in before:
            continue
        old = before[name]
        ratio = fig["seconds"] / old["seconds"]
        kind = figure_kind(fig)
        # params as JSON has them (a tuple of this run is the stored run's list)
        p, q = (json.loads(json.dumps(f.get("params") or {})) for f in (old, fig))
        settings = {k: [p.get(k), q.get(k)] for k in sorted({*p, *q}) if p.get(k) != q.get(k)}
        floors = (old.get("floor_s"), fig.get("floor_s"))
        floor_multiple = ratio * floors[0] / floors[1] if all(isinstance(f, (int, float)) and f > 0
                                                              for f in floors) else None
        flag = ""
        if settings:
            flag = "settings differ"
        elif kind == "ours" and ratio > threshold:
            flag = "slower"
        elif kind == "ours" and ratio < 1 / threshold:
            flag = "faster"
        rows.append(dict(name=name, kind=kind, stored_s=old["seconds"], now_s=fig["seconds"], ratio=ratio,
                         floor_multiple_ratio=floor_multiple, settings=settings, flag=flag))
    warnings = _machine_warnings(now, stored)
    floor_ratios = sorted(r["ratio"] for r in rows if r["kind"] == "floor" and not r["settings"])
    if floor_ratios:
        mid = floor_ratios[len(floor_ratios) // 2]
        if not 1 / threshold <= mid <= threshold:
            state = "busier or slower" if mid > 1 else "faster or quieter"
            warnings.append(f"the floors themselves take {mid:.2f}x their stored times (median of "
                            f"{len(floor_ratios)}): this machine is {state} than when stored; read the x-floor column")
    return dict(source=source, threshold=threshold, stored_machine=stored["machine"], now_machine=now["machine"],
                warnings=warnings, rows=rows, only_stored=[n for n in before if n not in after],
                only_now=[n for n in after if n not in before],
                slower=[r["name"] for r in rows if r["flag"] == "slower"],
                faster=[r["name"] for r in rows if r["flag"] == "faster"])


def comparison_summary(comparison: dict) -> str:
    """The closing line of a comparison: which figures of ours got slower, or that none did."""
    rows = {r["name"]: r for r in comparison["rows"]}
    ours = [r for r in rows.values() if r["kind"] == "ours" and not r["settings"]]
    thr = comparison["threshold"]
    head = f"vs {comparison['source']}"
    if not ours:
        text = f"{head}: no figure of ours to compare (none in both runs with the same settings)"
    elif comparison["slower"]:
        text = (f"{head}: SLOWER: {len(comparison['slower'])} of {len(ours)} figures of ours above {thr:.2f}x the "
                "stored run: " + ", ".join(f"{n} {rows[n]['ratio']:.2f}x" for n in comparison["slower"]))
    else:
        ratios = sorted(r["ratio"] for r in ours)
        text = (f"{head}: no figure of ours above {thr:.2f}x the stored run ({len(ours)} compared, median ratio "
                f"{ratios[len(ratios) // 2]:.2f})")
    if comparison["faster"]:
        text += f"; {len(comparison['faster'])} faster below {1 / thr:.2f}x"
    if comparison["warnings"]:
        text += f" ({len(comparison['warnings'])} warning{'s' if len(comparison['warnings']) > 1 else ''} above)"
    return text


def comparison_markdown(comparison: dict) -> str:
    """The comparison as text (``bench_compare.md``): both machines, the warnings, one row per
    figure in both runs (times in ms per step, the ratio now / stored, the ratio of multiples
    of the floor, the flag), the figures in one run only, and the closing line.
    """
    a, b = comparison["stored_machine"], comparison["now_machine"]
    lines = [f"Compared with {comparison['source']}: stored {a.get('date', '(undated)')} on {_machine_text(a)}; "
             f"now {b.get('date', '(undated)')} on {_machine_text(b)}. Ratio = now / stored, ms per step; a figure "
             f"of ours above {comparison['threshold']:.2f}x is SLOWER. Floors and peers measure the machine.", ""]
    lines += [f"warning: {w}" for w in comparison["warnings"]]
    if comparison["warnings"]:
        lines.append("")
    lines += ["| figure | kind | stored ms | now ms | now / stored | x floor now / stored | |",
              "|---|---|---:|---:|---:|---:|---|"]
    for r in comparison["rows"]:
        multiple = "" if r["floor_multiple_ratio"] is None else f"{r['floor_multiple_ratio']:.3f}"
        flag = {"slower": "**SLOWER**", "faster": "faster"}.get(r["flag"], r["flag"])
        if r["settings"]:
            flag += ": " + ", ".join(f"{k} {x} -> {y}" for k, (x, y) in r["settings"].items())
        lines.append(f"| {r['name']} | {r['kind']} | {r['stored_s'] * 1e3:.4g} | {r['now_s'] * 1e3:.4g} | "
                     f"{r['ratio']:.3f} | {multiple} | {flag} |")
    lines.append("")
    if comparison["only_stored"]:
        lines.append(f"Only in the stored run: {', '.join(comparison['only_stored'])}")
    if comparison["only_now"]:
        lines.append(f"Only in this run: {', '.join(comparison['only_now'])}")
    if comparison["only_stored"] or comparison["only_now"]:
        lines.append("")
    lines.append(comparison_summary(comparison))
    return "\n".join(lines) + "\n"
