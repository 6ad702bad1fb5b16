"""``lensforge calibrate``: X and Z from a recorded bench session (a thin layer over
``calibration.session.calibrate``).

``--robot`` is the robot MODEL (a built-in name or a robot TOML); ``--robot-poses`` is the file of
recorded flange poses. Outputs are written as one folder, all or none."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..progress import progress_bar
from ._common import ROBOT_HELP, bench_arg, emit_json, info

def calibrate_cmd(
    design: str = typer.Argument(..., help="design JSON (or a paper lens name)"),
    measurements: Path = typer.Option(..., "--measurements", "-m",
                                      help="WFS measurements: CSV pose,Z1..ZK (um, Thorlabs order), lensforge JSON, "
                                           "or a folder / quoted glob of per-pose Thorlabs WFS exports or SDK "
                                           "spot fields (pose id = last integer in the file name)"),
    robot_poses: Path = typer.Option(..., "--robot-poses", "-r",
                                     help="flange poses: CSV pose,X,Y,Z,A,B,C (mm/deg), CSV pose,x,y,z,qw,qx,qy,qz "
                                          "with '# units: m|mm', or JSON 4x4"),
    robot: Optional[str] = typer.Option(None, "--robot", help=ROBOT_HELP),
    pose_pattern: Optional[str] = typer.Option(None, "--pose-pattern",
                                               help="regular expression whose first group is the pose id in a "
                                                    "measurement file's name (default: its last integer)"),
    reference_pose: Optional[str] = typer.Option(None, "--reference-pose",
                                                 help="the pose id of the user reference the measurements are "
                                                      "relative to (default: the files' reference_pose, if any)"),
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

    Writes calibration.json, easy_handeye.yaml (ROS), lensforge_calibration.launch.py (ROS 2
    static transforms of Z and X), summary.txt and residuals.png."""
    with progress_bar(None, "estimating lens poses", enabled=not (no_progress or json_out)) as bar:
        from ..calibration.formats import write_bundle
        from ..calibration.session import calibrate

        res = calibrate(design, measurements, robot_poses, bench=bench_arg(bench), robot=robot, method=method,
                        tolerances=tolerances, progress=bar.update, pose_pattern=pose_pattern,
                        reference_pose=reference_pose)
    paths = write_bundle(out, res.files())
    info(res.summary().rstrip())
    info("files: " + ", ".join(str(v) for v in paths.values()))
    if json_out:
        emit_json(res.to_json())
