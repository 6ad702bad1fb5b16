"""S(p) wall time against numba's thread count, on an idle machine and with one core taken.

Run: .venv/bin/python benchmarks/bench_threads.py [--lens zernike] [--reps 60]

One S(p) (13 poses x ~113 lenslets x 4 aimed sub-aperture rays, each traced with its
derivatives, + the Zernike fit) is a ~2.5 ms job: on two threads the parallel kernels wait
at every region's end for the slower thread, and when another process holds a core that
thread is the one the OS has descheduled. Rows:

- ``default``: what the library does with nothing set (``LENSFORGE_NUM_THREADS`` unset);
- ``threads=n``: ``LENSFORGE_NUM_THREADS=n`` with numba's pool allowed n threads;
- ``serial``: the same kernels compiled with ``parallel=False`` (``prange`` runs as ``range``),
  swapped in for this row only: what a parallel kernel on one thread costs over a serial one;
- each idle and with a busy-loop process started beside it (``loaded``).

Medians and 90th percentiles over single calls (a best-of would hide the contention).
The machine's load average is printed: on a shared machine "idle" means "no busy loop of ours".
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import numpy as np


def _time_calls(fn, reps: int) -> np.ndarray:
    fn()
    out = np.empty(reps)
    for i in range(reps):
        t0 = time.perf_counter()
        fn()
        out[i] = time.perf_counter() - t0
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--lens", default="zernike")
    ap.add_argument("--reps", type=int, default=60)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--no-serial", action="store_true", help="skip the serial-kernel row (compiles two kernels)")
    args = ap.parse_args()

    import numba

    import lensforge as lf
    from lensforge.optics.sensitivity import sensitivity_from_model
    from lensforge.optics.shack_hartmann import ForwardModel

    bench = lf.Bench.default()
    model = ForwardModel(bench, lf.paper_lens(args.lens))
    job = lambda: sensitivity_from_model(model)
    n_max = numba.config.NUMBA_NUM_THREADS
    print(f"numba pool: {n_max} threads, layer {numba.config.THREADING_LAYER}; cores {os.cpu_count()}; "
          f"load average {os.getloadavg()[0]:.2f}")
    import numba as nb

    from lensforge.optics import trace

    parallel_kernels = {"_trace_grid": trace._trace_grid, "_aim": trace._aim}
    serial_kernels = {} if args.no_serial else {
        k: nb.njit(cache=False, parallel=False, fastmath=v.targetoptions.get("fastmath", False))(v.py_func)
        for k, v in parallel_kernels.items()}
    configs = [("default", None)] + [(f"threads={n}", n) for n in args.threads if n <= n_max]
    if serial_kernels:
        configs.append(("serial", "serial"))
    for load in ("idle", "loaded"):
        hog = None
        if load == "loaded":
            hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
            time.sleep(0.5)
        try:
            for name, n in configs:
                os.environ.pop("LENSFORGE_NUM_THREADS", None)
                numba.set_num_threads(n_max)
                if isinstance(n, int):
                    os.environ["LENSFORGE_NUM_THREADS"] = str(n)
                    numba.set_num_threads(n)
                for k, v in (serial_kernels if n == "serial" else parallel_kernels).items():
                    setattr(trace, k, v)
                try:
                    t = _time_calls(job, args.reps) * 1e3
                finally:
                    for k, v in parallel_kernels.items():
                        setattr(trace, k, v)
                print(f"{load:6s} {name:10s} S(p) median {np.median(t):7.2f} ms  p90 {np.percentile(t, 90):7.2f} ms  "
                      f"min {t.min():6.2f} ms")
        finally:
            if hog is not None:
                hog.kill()
                hog.wait()
    print(f"threading layer used: {numba.threading_layer()}; load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
