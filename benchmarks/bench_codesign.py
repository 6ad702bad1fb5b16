"""Co-design benchmark (issue 22): the old bench against the co-designed bench.

    .venv/bin/python benchmarks/bench_codesign.py OLD.json NEW.json [--poses 24] [--out exports/bench_codesign]

OLD.json: a design on the paper's bench (``lensforge design --model zernike --seed 0 --bench paper``);
NEW.json: the co-designed default (``lensforge design --model zernike --seed 0``). For each: the
bench, single-pose CRLB (um, urad), the sensor range and largest lenslet slope at nominal and
over the plan, and ``lensforge plan -n POSES``'s predicted Z 1-sigma (RMS norms over the three
axes, um and mdeg) with the lens free and known, and their ratio. The plan is the one
``calibration.session.plan`` writes (joint Ds-optimal for Z, default tolerances). Writes a JSON
summary under --out; the table goes to stdout. The as-built study is ``lensforge study DESIGN
--lenses N --calibration joint`` (with ``-t`` a zero-tolerance file for the perfect lens).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import lensforge as lf  # noqa: E402
from lensforge.calibration.session import plan  # noqa: E402
from lensforge.design.bench_vars import bench_label  # noqa: E402
from lensforge.optics.shack_hartmann import ForwardModel  # noqa: E402


def figures(path: str, n: int) -> dict:
    d = lf.load_design(path)
    m = d.compute_metrics()
    std = np.sqrt(np.diag(m.crlb))
    model = ForwardModel(d.bench, d.lens)
    t0 = time.perf_counter()
    p = plan(path, n=n)
    t_plan = time.perf_counter() - t0
    res = model.evaluate(np.concatenate([np.zeros((1, 6)), p.x]), check_range=False)
    use = res.range_use.max(axis=1)
    slope = np.abs(res.slopes).max(axis=(1, 2)) * 1e3
    zs, zk = p.z_std, p.z_std_known_lens
    tr, rot = float(np.linalg.norm(zs[:3]) * 1e3), float(np.degrees(np.linalg.norm(zs[3:])) * 1e3)
    trk, rotk = float(np.linalg.norm(zk[:3]) * 1e3), float(np.degrees(np.linalg.norm(zk[3:])) * 1e3)
    return {"design": path, "bench": bench_label(d.bench),
            "crlb_um": (std[:3] * 1e3).tolist(), "crlb_urad": (std[3:] * 1e6).tolist(),
            "range_use_nominal": float(use[0]), "range_use_plan_max": float(use[1:].max()),
            "slope_mrad_nominal": float(slope[0]), "slope_mrad_plan_max": float(slope[1:].max()),
            "in_range_nominal_and_plan": bool(np.all(use <= 1.0)), "spot_assignment": d.bench.sensor.spot_assignment,
            "plan_Z_um": tr, "plan_Z_mdeg": rot, "plan_Z_known_um": trk, "plan_Z_known_mdeg": rotk,
            "ratio_translation": tr / trk, "ratio_rotation": rot / rotk, "plan_s": t_plan,
            "design_wall_s": d.wall_time_s}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("designs", nargs="+")
    ap.add_argument("--poses", type=int, default=24)
    ap.add_argument("--out", default="exports/bench_codesign")
    a = ap.parse_args()
    rows = [figures(p, a.poses) for p in a.designs]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(rows, indent=2))
    print("| design / bench | CRLB translation (um) | CRLB rotation (urad) | range use nominal / plan | "
          f"Z 1-sigma, plan -n {a.poses}, lens free | lens free / known |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {Path(r['design']).name}: {r['bench']} | {min(r['crlb_um']):.2g}-{max(r['crlb_um']):.2g} | "
              f"{min(r['crlb_urad']):.3g}-{max(r['crlb_urad']):.3g} | {r['range_use_nominal']:.2f} / "
              f"{r['range_use_plan_max']:.2f} ({r['spot_assignment']}) | {r['plan_Z_um']:.1f} um, "
              f"{r['plan_Z_mdeg']:.2f} mdeg | {r['ratio_translation']:.2f} / {r['ratio_rotation']:.2f} |")


if __name__ == "__main__":
    main()
