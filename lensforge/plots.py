"""Plots (matplotlib, Agg backend, PNG). Generic building blocks that draw on an Axes
or return a Figure, plus ``save_figure`` (atomic) and ``design_plots`` (the set for a
design file). Other modules add their plots here the same way.

Units are in every label: sag in mm, Zernike response in um of wavefront per 1 mm
(translations) or per 1 deg (rotations).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

__all__ = ["new_figure", "save_figure", "plot_singular_values", "sag_departure", "plot_sag_maps",
           "plot_zernike_response", "design_plots"]


def new_figure(*args, **kwargs):
    """A matplotlib Figure (no pyplot state; Agg canvas)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(*args, **kwargs)
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig, path, dpi: int = 120) -> Path:
    """Write a figure as PNG atomically; returns the path."""
    from .fileio import write_atomic

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    return write_atomic(path, buf.getvalue())


def plot_singular_values(ax, spectra: dict, title: str = "Singular values of the scaled, whitened S"):
    """Bar/line plot of singular-value spectra {label: sv (descending)} on a log axis."""
    for label, sv in spectra.items():
        sv = np.asarray(sv, dtype=float)
        sv = np.where(sv > 0, sv, np.nan)
        ax.semilogy(np.arange(1, sv.size + 1), sv, "o-", label=label)
    ax.set_xlabel("index i")
    ax.set_ylabel("sigma_i of S~ (dimensionless)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return ax


def sag_departure(surface, x, y, n_phi: int = 64):
    """(sag, departure from rotational symmetry) at (x, y) in mm: the departure is the
    sag minus its azimuthal mean on the circle of the same radius."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    z = surface.sag(x, y)
    r = np.hypot(x, y)
    phi = np.linspace(0.0, 2 * np.pi, n_phi, endpoint=False)
    ring = surface.sag(r[..., None] * np.cos(phi), r[..., None] * np.sin(phi))
    return z, z - ring.mean(axis=-1)


def plot_sag_maps(lens, n: int = 121):
    """Figure: sag of front and back surface and their departure from rotational symmetry (mm)."""
    fig = new_figure(figsize=(10, 8.5), layout="constrained")
    a = 0.5 * lens.aperture
    g = np.linspace(-a, a, n)
    X, Y = np.meshgrid(g, g)
    outside = X**2 + Y**2 > a * a
    for row, side in enumerate(("front", "back")):
        z, dep = sag_departure(getattr(lens, side), X, Y)
        for col, (data, what) in enumerate(((z, "sag"), (dep, "departure from rotational symmetry"))):
            ax = fig.add_subplot(2, 2, 2 * row + col + 1)
            data = np.where(outside, np.nan, data)
            im = ax.imshow(data, extent=(-a, a, -a, a), origin="lower", cmap="viridis" if col == 0 else "RdBu_r")
            ax.set_title(f"{side} {what} (mm)", fontsize=9)
            ax.set_xlabel("x (mm)")
            ax.set_ylabel("y (mm)")
            fig.colorbar(im, ax=ax, shrink=0.8, label="mm")
    fig.suptitle(lens.name or "lens")
    return fig


def plot_zernike_response(S, modes, pose_scales, title: str = "Zernike response per pose DOF"):
    """Figure: column j of S times the pose scale (um of wavefront per 1 mm / per 1 deg)."""
    from .optics.pose import DOF_NAMES

    S = np.asarray(S, dtype=float)
    fig = new_figure(figsize=(12, 6.5), layout="constrained")
    scales = np.asarray(pose_scales, dtype=float)
    for j in range(6):
        ax = fig.add_subplot(2, 3, j + 1)
        ax.bar(np.arange(S.shape[0]), S[:, j] * scales[j], color="tab:blue")
        unit = f"{scales[j]:g} mm" if j < 3 else f"{np.degrees(scales[j]):g} deg"
        ax.set_title(f"{DOF_NAMES[j]}: um per {unit}", fontsize=9)
        ax.set_xticks(np.arange(S.shape[0]))
        ax.set_xticklabels([str(m) for m in modes], fontsize=6)
        ax.set_xlabel("Noll j")
        ax.grid(True, axis="y", alpha=0.3)
    fig.suptitle(title)
    return fig


def design_plots(design, out_dir, stem: str | None = None) -> list[Path]:
    """Write the PNGs of a design (or lens) into out_dir: singular values, sag maps,
    Zernike response. Returns the paths."""
    from .optics.bench import Bench
    from .optics.lens import Lens
    from .optics.shack_hartmann import lenslet_pupil

    out = Path(out_dir)
    if isinstance(design, Lens):
        lens, bench, m = design, Bench.default(), None
    else:
        lens, bench = design.lens, design.bench
    from .optics.sensitivity import metrics

    m = metrics(bench, lens)
    stem = stem or (getattr(design, "model", None) or "lens")
    paths = []
    fig = new_figure(figsize=(6, 4))
    plot_singular_values(fig.add_subplot(1, 1, 1), {f"{stem} (rank {m.rank}, kappa {m.kappa:.3g})": m.singular_values})
    paths.append(save_figure(fig, out / f"{stem}_singular_values.png"))
    paths.append(save_figure(plot_sag_maps(lens), out / f"{stem}_sag.png"))
    modes = lenslet_pupil(bench.sensor).modes
    paths.append(save_figure(plot_zernike_response(m.S, modes, bench.pose_scales), out / f"{stem}_zernike_response.png"))
    return paths
