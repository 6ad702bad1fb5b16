"""Optics hot-path benchmark: trace throughput and one sensitivity matrix S(p).

Run: .venv/bin/python benchmarks/bench_optics.py
Prints rays/s for ~800 and ~10,000 rays (13 poses batched, as S(p) does) and the
wall time of one S(p) (13 poses x ~113 lenslets x 4 aimed sub-aperture rays + fit) per paper lens.
"""

from __future__ import annotations

import time

import numpy as np

import lensforge as lf
from lensforge.optics.sensitivity import sensitivity_from_model
from lensforge.optics.shack_hartmann import ForwardModel
from lensforge.optics.trace import lens_kernel, trace_rays


def best_of(fn, repeat=7, number=5):
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - t0) / number)
    return best


def main():
    import numba

    bench = lf.Bench.default()
    print(f"numba threads: {numba.get_num_threads()}")
    for name in ["spherical", "zernike", "polynomial"]:
        lens = lf.paper_lens(name)
        kern = lens_kernel(lens, bench.laser.wavelength_nm)
        poses = np.zeros((13, 6))
        for n_rays in (800, 10_000):
            side = int(np.ceil(np.sqrt(n_rays / 13 if n_rays == 10_000 else n_rays)))
            g = np.linspace(-1.7, 1.7, side)
            uv = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
            P = poses if n_rays == 10_000 else poses[:1]
            trace_rays(bench, lens, P, uv, kernel=kern)  # warm-up / compile
            t = best_of(lambda: trace_rays(bench, lens, P, uv, kernel=kern))
            n = uv.shape[0] * P.shape[0]
            print(f"{name:20s} trace {n:6d} rays: {t * 1e3:7.3f} ms  {n / t / 1e6:6.2f} M rays/s")
        model = ForwardModel(bench, lens)
        sensitivity_from_model(model)
        t = best_of(lambda: sensitivity_from_model(model), repeat=5, number=10)
        print(f"{name:20s} S(p): {t * 1e3:7.3f} ms  (exact: {model.pupil.n_lenslets} lenslets x {model.quad_weights.size} "
              f"aimed rays, each traced 5x with its derivatives)")
        t = best_of(lambda: lf.metrics(bench, lens), repeat=3, number=5)
        print(f"{name:20s} metrics (S + SVD + CRLB, from scratch): {t * 1e3:7.3f} ms")


if __name__ == "__main__":
    main()
