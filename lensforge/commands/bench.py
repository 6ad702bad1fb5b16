"""Real-bench commands: ``plan``, ``calibrate``, ``estimate`` and ``simulate-session``.

Thin layers over ``calibration.session`` (plan, calibrate, estimate) and
``verification.session_sim`` (simulate_session). Outputs are written as one folder,
all or none (``calibration.formats.write_bundle``).

Options: ``--robot`` is always the robot MODEL (a built-in name: kr10_r1100_sixx,
ur5e, or a robot TOML); ``--robot-poses`` is the file of recorded flange poses.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Optional

import numpy as np
import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from ..optics.bench import load_bench
from ._common import check_seed, emit_json, info

# help texts name the registries without importing them (scipy): `lensforge --help` stays fast
_ROBOT_HELP = "robot model: a name of calibration.robot.ROBOTS (kr10_r1100_sixx, ur5e) or a robot TOML (default kr10_r1100_sixx)"


def _bench(path: Optional[str]):
    return load_bench(path) if path else None


@contextmanager
def _progress(enabled: bool, label: str):
    """Yields a callable (done, total) driving a rich progress bar on stderr (or a no-op)."""
    if not enabled:
        yield None
        return
    with Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), transient=True) as p:
        task = p.add_task(label, total=None)

        def update(done, total):
            p.update(task, completed=done, total=total)
        yield update


def plan_cmd(
    design: str = typer.Argument(..., help="design JSON (or a paper lens name)"),
    robot: Optional[str] = typer.Option(None, "--robot", help=_ROBOT_HELP),
    n: int = typer.Option(12, "-n", "--poses", help="number of calibration poses"),
    seed: int = typer.Option(0, "--seed", help="seed of the candidate poses"),
    tolerances: str = typer.Option("default", "-t", "--tolerances",
                                   help="tolerance TOML of the as-built lens prior the design plans for "
                                        "('default': the package's file; 'none': the lens as designed)"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML (default: the design's)"),
    formats_: str = typer.Option("auto", "--formats",
                                 help="comma list of calibration.formats.PLAN_WRITERS names; auto = csv,json (+krl for a KUKA)"),
    out: Path = typer.Option(Path("exports/plan"), "-o", "--out", help="output folder"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable summary on stdout"),
) -> None:
    """Plan the robot's calibration poses.

    The joint calibration's Ds-optimal design for Z with the as-built lens free;
    reach-checked by inverse kinematics and pupil-lit on the design.

    Writes plan_xyzabc.csv (pose,X,Y,Z,A,B,C: mm, deg, KUKA R = Rz(A) Ry(B) Rx(C)),
    plan_4x4.json, for a KUKA lf_calib.src/.dat (KRL E6POS points; $BASE = robot root,
    $TOOL = flange) and plan.json (predicted Z 1-sigma)."""
    from ..calibration.formats import write_bundle
    from ..calibration.session import plan

    check_seed(seed)
    p = plan(design, bench=_bench(bench), robot=robot, n=n, seed=seed, tolerances=tolerances)
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
    info(f"  random poses would give {d['random_over_designed_Z_translation']:.2f}x the Z translation error")
    info("files: " + ", ".join(str(v) for v in paths.values()))
    if json_out:
        emit_json({**d, "files": {k: str(v) for k, v in paths.items()}})


def calibrate_cmd(
    design: str = typer.Argument(..., help="design JSON (or a paper lens name)"),
    measurements: Path = typer.Option(..., "--measurements", "-m",
                                      help="WFS Zernike export: CSV pose,Z1..ZK (um, Thorlabs order) or lensforge JSON"),
    robot_poses: Path = typer.Option(..., "--robot-poses", "-r",
                                     help="flange poses: CSV pose,X,Y,Z,A,B,C (mm/deg), CSV pose,x,y,z,qw,qx,qy,qz "
                                          "with '# units: m|mm', or JSON 4x4"),
    robot: Optional[str] = typer.Option(None, "--robot", help=_ROBOT_HELP),
    method: str = typer.Option("joint", "--method", help="calibration method (calibration.session.CALIBRATION_METHODS): "
                                                         "joint (default; estimates the as-built lens with X and Z) "
                                                         "or two-stage"),
    tolerances: str = typer.Option("default", "-t", "--tolerances",
                                   help="tolerance TOML of the joint method's as-built lens prior "
                                        "('default': the package's file; 'none': no prior, the two-stage "
                                        "pipeline is used with a warning); recorded in calibration.json"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML (default: the design's)"),
    out: Path = typer.Option(Path("exports/calibration"), "-o", "--out", help="output folder"),
    no_progress: bool = typer.Option(False, "--no-progress", help="no progress bar"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable result on stdout"),
) -> None:
    """Calibrate X and Z from a recorded bench session.

    X = lens in the flange, Z = sensor in the robot base (mm, deg, 1-sigma).

    Writes calibration.json, easy_handeye.yaml (ROS), summary.txt and residuals.png."""
    with _progress(not (no_progress or json_out), "estimating lens poses") as cb:
        from ..calibration.formats import write_bundle
        from ..calibration.session import calibrate

        res = calibrate(design, measurements, robot_poses, bench=_bench(bench), robot=robot, method=method,
                        tolerances=tolerances, progress=cb)
    paths = write_bundle(out, res.files())
    info(res.summary().rstrip())
    info("files: " + ", ".join(str(v) for v in paths.values()))
    if json_out:
        emit_json(res.to_json())


def estimate_cmd(
    design: str = typer.Argument(..., help="design JSON (or a paper lens name)"),
    measurement: Path = typer.Option(..., "--measurement", "-m", help="WFS Zernike CSV/JSON (one pose, or --pose)"),
    pose: Optional[str] = typer.Option(None, "--pose", help="pose id to use when the file holds several"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML (default: the design's)"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable result on stdout"),
) -> None:
    """Estimate one lens pose with its covariance.

    The pose is relative to the lens's nominal placement: translation (um), rotation (mrad)."""
    from ..calibration.session import estimate
    from ..optics.pose import DOF_NAMES

    r = estimate(design, measurement, bench=_bench(bench), pose_id=pose)
    e = r["estimate"]
    std = e.std
    info(f"pose {r['pose_id']}: chi2/dof = {e.chi2_dof:.3g}, {'converged' if e.converged else 'NOT converged'}")
    for k, name in enumerate(DOF_NAMES):
        if k < 3:
            info(f"  {name} = {e.pose[k] * 1e3:10.2f} um  +- {std[k] * 1e3:.2f} um")
        else:
            info(f"  {name} = {e.pose[k] * 1e3:10.4f} mrad +- {std[k] * 1e3:.4f} mrad")
    if json_out:
        emit_json({"schema_version": 1, "pose_id": r["pose_id"], **e.to_dict(),
                   "cov": [[(float(v) if np.isfinite(v) else None) for v in row] for row in e.cov],
                   "cov_units": "mm and rad, pose vector (tx, ty, tz, rx, ry, rz)"})


def simulate_session_cmd(
    design: str = typer.Argument(..., help="design JSON (or a paper lens name)"),
    tolerances: str = typer.Option("default", "-t", "--tolerances",
                                   help="tolerance TOML, 'default' (built-in) or 'none' (lens exactly as designed)"),
    seed: int = typer.Option(0, "--seed", help="seed (same seed, same session)"),
    robot: Optional[str] = typer.Option(None, "--robot", help=_ROBOT_HELP),
    n: int = typer.Option(12, "-n", "--poses", help="number of calibration poses"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML (default: the design's)"),
    out: Path = typer.Option(..., "-o", "--out", help="output folder"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable summary on stdout"),
) -> None:
    """Simulate a bench session's files to rehearse calibrate.

    Writes robot_poses.csv, wfs_zernike.csv and truth.json."""
    from ..calibration.formats import write_bundle
    from ..calibration.session import frame_dict

    from ..verification.session_sim import simulate_session

    check_seed(seed)
    tol = None if tolerances.lower() == "none" else tolerances
    s = simulate_session(design, tolerances=tol, seed=seed, bench=_bench(bench), robot=robot, n=n)
    paths = write_bundle(out, s.files())
    info(f"session: {len(s.ids)} poses, {len(s.unlit)} unlit on the as-built lens"
         + (f" ({', '.join(s.unlit)})" if s.unlit else ""))
    info("files: " + ", ".join(str(v) for v in paths.values()))
    info(f"next: lensforge calibrate {design} --measurements {paths['wfs_zernike.csv']} "
         f"--robot-poses {paths['robot_poses.csv']}")
    if json_out:
        emit_json({"schema_version": 1, "poses": list(s.ids), "unlit": list(s.unlit),
                   "Z": frame_dict(s.Z, np.zeros((6, 6)))["xyzabc"], "files": {k: str(v) for k, v in paths.items()}})

