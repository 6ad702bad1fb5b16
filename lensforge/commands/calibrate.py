"""``lensforge calibrate``: X and Z from a recorded bench session (a thin layer over
``calibration.session.calibrate``).

``--robot`` is the robot MODEL (a built-in name or a robot TOML); ``--robot-poses`` is the file of
recorded flange poses. Outputs are written as one folder, all or none.

A calibration that fails its chi2 model check (``calibration.model_check``) is not a
calibration: the diagnostics are written (calibration.json with ``"valid": false`` and the
reason, summary.txt, residuals.png) but no easy_handeye.yaml (an earlier run's is removed),
the likely mistake is named where one of the usual convention mistakes explains the data
(``calibration.diagnosis``), and the command exits 3. ``--accept-failed-check`` writes
everything and exits 0 (research)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Optional

import typer

from ..errors import CalibrationError, ConfigError, LensforgeError
from ..fileio import check_output
from ..progress import progress_bar
from ._common import ROBOT_HELP, bench_arg, emit_json, end_on_failed_check, info

ACCEPT_HELP = ("write the result of a fit that fails its chi2 model check as a calibration anyway (research; "
               "the JSON keeps \"valid\": false); default: exit 3 with diagnostics only")


def explain_no_fit(e: CalibrationError, design, measurements, robot_poses, bench, robot, method, tolerances,
                   wfs_header) -> None:
    """When the calibration could not fit at all (too few lens poses found), re-try the usual
    convention mistakes (``calibration.diagnosis``); if one makes the fit pass, a ConfigError
    (exit 2) naming it, after the original reason."""
    if "poses gave a lens pose" not in str(e):
        return
    from ..calibration.diagnosis import diagnose_session

    info("no fit: trying the usual convention mistakes ...")
    try:
        dx = diagnose_session(design, measurements, robot_poses, None, bench=bench_arg(bench), robot=robot,
                              method=method, tolerances=tolerances, wfs_header=wfs_header)
    except LensforgeError:
        return
    if dx.mistake is not None and not dx.mistake.partial:
        reason = " ".join(str(e).split(";")[0].split())
        raise ConfigError(f"{reason}; {dx.mistake.message}") from None


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
    method: str = typer.Option("joint", "--method", help="calibration method (calibration.pipeline.METHODS): "
                                                         "joint (default; estimates the as-built lens with X and Z) "
                                                         "or two-stage"),
    tolerances: str = typer.Option("default", "-t", "--tolerances",
                                   help="tolerance TOML of the joint method's as-built lens prior "
                                        "('default': the package's file; 'none': no prior, the two-stage "
                                        "pipeline is used with a warning); recorded in calibration.json"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML (default: the design's)"),
    focal_length_sigma: Optional[float] = typer.Option(
        None, "--focal-length-sigma", help="relative 1-sigma prior of the sensor's effective lenslet focal "
                                           "length, estimated with X and Z by the joint method and reported "
                                           "(default: the bench's sensor.focal_length_rel_sigma, 0 = known; "
                                           "e.g. 0.01 for the device's own MLA data)"),
    wfs_header: str = typer.Option("error", "--wfs-header",
                                   help="when the WFS file's header (wavelength, pupil) contradicts the bench: "
                                        "error (default), file (use the file's values) or bench (the bench's)"),
    out: Path = typer.Option(Path("exports/calibration"), "-o", "--out", help="output folder"),
    accept_failed_check: bool = typer.Option(False, "--accept-failed-check", help=ACCEPT_HELP),
    no_progress: bool = typer.Option(False, "--no-progress", help="no progress bar"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable result on stdout"),
) -> None:
    """Calibrate X and Z from a recorded bench session.

    X = lens in the flange, Z = sensor in the robot base (mm, deg, 1-sigma).

    Writes calibration.json, easy_handeye.yaml (ROS), lensforge_calibration.launch.py (ROS 2
    static transforms of Z and X), summary.txt and residuals.png. A fit that fails its chi2
    model check exits 3 with the diagnostics and the likely mistake, and writes neither
    easy_handeye.yaml nor the launch file."""
    check_output(out, folder=True, need_mb=2)
    with progress_bar(None, "estimating lens poses", enabled=not (no_progress or json_out)) as bar:
        from ..calibration.formats import write_bundle
        from ..calibration.ros2 import LAUNCH_FILE_NAME
        from ..calibration.session import calibrate

        try:
            res = calibrate(design, measurements, robot_poses, bench=bench_arg(bench), robot=robot, method=method,
                            tolerances=tolerances, progress=bar.update, wfs_header=wfs_header,
                            pose_pattern=pose_pattern, reference_pose=reference_pose,
                            focal_length_sigma=focal_length_sigma)
        except CalibrationError as e:  # too few lens poses to fit: the same convention mistakes are the usual cause
            explain_no_fit(e, design, measurements, robot_poses, bench, robot, method, tolerances, wfs_header)
            raise
    mistake = None
    if not res.valid and not accept_failed_check:
        from ..calibration.diagnosis import diagnose_session

        info(f"model check failed (chi2/dof {res.chi2_dof:.3g}): trying the usual convention mistakes ...")
        dx = diagnose_session(design, measurements, robot_poses, res, bench=bench_arg(bench), robot=robot,
                              method=method, tolerances=tolerances, wfs_header=wfs_header)
        mistake = dx.mistake
        res = replace(res, extra={**res.extra, "diagnosis": dx.to_dict()})
    paths = write_bundle(out, res.files(accept_failed_check=accept_failed_check),
                         drop=() if (res.valid or accept_failed_check) else ("easy_handeye.yaml", LAUNCH_FILE_NAME))
    info(res.summary().rstrip())
    info("files: " + ", ".join(str(v) for v in paths.values()))
    if json_out:
        emit_json(res.to_json())
    end_on_failed_check(res.valid, res.check_failure, res.chi2_dof, accept_failed_check,
                        mistake=None if mistake is None else f"{mistake.message}; diagnostics in {out}",
                        unexplained=(f"{res.check_failure}; none of the usual convention mistakes (units, angle "
                                     "units, quaternion and Zernike order, waves, sign, another design) explains "
                                     "it; check the lens as built, the bench file and the noise model; diagnostics "
                                     f"in {out}, no easy_handeye.yaml written"))
