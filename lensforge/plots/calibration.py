"""Plots of a calibration: the hand-eye residuals per pose, and the calibration's
residual chart (``residuals.png`` of ``lensforge calibrate``)."""

from __future__ import annotations

import numpy as np

from .figure import new_figure

__all__ = ["plot_handeye_residuals", "plot_calibration_residuals"]


def plot_handeye_residuals(residuals, residual_chi2=None, title: str = "Hand-eye residuals per pose"):
    """Figure: per-pose residual e_i = log((Z B_i)^-1 A_i X) of a hand-eye solve:
    translation (um) and rotation (mrad) components, and the whitened chi^2 per pose
    against the chi^2(6) 95 % level. residuals: (n, 6) in mm and rad."""
    from scipy.stats import chi2

    e = np.asarray(residuals, dtype=float)
    n = e.shape[0]
    i = np.arange(1, n + 1)
    rows = 3 if residual_chi2 is not None else 2
    fig = new_figure(figsize=(max(7, 0.28 * n + 3), 2.6 * rows), layout="constrained")
    width = 0.27
    for k, (sl, scale, unit, what) in enumerate(((slice(0, 3), 1e3, "um", "translation"),
                                                 (slice(3, 6), 1e3, "mrad", "rotation"))):
        ax = fig.add_subplot(rows, 1, k + 1)
        for c, comp in enumerate("xyz"):
            ax.bar(i + (c - 1) * width, e[:, sl][:, c] * scale, width, label=f"{what} {comp}")
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_ylabel(f"{what} residual ({unit})")
        ax.legend(fontsize=7, ncol=3)
        ax.grid(True, axis="y", alpha=0.3)
        ax.set_xticks(i)
        ax.tick_params(axis="x", labelsize=7)
    if residual_chi2 is not None:
        ax = fig.add_subplot(rows, 1, 3)
        c2 = np.asarray(residual_chi2, dtype=float)
        lim = float(chi2.ppf(0.95, 6))
        ax.bar(i, c2, color=np.where(c2 > lim, "tab:red", "tab:gray"))
        ax.axhline(lim, color="tab:red", ls="--", lw=1, label=f"chi^2(6) 95 % = {lim:.1f}")
        ax.set_ylabel("whitened chi^2 per pose")
        ax.legend(fontsize=7)
        ax.set_xticks(i)
        ax.tick_params(axis="x", labelsize=7)
    fig.axes[-1].set_xlabel("pose index")
    fig.suptitle(title)
    return fig


def plot_calibration_residuals(result):
    """Figure, per pose of a ``CalibrationResult``: two-stage: the hand-eye residual chi2 (6 DOF) and
    the lens-pose fit chi2/dof; joint: the robot pose error chi2 a^T Sigma_A^-1 a (6 DOF) and the
    whitened Zernike residual chi2 / m; each with its expectation and the outlier threshold;
    outliers in red, poses left out named below."""
    ids = [p["pose"] for p in result.per_pose]
    he = np.array([p["handeye_chi2"] if p["handeye_chi2"] is not None else np.nan for p in result.per_pose])
    ec = np.array([p["estimate_chi2_dof"] for p in result.per_pose])
    col = ["tab:red" if p["outlier"] else "tab:blue" for p in result.per_pose]
    joint = "n_zernike_modes" in result.extra
    top_thr, bottom_thr = result.outlier_threshold, float("nan")
    labels = ("hand-eye residual chi2 (6 DOF)", "lens-pose fit chi2/dof")
    if joint:
        m = result.extra["n_zernike_modes"]
        top_thr, bottom_thr = float("nan"), result.extra["outlier_threshold_zernike_chi2"] / m
        labels = ("robot pose error chi2\n(6 DOF, vs repeatability)", f"Zernike residual chi2/m\n(m = {m} modes)")
    fig = new_figure(figsize=(max(6, 0.35 * len(ids) + 2), 6), layout="constrained")
    ax = fig.subplots(2, 1, sharex=True)
    ax[0].bar(ids, he, color=col)
    ax[0].axhline(6.0, color="k", lw=0.8, ls=":",
                  label="prior mean (6; fitted errors fall below)" if joint else "expected (6 DOF)")
    ax[1].bar(ids, ec, color=col)
    ax[1].axhline(1.0, color="k", lw=0.8, ls=":", label="expected (1)")
    for a, thr in ((ax[0], top_thr), (ax[1], bottom_thr)):
        if np.isfinite(thr):
            a.axhline(thr, color="tab:red", lw=0.8, ls="--", label="outlier threshold")
    ax[0].set_ylabel(labels[0])
    ax[0].set_yscale("log")
    ax[1].set_ylabel(labels[1])
    for a in ax:
        a.legend(fontsize=8)
    ax[0].set_title(f"{result.method}: chi2/dof = {result.chi2_dof:.3g}, p = {result.p_value:.2g}, "
                    f"{len(result.poses_used)} poses used")
    left_out = [r["pose"] for r in result.poses_rejected]
    ax[1].set_xlabel("pose id (red: flagged outlier)"
                     + (f"; left out: {', '.join(left_out[:12])}" if left_out else ""))
    ax[1].tick_params(axis="x", labelrotation=90)
    return fig
