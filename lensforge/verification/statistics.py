"""The one place where lensforge turns samples into reported statistics.

Every console line, JSON field and plot of a study (as-built ``study``, ``budget``,
``estimate-study``, ``scenario``) takes its median / percentile / max from
:func:`error_stats` (or :func:`percentile`) and its counts from :func:`outcome_counts`,
so the numbers cannot disagree.

Percentile method: ``numpy.percentile(..., method="higher")``, the smallest sample value
at or above the q-th percentile. It is always a value that a trial actually reached, it is
conservative for a pass/fail against a target, and it handles a failed trial counted as an
infinitely large error (+inf) without interpolating into it: the p95 is finite exactly when
at most 5 % of the trials failed.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["PERCENTILE_METHOD", "percentile", "median", "error_stats", "box_stats", "outcome_counts", "format_counts"]

PERCENTILE_METHOD = "higher"


def percentile(values, q: float) -> float | None:
    """q-th percentile (0..100) of ``values``; nan counts as +inf (a failure). None when
    there are no values or the percentile falls on a failure."""
    v = np.asarray(values, dtype=float).ravel()
    if v.size == 0:
        return None
    v = np.where(np.isnan(v), np.inf, v)
    r = float(np.percentile(v, float(q), method=PERCENTILE_METHOD))
    return r if math.isfinite(r) else None


def median(values) -> float:
    """:func:`percentile` 50 as a float: nan when undefined (for tables of float columns)."""
    p = percentile(values, 50)
    return math.nan if p is None else p


def error_stats(values, q: float = 95.0) -> dict:
    """{"median", "p<q>", "max"} of ``values`` (None where a failure decides it)."""
    return {"median": percentile(values, 50), f"p{q:g}": percentile(values, q), "max": percentile(values, 100)}


def box_stats(values) -> dict:
    """Box-plot statistics (matplotlib ``Axes.bxp``) from :func:`percentile`: quartiles, Tukey
    whiskers (the most extreme samples within 1.5 IQR of the box) and the samples beyond them."""
    v = np.asarray(values, dtype=float).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"med": np.nan, "q1": np.nan, "q3": np.nan, "whislo": np.nan, "whishi": np.nan, "fliers": []}
    q1, med, q3 = percentile(v, 25), percentile(v, 50), percentile(v, 75)
    lo, hi = q1 - 1.5 * (q3 - q1), q3 + 1.5 * (q3 - q1)
    inside = v[(v >= lo) & (v <= hi)]
    return {"med": med, "q1": q1, "q3": q3, "whislo": float(inside.min()), "whishi": float(inside.max()),
            "fliers": v[(v < lo) | (v > hi)]}


def outcome_counts(records) -> dict:
    """Counts over study trial records (dicts with "ok", "failure", and per-pose counts).

    Returns n, n_ok, n_failed, failures (reason -> count), and the pose counts
    pupil_lost_poses, not_converged_poses, out_of_range_poses.
    """
    records = list(records)
    failures: dict[str, int] = {}
    for r in records:
        if not r["ok"]:
            key = str(r.get("failure", "failed")).split(":")[0].split(" (")[0]
            failures[key] = failures.get(key, 0) + 1
    n_ok = sum(bool(r["ok"]) for r in records)
    return {
        "n": len(records), "n_ok": n_ok, "n_failed": len(records) - n_ok, "failures": failures,
        "pupil_lost_poses": int(sum(r.get("n_pupil_lost", 0) for r in records)),
        "not_converged_poses": int(sum(r.get("n_not_converged", 0) for r in records)),
        "out_of_range_poses": int(sum(r.get("n_out_of_range", 0) for r in records)),
    }


def format_counts(summary: dict) -> str:
    """One console line with every count of a study summary (zeros included)."""
    fails = ", ".join(f"{k} {v}" for k, v in sorted(summary.get("failures", {}).items()))
    n_failed = summary["n_lenses"] - summary["n_ok"]
    return (f"{n_failed} of {summary['n_lenses']} lenses failed" + (f" ({fails})" if fails else "")
            + f"; poses: {summary.get('pupil_lost_poses', 0)} lost the pupil, "
            f"{summary.get('not_converged_poses', 0)} did not converge, "
            f"{summary.get('out_of_range_poses', 0)} out of the sensor's range")
