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
and SIGKILL + resume, E the robot-side inputs (plan, simulate-session, calibrate,
estimate: spoiled WFS and robot-pose CSVs, robot TOMLs, BOMs), F issue 23's cases, each in
its own process with its wall time and peak memory (wait4): the usual convention mistakes
on an as-built session through `calibrate` (joint, the default) and `estimate` (exit 3 with the
likely mistake named, or exit 2 refusing the file and naming it), /dev/zero for every input
option, memory and time bombs (poses, rows, coefficients, trials), implausible values (reach,
repeatability, header vs bench, all-zero WFS, degenerate plans, handeye --noise), overwrites,
and SIGTERM at random moments (exit 143, ``error: terminated``, nothing left behind). A run
over 60 s of CPU or 1 GB on bad input counts as "slow or big". Writes JSON counts to stdout, details
of bad attempts to stderr.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import random
import resource
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

from hostile import base_args, cli, command_options, mapped, poses_file  # noqa: E402  (the suite's helpers)
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
    if code == 3 and len(errors) == 1 and err.rstrip().splitlines()[-1].startswith("error: model check failed"):
        return "clean exit 3"
    if code == 0 and not errors:
        return "success"
    if code == 1 and args and args[0] == "export" and not errors:
        return "success"  # exported, but the report says it is not printable
    return "traceback"  # any other exit: not the promised behaviour


def record(part, args, outcome, err, nonsense=False):
    """nonsense: True (the input is wrong: success is accepted nonsense), or a string that a
    success must print (the command accepted the rest of the input and said what it dropped)."""
    if outcome == "success" and (nonsense is True or (isinstance(nonsense, str) and nonsense not in err)):
        outcome = "accepted nonsense"
    counts[outcome] += 1
    counts[f"{part}: {outcome}"] += 1
    if outcome not in ("success", "clean exit 2", "clean Ctrl-C", "clean exit 3", "clean SIGTERM"):
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


def _csv_edit(text: str, fn) -> str:
    """Apply fn(rows) to the data rows of a lensforge CSV (comment lines kept as they are)."""
    lines = text.splitlines()
    head = [ln for ln in lines if ln.startswith("#")]
    rows = [ln.split(",") for ln in lines if not ln.startswith("#")]
    rows = fn(rows) or rows
    return "\n".join(head + [",".join(r) for r in rows]) + "\n"


def _set(r, c, v):
    def f(rows):
        rows[r][c] = v
    return f


def part_e():
    """The robot-side commands: plan, simulate-session, calibrate, estimate (and handeye's
    POSES file in part B) on a valid simulated session whose files are spoiled one way each."""
    lens = "extended_polynomial"
    with tempfile.TemporaryDirectory() as t:
        t = Path(t)
        outcome, _, err = run(["simulate-session", lens, "-n", "8", "--seed", "3", "-o", t / "sess"], t)
        record("E simulate-session (valid)", ["simulate-session"], outcome, err)
        if outcome != "success":
            return
        wfs0, rob0 = (t / "sess" / "wfs_zernike.csv").read_text(), (t / "sess" / "robot_poses.csv").read_text()
        wfs_bad = {
            "NaN entry": _csv_edit(wfs0, _set(1, 3, "nan")), "inf entry": _csv_edit(wfs0, _set(2, 4, "inf")),
            "text entry": _csv_edit(wfs0, _set(1, 2, "abc")), "1e300 entry": _csv_edit(wfs0, _set(1, 2, "1e300")),
            "3 modes": _csv_edit(wfs0, lambda rows: [r[:4] for r in rows]),
            "short row": _csv_edit(wfs0, lambda rows: rows[:2] + [rows[2][:5]] + rows[3:]),
            "ids mismatched": _csv_edit(wfs0, _set(1, 0, "99")),
            "ids duplicated": _csv_edit(wfs0, _set(2, 0, "1")),
            "wavelength 0": wfs0.replace("# wavelength_nm: 532.0", "# wavelength_nm: 0"),
            "wavelength in m": wfs0.replace("# wavelength_nm: 532.0", "# wavelength_nm: 5.32e-7"),
            "pupil radius 0": wfs0.replace("# pupil_radius_mm: 0.9", "# pupil_radius_mm: 0"),
            "pupil radius 1e9": wfs0.replace("# pupil_radius_mm: 0.9", "# pupil_radius_mm: 1e9"),
            "no rows": "\n".join(ln for ln in wfs0.splitlines() if ln.startswith("#") or ln.startswith("pose")),
            "truncated": wfs0[: len(wfs0) // 2], "garbage": wfs0[:300] + "\udcff\x00\x80" + wfs0[300:],
            "empty": "", "NUL": "\0" * 64,
        }
        rob_bad = {
            "NaN entry": _csv_edit(rob0, _set(1, 2, "nan")), "text entry": _csv_edit(rob0, _set(1, 1, "x")),
            "units m (values in mm)": rob0.replace("# units: mm", "# units: m"),
            "units furlong": rob0.replace("# units: mm", "# units: furlong"),
            "angles 1e6 deg": _csv_edit(rob0, _set(1, 4, "1e6")), "ids mismatched": _csv_edit(rob0, _set(3, 0, "77")),
            "one pose": _csv_edit(rob0, lambda rows: rows[:2]), "truncated": rob0[: len(rob0) // 3],
            "missing column": _csv_edit(rob0, lambda rows: [r[:6] for r in rows]),
            "garbage": rob0[:50] + "\udcff\x00" + rob0[50:],
        }
        boms = {"wfs CSV BOM (valid)": ("wfs", "\ufeff" + wfs0), "robot poses CSV BOM (valid)": ("rob", "\ufeff" + rob0)}

        def write(name, text):
            return _write(t / name, text.encode("utf-8", "surrogateescape"))

        def calibrate(w, r):
            return ["calibrate", lens, "-m", w, "-r", r, "--method", "two-stage", "--no-progress", "-o", t / "cal"]

        w_ok, r_ok = t / "sess" / "wfs_zernike.csv", t / "sess" / "robot_poses.csv"
        # unmatched ids are dropped and reported ("rejected pose ID: no ... in FILE"), by design
        said = {"ids mismatched": "rejected pose 99"}
        for name, text in wfs_bad.items():
            w = write("w.csv", text)
            for args in (calibrate(w, r_ok), ["estimate", lens, "-m", w, "--pose", "1"]):
                outcome, _, err = run(args, t)
                record(f"E wfs {name}", args, outcome, err, nonsense=said.get(name, True))
        said = {"ids mismatched": "rejected pose 77"}
        for name, text in rob_bad.items():
            r = write("r.csv", text)
            outcome, _, err = run(calibrate(w_ok, r), t)
            record(f"E robot poses {name}", ["calibrate", name], outcome, err, nonsense=said.get(name, True))
        for name, (which, text) in boms.items():
            f = write("bom.csv", text)
            args = calibrate(f, r_ok) if which == "wfs" else calibrate(w_ok, f)
            outcome, _, err = run(args, t)
            record(f"E {name}", ["calibrate", name], outcome, err)
        robot = (ROOT / "lensforge" / "calibration" / "robots" / "kr10_r1100_sixx.toml").read_text()
        robots = {"reach -1": robot.replace("reach_mm = 1101.0", "reach_mm = -1"),
                  "repeatability 0": robot.replace("repeatability_mm = 0.02", "repeatability_mm = 0"),
                  "axis zero": robot.replace("axis = [0.0, 0.0, -1.0]", "axis = [0.0, 0.0, 0.0]", 1),
                  "limits reversed": robot.replace("limits_deg = [-170.0, 170.0]", "limits_deg = [170.0, -170.0]"),
                  "origin NaN": robot.replace("origin_mm = [0.0, 0.0, 400.0]", "origin_mm = [nan, 0.0, 400.0]"),
                  "kinematics bogus": robot.replace('kinematics = "urdf"', 'kinematics = "magic"'),
                  "no joints": robot.split("[[joints]]")[0], "BOM (valid)": "\ufeff" + robot,
                  "truncated": robot[: len(robot) // 2]}
        for name, text in robots.items():
            rb = write("robot.toml", text)
            nonsense = "valid" not in name
            for args in (["plan", lens, "--robot", rb, "-n", "8", "-o", t / "plan"],
                         ["simulate-session", lens, "--robot", rb, "-n", "8", "-o", t / "s2"]):
                outcome, _, err = run(args, t)
                record(f"E robot {name}", args, outcome, err, nonsense=nonsense)
                for d in ("plan", "s2"):
                    subprocess.run(["rm", "-rf", str(t / d)])
        for opt, vals in (("-n", ["0", "2", "-3", "100000"]), ("--seed", ["-1", "1e3"])):
            for v in vals:
                for cmd in ("plan", "simulate-session"):
                    args = [cmd, lens, opt, v, "-o", t / f"o-{cmd}-{v}"]
                    outcome, _, err = run(args, t)
                    record(f"E {cmd} {opt} {v}", args, outcome, err)


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
            while not mapped(p.pid, "numpy") and p.poll() is None and time.monotonic() - t0 < 60:
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


# ----------------------------------------------------------------------------- part F (issue 23)

MAX_S, MAX_BYTES = 60.0, 1e9  # "0 runs over a minute or a GB on bad input"


def run_sub(args, cwd, timeout=600):
    """Run ``python -m lensforge ARGS`` in its own process: (outcome, code, stderr, CPU s, peak bytes).
    The time is the process tree's CPU time (user + system, from wait4 via RUSAGE_CHILDREN):
    on a machine shared with other jobs the wall time measures the load, not the command."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    p = _spawn(args, cwd)
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.kill()
        out, err = p.communicate()
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    dt = (r1.ru_utime + r1.ru_stime) - (r0.ru_utime + r0.ru_stime)
    peak = r1.ru_maxrss * 1024.0  # the largest child so far
    return classify(args, p.returncode, err), p.returncode, err, dt, peak


_PEAK = [0.0]


def record_f(name, args, cwd, expect, words=(), timeout=600):
    """expect: "refused" (exit 2), "failed check" (exit 3), "refused or failed" (2 or 3), "ok" (exit 0);
    words: what the error line must say (else: misleading message)."""
    outcome, code, err, dt, peak = run_sub(args, cwd, timeout)
    grew = peak > _PEAK[0] + 1.0
    _PEAK[0] = max(_PEAK[0], peak)
    line = next((ln for ln in reversed(err.splitlines()) if ln.startswith("error:")), "")
    ok_codes = {"refused": (2,), "failed check": (3,), "refused or failed": (2, 3), "ok": (0,)}[expect]
    if outcome in ("clean exit 2", "clean exit 3") and code in ok_codes and not all(w in line for w in words):
        outcome = "misleading message"
    elif outcome == "success" and expect != "ok":
        outcome = "accepted nonsense"
    elif outcome in ("clean exit 2", "clean exit 3") and code not in ok_codes:
        outcome = "misleading message"
    if expect != "ok" and (dt > MAX_S or (grew and peak > MAX_BYTES)):
        outcome = "slow or big"
    counts[outcome] += 1
    counts[f"F {name}: {outcome}"] += 1
    timing = f"{dt:.1f} s CPU" + (f", peak {peak / 1e9:.2f} GB" if grew else "")
    print(json.dumps({"F": name, "outcome": outcome, "code": code, "time": timing, "line": line[:300]}),
          file=sys.stderr, flush=True)
    if outcome not in ("success", "clean exit 2", "clean exit 3"):
        bad.append({"part": f"F {name}", "args": [str(a) for a in args], "outcome": outcome, "time": timing,
                    "stderr": err[-800:]})


def _shift(dx, dy, dz):
    import numpy as np

    T = np.eye(4)
    T[:3, 3] = dx, dy, dz
    return T


def part_f(rnd: random.Random, n_signals: int = 8):
    import numpy as np

    from lensforge.calibration import formats
    from lensforge.optics.zernike import noll_to_thorlabs

    lens = "extended_polynomial"
    with tempfile.TemporaryDirectory() as t:
        t = Path(t)
        # an as-built session (default tolerances): the joint default method passes on it
        outcome, code, err, dt, _ = run_sub(["simulate-session", lens, "--seed", "5", "-o", t / "sess"], t)
        record("F simulate-session (valid)", ["simulate-session"], outcome, err)
        if outcome != "success":
            return
        w_ok, r_ok = t / "sess" / "wfs_zernike.csv", t / "sess" / "robot_poses.csv"
        poses, wfs = formats.read_robot_poses(r_ok), formats.read_wfs(w_ok)
        ids, T, z, hdr = poses.ids, poses.T, wfs.zernike, dict(wfs.header)

        def cal(w=w_ok, r=r_ok, design=lens, *extra):
            return ["calibrate", design, "-m", w, "-r", r, "--no-progress", "-o", t / "cal", *extra]

        def wfile(name, zz, h=None):
            return _write(t / name, formats.wfs_csv(wfs.ids, zz, hdr if h is None else h))

        record_f("calibrate as given (valid)", cal(), t, "ok")
        Tm = T.copy()
        Tm[:, :3, 3] /= 1000.0
        xyz = np.array([formats.matrix_to_xyzabc(a) for a in T])
        q = formats.matrix_to_quaternion(T)
        zn = np.zeros_like(z)
        for k in range(1, z.shape[1] + 1):
            zn[:, k - 1] = z[:, noll_to_thorlabs(k) - 1]
        mistakes = {
            "quaternion mm under units m": (cal(r=_write(t / "r1.csv", formats.quaternion_csv(ids, T).replace(
                "# units: mm", "# units: m"))), "refused", ("reach", "# units: m")),
            # robot-file mistakes put the lens far from the nominal cell's sensor: refused before fitting
            # (cell_plausibility), the re-read named; a fit that ran anyway fails its check naming it
            "metres under units mm": (cal(r=_write(t / "r2.csv", formats.quaternion_csv(ids, Tm))),
                                      "refused or failed", ("read in m",)),
            "ABC in radians": (cal(r=_write(t / "r3.csv", "pose,X,Y,Z,A,B,C\n" + "\n".join(
                ",".join([i] + [f"{v:.6f}" for v in r[:3]] + [f"{v:.9f}" for v in np.radians(r[3:])])
                for i, r in zip(ids, xyz)) + "\n")), "refused or failed", ("radians",)),
            "quaternion xyzw": (cal(r=_write(t / "r4.csv", "# units: mm\npose,x,y,z,qw,qx,qy,qz\n" + "\n".join(
                ",".join([i] + [f"{v:.6f}" for v in a[:3, 3]] + [f"{v:.10f}" for v in qq[[1, 2, 3, 0]]])
                for i, a, qq in zip(ids, T, q)) + "\n")), "refused or failed", ("x, y, z, w",)),
            "one pose 200 mm off": (cal(r=_write(t / "r6.csv", formats.quaternion_csv(ids, np.concatenate(
                [T[:1] @ _shift(0, 0, 200.0), T[1:]])))), "refused", ("pose " + ids[0], "re-record")),
            "poses in another base frame": (cal(r=_write(t / "r7.csv", formats.quaternion_csv(ids, _shift(
                0, 200.0, 0)[None] @ T))), "refused", ("base frame", "[cell]")),
            "WFS in Noll order": (cal(w=wfile("w1.csv", zn)), "failed check", ("Noll order",)),
            "WFS in waves": (cal(w=wfile("w2.csv", z / 0.532)), "failed check", ("waves",)),
            "WFS signs flipped": (cal(w=wfile("w3.csv", -z)), "failed check", ("signs",)),
            "wrong design": (cal(design="zernike"), "refused or failed", ()),
            "all-zero WFS": (cal(w=wfile("w4.csv", 0 * z)), "refused", ("every coefficient is 0",)),
            "constant WFS": (cal(w=wfile("w5.csv", np.repeat(z[:1], len(z), 0))), "refused", ("same coefficients",)),
            "pupil 0.8 vs 0.9 mm": (cal(w=wfile("w6.csv", z, {**hdr, "pupil_radius_mm": 0.8})), "refused",
                                    ("0.8", "0.9", "--wfs-header")),
            "633 vs 532 nm": (cal(w=wfile("w7.csv", z, {**hdr, "wavelength_nm": 633.0})), "refused", ("633", "532")),
            "KUKA poses with --robot ur5e": (cal() + ["--robot", "ur5e"], "refused", ("reach",)),
            "poses at 1 km": (cal(r=_write(t / "r5.csv", formats.xyzabc_csv(ids, T * np.array(
                [[1, 1, 1, 1e6], [1, 1, 1, 1e6], [1, 1, 1, 1e6], [1, 1, 1, 1]])))), "refused", ("reach",)),
            "estimate: WFS in Noll order": (["estimate", lens, "-m", t / "w1.csv", "--pose", wfs.ids[0]],
                                            "refused or failed", ()),
            "estimate: wrong design": (["estimate", "polynomial", "-m", w_ok, "--pose", wfs.ids[0]],
                                       "refused or failed", ()),
        }
        for name, (args, expect, words) in mistakes.items():
            record_f(name, args, t, expect, words)
        # /dev/zero everywhere a file goes in
        Z0 = "/dev/zero"
        zero = {"evaluate": ["evaluate", Z0], "compare": ["compare", Z0], "plot": ["plot", Z0, "-o", t / "p"],
                "export": ["export", Z0, "--stl", "--no-slicer", "-o", t / "e"],
                "estimate-study": ["estimate-study", Z0, "--trials", "2", "-o", t / "es"],
                "estimate -m": ["estimate", lens, "-m", Z0], "calibrate -m": cal(w=Z0), "calibrate -r": cal(r=Z0),
                "calibrate -r json": cal(r=_symlink(t, Z0, "zero.json")), "handeye": ["handeye", Z0],
                "handeye --noise": ["handeye", ROOT / "examples" / "handeye_poses.json", "--noise", Z0],
                "study -t": ["study", lens, "-t", Z0, "-n", "2", "--workers", "0", "-o", t / "st"],
                "study --pose-plan": ["study", lens, "--pose-plan", Z0, "-n", "2", "--workers", "0", "-o", t / "st"],
                "budget -t": ["budget", lens, "-t", Z0, "-n", "2", "--workers", "0", "-o", t / "bu"],
                "evaluate --bench": ["evaluate", lens, "--bench", Z0],
                "plan --robot": ["plan", lens, "--robot", Z0, "-o", t / "pl"],
                "simulate-session -t": ["simulate-session", lens, "-t", Z0, "-o", t / "s0"],
                "design --bench": ["design", "--bench", Z0, "-o", t / "d.json"],
                "design --robust": ["design", "--robust", Z0, "-o", t / "d.json"]}
        for name, args in zero.items():  # the line names the file as given (the symlink for the JSON case)
            record_f(f"/dev/zero {name}", args, t, "refused", ("zero.json",) if "json" in name else ("/dev/zero",))
        # memory and time bombs
        big_rows = _write(t / "rows.csv", "pose,X,Y,Z,A,B,C\n" + "\n".join(f"{i},0,-500,1000,0,0,0"
                                                                          for i in range(100_000)) + "\n")
        big_design = _write(t / "bigdesign.json", json.dumps({
            "schema_version": 1, "kind": "lensforge.design", "model": "zernike", "free": [], "parameters": {},
            "bounds": {}, "lens": {**paper_lens("zernike").to_dict(),
                                   "front": {**paper_lens("zernike").to_dict()["front"],
                                             "coefficients": [0.0] * 1_000_000}},
            "bench": Bench.default().to_dict()}))
        plan_big = _write(t / "planbig.json", json.dumps({"poses": [[0, 0, 0, 0, 0, 0]] * 100_000}))
        bombs = {"study --poses 100000": (["study", lens, "--poses", "100000", "-n", "2", "--workers", "0", "-o",
                                           t / "st"], ("100000",)),
                 "budget --poses 100000": (["budget", lens, "--poses", "100000", "-n", "2", "--workers", "0", "-o",
                                            t / "bu"], ("100000",)),
                 "study --pose-plan 100000 poses": (["study", lens, "--pose-plan", plan_big, "-n", "2", "--workers",
                                                     "0", "-o", t / "st"], ("100000",)),
                 "calibrate 100000 rows": (cal(r=big_rows), ("100000",)),
                 "plan -n 100000": (["plan", lens, "-n", "100000", "-o", t / "pl"], ("100000",)),
                 "plan -n 1500": (["plan", lens, "-n", "1500", "-o", t / "pl"], ("1500", "3 .. 100")),
                 "study --poses 1500": (["study", lens, "--poses", "1500", "-n", "1", "--workers", "0", "-o",
                                         t / "st"], ("1500", "3 .. 100")),
                 "budget --poses 1500": (["budget", lens, "--poses", "1500", "-n", "1", "--workers", "0", "-o",
                                          t / "bu"], ("1500", "3 .. 100")),
                 "calibrate 1500 matched poses": (cal(w=_write(t / "w1500.csv", formats.wfs_csv(
                     [str(i) for i in range(1500)], np.repeat(z[:1], 1500, 0) + 1e-3 * np.arange(1500)[:, None],
                     hdr)), r=_write(t / "r1500.csv", formats.quaternion_csv(
                         tuple(str(i) for i in range(1500)), np.repeat(T[:1], 1500, 0)))), ("1500", "matched")),
                 "simulate-session -n 100000": (["simulate-session", lens, "-n", "100000", "-o", t / "s1"],
                                                ("100000",)),
                 "design with 1e6 coefficients: evaluate": (["evaluate", big_design], ("1000000",)),
                 "design with 1e6 coefficients: export": (["export", big_design, "--stl", "--no-slicer", "-o",
                                                           t / "e"], ("1000000",)),
                 "estimate-study --trials 1e7": (["estimate-study", lens, "--trials", "10000000", "-o", t / "es"],
                                                 ("10000000",)),
                 "study --lenses 1e7": (["study", lens, "-n", "10000000", "--workers", "0", "-o", t / "st"],
                                        ("10000000",))}
        for name, (args, words) in bombs.items():
            record_f(f"bomb {name}", args, t, "refused", words)
        # implausible values
        robot = (ROOT / "lensforge" / "calibration" / "robots" / "kr10_r1100_sixx.toml").read_text()
        rb = _write(t / "rep20.toml", robot.replace("repeatability_mm = 0.02", "repeatability_mm = 20.0"))
        record_f("robot repeatability 20 mm", cal() + ["--robot", rb], t, "refused", ("repeatability_mm",))
        record_f("plan with repeatability 20 mm", ["plan", lens, "--robot", rb, "-o", t / "pl"], t, "refused",
                 ("repeatability_mm",))
        for name, poses_ in (("8 identical poses", [[0.1, 0, 0, 0.01, 0, 0]] * 8),
                             ("one rotation axis", [[0.1 * i, 0, 0, 0.01 * i, 0, 0] for i in range(8)])):
            f = _write(t / "plan.json", json.dumps({"poses": poses_}))
            record_f(f"degenerate plan: {name}", ["study", lens, "--pose-plan", f, "-n", "2", "--workers", "0", "-o",
                                                  t / "st"], t, "refused", ("degenerate pose plan", "unobservable"))
        ex = json.loads((ROOT / "examples" / "handeye_poses.json").read_text())
        bare = {k: v for k, v in ex.items() if k not in ("noise", "cov_A", "cov_B", "sigma_A", "sigma_B")}
        pf = _write(t / "he.json", json.dumps(bare))
        for name, noise, expect, words in (
                ("flat keys (the --help format)", {"robot_sigma_trans_mm": 0.02, "robot_sigma_rot_deg": 0.001,
                                                   "lens_sigma_trans_mm": 0.002, "lens_sigma_rot_deg": 0.01},
                 "refused or failed", ()),
                ("negative sigma", {"robot_sigma_trans_mm": -0.02}, "refused", ("robot_sigma_trans_mm",)),
                ("sigma 1 km", {"robot_sigma_trans_mm": 1e6}, "refused", ("robot_sigma_trans_mm",)),
                ("unknown key", {"robot_sigma": 0.02}, "refused", ("unknown key",)),
                ("all zero", {"robot_sigma_trans_mm": 0.0}, "refused", ("no noise",))):
            nf = _write(t / "noise.json", json.dumps(noise))
            if expect == "refused or failed":  # valid: used as given (exit 0, or 3 if the data misfit it)
                outcome, code, err, dt, _ = run_sub(["handeye", pf, "--noise", nf], t)
                ok = code in (0, 3) and "noise model given" in err and "Traceback" not in err
                record("F handeye --noise " + name, ["handeye"], "success" if ok else "accepted nonsense", err)
            else:
                record_f(f"handeye --noise {name}", ["handeye", pf, "--noise", nf], t, expect, words)
        # overwrite protection and temp paths
        record_f("simulate-session over a session", ["simulate-session", lens, "-o", t / "sess"], t, "refused",
                 ("--force",))
        record_f("simulate-session --force", ["simulate-session", lens, "-n", "6", "-o", t / "sess2", "--force"], t,
                 "ok")
        # SIGTERM at random moments: exit 143, "error: terminated", nothing left behind
        cmds = [["study", lens, "-n", "50", "--poses", "8", "--workers", "0", "--no-progress", "-o", "st"],
                ["export", lens, "--no-slicer", "-o", "ex"], ["estimate-study", lens, "--trials", "500", "-o", "es"],
                ["simulate-session", lens, "-o", "ss"], cal(r=r_ok)[:-2] + ["-o", "calt"]]
        for k in range(n_signals):
            args = rnd.choice(cmds)
            with tempfile.TemporaryDirectory() as d:
                p = _spawn(args, d)
                t0 = time.monotonic()
                while not mapped(p.pid, "numpy") and p.poll() is None and time.monotonic() - t0 < 60:
                    time.sleep(0.02)
                time.sleep(rnd.uniform(0.0, 8.0))
                if p.poll() is not None:
                    out, err = p.communicate()
                    record("F SIGTERM (finished first)", args, classify(args, p.returncode, err), err)
                    continue
                ts = time.monotonic()
                p.send_signal(signal.SIGTERM)
                try:
                    out, err = p.communicate(timeout=60)
                except subprocess.TimeoutExpired:
                    p.kill()
                    out, err = p.communicate()
                dt = time.monotonic() - ts
                errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
                clean = p.returncode == 143 and "Traceback" not in err and errors == ["error: terminated"]
                left = [f for f in os.listdir(d) if f.startswith(".")]
                half = [f for f in os.listdir(d) if not f.startswith(".") and f not in ("st",)]
                outcome = "clean SIGTERM" if clean and dt <= 2.0 and not left and not half else "unclean SIGTERM"
                record("F SIGTERM", [*args, f"dt={dt:.2f}s", f"left={left + half}"], outcome, err)


def _symlink(t: Path, target: str, name: str) -> Path:
    p = t / name
    if not p.exists():
        os.symlink(target, p)
    return p


def main_() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--random", type=int, default=200)
    ap.add_argument("--signals", type=int, default=30)
    ap.add_argument("--seed", type=int, default=12)
    ap.add_argument("--parts", default="FEBCAD", help="parts to run, in this order")
    a = ap.parse_args()
    rnd = random.Random(a.seed)
    t0 = time.time()
    parts = {"A": lambda: part_a(a.random, rnd), "B": part_b, "C": part_c, "D": lambda: part_d(a.signals, rnd),
             "E": part_e, "F": lambda: part_f(rnd, max(4, a.signals // 3))}
    for name in a.parts:
        if name in parts:
            parts[name]()
            # the counts so far, one line per part: a campaign stopped by a timeout keeps them
            print(json.dumps({"after_part": name, "outcomes": _totals()}), file=sys.stderr, flush=True)
    for b in bad:
        print(json.dumps(b), file=sys.stderr)
    total = _totals()
    print(json.dumps({"attempts": sum(total.values()), "outcomes": total,
                      "by_part": {k: v for k, v in sorted(counts.items()) if ":" in k},
                      "wall_s": round(time.time() - t0)}, indent=1))


def _totals() -> dict:
    return {k: v for k, v in counts.items() if ":" not in k}


if __name__ == "__main__":
    main_()
