"""Sphinx configuration of the torchmcmcpf documentation.

Build: ``python -m sphinx -W -b html docs docs/_build/html`` (warnings are errors, as in CI).
The notebooks of ``notebooks/`` are rendered as the examples gallery without being executed
(``pytest --nbmake`` already executes them in CI); they are copied here at build time.
"""

from __future__ import annotations

import re
import shutil
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

import torchmcmcpf  # noqa: E402

project = "torchmcmcpf"
author = "the torchmcmcpf developers"
copyright = "2026, the torchmcmcpf developers"
release = torchmcmcpf.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "myst_nb",
]

source_suffix = {".rst": "restructuredtext", ".md": "myst-nb", ".ipynb": "myst-nb"}
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store", "**.ipynb_checkpoints"]
myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3
nb_execution_mode = "off"  # nbmake runs the notebooks in the test command

autosummary_generate = True
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_mock_imports: list[str] = []
napoleon_numpy_docstring = True
napoleon_google_docstring = False
napoleon_use_rtype = False
napoleon_use_ivar = False
napoleon_custom_sections = [("Usage", "example"), ("Attributes", "params_style")]
nitpicky = False
# Type fields hold shapes such as "(B, N, K, D)"; their words are not objects to link, and
# an ambiguous one (a field named "x" on several containers) is not an error.
suppress_warnings = ["myst.header", "ref.python"]

html_theme = "alabaster"
html_static_path = ["_static"]
html_theme_options = {"description": "MCMC-based particle filters for multi-target tracking in batched PyTorch"}


def _copy_notebooks(app) -> None:
    """Copy ``notebooks/*.ipynb`` into ``docs/examples/`` (ignored by git) for the gallery."""
    target = HERE / "examples"
    target.mkdir(exist_ok=True)
    for nb in sorted((ROOT / "notebooks").glob("*.ipynb")):
        shutil.copy2(nb, target / nb.name)


_STAR = re.compile(r"(?<![\\*\w])\*(?=[A-Za-z_]\w*)")


def _escape_shape_stars(app, what, name, obj, options, lines) -> None:
    """Shapes such as ``(B, *S, K, D)`` are the library's vocabulary (``torchmcmcpf.typing``);
    outside inline literals their ``*`` would open reST emphasis, so escape it.
    """
    for i, line in enumerate(lines):
        parts = re.split(r"(``.*?``|`[^`]*`)", line)
        lines[i] = "".join(p if p.startswith("`") else _STAR.sub(r"\\*", p) for p in parts)


def setup(app):
    """Sphinx extension hook: copy the notebooks, escape ``*`` in shapes."""
    app.connect("builder-inited", _copy_notebooks)
    app.connect("autodoc-process-docstring", _escape_shape_stars)
