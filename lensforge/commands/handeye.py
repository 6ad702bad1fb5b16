"""``lensforge handeye``: robot-world-hand-eye calibration A_i X = Z B_i.

Inputs: POSES.json ``{"units": "mm"|"m", "A": [4x4...], "B": [4x4...], "noise": {...}}``
or two pose files matched by id (``--robot-poses`` for A, ``--lens-poses`` for B, any
format ``calibrate`` reads: XYZABC CSV, quaternion CSV with ``# units:``, JSON 4x4).

Noise model (A = robot flange, B = lens; per-axis 1-sigma):
``"noise": {"robot_sigma_trans_mm", "robot_sigma_rot_deg", "lens_sigma_trans_mm",
"lens_sigma_rot_deg"}``, or full covariances ``"cov_A"`` / ``"cov_B"``: one 6x6 or one
per pose, right perturbation (t mm, rotation vector rad), in (mm, rad)^2 whatever the
units of the poses. Legacy keys ``sigma_A`` / ``sigma_B`` ({translation_mm,
rotation_rad}) are accepted. Without a noise model the noise is estimated from the
residuals. It can also come from ``--noise NOISE.json`` (the same keys).

A noisy problem is solved and warned about with its predicted 1-sigma, never refused;
degenerate motion (directions the motion lacks) is refused naming them, or with
``--allow-degenerate`` solved with a null 1-sigma on those directions.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from ..errors import ConfigError
from ..fileio import dumps_json, read_json
from ..input_checks import POSE_TRANSLATION, Num, check_header, number, number_array
from ._common import emit_json, info

_NOISE_KEYS = ("robot_sigma_trans_mm", "robot_sigma_rot_deg", "lens_sigma_trans_mm", "lens_sigma_rot_deg")


def _matrices(name: str, key: str, v, scale: float) -> np.ndarray:
    rng = Num(POSE_TRANSLATION.lo / scale, POSE_TRANSLATION.hi / scale, "m" if scale != 1.0 else "mm")
    M = number_array(v, f"{name}:{key}", (None, 4, 4), rng)  # strict: no strings, NaN or 1e300; range in the file's unit
    if M.ndim != 3:
        raise ConfigError(f"{name}:{key}: give a list of 4x4 homogeneous matrices, got an empty list")
    M = M.copy()
    M[:, :3, 3] *= scale
    return M


def _cov(name: str, key: str, v, n: int) -> np.ndarray:
    per_pose = isinstance(v, list) and bool(v) and isinstance(v[0], list) and bool(v[0]) and isinstance(v[0][0], list)
    C = number_array(v, f"{name}:{key}", (None, 6, 6) if per_pose else (6, 6), Num(-1e6, 1e6, "mm^2 / rad^2"))
    if C.shape not in ((6, 6), (n, 6, 6)):
        raise ConfigError(f"{name}:{key}: expected one 6x6 or one per pose ({n}, 6, 6), got shape {C.shape}")
    return C


def _sig(name: str, key: str, s) -> tuple[float, float]:
    if not isinstance(s, dict) or not {"translation_mm", "rotation_rad"} <= set(s):
        raise ConfigError(f"{name}:{key}: expected {{\"translation_mm\": .., \"rotation_rad\": ..}}")
    t = number(s["translation_mm"], f"{name}:{key}.translation_mm", Num(0.0, 1e3, "mm"))
    r = number(s["rotation_rad"], f"{name}:{key}.rotation_rad", Num(0.0, 1.0, "rad"))
    return t, r


def noise_model(data: dict, name: str, n: int) -> tuple:
    """(sigma for A, cov_B) for solve_handeye from a dict holding "noise", "cov_A"/"cov_B"
    or the legacy "sigma_A"/"sigma_B" (see the module docstring)."""
    sigma = cov_B = None
    if "noise" in data:
        nz = data["noise"]
        if not isinstance(nz, dict) or set(nz) - set(_NOISE_KEYS) or not set(nz):
            raise ConfigError(f"{name}:noise: expected keys {', '.join(_NOISE_KEYS)}")
        vals = {}
        for k in _NOISE_KEYS:
            v = nz.get(k, 0.0)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
                raise ConfigError(f"{name}:noise.{k}: must be a number >= 0, got {v!r}")
            vals[k] = float(v)
        if vals["robot_sigma_trans_mm"] or vals["robot_sigma_rot_deg"]:
            sigma = np.diag([vals["robot_sigma_trans_mm"] ** 2] * 3 + [np.radians(vals["robot_sigma_rot_deg"]) ** 2] * 3)
        if vals["lens_sigma_trans_mm"] or vals["lens_sigma_rot_deg"]:
            cov_B = np.diag([vals["lens_sigma_trans_mm"] ** 2] * 3 + [np.radians(vals["lens_sigma_rot_deg"]) ** 2] * 3)
    for key in ("cov_A", "sigma_A"):
        if key in data:
            if sigma is not None:
                raise ConfigError(f"{name}: give the robot noise once (noise, cov_A or sigma_A)")
            sigma = _cov(name, key, data[key], n) if key == "cov_A" else _sig(name, key, data[key])
    for key in ("cov_B", "sigma_B"):
        if key in data:
            if cov_B is not None:
                raise ConfigError(f"{name}: give the lens noise once (noise, cov_B or sigma_B)")
            if key == "cov_B":
                cov_B = _cov(name, key, data[key], n)
            else:
                t, r = _sig(name, key, data[key])
                cov_B = np.diag([t * t] * 3 + [r * r] * 3)
    return sigma, cov_B


def load_poses(path: str | Path) -> dict:
    """Parse POSES.json (module docstring). Returns keyword arguments for solve_handeye
    (A, B in mm, sigma, cov_B). Raises ConfigError naming the file and field."""
    p = Path(path)
    data = read_json(p, "poses file")
    if not isinstance(data, dict):
        raise ConfigError(f"poses file {p}: expected a JSON object with keys units, A, B")
    check_header(data, f"poses file {p.name}", kind="lensforge.poses")
    units = data.get("units")
    if units not in ("mm", "m"):
        raise ConfigError(f"{p.name}:units: must be \"mm\" or \"m\" (got {units!r})")
    scale = 1000.0 if units == "m" else 1.0
    out = {}
    for key in ("A", "B"):
        if key not in data:
            raise ConfigError(f"{p.name}:{key}: missing; give a list of 4x4 homogeneous matrices")
        out[key] = _matrices(p.name, key, data[key], scale)
    if out["A"].shape[0] != out["B"].shape[0]:
        raise ConfigError(f"{p.name}: A has {out['A'].shape[0]} poses but B has {out['B'].shape[0]}; give one B per A")
    if out["A"].shape[0] < 3:
        raise ConfigError(f"{p.name}:A: need at least 3 pose pairs, got {out['A'].shape[0]}")
    out["sigma"], out["cov_B"] = noise_model(data, p.name, out["A"].shape[0])
    return out


def load_pose_files(robot_poses: Path, lens_poses: Path) -> tuple[np.ndarray, np.ndarray, list]:
    """A and B (mm) matched by id from two pose files; ids in one file only are left out."""
    from ..calibration.formats import read_robot_poses

    ta, tb = read_robot_poses(robot_poses), read_robot_poses(lens_poses)
    common = [i for i in ta.ids if i in set(tb.ids)]
    if len(common) < 3:
        raise ConfigError(f"{robot_poses} and {lens_poses}: field pose: only {len(common)} pose ids match (need >= 3)")
    A = ta.T[[ta.ids.index(i) for i in common]]
    B = tb.T[[tb.ids.index(i) for i in common]]
    return A, B, common


def handeye_cmd(
    poses: Optional[Path] = typer.Argument(None, help="POSES.json: {\"units\": \"mm\"|\"m\", \"A\": [4x4...], "
                                                      "\"B\": [4x4...], \"noise\": {...}}"),
    robot_poses: Optional[Path] = typer.Option(None, "--robot-poses", help="A: flange poses file (any calibrate format)"),
    lens_poses: Optional[Path] = typer.Option(None, "--lens-poses", help="B: lens poses file (any calibrate format)"),
    noise: Optional[Path] = typer.Option(None, "--noise", help="JSON noise model: robot_sigma_trans_mm, robot_sigma_rot_deg, lens_sigma_trans_mm, lens_sigma_rot_deg (1-sigma per axis) or cov_A / cov_B; default: estimated from the residuals"),
    method: str = typer.Option("ml", "--method", help="ml | shah | li"),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="output folder (handeye.json, easy_handeye.yaml)"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable result on stdout"),
    allow_degenerate: bool = typer.Option(
        False, "--allow-degenerate",
        help="solve degenerate motion anyway: its unobservable directions get a null 1-sigma"),
    obs_limit_mm: float = typer.Option(1.0, "--obs-limit-mm",  # = calibration.handeye.OBS_LIMITS (lazy import)
                                       help="predicted 1-sigma (mm) beyond which a direction is reported "
                                            "unobservable (solved and warned, never refused)"),
    obs_limit_rad: float = typer.Option(0.01, "--obs-limit-rad",
                                        help="the same for rotations (rad)"),
    plot: Path = typer.Option(None, "--plot", help="write the residuals per pose as a PNG here"),
) -> None:
    """Robot-world-hand-eye calibration A_i X = Z B_i.

    A = robot flange in the robot base, B = lens in the sensor frame (4x4, mm or m);
    X, Z with covariances, chi2 model check and observability."""
    # imported here so that `lensforge --help` stays fast (no scipy at CLI import)
    from ..calibration.formats import easy_handeye_yaml, write_bundle
    from ..calibration.handeye import solve_handeye
    from ..calibration.session_result import frame_dict

    if poses is not None and (robot_poses or lens_poses):
        raise ConfigError("handeye: give POSES.json or --robot-poses with --lens-poses, not both")
    if poses is not None:
        kw = load_poses(poses)
        ids = [str(i + 1) for i in range(kw["A"].shape[0])]
    elif robot_poses and lens_poses:
        A, B, ids = load_pose_files(robot_poses, lens_poses)
        kw = {"A": A, "B": B, "sigma": None, "cov_B": None}
    else:
        raise ConfigError("handeye: give POSES.json, or --robot-poses and --lens-poses")
    if noise is not None:
        if kw["sigma"] is not None or kw["cov_B"] is not None:
            raise ConfigError(f"{noise}: the poses file already holds a noise model; give it once")
        data = read_json(noise, "noise file")
        if not isinstance(data, dict):
            raise ConfigError(f"noise file {noise}: expected a JSON object")
        kw["sigma"], kw["cov_B"] = noise_model(data, Path(noise).name, kw["A"].shape[0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = solve_handeye(kw["A"], kw["B"], method=method, sigma=kw["sigma"], cov_B=kw["cov_B"],
                            on_degenerate="warn" if allow_degenerate else "raise",
                            obs_limits=(obs_limit_mm, obs_limit_rad))
    Zf, Xf = frame_dict(res.Z, res.cov_Z), frame_dict(res.X, res.cov_X)
    info(f"hand-eye ({res.method}, {res.residuals.shape[0]} poses, noise model {res.noise_model}): "
         f"chi2/dof = {res.chi2_dof:.3g}")

    def show(label, f):
        s = f["std"]
        um = " ".join("null" if s[k] is None else f"{s[k] * 1e3:.2f}" for k in ("tx_mm", "ty_mm", "tz_mm"))
        md = " ".join("null" if s[k] is None else f"{s[k] * 1e3:.3f}" for k in ("rx_deg", "ry_deg", "rz_deg"))
        info(f"  {label} X Y Z (mm): " + " ".join(f"{v:.4f}" for v in f["xyzabc"][:3]) + f"   1-sigma {um} um")
        info(f"  {label} A B C (deg): " + " ".join(f"{v:.5f}" for v in f["xyzabc"][3:]) + f"   1-sigma {md} mdeg")
        info(f"  {label} quaternion (w x y z): " + " ".join(f"{v:.8f}" for v in f["quaternion_wxyz"]))
    show("Z", Zf)
    show("X", Xf)
    for w in res.warnings:
        info(f"warning: {w}")
    result = {**res.to_dict(), "schema_version": 1, "pose_ids": ids, "frames": {"Z": Zf, "X": Xf}}
    if out is not None:
        paths = write_bundle(out, {"handeye.json": dumps_json(result) + "\n", "easy_handeye.yaml": easy_handeye_yaml(res.Z)})
        info("files: " + ", ".join(str(v) for v in paths.values()))
    if plot is not None:
        from ..plots.calibration import plot_handeye_residuals
        from ..plots.figure import save_figure

        title = f"{Path(poses).name}: hand-eye residuals per pose ({res.method}, chi2/dof {res.chi2_dof:.3g})"
        info(f"wrote {save_figure(plot_handeye_residuals(res.residuals, res.residual_chi2, title), plot)}")
    if json_out:
        emit_json(result)
