"""``lensforge estimate`` (one lens pose with its covariance, from a WFS file) and
``lensforge estimate-study`` (pose-estimation accuracy against the CRLB, Fig. 5 / Table 2)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import numpy as np
import typer

from ..errors import CalibrationError, ConfigError
from ..fileio import check_output, staged_dir, write_atomic
from ..progress import progress_bar
from ._common import MAX_TRIALS, bench_arg, check_seed, emit_json, end_on_failed_check, info, load_bench_arg


def estimate_study(
    lenses: List[str] = typer.Argument(..., help="paper lens names (spherical, polynomial, extended_polynomial, zernike) or design JSON files"),
    trials: int = typer.Option(100, "--trials", help="estimates per lens"),
    method: str = typer.Option("lm", "--method", help="pose estimator: lm (least squares) | ukf (the paper's baseline); the registry ESTIMATORS in calibration/pose_estimation.py"),
    ukf_repeats: int = typer.Option(12, "--ukf-repeats", help="ukf: updates on the same measurement (paper: 12)"),
    seed: int = typer.Option(0, "--seed", help="random seed (SeedSequence; same trials for every lens)"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML (default: the design's bench or the built-in default)"),
    out: Path = typer.Option(Path("exports/estimate"), "-o", "--out", help="output folder (JSON, per-trial CSV, box plot PNG)"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable JSON on stdout"),
    no_progress: bool = typer.Option(False, "--no-progress", help="no progress bar"),
) -> None:
    """Pose-estimation accuracy against the Cramer-Rao bound.

    Estimates each lens's pose from noisy measurements TRIALS times, reports the error
    statistics (um, urad) against the CRLB and writes a Fig. 5-style box plot."""
    from ..calibration.pose_estimation import ESTIMATORS
    from ..optics.lens import resolve_lens
    from ..verification.estimation_study import format_table, save_study, study_lens, study_to_dict

    # ConfigError, not typer.Exit: under main()'s standalone_mode=False a typer.Exit
    # comes back as a return value and the exit status is lost
    if method not in ESTIMATORS:
        raise ConfigError(f"--method: {method!r} is not one of {', '.join(ESTIMATORS)}")
    if trials < 1 or ukf_repeats < 1:
        raise ConfigError(f"--trials and --ukf-repeats: must be >= 1, got {trials} and {ukf_repeats}")
    check_seed(seed)
    if trials > MAX_TRIALS:
        raise ConfigError(f"--trials: {trials} is over the limit of {MAX_TRIALS} estimates per lens")
    opts = {"ukf_repeats": ukf_repeats} if method == "ukf" else {}
    loaded = [resolve_lens(arg) for arg in lenses]  # every input validated before any work
    benches = [load_bench_arg(bench, r) for r in loaded]
    check_output(out, folder=True, need_mb=5)
    results = []
    with progress_bar(trials * len(lenses), "estimates", not (no_progress or json_out)) as bar:
        for r, b in zip(loaded, benches):
            bar.describe(f"{r.label}: {method} estimates")
            results.append(study_lens(b, r.lens, r.label, trials, method, seed, tick=bar.advance, **opts))
    meta = {"method": method, "trials": trials, "seed": seed,
            **({"ukf_repeats": ukf_repeats} if method == "ukf" else {})}
    with staged_dir(out) as st:  # JSON, CSV and PNG together or not at all
        paths = {k: st.final(v) for k, v in save_study(results, st.tmp, **meta).items()}
    if json_out:
        emit_json({**study_to_dict(results, **meta), "files": {k: str(v) for k, v in paths.items()}})
    else:
        info(format_table(results))
        info("files: " + ", ".join(str(p) for p in paths.values()))


def estimate_cmd(
    design: str = typer.Argument(..., help="design JSON (or a paper lens name)"),
    measurement: Path = typer.Option(..., "--measurement", "-m", help="WFS Zernike CSV/JSON (one pose, or --pose)"),
    pose: Optional[str] = typer.Option(None, "--pose", help="pose id to use when the file holds several"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML (default: the design's)"),
    wfs_header: str = typer.Option("error", "--wfs-header",
                                   help="when the WFS file's header (wavelength, pupil) contradicts the bench: "
                                        "error (default), file (use the file's values) or bench (the bench's)"),
    accept_failed_check: bool = typer.Option(False, "--accept-failed-check",
                                             help="report a pose whose fit fails its chi2 model check with exit 0 "
                                                  "(research; the JSON keeps \"valid\": false); default: exit 3"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable result on stdout"),
) -> None:
    """Estimate one lens pose with its covariance.

    The pose is relative to the lens's nominal placement: translation (um), rotation (mrad).
    A fit that fails its chi2 model check exits 3, naming the likely mistake where one is found."""
    from ..calibration.model_check import check_chi2
    from ..calibration.session import estimate
    from ..optics.pose import DOF_NAMES

    try:
        r = estimate(design, measurement, bench=bench_arg(bench), pose_id=pose, wfs_header=wfs_header)
    except CalibrationError as exc:  # no pose found: the usual convention mistakes are the usual cause
        if "no lens pose found" in str(exc):
            from ..calibration.diagnosis import diagnose_estimate

            dx = diagnose_estimate(design, measurement, float("inf"), bench=bench_arg(bench), pose_id=pose,
                                   wfs_header=wfs_header)
            if dx.mistake is not None:
                raise ConfigError(f"{' '.join(str(exc).split())}; {dx.mistake.message}") from None
        raise
    e = r["estimate"]
    mc = check_chi2(e.chi2, e.dof, what="pose estimate")
    std = e.std
    state = "converged" if e.converged else "NOT converged"
    info(f"pose {r['pose_id']}: chi2/dof = {e.chi2_dof:.3g}, {state}"
         + ("" if mc.passed else f"; MODEL CHECK FAILED (above {mc.threshold_chi2_dof:.3g}): not a pose estimate"))
    for k, name in enumerate(DOF_NAMES):
        if k < 3:
            info(f"  {name} = {e.pose[k] * 1e3:10.2f} um  +- {std[k] * 1e3:.2f} um")
        else:
            info(f"  {name} = {e.pose[k] * 1e3:10.4f} mrad +- {std[k] * 1e3:.4f} mrad")
    lin = r["linearity"]
    if not lin.reliable:
        info(f"  warning: {lin.message}")
    mistake = dx = None
    if not mc.passed and not accept_failed_check:
        from ..calibration.diagnosis import diagnose_estimate

        dx = diagnose_estimate(design, measurement, e.chi2_dof, bench=bench_arg(bench), pose_id=r["pose_id"],
                               wfs_header=wfs_header)
        mistake = dx.mistake
    if json_out:
        emit_json({"schema_version": 1, "pose_id": r["pose_id"], "valid": mc.passed,
                   "check_failure": None if mc.passed else mc.reason, "model_check": mc.to_dict(),
                   **({"diagnosis": dx.to_dict()} if dx is not None else {}), **e.to_dict(),
                   "cov": [[(float(v) if np.isfinite(v) else None) for v in row] for row in e.cov],
                   "cov_units": "mm and rad, pose vector (tx, ty, tz, rx, ry, rz)", "linearity": lin.to_dict()})
    end_on_failed_check(mc.passed, mc.reason, e.chi2_dof, accept_failed_check, accepted_as="reported",
                        mistake=None if mistake is None else mistake.message,
                        unexplained=("the measured wavefront does not fit the design's model at any pose; none of "
                                     "the usual mistakes (Zernike order, waves, sign, another design) explains it; "
                                     "check the lens as built, the bench file (pupil, wavelength) and the sensor's "
                                     "noise"))
