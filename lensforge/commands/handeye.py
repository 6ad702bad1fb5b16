"""``lensforge handeye POSES.json``: robot-world-hand-eye calibration A_i X = Z B_i."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from ..errors import ConfigError
from ..fileio import read_json
from ._common import emit_json, info


def load_poses(path: str | Path) -> dict:
    """Parse POSES.json: {"units": "mm", "A": [4x4...], "B": [4x4...]} with optional
    "sigma_A": {"translation_mm", "rotation_rad"} and "cov_B": [6x6...] (one per pose or
    one for all) or "sigma_B": {"translation_mm", "rotation_rad"}. Returns keyword
    arguments for solve_handeye (A, B, sigma, cov_B). Raises ConfigError."""
    p = Path(path)
    data = read_json(p, "poses file")
    if not isinstance(data, dict):
        raise ConfigError(f"poses file {p}: expected a JSON object with keys units, A, B")
    units = data.get("units")
    if units != "mm":
        raise ConfigError(f"{p.name}:units: must be \"mm\" (got {units!r}); convert translations to mm")
    out = {}
    for key in ("A", "B"):
        if key not in data:
            raise ConfigError(f"{p.name}:{key}: missing; give a list of 4x4 homogeneous matrices")
        try:
            M = np.asarray(data[key], dtype=float)
        except (TypeError, ValueError):
            raise ConfigError(f"{p.name}:{key}: must be a list of 4x4 numeric matrices") from None
        if M.ndim != 3 or M.shape[1:] != (4, 4):
            raise ConfigError(f"{p.name}:{key}: expected shape (n, 4, 4), got {M.shape}")
        out[key] = M
    if out["A"].shape[0] != out["B"].shape[0]:
        raise ConfigError(f"{p.name}: A has {out['A'].shape[0]} poses but B has {out['B'].shape[0]}; give one B per A")
    if out["A"].shape[0] < 3:
        raise ConfigError(f"{p.name}:A: need at least 3 pose pairs, got {out['A'].shape[0]}")

    def sig(key):
        s = data[key]
        if not isinstance(s, dict) or not {"translation_mm", "rotation_rad"} <= set(s):
            raise ConfigError(f"{p.name}:{key}: expected {{\"translation_mm\": .., \"rotation_rad\": ..}}")
        try:
            t, r = float(s["translation_mm"]), float(s["rotation_rad"])
        except (TypeError, ValueError):
            raise ConfigError(f"{p.name}:{key}: translation_mm and rotation_rad must be numbers") from None
        if not (t >= 0 and r >= 0):
            raise ConfigError(f"{p.name}:{key}: sigmas must be >= 0")
        return t, r

    out["sigma"] = sig("sigma_A") if "sigma_A" in data else None
    if "cov_B" in data and "sigma_B" in data:
        raise ConfigError(f"{p.name}: give cov_B or sigma_B, not both")
    if "cov_B" in data:
        try:
            C = np.asarray(data["cov_B"], dtype=float)
        except (TypeError, ValueError):
            raise ConfigError(f"{p.name}:cov_B: must be 6x6 numeric matrices") from None
        if C.shape not in ((6, 6), (out["A"].shape[0], 6, 6)):
            raise ConfigError(f"{p.name}:cov_B: expected one 6x6 or one per pose, got shape {C.shape}")
        out["cov_B"] = C
    elif "sigma_B" in data:
        t, r = sig("sigma_B")
        out["cov_B"] = np.diag([t * t] * 3 + [r * r] * 3)
    else:
        out["cov_B"] = None
    return out


def handeye_cmd(
    poses: Path = typer.Argument(..., help="POSES.json: {\"units\": \"mm\", \"A\": [4x4...], \"B\": [4x4...]}"),
    method: str = typer.Option("ml", "--method", help="ml | shah | li"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable result on stdout"),
    allow_degenerate: bool = typer.Option(
        False, "--allow-degenerate",
        help="report degenerate motion as observable=false instead of failing"),
    obs_limit_mm: Optional[float] = typer.Option(None, "--obs-limit-mm",
                                                 help="predicted 1-sigma (mm) beyond which a direction is reported "
                                                      "unobservable (solved and warned, never refused); default "
                                                      "calibration.handeye.OBS_LIMITS (1 mm)"),
    obs_limit_rad: Optional[float] = typer.Option(None, "--obs-limit-rad",
                                                  help="the same for rotations (rad); default OBS_LIMITS (0.01 rad)"),
):
    """Solve A_i X = Z B_i (A = robot flange in base, B = lens in sensor frame)."""
    from ..calibration.handeye import OBS_LIMITS, solve_handeye  # imported here: `lensforge --help` stays fast

    obs_limit_mm = OBS_LIMITS[0] if obs_limit_mm is None else obs_limit_mm
    obs_limit_rad = OBS_LIMITS[1] if obs_limit_rad is None else obs_limit_rad

    kw = load_poses(poses)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = solve_handeye(kw["A"], kw["B"], method=method, sigma=kw["sigma"], cov_B=kw["cov_B"],
                            on_degenerate="warn" if allow_degenerate else "raise",
                            obs_limits=(obs_limit_mm, obs_limit_rad))
    sz = res.std_Z
    info(f"hand-eye ({res.method}, {res.residuals.shape[0]} poses, noise model {res.noise_model}): "
         f"chi2/dof = {res.chi2_dof:.3g}")
    info(f"  Z translation (mm): {np.array2string(res.Z[:3, 3], precision=4)}  "
         f"1-sigma {np.array2string(sz[:3] * 1e3, precision=2)} um")
    info(f"  Z rotation 1-sigma: {np.array2string(sz[3:] * 1e3, precision=3)} mrad")
    info(f"  X translation (mm): {np.array2string(res.X[:3, 3], precision=4)}  "
         f"1-sigma {np.array2string(res.std_X[:3] * 1e3, precision=2)} um")
    for w in res.warnings:
        info(f"warning: {w}")
    if json_out:
        emit_json(res.to_dict())
