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

from ..errors import ConfigError, LensforgeError
from ..fileio import dumps_json, read_json
from ..input_checks import POSE_TRANSLATION, Num, check_header, number, number_array
from ._common import emit_json, end_on_failed_check, info

_NOISE_KEYS = ("robot_sigma_trans_mm", "robot_sigma_rot_deg", "lens_sigma_trans_mm", "lens_sigma_rot_deg")
# ASSUMPTION: 1-sigma beyond 10 mm or 10 deg is no calibration noise but a unit or typing mistake
_NOISE_MAX = {"robot_sigma_trans_mm": 10.0, "robot_sigma_rot_deg": 10.0, "lens_sigma_trans_mm": 10.0,
              "lens_sigma_rot_deg": 10.0}


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
            top = _NOISE_MAX[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or not 0 <= v <= top:
                raise ConfigError(f"{name}:noise.{k}: must be a number from 0 to {top:g} "
                                  f"({'mm' if k.endswith('_mm') else 'deg'}, 1-sigma per axis), got {v!r}")
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


NOISE_FILE_KEYS = _NOISE_KEYS + ("noise", "cov_A", "cov_B", "sigma_A", "sigma_B", "schema_version", "kind")


def load_noise_file(path: Path, n: int) -> tuple:
    """(sigma, cov_B) of a --noise JSON file: the flat keys --help shows
    ({"robot_sigma_trans_mm": 0.02, ...}), the same under "noise", or cov_A / cov_B (and the
    legacy sigma_A / sigma_B). Unknown keys and negative sigmas are refused; a file that sets
    no noise at all too."""
    data = read_json(path, "noise file")
    name = Path(path).name
    if not isinstance(data, dict):
        raise ConfigError(f"noise file {path}: expected a JSON object with keys {', '.join(_NOISE_KEYS)}")
    unknown = sorted(set(data) - set(NOISE_FILE_KEYS))
    if unknown:
        raise ConfigError(f"{name}: unknown key(s) {', '.join(unknown)}; expected {', '.join(_NOISE_KEYS)} "
                          "(1-sigma per axis) or cov_A / cov_B")
    flat = {k: data[k] for k in _NOISE_KEYS if k in data}
    if flat and "noise" in data:
        raise ConfigError(f"{name}: give the sigmas either at the top level or under \"noise\", not both")
    if flat:
        data = {**{k: v for k, v in data.items() if k not in _NOISE_KEYS}, "noise": flat}
    sigma, cov_B = noise_model(data, name, n)
    if sigma is None and cov_B is None:
        raise ConfigError(f"{name}: no noise given (every sigma is 0 or missing); give "
                          f"{', '.join(_NOISE_KEYS)} or leave out --noise to estimate it from the residuals")
    return sigma, cov_B


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


def diagnose_handeye(kw: dict, method: str, failed) -> dict | None:
    """The likely mistake behind a hand-eye solve that fails its model check: re-solve with A
    or B in other units, inverted, or A and B swapped (each a fraction of a second); the
    first whose solve passes, as {"mistake", "message", "chi2_dof_before", "chi2_dof_after"}."""
    from ..calibration.handeye import solve_handeye
    from ..calibration.model_check import check_chi2
    from ..optics.pose import invert_poses

    A, B = kw["A"], kw["B"]

    def scaled(M, k):
        M = M.copy()
        M[:, :3, 3] *= k
        return M
    tries = [("units m", "the fit passes if the poses are read in m: the file's units are probably wrong",
              scaled(A, 1e3), scaled(B, 1e3)),
             ("units mm", "the fit passes if the poses are read in mm: the file's units are probably wrong",
              scaled(A, 1e-3), scaled(B, 1e-3)),
             ("A units", "the fit passes if A (robot) is read in other units (x1000)", scaled(A, 1e3), B),
             ("A units", "the fit passes if A (robot) is read in other units (/1000)", scaled(A, 1e-3), B),
             ("B units", "the fit passes if B (lens) is read in other units (x1000)", A, scaled(B, 1e3)),
             ("B units", "the fit passes if B (lens) is read in other units (/1000)", A, scaled(B, 1e-3)),
             ("A inverted", "the fit passes if A is inverted: give the flange in the robot base (^W T_E), not "
                            "the base in the flange", invert_poses(A), B),
             ("B inverted", "the fit passes if B is inverted: give the lens in the sensor frame (^S T_O)",
              A, invert_poses(B)),
             ("A and B swapped", "the fit passes with A and B swapped: A is the robot flange, B the lens", B, A)]
    best = None
    for name, message, A2, B2 in tries:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r = solve_handeye(A2, B2, method=method, sigma=kw["sigma"], cov_B=kw["cov_B"], on_degenerate="warn")
        except (LensforgeError, np.linalg.LinAlgError, ValueError):  # a try that cannot be solved explains nothing
            continue
        # passing, and closest to the noise model (chi2/dof ~ 1): rescaling A and B together also
        # "passes", with the noise then far too large for the numbers (chi2/dof << 1)
        if check_chi2(r.chi2, r.dof).passed and r.chi2_dof > 0:
            score = abs(np.log(r.chi2_dof))
            if best is None or score < best[0]:
                best = (score, {"mistake": name, "message": message, "chi2_dof_before": float(failed.chi2_dof),
                                "chi2_dof_after": float(r.chi2_dof)})
    return None if best is None else best[1]


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
    accept_failed_check: bool = typer.Option(False, "--accept-failed-check",
                                             help="write the result of a solve that fails its chi2 model check as "
                                                  "a calibration anyway (research); default: exit 3, no "
                                                  "easy_handeye.yaml"),
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
        kw["sigma"], kw["cov_B"] = load_noise_file(noise, kw["A"].shape[0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = solve_handeye(kw["A"], kw["B"], method=method, sigma=kw["sigma"], cov_B=kw["cov_B"],
                            on_degenerate="warn" if allow_degenerate else "raise",
                            obs_limits=(obs_limit_mm, obs_limit_rad))
    from ..calibration.model_check import check_chi2

    mc = check_chi2(res.chi2, res.dof, what="hand-eye solve") if res.noise_model == "given" else None
    valid = mc is None or mc.passed
    mistake = None
    if not valid and not accept_failed_check:
        mistake = diagnose_handeye(kw, method, mc)
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
    result = {**res.to_dict(), "schema_version": 1, "pose_ids": ids, "frames": {"Z": Zf, "X": Xf},
              "valid": valid, "check_failure": None if valid else mc.reason,
              "model_check": (mc.to_dict() if mc is not None else
                              {"valid": True, "reason": "no noise model given: the noise is estimated from the "
                                                        "residuals, so chi2 cannot test the fit"}),
              **({"diagnosis": mistake} if mistake is not None else {})}
    if not valid:
        info(f"MODEL CHECK FAILED: {mc.reason}; not a calibration" + ("" if accept_failed_check else
                                                                        ": no easy_handeye.yaml written"))
    if out is not None:
        files = {"handeye.json": dumps_json(result) + "\n"}
        if valid or accept_failed_check:
            files["easy_handeye.yaml"] = easy_handeye_yaml(res.Z)
        paths = write_bundle(out, files, drop=() if "easy_handeye.yaml" in files else ("easy_handeye.yaml",))
        info("files: " + ", ".join(str(v) for v in paths.values()))
    if plot is not None:
        from ..plots.calibration import plot_handeye_residuals
        from ..plots.figure import save_figure

        title = f"{Path(poses).name}: hand-eye residuals per pose ({res.method}, chi2/dof {res.chi2_dof:.3g})"
        info(f"wrote {save_figure(plot_handeye_residuals(res.residuals, res.residual_chi2, title), plot)}")
    if json_out:
        emit_json(result)
    end_on_failed_check(valid, None if mc is None else mc.reason, res.chi2_dof, accept_failed_check,
                        mistake=None if mistake is None else mistake["message"],
                        unexplained=("the residuals exceed the given noise model; none of the usual mistakes "
                                     "(units, inverted A or B, A and B swapped) explains it; check the noise model "
                                     "and the pose files" + (f"; diagnostics in {out}" if out is not None else "")))
