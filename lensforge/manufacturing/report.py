"""Export a lens for printing and gather the printability report (library side of
``lensforge export``). Lengths mm, volumes mm^3, times s."""

from __future__ import annotations

from os import PathLike

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import LensforgeError
from ..fileio import dumps_json, write_atomic
from ..optics.bench import Bench
from ..optics.lens import Lens
from .features import DEFAULT_FLANGE_MM, FeatureSpec, with_flange
from .mesh import StlExport, build_lens_mesh, check_mesh, orient_mesh, save_3mf, save_stl
from .printer import FORM2, PrinterProfile, PrintReport, check_layer, printability
from .slicer import SlicerCheck, slicer_check

if TYPE_CHECKING:
    from .step import StepExport

__all__ = ["ExportReport", "export_lens", "export_steps", "REPORT_SCHEMA_VERSION"]

REPORT_SCHEMA_VERSION = 1


@dataclass(frozen=True)
class ExportReport:
    """Everything ``lensforge export`` wrote and checked (``to_dict()`` is the JSON report).

    Parameters
    ----------
    lens_name : str
        The lens's name.
    stl : StlExport or None
        The STL written, if any.
    step : StepExport or None
        The STEP written, if any.
    print_report : PrintReport
        Printer fit, orientation and staircase for the Form 2.
    slicer : SlicerCheck or None
        PrusaSlicer's verdict, if run.
    mesh_check : dict
        Watertight/manifold/volume of the mesh (also when no STL was written).
    report_path : pathlib.Path or None
        The report JSON written, if any.
    wall_s : float
        Wall time, s.
    threemf_path : pathlib.Path or None
        The 3MF written, if any.
    edge_diameter_mm : float or None
        Mechanical edge diameter of the exported lens, mm.
    oriented : tuple or None
        4x4 {O} -> print coordinates applied to the STL/3MF, or None.
    extra_files : tuple
        (kind, path) of the optiland model, prescription, ...
    """

    lens_name: str
    stl: StlExport | None
    step: StepExport | None
    print_report: PrintReport
    slicer: SlicerCheck | None
    mesh_check: dict  # watertight/manifold/volume of the mesh (also when no STL was written)
    report_path: Path | None
    wall_s: float
    threemf_path: Path | None = None
    edge_diameter_mm: float | None = None
    oriented: tuple | None = None  # 4x4 {O} -> print coordinates applied to the STL/3MF, or None
    extra_files: tuple = ()  # (kind, path) of the optiland model, prescription, ...

    def checks(self) -> dict:
        """Each check -> "ok", "failed" or "not run: <why>" (plain words)."""
        out = {"mesh": "ok" if self.mesh_check["ok"] else "failed",
               "printer fit": "ok" if self.print_report.fits else "failed"}
        if self.step is None:
            out["STEP solid"] = "not run: no STEP requested"
        else:
            out["STEP solid"] = "ok" if self.step.ok else "failed"
        if self.slicer is None:
            out["PrusaSlicer"] = "not run: no STL written or --no-slicer"
        elif not self.slicer.available:
            out["PrusaSlicer"] = "not run: prusa-slicer not installed"
        else:
            out["PrusaSlicer"] = "ok" if self.slicer.ok else "failed"
        return out

    @property
    def ok(self) -> bool:
        """No check that ran failed (checks that did not run are listed by :meth:`checks`)."""
        return all(v != "failed" for v in self.checks().values())

    @property
    def complete(self) -> bool:
        """Every check ran."""
        return all(not v.startswith("not run") for v in self.checks().values())

    def overall(self) -> str:
        """ "OK" only when every check ran and passed."""
        checks = self.checks()
        if not self.ok:
            return "PROBLEMS: " + ", ".join(k for k, v in checks.items() if v == "failed") + " (see above)"
        skipped = [f"{k} ({v[len('not run: '):]})" for k, v in checks.items() if v.startswith("not run")]
        if skipped:
            return "no problems in the checks that ran; NOT checked: " + "; ".join(skipped)
        return "OK (all checks ran and passed)"

    def to_dict(self) -> dict:
        return {
            "schema_version": REPORT_SCHEMA_VERSION,
            "lens": self.lens_name,
            "ok": self.ok,
            "complete": self.complete,
            "checks": self.checks(),
            "overall": self.overall(),
            "files": {k: str(v) for k, v in (("stl", self.stl and self.stl.path), ("step", self.step and self.step.path),
                                               ("3mf", self.threemf_path), *self.extra_files,
                                               ("report", self.report_path)) if v},
            "edge_diameter_mm": self.edge_diameter_mm,
            "mesh_transform": None if self.oriented is None else [list(r) for r in self.oriented],
            "mesh": self.mesh_check,
            "stl": self.stl.to_dict() if self.stl else None,
            "step": self.step.to_dict() if self.step else None,
            "printer": self.print_report.to_dict(),
            "slicer": self.slicer.to_dict() if self.slicer else {"available": False, "verdict": "not run"},
            "wall_s": self.wall_s,
        }

    def summary(self) -> str:
        """Readable summary (units in every label)."""
        m = self.mesh_check
        pr = self.print_report
        bb = pr.extents_mm
        lines = [
            f"lens: {self.lens_name}",
            f"  mesh: {m['triangles']} triangles, chord error {1000 * m['chord_error_mm']:.3f} um "
            f"(tolerance {1000 * m['chord_tol_mm']:.3f} um), watertight {_yn(m['watertight'])}, "
            f"manifold {_manifold_words(m['manifold_status'])}, genus {m['genus']}",
            f"  volume: {m['volume_mm3']:.4f} mm^3 (analytic {m['analytic_volume_mm3']:.4f} mm^3, "
            f"rel. error {m['volume_rel_error']:.2e})",
            f"  bounding box: {bb[0]:.3f} x {bb[1]:.3f} x {bb[2]:.3f} mm; fits the {pr.printer}: {_yn(pr.fits)}",
            f"  orientation: build direction {tuple(round(v, 3) for v in pr.orientation.build_direction)} in {{O}} "
            f"(tilt {pr.orientation.tilt_deg:.0f} deg), RMS cusp {1000 * pr.orientation.rms_cusp_mm:.2f} um at "
            f"{1000 * pr.layer_mm:.0f} um layers, {pr.orientation.layers} layers; "
            + ("applied to the STL/3MF (build direction = +z)" if self.oriented is not None
               else "not applied (files in the lens frame {O}; --orient applies it)"),
        ]
        if self.edge_diameter_mm is not None:
            lines.insert(1, f"  edge diameter: {self.edge_diameter_mm:.3f} mm (clear aperture + flange)")
        for s in pr.staircase_axis_vertical:
            lines.append(f"  staircase ({s.surface}, axis vertical): max slope {s.max_slope_deg:.1f} deg, "
                         f"max cusp {1000 * s.max_cusp_mm:.1f} um")
        if pr.small_features:
            lines.append("  below XY resolution: " + ", ".join(
                f"{f['feature']} {1000 * f['size_mm']:.0f} um" for f in pr.small_features))
        if self.stl:
            lines.append(f"  STL: {self.stl.path} ({self.stl.file_bytes} bytes, {self.stl.wall_s:.2f} s)")
        if self.threemf_path is not None:
            lines.append(f"  3MF: {self.threemf_path}")
        if self.step:
            s = self.step
            lines.append(f"  STEP: {s.path} ({s.file_bytes} bytes, {s.wall_s:.2f} s): max deviation "
                         f"{1e6 * s.max_deviation_mm:.2f} nm (goal {1e6 * s.deviation_goal_mm:.0f} nm), valid "
                         f"{_yn(s.valid)}, re-import volume rel. error {s.reimport_volume_rel_error:.1e}")
        if self.slicer is None:
            lines.append("  slicer: not run")
        else:
            extra = f" ({self.slicer.info_line}, {self.slicer.layers} layers)" if self.slicer.available else ""
            lines.append(f"  slicer (PrusaSlicer SLA): {self.slicer.verdict}{extra}")
        for kind, path in self.extra_files:
            lines.append(f"  {kind}: {path}")
        lines.append(f"  overall: {self.overall()}")
        return "\n".join(lines)


def _yn(b) -> str:
    return "yes" if b else "no"


def _manifold_words(status: str) -> str:
    return "yes" if status == "NoError" else f"no (manifold3d: {status})"


def export_steps(stl: bool, step: bool, threemf: bool = False, optiland: bool = False,
                 run_slicer: bool = True) -> list[str]:
    """Names of the steps :func:`export_lens` will report to its progress callback, in order."""
    steps = ["mesh", "printability"]
    steps += ["STL"] if stl else []
    steps += ["3MF"] if threemf else []
    steps += ["STEP"] if step else []
    steps += ["optiland model", "prescription"] if optiland else []
    steps += ["PrusaSlicer"] if run_slicer and stl else []
    return steps


def export_lens(lens: Lens, out_dir: str | PathLike[str], stem: str, stl: bool = True, step: bool = True,
                features: FeatureSpec | None = None, layer_mm: float = 0.025, chord_tol_mm: float = 1e-3,
                run_slicer: bool = True, profile: PrinterProfile = FORM2,
                write_report: bool = True, threemf: bool = False, flange_mm: float | None = DEFAULT_FLANGE_MM,
                orient: bool = False, optiland: bool = False, bench: Bench | None = None,
                progress: Callable[[str], None] | None = None) -> ExportReport:
    """Write OUT_DIR/STEM.stl and/or .step (and .3mf) and STEM.report.json; check printability.

    The slicer runs on the written STL (verdict "not available" without PrusaSlicer).

    Parameters
    ----------
    lens : Lens
        The lens ({O}, mm).
    out_dir : str or os.PathLike
        Output folder.
    stem : str
        File stem (a plain name).
    stl, step, threemf : bool
        Which files to write.
    features : FeatureSpec, optional
        Handling features.
    layer_mm : float
        Layer height, mm (Form 2: 0.025, 0.05, 0.1).
    chord_tol_mm : float
        Largest mesh deviation from the surfaces, mm.
    run_slicer : bool
        Check the STL with PrusaSlicer when installed.
    profile : PrinterProfile
        The printer (default the Form 2).
    write_report : bool
        Write STEM.report.json.
    flange_mm : float or None
        Mechanical edge beyond the clear aperture, mm (None or 0: keep the lens's edge diameter).
    orient : bool
        Turn the STL/3MF into the suggested print orientation (build direction +z, resting
        on z = 0; the STEP stays in {O}).
    optiland : bool
        Also write STEM.optiland.json and STEM.opticstudio.txt for ``bench``.
    bench : Bench, optional
        The bench of the optiland model (default bench if None).
    progress : callable, optional
        Called with each step's name (:func:`export_steps`) when it starts.

    Returns
    -------
    ExportReport
        What was written and checked.

    Raises
    ------
    MissingDependencyError
        STEP asked for without the CAD stack, or no mesh stack (``pip install 'lensforge[export]'``).
    LensforgeError
        A bad stem or layer, or a mesh/solid that fails its checks.
    """
    t0 = time.perf_counter()
    if step:  # the CAD stack is the `export` extra: say so before any work (MissingDependencyError)
        from .step import export_step
    tick = progress or (lambda _name: None)
    layer = check_layer(layer_mm, profile)
    if not stem or "/" in stem or stem.startswith("."):
        raise LensforgeError(f"name: {stem!r} is not a usable file stem; pass a plain name")
    out_dir = Path(out_dir)
    spec = features or FeatureSpec()
    if flange_mm:
        lens = with_flange(lens, flange_mm)
    stl_res = step_res = sl = None
    tick("mesh")
    lm = build_lens_mesh(lens, chord_tol_mm, spec)
    tick("printability")
    pr = printability(lens, lm.mesh.vertices, layer, lm.features, profile)
    out_mesh = orient_mesh(lm, pr.orientation.build_direction) if orient else lm
    if stl:
        tick("STL")
        stl_res = save_stl(out_mesh, out_dir / f"{stem}.stl", t0)
        chk = stl_res.check
    else:
        chk = check_mesh(lm.mesh, lm.analytic_volume_mm3, lm.volume_bound_mm3)
    tmf = None
    if threemf:
        tick("3MF")
        tmf = save_3mf(out_mesh, out_dir / f"{stem}.3mf")
    mesh_check = chk.to_dict()
    mesh_check.update(chord_error_mm=lm.chord_error_mm, chord_tol_mm=lm.chord_tol_mm, n_rings=lm.n_rings,
                      n_rim=lm.n_rim)
    if step:
        tick("STEP")
        step_res = export_step(lens, out_dir / f"{stem}.step", features=spec)
    extra = []
    if optiland:
        from .prescription import write_optiland, write_prescription

        b = bench or Bench.default()
        tick("optiland model")
        extra.append(("optiland", write_optiland(lens, b, out_dir / f"{stem}.optiland.json")))
        tick("prescription")
        extra.append(("opticstudio", write_prescription(lens, b, out_dir / f"{stem}.opticstudio.txt")))
    if run_slicer and stl_res is not None:
        tick("PrusaSlicer")
        sl = slicer_check(stl_res.path, layer, expected_volume_mm3=stl_res.volume_mm3)
    rp = out_dir / f"{stem}.report.json" if write_report else None
    rep = ExportReport(lens.name or stem, stl_res, step_res, pr, sl, mesh_check, rp, 0.0, tmf,
                       edge_diameter_mm=lens.edge_diameter, oriented=out_mesh.transform, extra_files=tuple(extra))
    rep = ExportReport(**{**rep.__dict__, "wall_s": time.perf_counter() - t0})
    if rp is not None:
        write_atomic(rp, dumps_json(rep.to_dict()) + "\n")
    return rep
