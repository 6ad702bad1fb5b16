"""``lensforge export``: printable STL/STEP files and a printability report."""

from __future__ import annotations

import math
from pathlib import Path

import typer

from ..errors import ConfigError
from ..manufacturing.features import FeatureSpec
from ..optics.lens import resolve_lens
from ._common import emit_json, info


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
    out: Path = typer.Option(Path("exports"), "-o", "--out", help="Output folder."),
    name: str = typer.Option(None, "--name", help="File stem (default: the design's name)."),
    slicer: bool = typer.Option(True, "--slicer/--no-slicer", help="Check the STL with PrusaSlicer if present."),
    json_out: bool = typer.Option(False, "--json", help="Machine-readable report on stdout."),
):
    """Export a lens as printable files and report whether the Form 2 can print it."""
    if not math.isfinite(layer) or layer <= 0:
        raise ConfigError(f"--layer: must be a positive number of um, got {layer}")
    if not math.isfinite(chord_tol) or chord_tol <= 0:
        raise ConfigError(f"--chord-tol: must be a positive number of mm, got {chord_tol}")
    if fiducial_kind not in ("flat", "notch"):
        raise ConfigError(f"--fiducial-kind: must be 'flat' or 'notch', got {fiducial_kind!r}")
    lens = resolve_lens(design).lens
    if edge_diameter is not None:
        if not math.isfinite(edge_diameter) or edge_diameter < lens.aperture:
            raise ConfigError(f"--edge-diameter: must be >= the clear aperture {lens.aperture} mm, "
                              f"got {edge_diameter}")
        lens = lens.replace(edge_diameter=float(edge_diameter)).validate()
    if not stl and not step:
        stl = step = True
    stem = name or Path(design).stem.replace(" ", "_")
    spec = FeatureSpec(fiducial=fiducial_kind if fiducial else None, tab=tab)
    from ..manufacturing.report import export_lens  # imports OCP (~0.8 s): only exports pay it

    rep = export_lens(lens, out, stem, stl=stl, step=step, features=spec, layer_mm=layer / 1000.0,
                      chord_tol_mm=chord_tol, run_slicer=slicer, threemf=threemf)
    info(rep.summary())
    if json_out:
        emit_json(rep.to_dict())
    if not rep.ok:
        raise typer.Exit(1)
