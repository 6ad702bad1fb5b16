"""``lensforge evaluate``: metrics of paper lenses or design files on a bench."""

from __future__ import annotations

from typing import List, Optional

import typer
from rich.console import Console
from rich.table import Table

from ._common import emit_json, load_bench_arg, load_lens_arg


def evaluate_lenses(names: list[str], bench_path: str | None = None) -> list[dict]:
    """Metrics rows (JSON-ready) for each lens argument (paper name or design file)."""
    from ..optics.sensitivity import metrics

    rows = []
    for name in names:
        lens, data = load_lens_arg(name)
        bench = load_bench_arg(bench_path, data)
        m = metrics(bench, lens)
        rows.append({"lens": name, "description": lens.name, **m.to_dict()})
    return rows


def metrics_table(rows: list[dict], title: str = "Sensitivity metrics (scaled, noise-whitened S)"):
    """A rich table of metrics rows (rank, kappa, sigma_min, J, CRLB std per DOF)."""
    from ..optics.pose import DOF_NAMES

    def fmt(v, spec=".3g"):
        return "inf" if v is None else format(v, spec)

    t = Table(title=title)
    for col in ["lens", "rank", "kappa", "sigma_min", "J"] + [f"CRLB {d} [{'um' if i < 3 else 'urad'}]" for i, d in enumerate(DOF_NAMES)]:
        t.add_column(col, justify="right" if col != "lens" else "left")
    for r in rows:
        std = r["crlb_std"]
        keys = [f"{d}_um" for d in DOF_NAMES[:3]] + [f"{d}_urad" for d in DOF_NAMES[3:]]
        t.add_row(r["lens"], str(r["rank"]), fmt(r["kappa"]), fmt(r["sigma_min"]), fmt(r["J"]),
                  *[fmt(std[k]) for k in keys])
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
