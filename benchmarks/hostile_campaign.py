"""Hostile-input campaign (issue 12): try every command the way a clumsy or hostile user
would, and count the outcomes.

    PYTHONPATH=$PWD python benchmarks/hostile_campaign.py [--random N] [--signals N] [--seed S]

Outcomes: success; clean exit 2 (one ``error:`` line); traceback (an exception escaped,
or "Traceback" on stderr, or an exit status other than 0 / 2, or 1 outside export);
accepted nonsense (exit 0 on an input that is known to be wrong); clean Ctrl-C (exit
130, last and only error line ``error: interrupted``, no traceback, within 2 s);
slow Ctrl-C (clean, but later than 2 s); unclean Ctrl-C. Parts: A random options, B
named nonsense files through every command that reads them, C output targets (under a
file, onto a folder, read-only and full tmpfs when root), D SIGINT at random moments
and SIGKILL + resume. Writes JSON counts to stdout, details of bad attempts to stderr.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import random
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

sys.path.insert(0, str(ROOT / "tests"))

from hostile import base_args, cli, command_options, poses_file  # noqa: E402  (the suite's helpers)
from lensforge.optics.bench import Bench  # noqa: E402
from lensforge.optics.lens import paper_lens  # noqa: E402

VALUES = ["-1", "0", "1", "2", "nan", "inf", "-inf", "1e9", "1e300", "-1e300", "1e-300", "abc", "", " ", "1.0",
          "9" * 30, "/nonexistent/dir/x", ".", "/", "\u00e9", "paper:nope", "1,2,3", "a=1:2", "x" * 300, "-0",
          "0x10", "1_000", "true", "None"]
counts = collections.Counter()
bad = []


def run(args, cwd) -> tuple[str, int, str]:
    """Run in process (in cwd); an exception escaping main counts as a traceback."""
    old = os.getcwd()
    os.chdir(cwd)
    try:
        code, _, err = cli(*args)
    except BaseException as e:
        return "traceback", -1, f"{type(e).__name__}: {e}"
    finally:
        os.chdir(old)
    return classify(args, code, err), code, err


def classify(args, code, err) -> str:
    errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
    if "Traceback" in err:
        return "traceback"
    if code == 2 and len(errors) == 1 and err.rstrip().splitlines()[-1].startswith("error:"):
        return "clean exit 2"
    if code == 0 and not errors:
        return "success"
    if code == 1 and args and args[0] == "export" and not errors:
        return "success"  # exported, but the report says it is not printable
    return "traceback"  # any other exit: not the promised behaviour


def record(part, args, outcome, err, nonsense=False):
    if nonsense and outcome == "success":
        outcome = "accepted nonsense"
    counts[outcome] += 1
    counts[f"{part}: {outcome}"] += 1
    if outcome not in ("success", "clean exit 2", "clean Ctrl-C"):
        bad.append({"part": part, "args": [str(a) for a in args], "outcome": outcome, "stderr": err[-800:]})


def part_a(n, rnd: random.Random):
    cmds = ["evaluate", "compare", "design", "plot", "export", "estimate-study", "scenario", "handeye", "study"]
    for k in range(n):
        cmd = rnd.choice(cmds)
        name, is_flag = rnd.choice(command_options(cmd))
        value = rnd.choice(VALUES) if rnd.random() < 0.8 else str(rnd.randint(-10**6, 10**6))
        if name in ("--scheduler",) or (name == "--workers" and value.lstrip("-").isdigit() and int(value) > 0):
            continue  # cluster start-ups are part D's business
        with tempfile.TemporaryDirectory() as t:
            t = Path(t)
            args = [cmd, *base_args(cmd, t), *([name] if is_flag else [name, value])]
            outcome, code, err = run(args, t)
            record("A options", args, outcome, err)


def _write(p: Path, text):
    p.write_bytes(text if isinstance(text, bytes) else text.encode())
    return p


def part_b():
    design = {"schema_version": 1, "kind": "lensforge.design", "model": "zernike", "free": [], "parameters": {},
              "bounds": {}, "lens": paper_lens("zernike").to_dict(), "bench": Bench.default().to_dict()}
    benches = {"noise 0": "[noise]\nslope_sigma_urad = 0\n", "pitch 1e-6": "[sensor]\npitch_mm = 1e-6\n",
               "aperture 1e6": "[sensor]\naperture_mm = 1e6\n", "pitch 1e4": "[sensor]\npitch_mm = 1e4\n",
               "noise -1": "[noise]\nslope_sigma_urad = -1\n", "noise nan": "[noise]\nslope_sigma_urad = nan\n",
               "huge int": "[noise]\nslope_sigma_urad = 1" + "0" * 400 + "\n",
               "garbage": b"\xff\xfe\x00garbage", "truncated": "[sensor]\npitch_mm = ", "schema 2": "schema_version = 2\n"}
    designs = {f"schema {v!r}": {**design, "schema_version": v} for v in (2, 0, "1", 1.0, None, True)}
    designs["no schema"] = {k: v for k, v in design.items() if k != "schema_version"}
    designs["kind wrong"] = {**design, "kind": "lensforge.tolerances"}
    designs["no lens"] = {k: v for k, v in design.items() if k != "lens"}
    designs["thickness -1"] = {**design, "lens": {**design["lens"], "thickness": -1}}
    designs["thickness 1e300"] = {**design, "lens": {**design["lens"], "thickness": 1e300}}
    designs["noise 0 inside"] = {**design, "bench": {**design["bench"], "noise": {"slope_sigma_urad": 0}}}
    tols = {"thickness 50 mm": "[thickness]\nsigma_mm = 50\n", "polish 25 mm": "[polishing]\ndepth_mm = 25\n",
            "1e308": "[form]\nrms_mm = 1e308\n", "string number": "[index]\nsigma = \"0.001\"\n",
            "negative": "[thickness]\nsigma_mm = -0.1\n", "schema 2": "schema_version = 2\n",
            "unknown table": "[nope]\nx = 1\n"}
    poses = {"string 1.0": lambda d: d["A"][2][0].__setitem__(3, "1.0"),
             "1e300": lambda d: d["A"][2][0].__setitem__(3, 1e300),
             "bool": lambda d: d["B"][1][1].__setitem__(1, True),
             "not rotation": lambda d: d["A"][0][0].__setitem__(0, 2.0),
             "units m": lambda d: d.__setitem__("units", "m"), "two poses": lambda d: (d["A"].pop(), d["B"].pop(),
                                                                                   d["A"].pop(), d["B"].pop(),
                                                                                   d["A"].pop(), d["B"].pop(),
                                                                                   d["A"].pop(), d["B"].pop(),
                                                                                   d["A"].pop(), d["B"].pop(),
                                                                                   d["A"].pop(), d["B"].pop())}
    with tempfile.TemporaryDirectory() as t:
        t = Path(t)
        for name, text in benches.items():
            b = _write(t / "bench.toml", text)
            for args in (["evaluate", "spherical", "--bench", b], ["compare", "spherical", "--bench", b],
                         ["estimate-study", "spherical", "--trials", "2", "--bench", b, "-o", t / "o1"],
                         ["scenario", "spherical", "--runs", "1", "--bench", b, "-o", t / "o2"],
                         ["study", "spherical", "-n", "2", "--workers", "0", "--bench", b, "-o", t / "o3"],
                         ["budget", "spherical", "-n", "2", "--workers", "0", "--bench", b, "-o", t / "o4"],
                         ["design", "--max-evals", "12", "--bench", b, "-o", t / "d.json"]):
                outcome, _, err = run(args, t)
                record(f"B bench {name}", args, outcome, err, nonsense=True)
        bom = _write(t / "bom.toml", b"\xef\xbb\xbf[noise]\nslope_sigma_urad = 4.0\n")
        outcome, _, err = run(["evaluate", "spherical", "--bench", bom], t)
        record("B bench BOM (valid)", ["evaluate"], outcome, err)
        for name, doc in designs.items():
            d = _write(t / "design.json", json.dumps(doc))
            for args in (["evaluate", d], ["compare", d], ["plot", d, "-o", t / "p"],
                         ["export", d, "--stl", "--no-slicer", "-o", t / "e"],
                         ["estimate-study", d, "--trials", "2", "-o", t / "o1"],
                         ["scenario", d, "--runs", "1", "-o", t / "o2"],
                         ["study", d, "-n", "2", "--workers", "0", "-o", t / "o3"],
                         ["budget", d, "-n", "2", "--workers", "0", "-o", t / "o4"]):
                outcome, _, err = run(args, t)
                record(f"B design {name}", args, outcome, err, nonsense=True)
        for name, text in tols.items():
            tf = _write(t / "tol.toml", text)
            for args in (["study", "spherical", "-n", "2", "--workers", "0", "-t", tf, "-o", t / "o3"],
                         ["budget", "spherical", "-n", "2", "--workers", "0", "-t", tf, "-o", t / "o4"],
                         ["design", "--max-evals", "12", "--robust", tf, "-o", t / "d.json"]):
                outcome, _, err = run(args, t)
                record(f"B tolerances {name}", args, outcome, err, nonsense=True)
        for name, fn in poses.items():
            pf = poses_file(t / "poses.json", fn)
            outcome, _, err = run(["handeye", pf], t)
            record(f"B poses {name}", ["handeye", name], outcome, err, nonsense=True)


def _mount_tmpfs(path: Path, opts: str) -> bool:
    if os.geteuid() != 0:
        return False
    path.mkdir(parents=True, exist_ok=True)
    return subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(path)], capture_output=True).returncode == 0


def part_c():
    writers = [("design", ["--max-evals", "12", "--no-progress"], "d.json"), ("plot", ["spherical"], "plots"),
               ("estimate-study", ["spherical", "--trials", "2"], "est"), ("scenario", ["spherical", "--runs", "1"], "sc"),
               ("study", ["spherical", "-n", "2", "--workers", "0", "--no-progress"], "st"),
               ("budget", ["spherical", "-n", "2", "--workers", "0"], "bu"),
               ("export", ["spherical", "--stl", "--no-slicer"], "ex"), ("demo", ["--quick"], "demo")]
    with tempfile.TemporaryDirectory() as t:
        t = Path(t)
        f = _write(t / "file", "x")
        (t / "dir").mkdir()
        full, ro = t / "full", t / "ro"
        have_full = _mount_tmpfs(full, "size=64k")
        if have_full:
            _write(full / "filler", b"\0" * 56 * 1024)
        have_ro = _mount_tmpfs(ro, "size=1m,ro")
        try:
            for cmd, args, target in writers:
                cases = {"under a file": f / target, "onto a file" if not target.endswith(".json") else "onto a folder":
                         (f if not target.endswith(".json") else t / "dir")}
                if have_full:
                    cases["full disk"] = full / target
                if have_ro:
                    cases["read-only"] = ro / target
                for case, out in cases.items():
                    before = sorted(os.listdir(out.parent)) if out.parent.is_dir() else None
                    outcome, _, err = run([cmd, *args, "-o", out], t)
                    after = sorted(os.listdir(out.parent)) if out.parent.is_dir() else None
                    if outcome == "clean exit 2" and before != after:
                        outcome = "traceback"  # left something behind
                        err += f"\nleftovers: {before} -> {after}"
                    record(f"C output {case}", [cmd, case], outcome, err, nonsense=True)
        finally:
            for m in (full, ro):
                subprocess.run(["umount", "-l", str(m)], capture_output=True)


def _spawn(args, cwd):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "lensforge", *map(str, args)], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _mapped(pid, name):
    try:
        return name in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


def part_d(n, rnd: random.Random):
    cmds = [["export", "spherical", "--no-slicer", "-o", "ex"], ["study", "spherical", "-n", "300", "--workers", "0",
            "--no-progress", "-o", "st"], ["study", "spherical", "-n", "300", "--workers", "2", "--no-progress", "-o", "st"],
            ["design", "--max-evals", "2000", "-o", "d.json", "--no-progress"], ["estimate-study", "spherical",
            "--trials", "3000", "-o", "est"], ["scenario", "spherical", "--runs", "200", "-o", "sc"],
            ["plot", "zernike", "-o", "plots"], ["demo", "--quick", "-o", "demo"], ["evaluate", "spherical"]]
    for k in range(n):
        args = rnd.choice(cmds)
        with tempfile.TemporaryDirectory() as t:
            p = _spawn(args, t)
            t0 = time.monotonic()  # wait until the interpreter has started (numpy mapped), then a random delay
            while not _mapped(p.pid, "numpy") and p.poll() is None and time.monotonic() - t0 < 60:
                time.sleep(0.02)
            time.sleep(rnd.uniform(0.0, 12.0 if "workers" in args else 6.0))
            if p.poll() is not None:
                out, err = p.communicate()
                record("D SIGINT (finished first)", args, classify(args, p.returncode, err), err)
                continue
            ts = time.monotonic()
            p.send_signal(signal.SIGINT)
            try:
                out, err = p.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                p.kill()
                out, err = p.communicate()
            dt = time.monotonic() - ts
            errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
            clean = (p.returncode == 130 and "Traceback" not in err and errors == ["error: interrupted"]
                     and err.rstrip().splitlines()[-1] == "error: interrupted")
            outcome = ("clean Ctrl-C" if clean and dt <= 2.0 else "slow Ctrl-C" if clean else "unclean Ctrl-C")
            leftovers = [f for f in os.listdir(t) if f.startswith(".") and "lock" not in f]
            if leftovers:
                outcome, err = "unclean Ctrl-C", err + f"\nleftovers {leftovers}"
            record("D SIGINT", [*args, f"dt={dt:.2f}s"], outcome, err)
    # SIGKILL a serial study at random moments, then resume: the store must be consistent
    for k in range(max(2, n // 6)):
        with tempfile.TemporaryDirectory() as t:
            a = ["study", "spherical", "-n", "4", "--poses", "8", "--workers", "0", "--no-progress", "-o", "st"]
            p = _spawn(a, t)
            time.sleep(rnd.uniform(1.0, 8.0))
            p.kill()
            p.communicate()
            outcome, code, err = run([*a, "--resume"], Path(t))
            store = Path(t) / "st" / "store.sqlite"
            ok = outcome == "success" and store.exists()
            if ok:
                with sqlite3.connect(store) as c:
                    ok = (c.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
                          and c.execute("SELECT COUNT(*) FROM trials").fetchone()[0] == 4)
            elif outcome == "clean exit 2" and "already exists" not in err:
                ok = True  # killed before the store existed: resume says so in one line
            record("D SIGKILL + resume", a, "success" if ok else "traceback", err)


def main_() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--random", type=int, default=200)
    ap.add_argument("--signals", type=int, default=30)
    ap.add_argument("--seed", type=int, default=12)
    ap.add_argument("--parts", default="ABCD")
    a = ap.parse_args()
    rnd = random.Random(a.seed)
    t0 = time.time()
    if "A" in a.parts:
        part_a(a.random, rnd)
    if "B" in a.parts:
        part_b()
    if "C" in a.parts:
        part_c()
    if "D" in a.parts:
        part_d(a.signals, rnd)
    for b in bad:
        print(json.dumps(b), file=sys.stderr)
    total = {k: v for k, v in counts.items() if ":" not in k}
    print(json.dumps({"attempts": sum(total.values()), "outcomes": total,
                      "by_part": {k: v for k, v in sorted(counts.items()) if ":" in k},
                      "wall_s": round(time.time() - t0)}, indent=1))


if __name__ == "__main__":
    main_()
