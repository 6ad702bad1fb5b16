"""``lensforge simulate-session``: the files a real bench session writes, simulated, to rehearse
``calibrate`` (a thin layer over ``verification.session_sim.simulate_session``)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import typer

from ..errors import ConfigError
from ..fileio import check_output
from ._common import ROBOT_HELP, bench_arg, check_seed, emit_json, info

SESSION_FILES = ("robot_poses.csv", "wfs_zernike.csv", "truth.json")  # what SimulatedSession.files() writes

def simulate_session_cmd(
    design: str = typer.Argument(..., help="design JSON (or a paper lens name)"),
    tolerances: str = typer.Option("default", "-t", "--tolerances",
                                   help="tolerance TOML, 'default' (built-in) or 'none' (lens exactly as designed)"),
    seed: int = typer.Option(0, "--seed", help="seed (same seed, same session)"),
    robot: Optional[str] = typer.Option(None, "--robot", help=ROBOT_HELP),
    n: int = typer.Option(12, "-n", "--poses", help="number of calibration poses"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML (default: the design's)"),
    out: Path = typer.Option(..., "-o", "--out", help="output folder"),
    force: bool = typer.Option(False, "--force", help="overwrite session files already in the output folder"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable summary on stdout"),
    instrument_files: bool = typer.Option(False, "--instrument-files",
                                          help="also write thorlabs/ (WFS software exports, one per pose) and "
                                               "spot_fields/ (SDK spot deviations + MLA data, NPZ)"),
) -> None:
    """Simulate a bench session's files to rehearse calibrate.

    Writes robot_poses.csv, wfs_zernike.csv and truth.json (with --instrument-files also the
    folders thorlabs/ and spot_fields/, each a valid --measurements); refuses to overwrite them
    (they could be a real session's) without --force."""
    from ..calibration.formats import write_bundle
    from ..calibration.plausibility import check_poses_count

    check_poses_count(n, "-n/--poses")
    existing = [f for f in SESSION_FILES if (Path(out) / f).exists()]
    if existing and not force:
        raise ConfigError(f"{out}: already holds {', '.join(existing)} (perhaps a real session's); choose another "
                          "-o/--out or give --force to overwrite")
    check_output(out, folder=True, need_mb=1)
    from ..calibration.session_result import frame_dict

    from ..verification.session_sim import simulate_session

    check_seed(seed)
    tol = None if tolerances.lower() == "none" else tolerances
    s = simulate_session(design, tolerances=tol, seed=seed, bench=bench_arg(bench), robot=robot, n=n)
    paths = write_bundle(out, s.files(instrument=instrument_files))
    info(f"session: {len(s.ids)} poses, {len(s.unlit)} unlit on the as-built lens"
         + (f" ({', '.join(s.unlit)})" if s.unlit else ""))
    info("files: " + ", ".join(str(v) for k, v in paths.items() if "/" not in k)
         + (f", {out / 'thorlabs'}/, {out / 'spot_fields'}/" if instrument_files else ""))
    info(f"next: lensforge calibrate {design} --measurements {paths['wfs_zernike.csv']} "
         f"--robot-poses {paths['robot_poses.csv']}")
    if json_out:
        emit_json({"schema_version": 1, "poses": list(s.ids), "unlit": list(s.unlit),
                   "Z": frame_dict(s.Z, np.zeros((6, 6)))["xyzabc"], "files": {k: str(v) for k, v in paths.items()}})
