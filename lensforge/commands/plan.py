"""``lensforge plan``: the robot's calibration poses (a thin layer over ``calibration.session.plan``).

Outputs are written as one folder, all or none (``calibration.formats.write_bundle``). ``--robot`` is
the robot MODEL (a built-in name or a robot TOML)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

from ..errors import ConfigError
from ..fileio import check_output
from ..progress import progress_bar
from ._common import ROBOT_HELP, bench_arg, check_seed, emit_json, info

def plan_cmd(
    design: str = typer.Argument(..., help="design JSON (or a paper lens name)"),
    robot: Optional[str] = typer.Option(None, "--robot", help=ROBOT_HELP),
    n: int = typer.Option(12, "-n", "--poses", help="number of calibration poses"),
    seed: int = typer.Option(0, "--seed", help="seed of the candidate poses"),
    tolerances: str = typer.Option("default", "-t", "--tolerances",
                                   help="tolerance TOML of the as-built lens prior the design plans for "
                                        "('default': the package's file; 'none': the lens as designed)"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML (default: the design's)"),
    box_mm: Optional[float] = typer.Option(None, "--box-mm", help="half-width of the box of lens poses about "
                                           "nominal, translation (mm; default: the box the design was checked "
                                           "over, its --plan-mm; paper lenses +-0.5)"),
    box_deg: Optional[float] = typer.Option(None, "--box-deg", help="half-width of the box, rotation (deg; "
                                            "default: the design's --plan-deg; paper lenses +-5)"),
    formats_: str = typer.Option("auto", "--formats",
                                 help="comma list of calibration.formats.PLAN_WRITERS names; auto = csv,json (+krl for a KUKA)"),
    out: Path = typer.Option(Path("exports/plan"), "-o", "--out", help="output folder"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable summary on stdout"),
    no_progress: bool = typer.Option(False, "--no-progress", help="no progress bar"),
) -> None:
    """Plan the robot's calibration poses.

    The joint calibration's Ds-optimal design for Z with the as-built lens free;
    reach-checked by inverse kinematics and pupil-lit on the design.

    Writes plan_xyzabc.csv (pose,X,Y,Z,A,B,C: mm, deg, KUKA R = Rz(A) Ry(B) Rx(C)),
    plan_4x4.json, for a KUKA lf_calib.src/.dat (KRL E6POS points; $BASE = robot root,
    $TOOL = flange) and plan.json (predicted Z 1-sigma)."""
    from ..calibration.formats import write_bundle
    from ..calibration.session import plan

    from ..calibration.plausibility import check_poses_count

    check_seed(seed)
    check_poses_count(n, "-n/--poses")
    check_output(out, folder=True, need_mb=1)  # before the search: a cross-talk bench's plan takes minutes
    for opt, v, hi in (("--box-mm", box_mm, 10.0), ("--box-deg", box_deg, 30.0)):
        if v is not None and not (math.isfinite(v) and 0 < v <= hi):
            raise ConfigError(f"{opt}: the plan box's half-width must be in (0, {hi:g}], got {v!r}")
    with progress_bar(None, "plan", enabled=not (no_progress or json_out)) as bar:
        p = plan(design, bench=bench_arg(bench), robot=robot, n=n, seed=seed, tolerances=tolerances,
                 work_translation_mm=box_mm, work_rotation_rad=None if box_deg is None else math.radians(box_deg),
                 progress=bar.describe)
    fm = tuple(s.strip() for s in formats_.split(",") if s.strip())
    if fm == ("auto",):
        fm = ("csv", "json", "krl") if p.robot.name.upper().startswith("KUKA") else ("csv", "json")
    paths = write_bundle(out, p.files(fm))
    d = p.to_dict()
    info(f"plan: {len(p.ids)} poses for the {p.robot.name}, all reachable and lit on the design's model")
    for label, key in ((f"as-built lens free ({d['n_lens_parameters']} parameters, {d['tolerances']})",
                        "predicted_Z_std"), ("lens known", "predicted_Z_std_known_lens")):
        s = d[key]
        info(f"  predicted Z 1-sigma, {label}: translation {s['tx_mm'] * 1e3:.1f} {s['ty_mm'] * 1e3:.1f} "
             f"{s['tz_mm'] * 1e3:.1f} um, rotation {s['rx_deg'] * 1e3:.1f} {s['ry_deg'] * 1e3:.1f} "
             f"{s['rz_deg'] * 1e3:.1f} mdeg ({{S}} axes)")
    r = d["random_over_designed_Z_translation"]
    info(f"  random poses would give {r:.2f}x the Z translation error" if r is not None
         else "  most random sets of as many poses would leave Z's translation unobservable")
    info("files: " + ", ".join(str(v) for v in paths.values()))
    if json_out:
        emit_json({**d, "files": {k: str(v) for k, v in paths.items()}})
