"""Export a lens for printing and gather the printability report (library side of
``lensforge export``). Lengths mm, volumes mm^3, times s."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from ..errors import LensforgeError
from ..fileio import dumps_json, write_atomic
from ..optics.lens import Lens
from .features import FeatureSpec
from .mesh import StlExport, build_lens_mesh, check_mesh, save_3mf, save_stl
from .printer import FORM2, PrinterProfile, PrintReport, check_layer, printability
from .slicer import SlicerCheck, slicer_check
from .step import StepExport, export_step

__all__ = ["ExportReport", "export_lens", "REPORT_SCHEMA_VERSION"]

REPORT_SCHEMA_VERSION = 1


@dataclass(frozen=True)
class ExportReport:
    """Everything ``lensforge export`` wrote and checked."""

    lens_name: str
    stl: StlExport | None
    step: StepExport | None
    print_report: PrintReport
    slicer: SlicerCheck | None
    mesh_check: dict  # watertight/manifold/volume of the mesh (also when no STL was written)
    report_path: Path | None
    wall_s: float
    threemf_path: Path | None = None

    @property
    def ok(self) -> bool:
        good = self.mesh_check["ok"] and self.print_report.fits
        if self.step is not None:
            good &= self.step.ok
        if self.slicer is not None and self.slicer.available:
            good &= self.slicer.ok
        return bool(good)

    def to_dict(self) -> dict:
        return {
            "schema_version": REPORT_SCHEMA_VERSION,
            "lens": self.lens_name,
            "ok": self.ok,
            "files": {k: str(v) for k, v in (("stl", self.stl and self.stl.path), ("step", self.step and self.step.path),
                                               ("3mf", self.threemf_path), ("report", self.report_path)) if v},
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
            f"manifold {m['manifold_status']}, genus {m['genus']}",
            f"  volume: {m['volume_mm3']:.4f} mm^3 (analytic {m['analytic_volume_mm3']:.4f} mm^3, "
            f"rel. error {m['volume_rel_error']:.2e})",
            f"  bounding box: {bb[0]:.3f} x {bb[1]:.3f} x {bb[2]:.3f} mm; fits the {pr.printer}: {_yn(pr.fits)}",
            f"  orientation: build direction {tuple(round(v, 3) for v in pr.orientation.build_direction)} in {{O}} "
            f"(tilt {pr.orientation.tilt_deg:.0f} deg), RMS cusp {1000 * pr.orientation.rms_cusp_mm:.2f} um at "
            f"{1000 * pr.layer_mm:.0f} um layers, {pr.orientation.layers} layers",
        ]
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
        lines.append(f"  overall: {'OK' if self.ok else 'PROBLEMS (see above)'}")
        return "\n".join(lines)


def _yn(b) -> str:
    return "yes" if b else "no"


def export_lens(lens: Lens, out_dir, stem: str, stl: bool = True, step: bool = True,
                features: FeatureSpec | None = None, layer_mm: float = 0.025, chord_tol_mm: float = 1e-3,
                run_slicer: bool = True, profile: PrinterProfile = FORM2,
                write_report: bool = True, threemf: bool = False) -> ExportReport:
    """Write OUT_DIR/STEM.stl and/or .step (and .3mf) and STEM.report.json; check printability.

    The slicer runs on the written STL (verdict "not available" without PrusaSlicer).
    """
    t0 = time.perf_counter()
    layer = check_layer(layer_mm, profile)
    if not stem or "/" in stem or stem.startswith("."):
        raise LensforgeError(f"name: {stem!r} is not a usable file stem; pass a plain name")
    out_dir = Path(out_dir)
    spec = features or FeatureSpec()
    stl_res = step_res = sl = None
    lm = build_lens_mesh(lens, chord_tol_mm, spec)
    if stl:
        stl_res = save_stl(lm, out_dir / f"{stem}.stl", t0)
        chk = stl_res.check
    else:
        chk = check_mesh(lm.mesh, lm.analytic_volume_mm3, lm.volume_bound_mm3)
    tmf = save_3mf(lm, out_dir / f"{stem}.3mf") if threemf else None
    mesh_check = chk.to_dict()
    mesh_check.update(chord_error_mm=lm.chord_error_mm, chord_tol_mm=lm.chord_tol_mm, n_rings=lm.n_rings,
                      n_rim=lm.n_rim)
    pr = printability(lens, lm.mesh.vertices, layer, lm.features, profile)
    if step:
        step_res = export_step(lens, out_dir / f"{stem}.step", features=spec)
    if run_slicer and stl_res is not None:
        sl = slicer_check(stl_res.path, layer, expected_volume_mm3=stl_res.volume_mm3)
    rp = out_dir / f"{stem}.report.json" if write_report else None
    rep = ExportReport(lens.name or stem, stl_res, step_res, pr, sl, mesh_check, rp, 0.0, tmf)
    rep = ExportReport(**{**rep.__dict__, "wall_s": time.perf_counter() - t0})
    if rp is not None:
        write_atomic(rp, dumps_json(rep.to_dict()) + "\n")
    return rep
