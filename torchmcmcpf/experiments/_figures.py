"""Figures of the studies: saving (marked in quick mode) and the legend label of a filter."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["save_figure", "np_label", "pyplot"]


def pyplot():  # noqa: ANN201 - matplotlib is imported lazily
    """``matplotlib.pyplot`` on the non-interactive Agg backend (studies write files only)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Figure, out: str | Path, filename: str, *, quick: bool = False) -> Path:
    """Save ``fig`` as ``out/filename`` (150 dpi) and close it; return the path. ``quick``
    stamps "quick mode" on the figure (small settings, not the paper's).
    """
    import matplotlib.pyplot as plt

    if quick:
        fig.text(0.99, 0.005, "quick mode: small settings", ha="right", va="bottom", fontsize="x-small",
                 color="C3")
    path = Path(out) / filename
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)
    return path


def np_label(name: str, num_particles: int) -> str:
    """Legend label of a filter: ``"<name>, Np = <N>"``."""
    return f"{name}, Np = {num_particles}"
