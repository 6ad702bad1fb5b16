"""``lensforge evaluate``: metrics of paper lenses or design files on a bench."""

from __future__ import annotations

from typing import List, Optional

import typer
from rich.console import Console
from rich.table import Table

from ..display import UNOBSERVABLE_NOTE, crlb_cells, crlb_columns
from ._common import emit_json, lens_labels, load_bench_arg, load_lens_arg


def evaluate_lenses(names: list[str], bench_path: str | None = None) -> list[dict]:
    """Metrics rows (JSON-ready) for each lens argument (paper name or design file)."""
    from ..optics.pose import DOF_NAMES
    from ..optics.sensitivity import metrics

    rows = []
    for name, label in zip(names, lens_labels(names)):
        lens, data = load_lens_arg(name)
        bench = load_bench_arg(bench_path, data)
        m = metrics(bench, lens)
        row = {"lens": name, "label": label, "description": lens.name, **m.to_dict()}
        # DESIGN.md's statistical rule: 1-sigma bound above the pose scale (or infinite)
        row.setdefault("unobservable", [d for d, s, sc in zip(DOF_NAMES, m.crlb_std, bench.pose_scales)
                                        if not s <= sc])
        rows.append(row)
    return rows


def metrics_table(rows: list[dict], title: str = "Sensitivity metrics (scaled, noise-whitened S)"):
    """A rich table of metrics rows (rank, kappa, sigma_min, J, CRLB std per DOF)."""
    def fmt(v, spec=".3g"):
        return "inf" if v is None else format(v, spec)

    t = Table(title=title, caption=UNOBSERVABLE_NOTE)
    for col in ["lens", "rank", "kappa", "sigma_min", "J"] + crlb_columns():
        t.add_column(col, justify="right" if col != "lens" else "left")
    for r in rows:
        t.add_row(r.get("label", r["lens"]), str(r["rank"]), fmt(r["kappa"]), fmt(r["sigma_min"]), fmt(r["J"]),
                  *crlb_cells(r["crlb_std"], unobservable=r.get("unobservable", ())))
    return t


def evaluate(
    lenses: List[str] = typer.Argument(..., help="paper lens names (spherical, polynomial, extended_polynomial, zernike) or design JSON files"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML (default: the design's bench or the built-in default)"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable JSON on stdout"),
):
    """Rank, condition number, sigma_min, cost J and Cramer-Rao bound of each lens."""
    rows = evaluate_lenses(lenses, bench)
    if json_out:
        emit_json({"schema_version": 1, "lenses": rows})
    else:
        Console(stderr=True, width=160).print(metrics_table(rows))
