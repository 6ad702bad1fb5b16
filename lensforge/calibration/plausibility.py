"""Plausibility checks before fitting: inputs that cannot be right are refused up front,
with the field, the values and the likely fix in one line (ConfigError).

- WFS files: an all-zero or constant file (no sensor reports the same wavefront at
  different poses to the last digit: a sensor that was not running, or a file of zeros);
  header values (wavelength, pupil) that contradict the bench are an error naming both,
  unless the caller chooses one (``wfs_header="file"`` or ``"bench"``).
- Robot flange poses beyond the robot's reach (a pose at 1 km, a KUKA cell with
  ``--robot ur5e``); a file whose poses come within reach read in other units says so.
- Robot repeatability and noise values outside physical ranges.
- A pose plan whose motion leaves hand-eye directions numerically unobservable (identical
  poses, rotations about one axis): refused, naming the directions.
- Resource limits (``MAX_POSES``, ``job_memory_bytes``): a job that cannot fit in memory is
  refused before it starts, with the estimate.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import ConfigError, LensforgeError
from .thorlabs import check_not_all_zero

__all__ = ["HEADER_RTOL", "HEADER_TOLERANCE", "INSTRUMENT_TOLERANCE", "MAX_POSES", "REPEATABILITY_RANGE_MM",
           "check_wfs_header", "check_wfs_values", "check_robot_reach", "check_repeatability", "check_plan_motion", "job_memory_bytes", "check_job_memory",
           "available_memory_bytes", "WFS_HEADER_MODES", "pose_file_kind", "check_poses_count"]

HEADER_RTOL = 1e-3  # header and bench agree to this relative difference (0.9 vs 0.9009 mm: printed rounding)
HEADER_ATOL_MM = 1e-3  # pupil centre: 1 um
WFS_HEADER_MODES = ("error", "file", "bench")

# ISO 9283 pose repeatability RP of industrial arms: 0.005 mm (small SCARA/precision arms) to
# ~0.5 mm (large payload arms); KR 10 +-0.02 mm, UR5e +-0.03 mm (data sheets). ASSUMPTION: a
# factor 5 beyond either end is a typing or unit mistake.
REPEATABILITY_RANGE_MM = (1e-3, 2.5)

# Poses per calibration, study trial or plan: a bench session has 12-50, and `lensforge plan`'s
# working box holds ~150 lit candidates. Cost and memory grow linearly (job_memory_bytes); measured
# on the paper bench (extended_polynomial, joint default, 1 core): 100 poses 33 s CPU / 0.71 GB,
# 150 poses 47 s / 0.95 GB, a study trial of 300 poses 88 s / 1.6 GB, of 1500 poses over 100 s /
# 3.2 GB. ASSUMPTION: more than 100 is a mistake, refused up front (a minute and a GB on bad input).
MAX_POSES = 100
# Rows of a robot-pose or WFS file (a robot log may hold many more rows than the matched poses);
# reading and matching them is cheap, only the matched poses (MAX_POSES) are calibrated.
MAX_ROWS = 2000
REACH_MARGIN_MM = 100.0  # ASSUMPTION: reach data sheets round; a flange pose this far beyond is not a pose


def pose_file_kind(path) -> tuple[str, str | None]:
    """(POSE_READERS name, units as written or None) of a robot-pose file, as
    ``formats.read_robot_poses`` detects it."""
    p = Path(path)
    if p.suffix.lower() == ".json":
        try:
            from ..fileio import read_json  # noqa: PLC0415

            return "json_4x4", str(read_json(p, "robot poses file").get("units"))
        except (LensforgeError, AttributeError):
            return "json_4x4", None
    units = None
    try:
        with open(p, "rb") as fh:  # the head only: a device or a huge file is not read whole
            text = fh.read(1 << 16).decode("utf-8-sig", errors="replace")
    except OSError:
        return "xyzabc_csv", None
    for line in text.splitlines():
        s = line.strip().lower()
        if s.startswith("#"):
            body = s.lstrip("#").strip()
            if body.startswith("units:"):
                units = body.split(":", 1)[1].strip()
            continue
        if s:
            return ("quaternion_csv" if "qw" in s else "xyzabc_csv"), units
    return "xyzabc_csv", units


# the header values a WFS file may carry, the bench field each must agree with, its unit and
# the difference tolerated: lensforge's own CSV writes them exactly (relative 1e-3: printed
# rounding, 0.9 vs 0.9009 mm; centre 1 um), an instrument's file to the software's printed
# precision (Thorlabs: wavelength to 0.5 nm, pupil diameter and centre to 0.01 mm)
_HEADER_FIELDS = (("wavelength_nm", "laser.wavelength_nm", "nm"),
                  ("pupil_radius_mm", "sensor.pupil_radius_mm", "mm"),
                  ("pupil_center_mm", "sensor.pupil_center_mm", "mm"))
HEADER_TOLERANCE = {"wavelength_nm": ("rel", HEADER_RTOL), "pupil_radius_mm": ("rel", HEADER_RTOL),
                    "pupil_center_mm": ("abs", HEADER_ATOL_MM)}
INSTRUMENT_TOLERANCE = {"wavelength_nm": ("abs", 0.5), "pupil_radius_mm": ("abs", 0.005),
                        "pupil_center_mm": ("abs", 0.005)}


def _bench_value(bench, field_: str):
    part, name = field_.split(".")
    return np.asarray(getattr(getattr(bench, part), name), float)


def _show(v: np.ndarray) -> str:
    return f"{float(v):g}" if v.ndim == 0 else "(" + ", ".join(f"{float(c):g}" for c in v) + ")"


def check_wfs_header(bench, header: dict, source: str, mode: str = "error") -> dict:
    """The header values to apply for WFS ``header`` against ``bench``.

    mode "error" (default): a value that contradicts the bench is a ConfigError naming both;
    "file": the file's values win; "bench": the bench's win (header values dropped). An
    instrument's own file (header ``instrument_file``: Thorlabs exports, SDK spot fields)
    describes the instrument's settings, so it must agree with the bench in "file" mode too,
    to the software's printed precision (``INSTRUMENT_TOLERANCE``)."""
    if mode not in WFS_HEADER_MODES:
        raise ConfigError(f"--wfs-header: {mode!r} is not one of {', '.join(WFS_HEADER_MODES)}")
    if mode == "bench":
        return {}
    instrument = bool(header.get("instrument_file"))
    if mode == "file" and not instrument:
        return dict(header)
    tolerance = INSTRUMENT_TOLERANCE if instrument else HEADER_TOLERANCE
    fix = ("set the instrument's setting to the bench's or give the bench of this instrument (--bench)"
           if instrument else "fix the WFS software's setting or the bench, or choose one with --wfs-header file|bench")
    for key, field_, unit in _HEADER_FIELDS:
        if key not in header:
            continue
        v, ref = np.asarray(header[key], float), _bench_value(bench, field_)
        kind, tol = tolerance[key]
        if np.max(np.abs(v - ref)) > (tol * np.max(np.abs(ref)) if kind == "rel" else tol):
            extra = f" (diameter {2 * float(v):g} against {2 * float(ref):g} mm)" if key == "pupil_radius_mm" else ""
            raise ConfigError(f"{source}: field {key}: the file's {_show(v)} {unit} contradicts the bench's "
                              f"{field_} = {_show(ref)} {unit}{extra}; {fix}")
    return dict(header)


def check_wfs_values(zernike_thorlabs: np.ndarray, source: str, rows=()) -> None:
    """Refuse an all-zero WFS file, a row of zeros, and a file whose rows are all the same."""
    check_not_all_zero(zernike_thorlabs, source)
    z = np.asarray(zernike_thorlabs, float)
    body = z[:, 1:] if z.shape[1] > 1 else z  # piston is ignored
    zero = np.flatnonzero(np.all(body == 0.0, axis=1))
    if len(zero):
        row = rows[zero[0]] if len(rows) > zero[0] else zero[0] + 1
        raise ConfigError(f"{source}: row {row}: every coefficient is 0 (a pose without a measurement); remove the row "
                          "or measure the pose again")
    if len(body) >= 2 and np.all(body == body[0]):
        raise ConfigError(f"{source}: all {len(body)} rows hold the same coefficients: the sensor did not measure "
                          "each pose (a copied row or a frozen export); export one measurement per pose")


def _reach_limit(robot) -> float:
    base = float(np.linalg.norm(robot.origins_mm[0])) if robot.origins_mm else 0.0
    return float(robot.reach_mm) + base + REACH_MARGIN_MM


def check_robot_reach(T: np.ndarray, robot, source: str, rows=(), units: str | None = None) -> None:
    """Refuse flange poses (n, 4, 4) (mm) beyond the robot's reach (its reach_mm from the base
    plus the base height and a margin); says so when the poses come within reach read in mm
    instead of m, or for another robot."""
    T = np.asarray(T, float)
    d = np.linalg.norm(T[:, :3, 3], axis=1)
    lim = _reach_limit(robot)
    bad = np.flatnonzero(d > lim)
    if not bad.size:
        return
    i = bad[0]
    row = rows[i] if len(rows) > i else i + 1
    hint = "check the file's units and the --robot model"
    if np.all(d / 1000.0 <= lim):
        hint = ("a thousandth of it is in reach: " + ("the values are probably mm: its `# units: m` line is probably wrong"
                                                       if units == "m" else "the values are probably um, not mm; "
                                                       "check the exporter's length unit"))
    raise ConfigError(f"{source}: row {row}: the flange is {d[i]:.6g} mm from the robot base, beyond the "
                      f"{robot.name}'s reach ({robot.reach_mm:g} mm); {hint}")


def check_repeatability(value_mm: float, where: str) -> float:
    """A robot repeatability (mm, ISO 9283 RP) inside ``REPEATABILITY_RANGE_MM``."""
    lo, hi = REPEATABILITY_RANGE_MM
    if not lo <= value_mm <= hi:
        raise ConfigError(f"{where}.repeatability_mm: {value_mm:g} mm is outside the physical range of robot arms "
                          f"({lo:g} to {hi:g} mm, ISO 9283 data sheets; a KR 10 has 0.02 mm); check the value and "
                          "its unit")
    return value_mm


def check_plan_motion(x: np.ndarray, T_SO_nominal: np.ndarray, X: np.ndarray, source: str) -> None:
    """Refuse a plan of lens poses x (n, 6) (mm, rad about nominal) whose motion leaves a
    hand-eye direction numerically null (identical poses, one rotation axis), naming them."""
    from ..optics.pose import pose_to_matrix
    from .handeye import handeye_observability

    x = np.asarray(x, float)
    B = np.asarray(T_SO_nominal, float) @ pose_to_matrix(x)
    sigma = np.diag([0.01 ** 2] * 3 + [1e-5 ** 2] * 3)  # any noise: only numerically null directions are refused
    obs = handeye_observability(B, X, sigma=sigma, cov_B=sigma, obs_limits=(1e9, 1e9))
    if obs["degenerate"]:
        distinct = len(np.unique(np.round(x, 9), axis=0))
        names = list(obs["null_directions"]) or ["some directions of X and Z"]
        if distinct == 1:
            what = (f"its {len(x)} poses are identical: without motion the rotations of X and Z and their "
                    f"translations along them are unobservable ({len(names)} directions)")
        else:
            what = (f"its {distinct} distinct poses leave {len(names)} direction(s) unobservable: "
                    + "; ".join(names[:2]) + (f"; and {len(names) - 2} more" if len(names) > 2 else ""))
        raise ConfigError(f"{source}: degenerate pose plan, {what}; give poses that rotate about at least two "
                          "different axes")


BYTES_PER_RAY_DIRECTION = 400.0  # measured: ForwardModel.jacobians of 400 poses, 113 lenslets x 4 rays, 6 directions:
# 357 MB more peak RSS than 50 poses (1.0 MB per pose = 452 rays x 6 x ~400 B); see tests/test_model_check.py


def job_memory_bytes(n_poses: int, n_modes: int, n_lenslets: int, n_params: int = 30, rays_per_lenslet: int = 4) -> float:
    """Estimated peak memory (bytes) of one calibration over n_poses: the batched trace holds,
    per pose, every aimed ray's state and its tangents along the 6 pose and n_params lens
    directions (``BYTES_PER_RAY_DIRECTION`` each, measured), plus the Zernike Jacobians and a
    fixed 200 MB of interpreter and libraries."""
    per_pose = n_lenslets * rays_per_lenslet * (6 + n_params) * BYTES_PER_RAY_DIRECTION + n_modes * (6 + n_params) * 32
    return float(n_poses) * per_pose + 200e6


def available_memory_bytes() -> float:
    """MemAvailable of the machine, capped by the cgroup's memory.max (inf if unknown)."""
    avail = float("inf")
    try:
        with open("/proc/meminfo") as fh:
            for ln in fh:
                if ln.startswith("MemAvailable:"):
                    avail = float(ln.split()[1]) * 1024.0
    except OSError:
        pass
    try:
        with open("/proc/self/cgroup") as fh:
            rel = next((ln.split(":", 2)[2].strip() for ln in fh if ln.startswith("0::")), None)
        if rel is not None:
            base = f"/sys/fs/cgroup{rel.rstrip('/')}"
            with open(f"{base}/memory.max") as fh:
                mx = fh.read().strip()
            with open(f"{base}/memory.current") as fh:
                cur = float(fh.read().strip())
            if mx.isdigit():
                avail = min(avail, float(mx) - cur)
    except (OSError, StopIteration, ValueError):
        pass
    return avail


def check_job_memory(estimate_bytes: float, what: str, option: str) -> None:
    """Refuse a job whose estimated memory exceeds what is available (or 64 GB), before it starts."""
    avail = min(available_memory_bytes(), 64e9)
    if estimate_bytes > 0.8 * avail:
        raise ConfigError(f"{option}: {what} needs about {estimate_bytes / 1e9:.3g} GB of memory, more than the "
                          f"{avail / 1e9:.3g} GB available; reduce it")


def check_poses_count(n: int, option: str, limit: int = MAX_POSES) -> int:
    """A number of poses from 3 to ``limit``."""
    if not 3 <= n <= limit:
        raise ConfigError(f"{option}: {n} poses is outside 3 .. {limit} (a calibration needs at least 3; "
                          f"more than {limit} is beyond any bench session and only costs minutes and gigabytes)")
    return n


def finite_positive(v: float) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
