"""Plots of the studies: as-built error histograms, sensitivity bars, budget chart, and the
pose-estimation study (Fig. 5 analogue).

Matplotlib with the Agg backend (no display); every figure is written atomically
as PNG. Axis labels carry units (mm, deg).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..verification.statistics import percentile
from .figure import new_figure, save_figure

__all__ = ["plot_error_histograms", "plot_sensitivity", "plot_budget", "plot_estimation_study"]


def _hist(ax, values, target, label, unit, stats: dict | None = None, percent: float = 95.0):
    """Histogram of the finite values; the median and percentile lines come from ``stats``
    ({"median": .., "pNN": ..}, the study summary) or else :func:`percentile` over all
    values (non-finite = failed, counted as worst)."""
    allv = np.asarray(values, dtype=float)
    v = allv[np.isfinite(allv)]
    n_bad = int(allv.size - v.size)
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
    key = f"p{percent:g}"
    for q, name, ls in ((50.0, "median", "-"), (percent, key, "--")):
        val = (stats or {}).get("median" if q == 50.0 else key) if stats is not None else percentile(allv, q)
        text = "median" if q == 50.0 else f"{q:g}th pct"
        if val is None:
            ax.plot([], [], color="k", ls=ls, label=f"{text}: undefined (failures)")
            continue
        ax.axvline(val, color="k", ls=ls, lw=1, label=f"{text} {val:.3g} {unit}")
    if target is not None:
        ax.axvline(target, color="tab:red", lw=1.5, label=f"target {target:g} {unit}")
    ax.set_xlabel(f"{label} ({unit})")
    ax.set_ylabel("as-built lenses")
    if n_bad:
        ax.plot([], [], " ", label=f"{n_bad} failed (not drawn; counted as worst)")
    ax.legend(fontsize=8)


def plot_error_histograms(rot_err_deg, trans_err_mm, path, target_deg=None, target_mm=None, title="",
                          summary: dict | None = None) -> Path:
    """Histograms of the hand-eye Z error: rotation (deg) and translation (mm).

    summary: the study summary (``summarize_errors``): its median and percentile are drawn,
    so the plot shows the console's numbers, and its counts of failed lenses and of poses
    that did not converge or fell out of range are written under the plot.
    """
    fig = new_figure(figsize=(10, 4.2), layout="constrained")
    a1, a2 = fig.subplots(1, 2)
    q = float((summary or {}).get("percentile", 95.0))
    _hist(a1, rot_err_deg, target_deg, "Z rotation error", "deg",
          None if summary is None else summary.get("rotation_deg"), q)
    _hist(a2, trans_err_mm, target_mm, "Z translation error", "mm",
          None if summary is None else summary.get("translation_mm"), q)
    if summary is not None:
        counts = (f"{summary.get('n_ok', '?')} of {summary.get('n_lenses', '?')} calibrations succeeded; poses: "
                  f"{summary.get('not_converged_poses', 0)} not converged, {summary.get('out_of_range_poses', 0)} "
                  f"out of range, {summary.get('pupil_lost_poses', 0)} pupil lost")
        fig.text(0.5, -0.02, counts, ha="center", va="top", fontsize=9)
    fig.suptitle(title or "Calibration error over as-built lenses")
    return save_figure(fig, path)


def plot_sensitivity(rows: list[dict], path, title="") -> Path:
    """Bars of the 95th-percentile Z error per tolerance component (one at a time, and all).

    rows: dicts with "component", "p95_rot_deg", "p95_trans_mm".
    """
    names = [r["component"] for r in rows]
    y = np.arange(len(rows))
    fig = new_figure(figsize=(10, 0.45 * len(rows) + 1.6), layout="constrained")
    a1, a2 = fig.subplots(1, 2, sharey=True)
    for ax, key, unit, col in ((a1, "p95_rot_deg", "deg", "tab:orange"), (a2, "p95_trans_mm", "mm", "tab:blue")):
        vals = np.array([r[key] if r[key] is not None else np.nan for r in rows], dtype=float)
        ax.barh(y, np.where(np.isfinite(vals), vals, 0.0), color=col)
        top = float(np.nanmax(vals, initial=0.0)) if np.isfinite(vals).any() else 1.0
        ax.set_xlim(0.0, 1.25 * top if top > 0 else 1.0)  # bars start at zero: lengths compare
        for yi, v in zip(y, vals):
            ax.text(v if np.isfinite(v) else 0.0, yi, f" {v:.3g}" if np.isfinite(v) else " failed", va="center",
                    fontsize=7)
        ax.set_xlabel(f"95th pct Z {'rotation' if unit == 'deg' else 'translation'} error ({unit})")
        ax.grid(True, axis="x", alpha=0.3)
    a1.set_yticks(y, names)
    a1.invert_yaxis()
    fig.suptitle(title or "Sensitivity: one tolerance at a time (nominal size) and all together")
    return save_figure(fig, path)


def plot_budget(rows: list[dict], path, title="") -> Path:
    """Bars of the budget scale per component: the largest multiple of the given tolerance
    that meets the target at the 95th percentile (1 = the given tolerance just fits)."""
    names = [r["component"] for r in rows]
    s = np.array([r["max_scale"] if r["max_scale"] is not None else np.nan for r in rows], dtype=float)
    y = np.arange(len(rows))
    fig = new_figure(figsize=(7, 0.45 * len(rows) + 1.6), layout="constrained")
    ax = fig.subplots()
    colors = ["tab:green" if v >= 1 else "tab:red" for v in np.nan_to_num(s, nan=1e9)]
    ax.barh(y, np.where(np.isfinite(s), np.maximum(s, 1e-4), 1e4), color=colors)
    ax.axvline(1.0, color="k", lw=1, ls="--", label="given tolerance (scale 1)")
    from matplotlib.patches import Patch

    handles = [Patch(color="tab:green", label="given tolerance meets the target (scale >= 1)"),
               Patch(color="tab:red", label="must be tightened (scale < 1)")]
    ax.set_xscale("log")
    ax.set_yticks(y, [f"{n} ({r.get('max_value_label', '')})" for n, r in zip(names, rows)])
    ax.invert_yaxis()
    ax.set_xlabel("largest tolerance scale meeting the target at the 95th pct (x given value)")
    ax.legend(handles=handles + ax.get_legend_handles_labels()[0], fontsize=8, loc="upper center",
              bbox_to_anchor=(0.5, -0.28), ncol=2, frameon=False)
    fig.suptitle(title or "Tolerance budget")
    return save_figure(fig, path)


def plot_estimation_study(results, path) -> Path:
    """Fig. 5-style box plot: per DOF, the error of every lens (um / urad). Written atomically."""
    from ..optics.pose import DOF_NAMES
    from ..verification.statistics import box_stats

    fig = new_figure(figsize=(12, 6.5), layout="constrained")
    axes = fig.subplots(2, 3)
    labels = [f"{r.name}\n({r.method})" for r in results]
    for j, ax in enumerate(axes.flat):
        unit, sc = ("um", 1e3) if j < 3 else ("urad", 1e6)
        boxes = []
        for r in results:
            e = r.errors[r.ok, j] * sc if DOF_NAMES[j] not in r.unobservable else np.array([])
            boxes.append(box_stats(e))
        ax.bxp(boxes, showfliers=True, flierprops={"markersize": 2})
        ax.set_xticks(range(1, len(labels) + 1), labels, fontsize=7, rotation=20)
        ax.axhline(0.0, color="0.6", lw=0.6)
        ax.set_title(f"{DOF_NAMES[j]} error ({unit})", fontsize=9)
        for k, r in enumerate(results):
            cv = r.crlb_var[r.ok, j]
            if DOF_NAMES[j] not in r.unobservable and np.isfinite(cv).any():
                b = np.sqrt(np.nanmean(cv[np.isfinite(cv)])) * sc
                ax.hlines([-b, b], k + 0.7, k + 1.3, colors="C3", linestyles="--", lw=0.8,
                          label="+-1 CRLB std" if k == 0 or not ax.get_legend_handles_labels()[0] else None)
            if DOF_NAMES[j] in r.unobservable:
                ax.text(k + 1, 0, "unobservable", ha="center", va="center", fontsize=6, rotation=90, color="C3")
    axes.flat[0].legend(fontsize=7, loc="upper right")
    n = len(results[0].status) if results else 0
    fig.suptitle(f"Pose-estimation error over {n} trials per lens (estimate - truth)", fontsize=10)
    return save_figure(fig, path)
