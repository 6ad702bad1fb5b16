"""``lensforge export``: printable STL/STEP files and a printability report."""

from __future__ import annotations

import json
import math
from contextlib import contextmanager
from pathlib import Path

import typer

from ..errors import ConfigError
from ..manufacturing.features import FeatureSpec
from ..fileio import check_output, dumps_json, staged_dir, write_atomic
from ..optics.lens import resolve_lens
from ..progress import progress_bar
from ._common import emit_json, info

MAX_TRIANGLES = 1e7  # ~2 GB in trimesh and OCP together; far finer than any printer resolves


def mesh_triangle_estimate(radius_mm: float, chord_tol_mm: float) -> float:
    """Triangles of a lens mesh (both faces) at a chord tolerance: a rim polygon of
    n = pi / acos(1 - tol / R) points and about n / (2 pi) rings of up to n points."""
    n_rim = math.pi / math.acos(max(-1.0, 1.0 - min(chord_tol_mm / radius_mm, 2.0)))
    return 2.0 * n_rim * max(8.0, n_rim / (2 * math.pi))


@contextmanager
def _steps(steps: list[str], enabled: bool = True):
    """The one progress bar (``progress.progress_bar``) over named export steps; yields the
    callback that starts each step."""
    with progress_bar(len(steps), f"export: {steps[0] if steps else ''}", enabled=enabled) as bar:
        def tick(name: str) -> None:
            bar.update(steps.index(name) if name in steps else 0)
            bar.describe(f"export: {name}")
        yield tick
        bar.update(len(steps))


def export_cmd(
    design: str = typer.Argument(..., help="Paper lens name, design JSON (key 'lens') or lens JSON."),
    stl: bool = typer.Option(False, "--stl", help="Write a binary STL (default: both STL and STEP)."),
    step: bool = typer.Option(False, "--step", help="Write an AP214 STEP solid (default: both)."),
    threemf: bool = typer.Option(False, "--3mf", help="Also write a 3MF mesh (mm)."),
    fiducial: bool = typer.Option(False, "--fiducial", help="Add an orientation fiducial on the edge."),
    fiducial_kind: str = typer.Option("flat", "--fiducial-kind", help="Fiducial shape: flat or notch."),
    tab: bool = typer.Option(False, "--tab", help="Add a gripper tab on the edge."),
    layer: float = typer.Option(25.0, "--layer", help="Layer height in um (Form 2: 25, 50, 100)."),
    chord_tol: float = typer.Option(0.001, "--chord-tol", help="Largest mesh deviation from the surfaces, mm."),
    edge_diameter: float = typer.Option(None, "--edge-diameter",
                                        help="Override the mechanical edge diameter, mm (room for features)."),
    flange: float = typer.Option(1.0, "--flange",
                                 help="Mechanical edge beyond the clear aperture, mm radial (room for --fiducial "
                                      "and --tab; 0 = edge at the clear aperture)."),
    orient: bool = typer.Option(False, "--orient",
                                help="Write the STL/3MF in the suggested print orientation (build direction +z)."),
    optiland: bool = typer.Option(False, "--optiland",
                                  help="Also write NAME.optiland.json (bench model for optiland) and "
                                       "NAME.opticstudio.txt (OpticStudio prescription)."),
    out: Path = typer.Option(Path("exports"), "-o", "--out", help="Output folder."),
    name: str = typer.Option(None, "--name", help="File stem (default: the design's name)."),
    slicer: bool = typer.Option(True, "--slicer/--no-slicer", help="Check the STL with PrusaSlicer if present."),
    no_progress: bool = typer.Option(False, "--no-progress", help="No progress bar."),
    json_out: bool = typer.Option(False, "--json", help="Machine-readable report on stdout."),
) -> None:
    """Export printable files and a printability report.

    STL/STEP (and 3MF) for the Form 2, with mesh, STEP, printer and PrusaSlicer checks."""
    if not math.isfinite(layer) or layer <= 0:
        raise ConfigError(f"--layer: must be a positive number of um, got {layer}")
    if not math.isfinite(chord_tol) or chord_tol <= 0:
        raise ConfigError(f"--chord-tol: must be a positive number of mm, got {chord_tol}")
    if fiducial_kind not in ("flat", "notch"):
        raise ConfigError(f"--fiducial-kind: must be 'flat' or 'notch', got {fiducial_kind!r}")
    if not math.isfinite(flange) or flange < 0:
        raise ConfigError(f"--flange: must be a width >= 0 mm, got {flange}")
    resolved = resolve_lens(design)
    lens = resolved.lens
    if name is not None and (not name or "/" in name or name.startswith(".") or "\0" in name):
        raise ConfigError(f"--name: {name!r} is not a usable file stem; pass a plain name such as lens1")
    if edge_diameter is not None:
        if not math.isfinite(edge_diameter) or edge_diameter < lens.aperture:
            raise ConfigError(f"--edge-diameter: must be >= the clear aperture {lens.aperture} mm, "
                              f"got {edge_diameter}")
        lens = lens.replace(edge_diameter=float(edge_diameter)).validate()
    if not stl and not step:
        stl = step = True
    stem = name or Path(design).stem.replace(" ", "_")
    spec = FeatureSpec(fiducial=fiducial_kind if fiducial else None, tab=tab)
    n_tri = mesh_triangle_estimate(lens.edge_diameter / 2, chord_tol)
    if n_tri > MAX_TRIANGLES:
        raise ConfigError(f"--chord-tol: {chord_tol:g} mm on a {lens.edge_diameter:g} mm lens needs about "
                          f"{n_tri:.2g} triangles, over the limit of {MAX_TRIANGLES:.0e}; use a larger tolerance "
                          "(the Form 2 prints 25 um layers; 0.001 mm is ample)")
    check_output(out, folder=True, need_mb=20 + 200 * n_tri / 1e6)
    from ..manufacturing.report import export_lens, export_steps  # imports OCP (~0.8 s): only exports pay it

    steps = export_steps(stl, step, threemf, optiland, slicer)
    with staged_dir(out) as st, _steps(steps, enabled=not no_progress and not json_out) as tick:
        # STL, STEP, 3MF, optiland model and report appear together or not at all
        rep = export_lens(lens, st.tmp, stem, stl=stl, step=step, features=spec, layer_mm=layer / 1000.0,
                          chord_tol_mm=chord_tol, run_slicer=slicer, threemf=threemf, write_report=False,
                          flange_mm=None if edge_diameter is not None else flange, orient=orient,
                          optiland=optiland, bench=resolved.bench_or(), progress=tick)
        report = rep.to_dict()
        report["files"]["report"] = str(st.tmp / f"{stem}.report.json")
        text = st.relocate(dumps_json(report))
        write_atomic(st.tmp / f"{stem}.report.json", text + "\n")
    info(st.relocate(rep.summary()))
    if json_out:
        emit_json(json.loads(text))
    if not rep.ok:
        raise typer.Exit(1)
