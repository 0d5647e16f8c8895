"""The guides in docs/guides/ are tested pages: their Python code blocks run, in order, as
one script per page (a later block sees the names of an earlier one)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

GUIDES = Path(__file__).resolve().parents[1] / "docs" / "guides"
PAGES = sorted(p for p in GUIDES.glob("*.md") if p.name != "index.md")
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def test_every_guide_has_code():
    assert PAGES, f"no guides found in {GUIDES}"
    for page in PAGES:
        assert BLOCK.findall(page.read_text()), f"{page.name} has no python block"


@pytest.mark.parametrize("page", PAGES, ids=[p.stem for p in PAGES])
def test_guide_runs(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    blocks = BLOCK.findall(page.read_text())
    assert blocks, f"{page.name} has no python block"
    namespace: dict = {"__name__": f"guide_{page.stem}"}
    # dont_inherit: the page runs as written, not under this file's ``from __future__ import
    # annotations`` (a dataclass of a page would then look its module up in sys.modules)
    code = compile("\n\n".join(blocks), str(page), "exec", dont_inherit=True)
    exec(code, namespace)  # the guides assert their own checks


def test_readme_api_tour_runs(tmp_path, monkeypatch):
    """The README's API tour runs as written (it compiles one filter: ~10-20 s on 2 cores)."""
    readme = (GUIDES.parents[1] / "README.md").read_text()
    tour = readme.split("## API tour", 1)[1]
    blocks = BLOCK.findall(tour.split("\n## ", 1)[0])
    assert blocks, "the README's API tour has no python block"
    monkeypatch.chdir(tmp_path)
    exec(compile(blocks[0], "README.md#api-tour", "exec"), {"__name__": "readme_api_tour"})


def test_names_the_readme_and_docs_use_exist():
    """Every ``tp.name`` in the README and the docs, and every filter and step function of the
    README's algorithm table, is an attribute of the top-level package."""
    import torchmcmcpf as tp

    root = GUIDES.parents[1]
    texts = [(root / "README.md").read_text(), *(p.read_text() for p in (root / "docs").rglob("*.md"))]
    dotted = {m for text in texts for m in re.findall(r"\btp\.([A-Za-z_]\w*)", text)}
    table = (root / "README.md").read_text().split("| filter | step function |", 1)[1].split("\n\n", 1)[0]
    named = {m for m in re.findall(r"^\| `(\w+)` \| `?(\w*)`?", table, re.M) for m in m if m}
    assert {"pmmh_step", "partitioned_sir_step", "SIRFilter"} <= named
    missing = sorted(n for n in dotted | named if not hasattr(tp, n))
    assert not missing, missing


def test_what_the_commands_write_is_ignored_by_git():
    import shutil
    import subprocess

    root = GUIDES.parents[1]
    if shutil.which("git") is None or not (root / ".git").exists():
        pytest.skip("not a git checkout")
    paths = ["bench-out/bench.json", "results/demo/metrics.json", "ckpt.pt", "result.pt", "docs/_build/html/x",
             "docs/examples/demo.ipynb", ".venv/bin/python"]
    done = subprocess.run(["git", "-C", str(root), "check-ignore", *paths], capture_output=True, text=True)
    assert sorted(done.stdout.split()) == sorted(paths), done.stdout


def test_readme_stays_a_five_minute_read():
    """Issue 25: the README is the quick start, the API tour, the tables and links; long
    text (results, design notes, performance tables) belongs on the documentation site."""
    readme = (GUIDES.parents[1] / "README.md").read_bytes()
    assert len(readme) < 15_000, (f"README.md is {len(readme)} bytes; move long sections to docs/ "
                                  "(reproduction.md, performance.md, design.md) and link them")
    text = readme.decode()
    for marker in ("<!-- demo-command -->", "<!-- test-command -->", "## Quick start", "## API tour",
                   "## Algorithms", "## Studies"):
        assert marker in text, marker
    from torchmcmcpf import experiments

    for name in experiments.discover():  # every study in the study table
        assert f"| `{name}` |" in text, name
