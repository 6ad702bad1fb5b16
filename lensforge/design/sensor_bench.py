"""Bench geometry as a choice: on which benches can the sensor measure a lens?

Lens-sensor distance and pupil radius decide the wavefront slopes the lenslets see.
``measurable_geometry`` scans both (within the bench's limits) and reports, per
combination, the nominal-pose sensor range (``ForwardModel.sensor_range``) and whether
the pupil is traced and lit; ``best_distance`` picks, per pupil radius, the distance
whose largest spot-assignment use is smallest. One ``evaluate`` per bench: cheap.
"""

from __future__ import annotations

import numpy as np

from ..errors import LensforgeError
from ..optics.bench import Bench
from ..optics.lens import Lens
from ..optics.shack_hartmann import ForwardModel

__all__ = ["measurable_geometry", "best_distance"]


def measurable_geometry(bench: Bench, lens: Lens, distances_mm, radii_mm) -> list[dict]:
    """One row per (distance, pupil radius): lit, sensor-range summary, measurable (lit and in range)."""
    rows = []
    for r in radii_mm:
        for d in distances_mm:
            row = {"distance_mm": float(d), "pupil_radius_mm": float(r)}
            try:
                b = bench.replace(placement={"distance_mm": float(d)}, sensor={"pupil_radius_mm": float(r)})
                model = ForwardModel(b, lens, validate=False)
                res = model.evaluate(np.zeros(6), check_range=False)
                lit = bool(np.all(res.status[0] == 0) and np.all(res.irradiance[0] >= res.threshold))
                sr = model.sensor_range().to_dict()
                row.update(lit=lit, sensor_range=sr, measurable=lit and sr["ok"])
            except LensforgeError as e:
                row.update(lit=False, sensor_range=None, measurable=False, error=str(e))
            rows.append(row)
    return rows


def best_distance(rows: list[dict]) -> dict:
    """Per pupil radius: the measurable distance with the smallest spot-assignment use (None if none)."""
    out = {}
    for r in sorted({row["pupil_radius_mm"] for row in rows}):
        ok = [row for row in rows if row["pupil_radius_mm"] == r and row["measurable"]]
        best = min(ok, key=lambda row: row["sensor_range"]["max_use"]) if ok else None
        out[r] = None if best is None else {"distance_mm": best["distance_mm"],
                                            "max_use": best["sensor_range"]["max_use"],
                                            "measurable_mm": [row["distance_mm"] for row in ok]}
    return out
