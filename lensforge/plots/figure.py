"""The figure and the file: a matplotlib Figure on the Agg canvas (no pyplot state) and
its atomic PNG. Every plot of lensforge is made and saved through these two."""

from __future__ import annotations

import io
from pathlib import Path

from ..fileio import write_atomic

__all__ = ["new_figure", "png_bytes", "save_figure"]


def new_figure(*args, **kwargs):
    """A matplotlib Figure (no pyplot state; Agg canvas)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(*args, **kwargs)
    FigureCanvasAgg(fig)
    return fig


def png_bytes(fig, dpi: int = 120) -> bytes:
    """The figure as PNG bytes (tight bounding box)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    return buf.getvalue()


def save_figure(fig, path, dpi: int = 120) -> Path:
    """Write a figure as PNG atomically; returns the path."""
    return write_atomic(path, png_bytes(fig, dpi))
