"""Figures: matplotlib on the Agg backend, and PNGs written atomically.

matplotlib is imported on first use: it is heavy, and most commands draw nothing.
"""

from __future__ import annotations

from pathlib import Path

from waveforest.atomic import atomic_path


def pyplot():
    """``matplotlib.pyplot`` on the non-interactive Agg backend (imported on first use: matplotlib is heavy)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(fig, path: str | Path, **savefig_kwargs) -> Path:
    """Write ``fig`` as PNG to ``path`` atomically (``fig.savefig(..., **savefig_kwargs)``), close it; return the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", **savefig_kwargs)
    pyplot().close(fig)
    return path
