"""``lensforge evaluate``: metrics of paper lenses or design files on a bench."""

from __future__ import annotations

from typing import List, Optional

import typer
from rich.console import Console
from rich.table import Table

from ..display import UNOBSERVABLE_NOTE, crlb_cells, crlb_columns
from ._common import emit_json, load_bench_arg


_NO_METRICS = {"rank": None, "kappa": None, "sigma_min": None, "J": None, "unobservable": None,
               "crlb_std": {k: None for k in ("tx_um", "ty_um", "tz_um", "rx_urad", "ry_urad", "rz_urad")}}


def evaluate_lenses(names: list[str], bench_path: str | None = None) -> list[dict]:
    """Metrics rows (JSON-ready) for each lens argument (paper name or design file).

    Each row carries ``sensor_range`` at the nominal pose (ok, max_slope_mrad, lenslets_out, ...);
    a lens out of the sensor's range gets null metrics (the sensor cannot measure it).
    """
    from ..design.bench_vars import bench_label, bench_summary
    from ..optics.lens import resolve_lens
    from ..optics.sensitivity import metrics
    from ..optics.shack_hartmann import ForwardModel

    rows = []
    for name in names:
        r = resolve_lens(name)
        lens = r.lens
        bench = load_bench_arg(bench_path, r)
        sr = ForwardModel(bench, lens).sensor_range()  # nominal pose; metrics need it in range
        m = metrics(bench, lens) if sr.ok else None
        rows.append({"lens": name, "label": r.label, "description": lens.name,
                     **(m.to_dict() if m else _NO_METRICS), "sensor_range": sr.to_dict(),
                     "bench": bench_summary(bench), "bench_label": bench_label(bench)})
    return rows


def _range_text(sr: dict | None) -> str:
    if sr is None:
        return "-"
    return ("ok" if sr["ok"] else f"OUT ({sr['lenslets_out']} lenslets)") + f", max {sr['max_slope_mrad']:.3g} mrad"


def metrics_table(rows: list[dict], title: str = "Sensitivity metrics (scaled, noise-whitened S)"):
    """A rich table of metrics rows (rank, kappa, sigma_min, J, CRLB std per DOF, the
    DOF unobservable by DESIGN.md's statistical rule)."""
    def fmt(v, spec=".3g"):
        return "inf" if v is None else format(v, spec)

    t = Table(title=title, caption=UNOBSERVABLE_NOTE)
    for col in ["lens", "bench", "rank", "kappa", "sigma_min", "J"] + crlb_columns() + ["sensor range"]:
        t.add_column(col, justify="right" if col != "lens" else "left")
    for r in rows:
        t.add_row(r.get("label", r["lens"]), r.get("bench_label", "-"), fmt(r["rank"], "d"), fmt(r["kappa"]), fmt(r["sigma_min"]), fmt(r["J"]),
                  *crlb_cells(r["crlb_std"], unobservable=r.get("unobservable") or ()), _range_text(r.get("sensor_range")))
    return t


def evaluate(
    lenses: List[str] = typer.Argument(..., help="paper lens names (spherical, polynomial, extended_polynomial, zernike) or design JSON files"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML (default: the design's bench or the built-in default)"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable JSON on stdout"),
) -> None:
    """Design metrics and Cramer-Rao bound of each lens.

    Rank, condition number kappa, sigma_min and cost J of the scaled, noise-whitened
    sensitivity matrix, and the 1-sigma Cramer-Rao bound per pose DOF (um, urad)."""
    rows = evaluate_lenses(lenses, bench)
    if json_out:
        emit_json({"schema_version": 1, "lenses": rows})
    else:
        Console(stderr=True, width=200).print(metrics_table(rows))
