"""Comparison of lenses on one bench: the analogue of the paper's Table 1.

Each entry (a paper lens, a design file, a lens) is evaluated afresh on the same
bench, so the rows compare like with like: rank, kappa, sigma_min, J (on the scaled,
whitened S), the D and A criteria, the CRLB std per DOF (um, urad), whether the
sensor can measure the lens at the nominal pose (``sensor_range`` under the bench's
spot-assignment model, and ``sensor_range_fixed`` with fixed lenslet windows), whether
the design constraints hold, and for design files the optimiser's cost (evaluations,
seconds).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..display import UNOBSERVABLE_NOTE, crlb_cells, crlb_columns, fmt_bound
from ..errors import LensforgeError
from ..optics.bench import Bench
from ..optics.lens import Lens, resolve_lens
from ..optics.pose import DOF_NAMES
from ..optics.sensitivity import metrics
from ..optics.shack_hartmann import ForwardModel
from .bench_vars import bench_label, bench_summary
from .constraints import Constraints, check_design
from .design_file import Design, load_design, metrics_dict

__all__ = ["CompareEntry", "resolve_entry", "compare_rows", "format_table", "feasibility_notes"]


@dataclass(frozen=True)
class CompareEntry:
    """One row's input: label, lens, and the design it came from (if any)."""

    label: str
    lens: Lens
    design: Design | None = None


def resolve_entry(arg) -> CompareEntry:
    """'paper:NAME' / a paper lens name, a design JSON path, a Design or a Lens."""
    if isinstance(arg, CompareEntry):
        return arg
    if isinstance(arg, Design):
        return CompareEntry(f"{arg.model} {arg.method} seed {arg.seed}", arg.lens, arg)
    if isinstance(arg, Lens):
        return CompareEntry(arg.name or "lens", arg)
    r = resolve_lens(arg)
    if "model" in r.data:  # a design file: keep its history and settings
        d = load_design(arg)
        return CompareEntry(f"{d.model} {d.method} seed {d.seed}", d.lens, d)
    return CompareEntry(r.label, r.lens)


def compare_rows(entries, bench: Bench | None = None, constraints: Constraints | None = None) -> list[dict]:
    """One dict per entry with stable keys (see module docstring); all on ``bench``, or with
    bench None each design file on its own bench (a paper lens on the default bench). Every
    row carries the bench it was evaluated on (``bench``: ``bench_vars.bench_summary``)."""
    cons = constraints or Constraints()
    rows = []
    for e in map(resolve_entry, entries):
        own = bench or (e.design.bench if e.design is not None else Bench.default())
        rows.append(_row(e, own, cons))
    return rows


def _row(e: CompareEntry, bench: Bench, cons: Constraints) -> dict:
    row = {"label": e.label, "lens": e.lens.name, "bench": bench_summary(bench), "bench_label": bench_label(bench)}
    try:
        m = metrics(bench, e.lens)
        md = metrics_dict(m)
        row.update({k: md[k] for k in ("rank", "kappa", "sigma_min", "J", "D", "A")})
        row["crlb_std"] = md["crlb_std"]
        row["unobservable"] = md.get("unobservable", [])  # DESIGN.md's statistical rule (Metrics.observability)
        row["error"] = None
    except LensforgeError as err:
        row.update({k: None for k in ("rank", "kappa", "sigma_min", "J", "D", "A")})
        row["crlb_std"] = None
        row["unobservable"] = list(DOF_NAMES)
        row["error"] = str(err)
    try:
        row["sensor_range"] = ForwardModel(bench, e.lens).sensor_range().to_dict()
        fixed = bench.replace(sensor={"spot_assignment": "fixed"})
        row["sensor_range_fixed"] = ForwardModel(fixed, e.lens).sensor_range().to_dict()
    except LensforgeError:
        row["sensor_range"] = row["sensor_range_fixed"] = None
    try:
        f = check_design(bench, e.lens, cons)
        row["feasible"] = f.ok
        row["violations"] = [v.constraint for v in f.violations]
        row["violation_messages"] = [v.message for v in f.violations]
    except LensforgeError as err:
        row["feasible"] = False
        row["violations"] = ["error"]
        row["violation_messages"] = [str(err)]
    d = e.design
    row["method"] = d.method if d else None
    row["seed"] = d.seed if d else None
    row["criterion"] = d.criterion if d else None
    row["n_evals"] = d.n_evals if d else None
    row["wall_time_s"] = d.wall_time_s if d else None
    return row


def _fmt(v, spec=".4g"):
    if v is None:
        return "-"
    if isinstance(v, float) and not np.isfinite(v):
        return "inf"
    return format(v, spec)


def _measurable(r: dict) -> str:
    """'tracking yes / fixed no (16 out)': can the sensor measure the lens at the nominal pose."""
    parts = []
    for key in ("sensor_range", "sensor_range_fixed"):
        sr = r.get(key)
        if sr is None:
            parts.append("-")
            continue
        parts.append(f"{sr['model']} " + ("yes" if sr["ok"] else f"no ({sr['lenslets_out']} out)"))
    return " / ".join(dict.fromkeys(parts))


def format_table(rows: list[dict]):
    """A rich Table of the rows (print it with a stderr Console)."""
    from rich.table import Table

    t = Table(title="Lens comparison, each on the bench shown (metrics of the scaled, whitened S; CRLB 1-sigma)",
              caption=UNOBSERVABLE_NOTE)
    cols = (["lens", "bench", "rank", "kappa", "sigma_min", "J", "D", "A"] + crlb_columns("")
            + ["max slope (mrad)", "measurable", "feasible", "evals", "time (s)"])
    for c in cols:
        t.add_column(c, justify="left" if c == "lens" else "right")
    for r in rows:
        lost = r["rank"] is not None and r["rank"] < len(DOF_NAMES)  # D and A hold a rank penalty, not a value
        t.add_row(
            r["label"], r.get("bench_label", "-"), _fmt(r["rank"], "d"), _fmt(r["kappa"]), _fmt(r["sigma_min"]), _fmt(r["J"]),
            fmt_bound(r["D"], lost, ".4g"), fmt_bound(r["A"], lost, ".4g"),
            *crlb_cells(r.get("crlb_std"), unobservable=r.get("unobservable", ())),
            _fmt((r.get("sensor_range") or {}).get("max_slope_mrad"), ".3g"), _measurable(r),
            "yes" if r["feasible"] else "no: " + ",".join(r["violations"]),
            _fmt(r["n_evals"], "d"), _fmt(r["wall_time_s"], ".1f"),
        )
    return t


def feasibility_notes(rows: list[dict]) -> list[str]:
    """One line per violated constraint of each row: what it means and what to change."""
    return [f"{r['label']}: {name}: {msg}" for r in rows if not r.get("feasible", True)
            for name, msg in zip(r["violations"], r.get("violation_messages", r["violations"]))]
