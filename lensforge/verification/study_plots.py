"""Plots of an as-built study: error histograms, sensitivity bars, budget chart.

Matplotlib with the Agg backend (no display); every figure is written atomically
as PNG. Axis labels carry units (mm, deg).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ..fileio import write_atomic
from .statistics import percentile

__all__ = ["plot_error_histograms", "plot_sensitivity", "plot_budget"]


def _fig(*args, **kw):
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt.subplots(*args, **kw)


def _save(fig, path) -> Path:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120, bbox_inches="tight")
    plt.close(fig)
    return write_atomic(path, buf.getvalue())


def _hist(ax, values, target, label, unit):
    all_v = np.asarray(values, dtype=float)  # nan = failed trial: counts in the percentiles as +inf
    v = all_v[np.isfinite(all_v)]
    if v.size == 0:
        ax.text(0.5, 0.5, "no successful trial", ha="center", transform=ax.transAxes)
        return
    pos = v[v > 0]
    if pos.size and pos.max() / max(pos.min(), 1e-300) > 100:
        bins = np.geomspace(pos.min(), pos.max(), 40)
        ax.set_xscale("log")
    else:
        bins = 40
    ax.hist(v, bins=bins, color="tab:blue", alpha=0.8)
    for q, ls in ((50, "-"), (95, "--")):
        pq = percentile(all_v, q)  # the same statistic as the console and the JSON summary
        if pq is None:
            ax.plot([], [], color="k", ls=ls, lw=1, label=f"{q}th pct: a failed trial")
        else:
            ax.axvline(pq, color="k", ls=ls, lw=1, label=f"{q}th pct {pq:.3g} {unit}")
    if target is not None:
        ax.axvline(target, color="tab:red", lw=1.5, label=f"target {target:g} {unit}")
    ax.set_xlabel(f"{label} ({unit})")
    ax.set_ylabel("as-built lenses")
    ax.legend(fontsize=8)


def plot_error_histograms(rot_err_deg, trans_err_mm, path, target_deg=None, target_mm=None, title="") -> Path:
    """Histograms of the hand-eye Z error: rotation (deg) and translation (mm)."""
    fig, (a1, a2) = _fig(1, 2, figsize=(10, 3.8))
    _hist(a1, rot_err_deg, target_deg, "Z rotation error", "deg")
    _hist(a2, trans_err_mm, target_mm, "Z translation error", "mm")
    fig.suptitle(title or "Calibration error over as-built lenses")
    return _save(fig, path)


def plot_sensitivity(rows: list[dict], path, title="") -> Path:
    """Bars of the 95th-percentile Z error per tolerance component (one at a time, and all).

    rows: dicts with "component", "p95_rot_deg", "p95_trans_mm".
    """
    names = [r["component"] for r in rows]
    y = np.arange(len(rows))
    fig, (a1, a2) = _fig(1, 2, figsize=(10, 0.45 * len(rows) + 1.6), sharey=True)
    for ax, key, unit, col in ((a1, "p95_rot_deg", "deg", "tab:orange"), (a2, "p95_trans_mm", "mm", "tab:blue")):
        vals = np.array([r[key] if r[key] is not None else np.nan for r in rows], dtype=float)
        ax.barh(y, np.where(np.isfinite(vals), vals, 0.0), color=col)
        ax.set_xscale("log") if np.nanmax(np.abs(vals), initial=0) > 0 and np.nanmin(vals[vals > 0], initial=1) > 0 else None
        ax.set_xlabel(f"95th pct Z {'rotation' if unit == 'deg' else 'translation'} error ({unit})")
    a1.set_yticks(y, names)
    a1.invert_yaxis()
    fig.suptitle(title or "Sensitivity: one tolerance at a time (nominal size) and all together")
    return _save(fig, path)


def plot_budget(rows: list[dict], path, title="") -> Path:
    """Bars of the budget scale per component: the largest multiple of the given tolerance
    that meets the target at the 95th percentile (1 = the given tolerance just fits)."""
    names = [r["component"] for r in rows]
    s = np.array([r["max_scale"] if r["max_scale"] is not None else np.nan for r in rows], dtype=float)
    y = np.arange(len(rows))
    fig, ax = _fig(figsize=(7, 0.45 * len(rows) + 1.6))
    colors = ["tab:green" if v >= 1 else "tab:red" for v in np.nan_to_num(s, nan=1e9)]
    ax.barh(y, np.where(np.isfinite(s), np.maximum(s, 1e-4), 1e4), color=colors)
    ax.axvline(1.0, color="k", lw=1, ls="--", label="given tolerance")
    ax.set_xscale("log")
    ax.set_yticks(y, [f"{n} ({r.get('max_value_label', '')})" for n, r in zip(names, rows)])
    ax.invert_yaxis()
    ax.set_xlabel("largest tolerance scale meeting the target at the 95th pct (x given value)")
    ax.legend(fontsize=8)
    fig.suptitle(title or "Tolerance budget")
    return _save(fig, path)
