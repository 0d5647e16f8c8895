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
    exec(compile("\n\n".join(blocks), str(page), "exec"), namespace)  # the guides assert their own checks


def test_readme_api_tour_runs(tmp_path, monkeypatch):
    """The README's API tour runs as written (it compiles one filter: ~10-20 s on 2 cores)."""
    readme = (GUIDES.parents[1] / "README.md").read_text()
    tour = readme.split("## API tour", 1)[1]
    blocks = BLOCK.findall(tour.split("\n## ", 1)[0])
    assert blocks, "the README's API tour has no python block"
    monkeypatch.chdir(tmp_path)
    exec(compile(blocks[0], "README.md#api-tour", "exec"), {"__name__": "readme_api_tour"})
