"""First contact: `lensforge --help` and the first `lensforge evaluate zernike` after a fresh install.

Run: .venv/bin/python benchmarks/bench_first_run.py [--repo PATH]
Clones the repository (default: this checkout) into a temporary folder, so every
``__pycache__`` is empty (no bytecode, no numba cache), then times, as a user sees them:
  1. ``python -m lensforge --help``                          (goal <= 0.5 s)
  2. ``python -m lensforge evaluate zernike``, cold cache    (goal <= 10 s; compiles the kernels)
  3. the same command again, warm cache
Wall time and the child's CPU time (user + sys) are both printed: on a shared machine the
CPU time is the figure that does not depend on the load (compiling is single-threaded).
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def timed(cmd: list[str], cwd: Path, env: dict) -> tuple[float, float, str]:
    """(wall s, child CPU s, stderr) of one command."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        sys.exit(f"error: {' '.join(cmd)} failed:\n{p.stderr}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, p.stderr


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repo", default=str(Path(__file__).resolve().parents[1]), help="git repository to clone")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="lensforge-first-run-"))
    try:
        clone = tmp / "clone"
        subprocess.run(["git", "clone", "-q", args.repo, str(clone)], check=True)
        env = {**os.environ, "PYTHONPATH": str(clone), "PYTHONDONTWRITEBYTECODE": "",
               "NUMBA_CACHE_DIR": str(tmp / "numba-cache")}  # empty cache, never the user's
        py = [sys.executable, "-m", "lensforge"]
        print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
        for label, cmd in (("--help", py + ["--help"]),
                           ("evaluate zernike (cold cache)", py + ["evaluate", "zernike"]),
                           ("evaluate zernike (warm cache)", py + ["evaluate", "zernike"]),
                           ("--help (warm)", py + ["--help"])):
            wall, cpu, err = timed(cmd, clone, env)
            note = next((ln.strip() for ln in err.splitlines() if ln.startswith("compiling")), "")
            print(f"{label:<32} wall {wall:6.2f} s   cpu {cpu:6.2f} s   {note}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
