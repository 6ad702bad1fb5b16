"""Solve time of solve_handeye per method for 12 and 24 poses (paper scene, noisy data).

Run: .venv/bin/python benchmarks/bench_handeye.py [--repeats 50]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from lensforge.calibration.handeye import METHODS, solve_handeye
from lensforge.calibration.robot import paper_scene, random_lens_poses, simulate_calibration

COV_B = np.diag([1e-3] * 3 + [1e-5] * 3) ** 2  # ASSUMPTION: ~pose-estimation CRLB


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=50)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    scene = paper_scene()
    print(f"{'poses':>5} {'method':>6} {'ms/solve':>9} {'Z err (um)':>11}")
    for n in (12, 24):
        x = random_lens_poses(rng, n, 1.0, math.radians(1.0))
        data = [simulate_calibration(scene, x, rng, cov_B=COV_B, check_reach=False) for _ in range(args.repeats)]
        for m in METHODS:
            solve_handeye(data[0].A, data[0].B, m, sigma=scene.noise, cov_B=COV_B)  # warm-up
            t0 = time.perf_counter()
            errs = []
            for d in data:
                r = solve_handeye(d.A, d.B, m, sigma=scene.noise, cov_B=COV_B)
                errs.append(np.linalg.norm(r.Z[:3, 3] - scene.Z[:3, 3]))
            dt = (time.perf_counter() - t0) / len(data)
            print(f"{n:>5} {m:>6} {dt * 1e3:>9.2f} {np.sqrt(np.mean(np.square(errs))) * 1e3:>11.1f}")


if __name__ == "__main__":
    main()
