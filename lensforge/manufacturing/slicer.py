"""Independent printability check with a real slicer: PrusaSlicer in SLA mode.

``prusa-slicer --info`` reports the mesh statistics after its own repair pass; a
broken STL still exits 0 and often still says ``manifold = yes`` (it was repaired),
so the verdict reads the repair counters too (edges_fixed, facets_reversed, ...).
``--export-sla`` then slices the part into layer images at the chosen layer height;
the verdict requires the archive to hold them. PrusaSlicer has no Form 2 profile:
it slices with its default SLA printer, which only matters for the layer images.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["SlicerCheck", "find_prusa_slicer", "parse_info", "slicer_check", "REPAIR_KEYS"]

# counters PrusaSlicer prints when it had to change the mesh
REPAIR_KEYS = ("open_edges", "edges_fixed", "degenerate_facets", "facets_removed", "facets_added",
               "facets_reversed", "backwards_edges")


def find_prusa_slicer() -> str | None:
    """Path of the prusa-slicer executable, or None."""
    return shutil.which("prusa-slicer")


def parse_info(text: str) -> dict:
    """The ``key = value`` lines of ``prusa-slicer --info`` (numbers converted)."""
    out = {}
    for line in text.splitlines():
        m = re.match(r"^\s*([A-Za-z_]+)\s*=\s*(.*?)\s*$", line)
        if not m:
            continue
        key, val = m.groups()
        try:
            out[key] = int(val)
        except ValueError:
            try:
                out[key] = float(val)
            except ValueError:
                out[key] = val
    return out


@dataclass(frozen=True)
class SlicerCheck:
    """Verdict of PrusaSlicer on an STL (volume mm^3, layer mm)."""

    available: bool
    verdict: str  # "ok", "not available" or "failed: <reasons>"
    info_line: str = ""  # the "manifold = ..." line as printed
    manifold: bool | None = None
    parts: int | None = None
    repairs: dict = field(default_factory=dict)
    volume_mm3: float | None = None
    sliced: bool | None = None
    layers: int | None = None
    layer_mm: float | None = None
    used_material_ml: float | None = None
    info: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.verdict == "ok"

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["ok"] = self.ok
        return d


def _run(cmd: list[str], timeout_s: float) -> tuple[int, str]:
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    return p.returncode, p.stdout + "\n" + p.stderr


def slicer_check(stl_path, layer_mm: float = 0.025, expected_volume_mm3: float | None = None,
                 slice_sla: bool = True, executable: str | None = None, timeout_s: float = 300.0) -> SlicerCheck:
    """Ask PrusaSlicer whether the STL is a clean manifold and slices in SLA mode.

    expected_volume_mm3: if given, PrusaSlicer's volume must agree within 0.1 %
    (it prints single precision). Returns verdict "not available" without prusa-slicer.
    """
    exe = executable or find_prusa_slicer()
    if exe is None:
        return SlicerCheck(False, "not available")
    stl = Path(stl_path)
    reasons = []
    try:
        rc, text = _run([exe, "--info", str(stl)], timeout_s)
    except (OSError, subprocess.TimeoutExpired) as e:
        return SlicerCheck(True, f"failed: prusa-slicer --info did not run ({e})")
    info = parse_info(text)
    line = next((ln.strip() for ln in text.splitlines() if ln.strip().startswith("manifold =")), "")
    manifold = {"yes": True, "no": False}.get(str(info.get("manifold", "")).strip())
    repairs = {k: info[k] for k in REPAIR_KEYS if isinstance(info.get(k), (int, float)) and info[k] > 0}
    parts = info.get("number_of_parts")
    volume = info.get("volume")
    if rc != 0:
        reasons.append(f"--info exit code {rc}")
    if manifold is not True:
        reasons.append(f"manifold = {info.get('manifold', 'missing')}")
    if repairs:
        reasons.append("mesh needed repair (" + ", ".join(f"{k} = {v}" for k, v in repairs.items()) + ")")
    if parts != 1:
        reasons.append(f"number_of_parts = {parts}")
    if expected_volume_mm3 is not None and isinstance(volume, (int, float)):
        if abs(volume - expected_volume_mm3) > 1e-3 * abs(expected_volume_mm3):
            reasons.append(f"volume {volume} mm^3 differs from {expected_volume_mm3:.6g} mm^3")
    sliced = layers = used = None
    if slice_sla:
        sliced = False
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "part.sl1"
            cmd = [exe, "--printer-technology", "SLA", "--export-sla", "--layer-height", f"{layer_mm:g}",
                   "--no-supports-enable", "--no-pad-enable", "--output", str(out), str(stl)]
            try:
                rc2, text2 = _run(cmd, timeout_s)
            except (OSError, subprocess.TimeoutExpired) as e:
                rc2, text2 = -1, str(e)
            if rc2 == 0 and out.exists() and zipfile.is_zipfile(out):
                with zipfile.ZipFile(out) as z:
                    pngs = [n for n in z.namelist() if n.endswith(".png") and not n.startswith("thumbnail")]
                    cfg = parse_info(z.read("config.ini").decode(errors="replace")) if "config.ini" in z.namelist() else {}
                layers = len(pngs)
                used = cfg.get("usedMaterial")
                sliced = len(pngs) > 0
            if not sliced:
                tail = text2.strip().splitlines()[-1:] or [""]
                reasons.append(f"SLA slicing failed (exit {rc2}: {tail[0]})")
    verdict = "ok" if not reasons else "failed: " + "; ".join(reasons)
    return SlicerCheck(True, verdict, line, manifold, parts, repairs,
                       float(volume) if isinstance(volume, (int, float)) else None,
                       sliced, layers, float(layer_mm), float(used) if isinstance(used, (int, float)) else None, info)
