"""Export benchmark: triangle count, chord error and STL size at the default tolerance,
STEP deviation, export wall times, and the PrusaSlicer verdict line.

Run: .venv/bin/python benchmarks/bench_export.py [LENS ...]   (default: the four paper lenses)
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import lensforge as lf
from lensforge.manufacturing.slicer import slicer_check


def main(names: list[str]) -> None:
    print(f"{'lens':<20} {'triangles':>9} {'chord um':>9} {'STL bytes':>10} {'STL s':>6} "
          f"{'STEP nm':>8} {'STEP vol err':>12} {'STEP s':>7}  slicer (25 um layers)")
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            lens = lf.paper_lens(name)
            stl = lf.export_stl(lens, Path(tmp) / f"{name}.stl")  # default chord_tol_mm = 1e-3
            step = lf.export_step(lens, Path(tmp) / f"{name}.step")
            t0 = time.perf_counter()
            sl = slicer_check(stl.path, 0.025, expected_volume_mm3=stl.volume_mm3)
            ts = time.perf_counter() - t0
            line = f"{sl.verdict}: {sl.info_line}, {sl.layers} layers, {ts:.1f} s" if sl.available else sl.verdict
            print(f"{name:<20} {stl.triangles:>9d} {1000 * stl.chord_error_mm:>9.3f} {stl.file_bytes:>10d} "
                  f"{stl.wall_s:>6.2f} {1e6 * step.max_deviation_mm:>8.3f} {step.reimport_volume_rel_error:>12.1e} "
                  f"{step.wall_s:>7.2f}  {line}")


if __name__ == "__main__":
    main(sys.argv[1:] or ["spherical", "polynomial", "extended_polynomial", "zernike"])
