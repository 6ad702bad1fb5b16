"""Benchmark of the as-built study: wall time of N lenses x P poses, 1 vs 2 Dask workers.

    .venv/bin/python benchmarks/bench_study.py --lenses 1000 --poses 24 --workers 2
    .venv/bin/python benchmarks/bench_study.py --lenses 100 --compare 1,2     # throughput scaling
    .venv/bin/python benchmarks/bench_study.py --profile --lenses 5           # pyinstrument, in process

Each trial: sample an as-built lens, trace the 24 poses with it, add sensor and robot
noise, estimate all poses with the nominal model (full nonlinear least squares),
solve the hand-eye problem. Prints one JSON line per run (lenses/s, wall s).
"""

from __future__ import annotations

import argparse
import json
import os
import time


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--design", default="zernike")
    ap.add_argument("--lenses", type=int, default=1000)
    ap.add_argument("--poses", type=int, default=24)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--compare", default="", help="comma list of worker counts, e.g. 1,2")
    ap.add_argument("--tolerance-scale", type=float, default=1.0, help="scale of the default tolerances")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--profile", action="store_true")
    a = ap.parse_args()

    from lensforge.asbuilt.tolerances import Tolerances
    from lensforge.verification.budget import scaled_all
    from lensforge.verification.study import StudyConfig, verify

    tol = scaled_all(Tolerances(), a.tolerance_scale) if a.tolerance_scale != 1.0 else Tolerances()
    cfg = StudyConfig(n_poses=a.poses)
    if a.profile:
        from pyinstrument import Profiler

        verify(a.design, tol, 1, a.seed, config=cfg, workers=0, progress=False)  # JIT warm-up
        p = Profiler()
        p.start()
        verify(a.design, tol, a.lenses, a.seed, config=cfg, workers=0, progress=False)
        p.stop()
        print(p.output_text(unicode=False, show_all=False))
        return
    counts = [int(w) for w in a.compare.split(",")] if a.compare else [a.workers]
    for w in counts:
        t = time.perf_counter()
        r = verify(a.design, tol, a.lenses, a.seed, config=cfg, workers=w, progress=True)
        wall = time.perf_counter() - t
        print(json.dumps({"design": a.design, "lenses": a.lenses, "poses": a.poses, "workers": w,
                          "wall_s": round(wall, 2), "run_s": round(r.stats.wall_s, 2),
                          "lenses_per_s": round(a.lenses / wall, 3), "n_ok": r.summary["n_ok"],
                          "load_avg": os.getloadavg()[0], "cpus": os.cpu_count()}), flush=True)


if __name__ == "__main__":
    main()
