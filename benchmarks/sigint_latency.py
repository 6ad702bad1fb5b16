"""Ctrl-C latency of ``lensforge export`` during start-up (heavy imports: numpy ... OCP).

Sends SIGINT at fixed delays after the start, several tries each, and reports the time
from the signal to the process's exit, the exit status, whether stderr is exactly
``error: interrupted`` (no traceback) and whether any output appeared.
``--to group`` mimics a terminal (the whole process group gets the signal);
``--to pid`` signals the ``lensforge`` process only (``kill -INT PID``).

    PYTHONPATH=$PWD python benchmarks/sigint_latency.py --tries 5 --to group
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def one(delay: float, to: str, cmd: list[str]) -> dict:
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "ex"
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        p = subprocess.Popen([sys.executable, "-m", "lensforge", *cmd, "-o", str(out)], cwd=d, env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
        time.sleep(delay)
        t0 = time.monotonic()
        if p.poll() is None:
            (os.killpg(p.pid, signal.SIGINT) if to == "group" else p.send_signal(signal.SIGINT))
        _, err = p.communicate(timeout=120)
        dt = time.monotonic() - t0
        left = sorted(os.listdir(d))
        try:
            os.killpg(p.pid, signal.SIGKILL)  # nothing may survive; this only cleans up a failure
            stray = True
        except ProcessLookupError:
            stray = False
    clean = p.returncode == 130 and err.strip() == "error: interrupted"
    return {"delay": delay, "latency_s": dt, "rc": p.returncode, "clean": clean, "outputs": left, "stray": stray,
            "err": err.strip()[-300:]}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tries", type=int, default=5)
    ap.add_argument("--to", choices=["group", "pid"], default="group")
    ap.add_argument("--delays", default="0.2,0.5,1,1.5,2,3")
    a = ap.parse_args()
    cmd = ["export", "spherical", "--no-slicer", "--no-progress"]
    rows = []
    for delay in [float(x) for x in a.delays.split(",")]:
        for _ in range(a.tries):
            r = one(delay, a.to, cmd)
            rows.append(r)
            flag = "" if r["clean"] and not r["outputs"] and not r["stray"] else f"  <-- {r}"
            print(f"t={delay:4.1f}s  latency {r['latency_s']:.2f}s  rc={r['rc']}{flag}", flush=True)
    bad = [r for r in rows if not r["clean"] or r["outputs"] or r["stray"]]
    print(f"signal to {a.to}: {len(rows)} tries, max latency {max(r['latency_s'] for r in rows):.2f} s, "
          f"{len(rows) - len(bad)} clean (exactly 'error: interrupted', exit 130, no output, no stray process), "
          f"{len(bad)} not")


if __name__ == "__main__":
    main()
