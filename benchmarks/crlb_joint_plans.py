"""Joint Cramer-Rao bound of Z with the as-built lens free vs known, per pose plan.

Predicts how much the as-built lens costs the joint calibration (issue 10's "Numbers
to reach"): for random plans of 24, 48 and 96 poses (the study's seeded box) and
Ds-optimal joint designs (``calibration.joint_design``) of 24 and 96 poses, the RMS
Z 1-sigma with theta free (prior from the default tolerance file) and with theta
known, and their ratio. A study of perfect lenses estimates with the lens known, so
the ratio is what the default-tolerance / perfect-lens error ratio tends to.
Writes the designed plans as --pose-plan files (``lensforge study --pose-plan``).

--wide: the same ratio for plans beyond the study's box (+-0.2/0.2/2 mm, +-6 deg):
random 24-pose plans with a wider span in one direction (tz, tx/ty, rz; poses that do
not light the pupil count for nothing), 24 random poses kept only where the nominal
lens lights the pupil, and Ds-optimal designs over wider boxes (rotation limits of the
bench raised to 20 deg for the prediction). A wider plan lowers the theta-free bound,
but the ratio drops below 2 only where the known-lens bound gets worse (few lit poses).

Run: OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1 \\
     .venv/bin/python benchmarks/crlb_joint_plans.py exports/zernike.json [-o exports/plans] [--wide]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from lensforge.calibration.joint_design import box_candidates, design_joint_poses, predicted_joint_uncertainty
from lensforge.asbuilt.lens_params import parameterise
from lensforge.calibration.robot import paper_scene
from lensforge.asbuilt.tolerances import DEFAULT_TOLERANCES_FILE, load_tolerances
from lensforge.optics.lens import resolve_lens
from lensforge.verification.study import StudyConfig, calibration_plan


def row_of(q: dict) -> dict:
    row = {k: q[k] for k in ("Z_translation_mm", "Z_rotation_deg", "Z_translation_known_lens_mm",
                             "Z_rotation_known_lens_deg")}
    row["ratio_translation"] = row["Z_translation_mm"] / row["Z_translation_known_lens_mm"]
    row["ratio_rotation"] = row["Z_rotation_deg"] / row["Z_rotation_known_lens_deg"]
    return row


def wide_rows(bench, lens, param, scene, out: Path) -> dict:
    """Rows for plans beyond the study's box (module doc, --wide)."""
    import dataclasses
    import math

    from lensforge.optics.bench import PoseLimits
    from lensforge.optics.shack_hartmann import ForwardModel

    rows = {}
    for txy, tz, rot, rz in [(0.2, 5, 6, 6), (0.2, 10, 6, 6), (1, 2, 6, 6), (2, 2, 6, 6), (0.2, 2, 6, 30),
                             (0.2, 2, 6, 90)]:
        plan = calibration_plan(StudyConfig(n_poses=24, pose_span_mm=(txy, txy, tz), pose_span_deg=(rot, rot, rz)))
        q = predicted_joint_uncertainty(bench, param, scene, plan)
        rows[f"random 24, {txy}/{txy}/{tz} mm {rot}/{rot}/{rz} deg ({q['n_lit']} lit)"] = row_of(q)
    model = ForwardModel(bench, lens)
    for txy, tz, rot, rz in [(2, 2, 6, 6), (2, 5, 6, 6), (2, 2, 10, 10), (2, 5, 6, 30)]:
        span = np.r_[txy, txy, tz, np.radians([rot, rot, rz])]
        cand = np.random.default_rng(7).uniform(-1.0, 1.0, (400, 6)) * span
        plan = cand[model.evaluate(cand, check_range=False).valid][:24]
        rows[f"lit random 24, {txy}/{txy}/{tz} mm {rot}/{rot}/{rz} deg"] = row_of(
            predicted_joint_uncertainty(bench, param, scene, plan))
    wide = dataclasses.replace(bench, pose_limits=PoseLimits(5.0, math.radians(20.0)))
    for mm, deg in [(0.0, 10.0), (0.0, 15.0), (2.0, 10.0), (2.0, 15.0)]:
        span = np.r_[0.2, 0.2, 2.0, np.radians([deg] * 3)]
        if mm:
            span[:3] = mm
        d = design_joint_poses(wide, param, scene, 24, box_candidates(np.random.default_rng(0), span, 200),
                               check_reach=True, max_passes=2)
        rows[f"designed 24, box {span[0]:g}/{span[1]:g}/{span[2]:g} mm {deg:g} deg"] = row_of(d.chosen)
        (out / f"joint_design_24_{span[0]:g}mm_{deg:g}deg.json").write_text(json.dumps({"poses": d.x.tolist()}))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("design")
    ap.add_argument("-o", "--out", type=Path, default=Path("exports/plans"))
    ap.add_argument("--wide", action="store_true", help="also plans beyond the study's box (slow: ~20 CPU-min)")
    a = ap.parse_args()
    r = resolve_lens(a.design)
    lens, bench = r.lens, r.bench_or()
    scene = paper_scene(bench.placement.distance_mm)
    param = parameterise(bench, lens, load_tolerances(DEFAULT_TOLERANCES_FILE),
                         calibration_plan(StudyConfig(n_poses=24)))
    print(f"theta: {param.k} directions")
    cfg = StudyConfig()
    span = np.r_[cfg.pose_span_mm, np.radians(cfg.pose_span_deg)]
    cand = box_candidates(np.random.default_rng(0), span, 200)
    a.out.mkdir(parents=True, exist_ok=True)
    rows = {}
    for n in (24, 48, 96):
        rows[f"random {n}"] = row_of(predicted_joint_uncertainty(bench, param, scene,
                                                                 calibration_plan(StudyConfig(n_poses=n))))
    for n in (24, 96):
        d = design_joint_poses(bench, param, scene, n, cand, check_reach=True, max_passes=2)
        rows[f"designed {n}"] = row_of(d.chosen)
        (a.out / f"joint_design_{n}.json").write_text(json.dumps({"poses": d.x.tolist()}))
    if a.wide:
        rows.update(wide_rows(bench, lens, param, scene, a.out))
    print(f"{'plan':<40} {'Z 1s theta free':>22} {'Z 1s theta known':>22} {'ratio t / r':>12}")
    for name, w in rows.items():
        print(f"{name:<40} {w['Z_translation_mm']:9.4f} mm {w['Z_rotation_deg']:7.4f} deg "
              f"{w['Z_translation_known_lens_mm']:9.4f} mm {w['Z_rotation_known_lens_deg']:7.4f} deg "
              f"{w['ratio_translation']:5.2f} / {w['ratio_rotation']:4.2f}")


if __name__ == "__main__":
    main()
