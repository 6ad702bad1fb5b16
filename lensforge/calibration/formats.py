"""Files of the real bench: robot flange poses, WFS Zernike exports, plans and results.

Readers and writers are registries (name -> function, as trimesh's exchange modules):
readers return validated arrays, writers return text, and ``write_bundle`` writes a
set of outputs atomically as one folder (``fileio.write_atomic`` per file inside a
temporary folder, then one rename). Every bad file raises ConfigError naming the
file, the row (1-based line number) and the field.

Robot flange poses ^W T_E (one pose per robot-recorded position, by id):

- ``xyzabc_csv``: ``pose,X,Y,Z,A,B,C``; X, Y, Z in mm, A, B, C in degrees, KUKA
  convention R = Rz(A) Ry(B) Rx(C) (KUKA System Software manual, "ABC" angles of
  $POS_ACT). An optional ``# units: mm`` line; other units are an error.
- ``quaternion_csv``: ``pose,x,y,z,qw,qx,qy,qz`` with a ``# units: m`` or
  ``# units: mm`` line before the header (mandatory: ROS tools write metres).
  Quaternions are normalised when their norm is within 1e-3 of 1 (printed ones
  are rounded); farther is an error.
- ``json_4x4``: ``{"schema_version": 1, "kind": "robot_poses", "units": "mm"|"m",
  "poses": [{"pose": ID, "matrix": 4x4}, ...]}``; the rotation block must be
  orthonormal with det +1 to 1e-6.

WFS measurements (Zernike coefficients of the wavefront in um of OPD):

- ``wfs_csv``: one row per pose, ``pose,Z1,Z2,...,ZK``: Thorlabs mode numbers
  k = OSA/ANSI j + 1 (mode 1 = piston, ignored), K a complete radial order
  ((n+1)(n+2)/2 columns). Optional header lines ``# wavelength_nm: 532``,
  ``# pupil_center_mm: 0.0, 0.0``, ``# pupil_radius_mm: 0.9`` describe the WFS
  software's pupil; absent ones come from the bench. ASSUMPTION: the coefficients
  are RMS-normalised (ANSI Z80.28) in um, with the sign of the WFS's wavefront
  (positive OPD leading), the lensforge convention.
  WFS software settings that produce it (Thorlabs WFS, "Setup"): wavelength = the
  laser's; pupil "circular", centre and diameter = the bench pupil (in mm, sensor
  coordinates); Zernike fit "up to order" = the bench's sensor.zernike_order (or
  higher: the file's order is used); wavefront unit um; no tip/tilt removal; then
  export the Zernike table of each pose and put them one row per pose id.
- ``wfs_json``: lensforge's own format ``{"schema_version": 1, "kind":
  "wfs_zernike", "units": "um", "ordering": "thorlabs", "wavelength_nm", 
  "pupil_center_mm", "pupil_radius_mm", "measurements": [{"pose": ID,
  "zernike": [Z1..ZK]}]}``.

- ``thorlabs_export``: a folder or a glob of the Thorlabs WFS software's own export
  files, one per pose, the pose id the last integer in each file name (or a pattern);
  modes by their explicit Order/Frequency; wavelength and pupil checked against the
  bench (a contradiction is an error naming both). Layout and the instrument settings
  that give a usable file: ``calibration.thorlabs``.
- ``spot_field``: a folder or glob of SDK spot-deviation fields (pixels, [Y][X], NaN =
  no spot, with the MLA data), CSV or NPZ, one per pose (``calibration.thorlabs``);
  calibrated on the per-lenslet slopes (``calibration.measurement``).
  A file whose tilt modes (or mean spot deviation) are zero in every pose was taken
  with tilt cancel ON and is refused, naming the setting.

Robot poses also come as KUKA ``$POS_ACT`` logs (``kuka_log``, format ``kuka_log``).

Plans (``PLAN_WRITERS``): ``csv`` (xyzabc_csv), ``json`` (json_4x4), ``krl`` (a
KUKA KRL ``.src``/``.dat`` pair, see ``krl_program``).
"""

from __future__ import annotations

import csv
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import ConfigError
from ..input_checks import field_number
from ..interrupts import committing, note_staging
from ..fileio import MAX_TABLE_BYTES, dumps_json, read_bounded, read_json, write_atomic

if TYPE_CHECKING:
    from .thorlabs import SpotFields

__all__ = [
    "xyzabc_to_matrix", "matrix_to_xyzabc", "quaternion_to_matrix", "matrix_to_quaternion",
    "PoseTable", "WfsData", "read_robot_poses", "read_wfs", "POSE_READERS", "WFS_READERS",
    "PLAN_WRITERS", "write_bundle", "krl_program", "easy_handeye_yaml", "pose_table_json",
    "wfs_csv", "ORTHO_TOL", "rotation_defects",
]

ORTHO_TOL = 1e-6  # |R^T R - I| tolerated in a rotation block
QUAT_NORM_TOL = 1e-3  # |(|q| - 1)| tolerated before normalising a printed quaternion
_UNITS_MM = {"mm": 1.0, "m": 1000.0}


# ----------------------------------------------------------------------------- conversions


def xyzabc_to_matrix(xyzabc) -> np.ndarray:
    """4x4 transform(s) (..., 4, 4) of KUKA X, Y, Z (mm), A, B, C (deg): R = Rz(A) Ry(B) Rx(C)."""
    v = np.asarray(xyzabc, dtype=float)
    flat = v.reshape(-1, 6)
    T = np.zeros((flat.shape[0], 4, 4))
    T[:, :3, :3] = Rotation.from_euler("ZYX", flat[:, 3:], degrees=True).as_matrix()
    T[:, :3, 3] = flat[:, :3]
    T[:, 3, 3] = 1.0
    return T.reshape(v.shape[:-1] + (4, 4))


def matrix_to_xyzabc(T) -> np.ndarray:
    """KUKA X, Y, Z (mm), A, B, C (deg) (..., 6) of 4x4 transform(s); A, C in (-180, 180],
    B in [-90, 90] (at B = +-90 deg only A - C or A + C is defined; C is then 0)."""
    T = np.asarray(T, dtype=float)
    flat = T.reshape(-1, 4, 4)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # gimbal lock: scipy sets the third angle to 0
        abc = Rotation.from_matrix(flat[:, :3, :3]).as_euler("ZYX", degrees=True)
    return np.concatenate([flat[:, :3, 3], abc], axis=1).reshape(T.shape[:-2] + (6,))


def quaternion_to_matrix(xyz, q_wxyz) -> np.ndarray:
    """4x4 transform(s) of translation(s) (..., 3) and unit quaternion(s) (w, x, y, z)."""
    xyz = np.asarray(xyz, dtype=float)
    q = np.asarray(q_wxyz, dtype=float).reshape(-1, 4)
    T = np.zeros((q.shape[0], 4, 4))
    T[:, :3, :3] = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    T[:, :3, 3] = xyz.reshape(-1, 3)
    T[:, 3, 3] = 1.0
    return T.reshape(xyz.shape[:-1] + (4, 4))


def matrix_to_quaternion(T) -> np.ndarray:
    """Unit quaternion(s) (..., 4) (w, x, y, z), w >= 0, of 4x4 transform(s) or 3x3 rotations."""
    M = np.asarray(T, dtype=float)
    R = M[..., :3, :3]
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()[:, [3, 0, 1, 2]]
    q[q[:, 0] < 0] *= -1.0
    return q.reshape(R.shape[:-2] + (4,))


# ----------------------------------------------------------------------------- containers


@dataclass(frozen=True, eq=False)
class PoseTable:
    """Poses by id: ids (n,) strings, T (n, 4, 4) in mm, source (file name), rows (n,)
    line numbers in the source (for messages); times: (n,) s of a robot log matched to the
    WFS files by time (``kuka_log``), else None."""

    ids: tuple
    T: np.ndarray
    source: str = ""
    rows: tuple = ()
    times: np.ndarray | None = None  # (n,) record times (s) of a log without ids (kuka_log)


@dataclass(frozen=True, eq=False)
class WfsData:
    """WFS Zernike measurements by pose id.

    ids (n,); zernike (n, K) in um in Thorlabs order (entry k-1 = mode k, piston
    first); order: radial order of the K modes; header: wavelength_nm,
    pupil_center_mm, pupil_radius_mm where the file gave them."""

    ids: tuple
    zernike: np.ndarray
    order: int
    header: dict = field(default_factory=dict)
    source: str = ""
    rows: tuple = ()


# ----------------------------------------------------------------------------- CSV helpers


def _read_text(path: Path, what: str) -> str:
    try:  # bounded: /dev/zero or a huge file is refused, not read whole (fileio.MAX_TABLE_BYTES)
        return read_bounded(path, what, MAX_TABLE_BYTES).decode("utf-8-sig")  # a UTF-8 BOM (Excel) is not data
    except FileNotFoundError:
        raise ConfigError(f"{what} {path}: not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{what} {path}: cannot be read ({e})") from None


def _split_csv(path: Path, what: str):
    """(comments {key: value}, header [names], rows [(line_no, [fields])]) of a CSV with
    ``# key: value`` comment lines before the header."""
    text = _read_text(path, what)
    comments, header, rows = {}, None, []
    for no, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            body = s.lstrip("#").strip()
            if ":" in body:
                k, v = body.split(":", 1)
                comments[k.strip().lower()] = (no, v.strip())
            continue
        fields = [f.strip() for f in next(csv.reader([s]))]
        if header is None:
            header = (no, [f.lower() for f in fields])
        else:
            rows.append((no, fields))
    if header is None:
        raise ConfigError(f"{path}: no header row; expected a CSV header line (see the file format in the docs)")
    if not rows:
        raise ConfigError(f"{path}: no data rows after the header")
    return comments, header, rows


def _ids_unique(path: Path, ids: list, rows: list) -> None:
    seen = {}
    for i, r in zip(ids, rows):
        if not i:
            raise ConfigError(f"{path}: row {r}, field pose: empty pose id")
        if i in seen:
            raise ConfigError(f"{path}: row {r}, field pose: duplicate pose id {i!r} (first at row {seen[i]}); "
                              "give each recorded pose its own id")
        seen[i] = r


def _check_header(path: Path, header, expected: list[str]):
    no, names = header
    if names != expected:
        raise ConfigError(f"{path}: row {no}, header: expected columns {','.join(expected)}, got {','.join(names)}")


def _numeric_rows(path: Path, rows, names: list[str]):
    """ids, (n, len(names)-1) numbers, line numbers; names as the messages show them."""
    ids, vals, nos = [], [], []
    for no, f in rows:
        if len(f) != len(names):
            raise ConfigError(f"{path}: row {no}: {len(f)} fields, expected {len(names)} ({','.join(names)})")
        ids.append(f[0])
        vals.append([field_number(path, no, n, t) for n, t in zip(names[1:], f[1:])])
        nos.append(no)
    _ids_unique(path, ids, nos)
    return ids, np.array(vals, dtype=float), nos


def _units(path: Path, comments: dict, required: bool, allowed=("mm", "m")) -> float:
    if "units" not in comments:
        if required:
            raise ConfigError(f"{path}: field units: missing; add a first line '# units: m' or '# units: mm'")
        return 1.0
    no, u = comments["units"]
    if u not in allowed:
        raise ConfigError(f"{path}: row {no}, field units: {u!r} is not one of {', '.join(allowed)}")
    return _UNITS_MM[u]


def rotation_defects(R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(|R^T R - I| max, det R, indices of improper ones) for rotation blocks R (n, 3, 3):
    improper = not orthonormal to ORTHO_TOL or det < 0."""
    orth = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    return orth, det, np.flatnonzero((orth > ORTHO_TOL) | (det < 0))


def _check_rotations(path: Path, T: np.ndarray, rows, field_name: str = "matrix") -> np.ndarray:
    orth, det, bad = rotation_defects(T[:, :3, :3])
    if bad.size:
        i = bad[0]
        raise ConfigError(f"{path}: row {rows[i]}, field {field_name}: rotation is not orthonormal with det +1 to "
                          f"1e-6 (|R^T R - I| = {orth[i]:.2e}, det = {det[i]:.6f}); export full-precision rotations")
    last = np.abs(T[:, 3, :] - [0, 0, 0, 1]).max(axis=1)
    bad = np.flatnonzero(last > 1e-9)
    if bad.size:
        raise ConfigError(f"{path}: row {rows[bad[0]]}, field {field_name}: last row must be [0, 0, 0, 1]")
    U, _, Vt = np.linalg.svd(T[:, :3, :3])
    T = T.copy()
    T[:, :3, :3] = U @ Vt  # exact SO(3) (removes ~1e-12 rounding)
    return T


# ----------------------------------------------------------------------------- pose readers


def read_xyzabc_csv(path) -> PoseTable:
    """Flange poses from ``pose,X,Y,Z,A,B,C`` (mm, deg, KUKA R = Rz(A) Ry(B) Rx(C))."""
    path = Path(path)
    comments, header, rows = _split_csv(path, "robot poses file")
    _units(path, comments, required=False, allowed=("mm",))
    names = ["pose", "x", "y", "z", "a", "b", "c"]
    _check_header(path, header, names)
    ids, v, nos = _numeric_rows(path, rows, ["pose", "X", "Y", "Z", "A", "B", "C"])
    _check_range(path, v[:, 3:], nos, ["A", "B", "C"], MAX_ANGLE_DEG, "deg")
    return PoseTable(tuple(ids), xyzabc_to_matrix(v), str(path), tuple(nos))


def read_quaternion_csv(path) -> PoseTable:
    """Flange poses from ``pose,x,y,z,qw,qx,qy,qz`` with a ``# units: m|mm`` line."""
    path = Path(path)
    comments, header, rows = _split_csv(path, "robot poses file")
    scale = _units(path, comments, required=True)
    names = ["pose", "x", "y", "z", "qw", "qx", "qy", "qz"]
    _check_header(path, header, names)
    ids, v, nos = _numeric_rows(path, rows, names)
    q = v[:, 3:]
    nq = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(nq - 1.0) > QUAT_NORM_TOL)
    if bad.size:
        raise ConfigError(f"{path}: row {nos[bad[0]]}, field qw..qz: quaternion norm {nq[bad[0]]:.6f} is not 1 "
                          f"(within {QUAT_NORM_TOL:g}); give a unit quaternion (w, x, y, z)")
    return PoseTable(tuple(ids), quaternion_to_matrix(v[:, :3] * scale, q / nq[:, None]), str(path), tuple(nos))


def _read_lensforge_json(path: Path, what: str, kind: str) -> dict:
    """A lensforge JSON file of this kind with schema_version 1 (ConfigError otherwise)."""
    data = read_json(path, what)
    if not isinstance(data, dict) or data.get("kind") != kind:
        raise ConfigError(f"{path}: field kind: expected a JSON object with \"kind\": \"{kind}\"")
    if data.get("schema_version") != 1:
        raise ConfigError(f"{path}: field schema_version: expected 1, got {data.get('schema_version')!r}")
    return data


def read_json_4x4(path) -> PoseTable:
    """Flange poses from lensforge's JSON (see the module docstring)."""
    path = Path(path)
    data = _read_lensforge_json(path, "robot poses file", "robot_poses")
    if data.get("units") not in _UNITS_MM:
        raise ConfigError(f"{path}: field units: missing or not \"mm\"/\"m\" (got {data.get('units')!r})")
    poses = data.get("poses")
    if not isinstance(poses, list) or not poses:
        raise ConfigError(f"{path}: field poses: expected a non-empty list of {{\"pose\": id, \"matrix\": 4x4}}")
    ids, Ts, nos = [], [], []
    for i, p in enumerate(poses):
        row = i + 1
        if not isinstance(p, dict) or "pose" not in p or "matrix" not in p:
            raise ConfigError(f"{path}: row {row} (poses[{i}]), field pose/matrix: missing")
        try:
            M = np.asarray(p["matrix"], dtype=float)
        except (TypeError, ValueError):
            raise ConfigError(f"{path}: row {row} (poses[{i}]), field matrix: not a 4x4 numeric matrix") from None
        if M.shape != (4, 4):
            raise ConfigError(f"{path}: row {row} (poses[{i}]), field matrix: expected 4x4, got shape {M.shape}")
        if not np.all(np.isfinite(M)):
            raise ConfigError(f"{path}: row {row} (poses[{i}]), field matrix: NaN or infinite value")
        ids.append(str(p["pose"]).strip())
        Ts.append(M)
        nos.append(row)
    _ids_unique(path, ids, nos)
    T = np.array(Ts)
    T[:, :3, 3] *= _UNITS_MM[data["units"]]
    return PoseTable(tuple(ids), _check_rotations(path, T, nos), str(path), tuple(nos))


def _read_kuka_log(path) -> PoseTable:
    from .kuka_log import read_kuka_log

    path = Path(path)
    d = read_kuka_log(path)
    _check_range(path, d["xyzabc"][:, 3:], d["rows"], ["A", "B", "C"], MAX_ANGLE_DEG, "deg")
    return PoseTable(d["ids"], xyzabc_to_matrix(d["xyzabc"]), str(path), d["rows"], times=d["times"])


POSE_READERS = {"xyzabc_csv": read_xyzabc_csv, "quaternion_csv": read_quaternion_csv, "json_4x4": read_json_4x4,
                "kuka_log": _read_kuka_log}


def _reader_name(registry: dict, fmt: str, what: str) -> str:
    """fmt if it names one of the registry's readers, else ConfigError listing them."""
    if fmt not in registry:
        raise ConfigError(f"{what} format: {fmt!r} is not one of {', '.join(registry)}")
    return fmt


def _sniff_pose_format(path: Path) -> str:
    if path.suffix.lower() == ".json":
        return "json_4x4"
    text = _read_text(path, "robot poses file")
    for line in text.splitlines():
        s = line.strip().lower()
        if s and not s.startswith("#"):
            cols = [c.strip().lstrip("$") for c in s.replace(";", ",").split(",")]
            if "pos_act" in cols or "time" in cols or "timestamp" in cols or ("s" in cols and "t" in cols) \
                    or (cols and cols[0] != "pose" and "x" in cols):
                return "kuka_log"
            return "quaternion_csv" if "qw" in s else "xyzabc_csv"
    raise ConfigError(f"{path}: empty robot poses file")


def read_robot_poses(path: str | os.PathLike[str], fmt: str | None = None) -> PoseTable:
    """Robot flange poses ^W T_E by pose id.

    Parameters
    ----------
    path : str or os.PathLike
        A CSV ``pose,X,Y,Z,A,B,C`` (mm, degrees, KUKA R = Rz(A) Ry(B) Rx(C)), a CSV
        ``pose,x,y,z,qw,qx,qy,qz`` with a ``# units:`` line, or JSON 4x4.
    fmt : str, optional
        A ``POSE_READERS`` name, or None to detect it (.json -> json_4x4; a CSV header with
        qw -> quaternion_csv, else xyzabc_csv).

    Returns
    -------
    PoseTable
        ``ids`` (n,) strings, ``T`` (n, 4, 4) mm, ``source``, ``rows`` (line numbers).

    Raises
    ------
    ConfigError
        A bad file (one line naming the file, row and field).
    """
    path = Path(path)
    return POSE_READERS[_reader_name(POSE_READERS, fmt or _sniff_pose_format(path), "pose")](path)


# ----------------------------------------------------------------------------- WFS readers


def _order_of(k: int):
    n = 0
    while (n + 1) * (n + 2) // 2 < k:
        n += 1
    return n if (n + 1) * (n + 2) // 2 == k else None


def _wfs_header(path: Path, comments: dict) -> dict:
    h = {}
    for key, n in (("wavelength_nm", 1), ("pupil_radius_mm", 1), ("pupil_center_mm", 2)):
        if key not in comments:
            continue
        no, text = comments[key]
        vals = [field_number(path, no, key, t.strip()) for t in text.replace(";", ",").split(",") if t.strip()]
        if len(vals) != n:
            raise ConfigError(f"{path}: row {no}, field {key}: expected {n} number(s), got {text!r}")
        if key != "pupil_center_mm" and vals[0] <= 0:
            raise ConfigError(f"{path}: row {no}, field {key}: must be > 0")
        h[key] = vals[0] if n == 1 else tuple(vals)
    return h


MIN_WFS_ORDER = 3  # a pose has 6 DOF: order 3 is the first with >= 6 modes besides piston (9)
MAX_ZERNIKE_UM = 1e4  # ASSUMPTION: 1 cm of wavefront, far beyond any Shack-Hartmann sensor's range
MAX_ANGLE_DEG = 360.0  # robot controllers report A, B, C within one turn


def _check_modes(path: Path, k: int, where: str) -> int:
    order = _order_of(k)
    if order is None or order < 1:
        raise ConfigError(f"{path}: {where}: {k} Zernike modes is not a complete radial order "
                          "(3, 6, 10, 15, 21, ... modes with piston); export all modes up to the fit order")
    if order < MIN_WFS_ORDER:
        raise ConfigError(f"{path}: {where}: {k} Zernike modes (radial order {order}) cannot fix a 6-DOF pose; "
                          f"export all modes up to radial order {MIN_WFS_ORDER} or more (10 or more modes)")
    return order


def _check_range(path: Path, v: np.ndarray, nos, names, limit: float, unit: str) -> None:
    """Every |value| <= limit, else one line naming the row, field and limit."""
    bad = np.argwhere(np.abs(v) > limit)
    if bad.size:
        r, c = bad[0]
        raise ConfigError(f"{path}: row {nos[r]}, field {names[c]}: {v[r, c]:.6g} {unit} is beyond the plausible "
                          f"{limit:g} {unit}; check the file's units and columns")


def read_wfs_csv(path) -> WfsData:
    """WFS Zernike CSV (see the module docstring)."""
    path = Path(path)
    comments, header, rows = _split_csv(path, "WFS measurements file")
    hno, names = header
    if not names or names[0] != "pose":
        raise ConfigError(f"{path}: row {hno}, header: first column must be 'pose'")
    k = len(names) - 1
    order = _check_modes(path, k, f"row {hno}, header")
    expected = ["pose"] + [f"z{i}" for i in range(1, k + 1)]
    if names != expected:
        bad = next(i for i, (a, b) in enumerate(zip(names, expected)) if a != b)
        raise ConfigError(f"{path}: row {hno}, header: column {bad + 1} is {names[bad]!r}, expected "
                          f"{expected[bad]!r} (Thorlabs mode numbers Z1..Z{k})")
    for no, f in rows:
        if len(f) != len(names):
            raise ConfigError(f"{path}: row {no}: {len(f) - 1} Zernike modes, expected {k} (as in the header)")
    ids, z, nos = _numeric_rows(path, rows, ["pose"] + [f"Z{i}" for i in range(1, k + 1)])
    _check_range(path, z, nos, [f"Z{i}" for i in range(1, k + 1)], MAX_ZERNIKE_UM, "um")
    header = _wfs_header(path, comments)
    from .thorlabs import check_not_all_zero, check_tilt_not_cancelled

    check_not_all_zero(z, str(path))  # a file of zeros is named as such, before the tilt check
    check_tilt_not_cancelled(z[:, 1:3], str(path), "Zernike tilt modes Z2, Z3")
    return WfsData(tuple(ids), z, order, header, str(path), tuple(nos))


def read_wfs_json(path) -> WfsData:
    """lensforge's own WFS JSON (see the module docstring)."""
    path = Path(path)
    data = _read_lensforge_json(path, "WFS measurements file", "wfs_zernike")
    if data.get("units") != "um" or data.get("ordering") != "thorlabs":
        raise ConfigError(f"{path}: fields units/ordering: expected \"um\" and \"thorlabs\"")
    ms = data.get("measurements")
    if not isinstance(ms, list) or not ms:
        raise ConfigError(f"{path}: field measurements: expected a non-empty list of {{\"pose\", \"zernike\"}}")
    ids, zs, nos = [], [], []
    k = None
    for i, m in enumerate(ms):
        row = i + 1
        if not isinstance(m, dict) or "pose" not in m or not isinstance(m.get("zernike"), list):
            raise ConfigError(f"{path}: row {row} (measurements[{i}]), field pose/zernike: missing")
        if k is None:
            k = len(m["zernike"])
            order = _check_modes(path, k, f"row {row}, field zernike")
        if len(m["zernike"]) != k:
            raise ConfigError(f"{path}: row {row}, field zernike: {len(m['zernike'])} modes, expected {k}")
        zs.append([field_number(path, row, f"zernike[{j}]", "x" if isinstance(v, bool) else str(v))
                   for j, v in enumerate(m["zernike"])])
        ids.append(str(m["pose"]).strip())
        nos.append(row)
    _ids_unique(path, ids, nos)
    comments = {key: (0, ", ".join(map(str, np.atleast_1d(data[key])))) for key in
                ("wavelength_nm", "pupil_radius_mm", "pupil_center_mm") if key in data}
    z = np.array(zs, dtype=float)
    _check_range(path, z, nos, [f"zernike[{j}]" for j in range(k)], MAX_ZERNIKE_UM, "um")
    return WfsData(tuple(ids), z, order, _wfs_header(path, comments), str(path), tuple(nos))


def _read_thorlabs_exports(path, pattern=None):
    from .thorlabs import read_export_folder

    d = read_export_folder(path, pattern)
    return WfsData(d["ids"], d["zernike"], d["order"], d["header"], d["source"], d["rows"])


def _read_spot_fields(path, pattern=None):
    from .thorlabs import read_spot_fields

    return read_spot_fields(path, pattern)


# name -> reader(path[, pattern]); the folder/glob readers take the pose-id pattern
WFS_READERS = {"wfs_csv": read_wfs_csv, "wfs_json": read_wfs_json, "thorlabs_export": _read_thorlabs_exports,
               "spot_field": _read_spot_fields}
_PER_POSE_READERS = ("thorlabs_export", "spot_field")


def _sniff_wfs_format(path: Path) -> str:
    from .thorlabs import expand_measurements, read_text_any

    files = expand_measurements(path)
    first = files[0] if files else path
    if first.suffix.lower() == ".npz":
        return "spot_field"
    if first.suffix.lower() == ".json":
        return "wfs_json"
    text = read_text_any(first, "WFS measurements file")
    if "***" in text:
        return "thorlabs_export"
    if any(line.strip().lower().replace(" ", "").startswith("iy,ix") for line in text.split("\n")[:200]):
        return "spot_field"
    if files:
        raise ConfigError(f"{path}: {first.name} is neither a Thorlabs WFS export (*** ZERNIKE FIT *** section) "
                          "nor a spot field (iy,ix,dx_px,dy_px); a folder holds one such file per pose")
    return "wfs_csv"


def read_wfs(path: str | os.PathLike[str], fmt: str | None = None,
             pose_pattern: str | None = None) -> WfsData | SpotFields:
    """WFS measurements by pose id.

    Parameters
    ----------
    path : str or os.PathLike
        A CSV (one row per pose id, Zernike um in Thorlabs order, mode k = OSA j + 1), a JSON,
        or a folder or glob of Thorlabs WFS exports (``*** ... ***`` sections) or of spot
        fields (.npz, or a CSV with an ``iy,ix,dx_px,dy_px`` header), one file per pose with
        the pose id from the file name (``thorlabs.pose_id_from_name``).
    fmt : str, optional
        A ``WFS_READERS`` name, or None to detect it.
    pose_pattern : str, optional
        A regular expression whose first group is the pose id in a file name (default: its
        last integer).

    Returns
    -------
    WfsData or thorlabs.SpotFields
        ``ids`` (n,), ``zernike`` (n, K) um in Thorlabs order (piston first), ``order`` and
        the header (wavelength_nm, pupil_center_mm, pupil_radius_mm where given); spot fields
        for per-lenslet files.

    Raises
    ------
    ConfigError
        A bad file (one line naming the file, row and field).
    """
    path = Path(path)
    fmt = _reader_name(WFS_READERS, fmt or _sniff_wfs_format(path), "WFS")
    if fmt in _PER_POSE_READERS:
        return WFS_READERS[fmt](path, pose_pattern)
    return WFS_READERS[fmt](path)


# ----------------------------------------------------------------------------- writers


def _fmt(v: float, nd: int = 6) -> str:
    s = f"{v:.{nd}f}"
    return "0." + "0" * nd if s == "-0." + "0" * nd else s


def xyzabc_csv(ids, T) -> str:
    """``pose,X,Y,Z,A,B,C`` text (mm, deg, KUKA ABC)."""
    v = matrix_to_xyzabc(np.asarray(T))
    lines = ["# units: mm", "pose,X,Y,Z,A,B,C"]
    lines += [",".join([str(i)] + [_fmt(c) for c in row]) for i, row in zip(ids, v)]
    return "\n".join(lines) + "\n"


def quaternion_csv(ids, T, units: str = "mm") -> str:
    """``pose,x,y,z,qw,qx,qy,qz`` text with its ``# units:`` line."""
    T = np.asarray(T)
    q = matrix_to_quaternion(T)
    t = T[:, :3, 3] / _UNITS_MM[units]
    lines = [f"# units: {units}", "pose,x,y,z,qw,qx,qy,qz"]
    lines += [",".join([str(i)] + [repr(float(c)) for c in np.concatenate([a, b])]) for i, a, b in zip(ids, t, q)]
    return "\n".join(lines) + "\n"


def pose_table_json(ids, T, extra: dict | None = None) -> str:
    """lensforge's robot-pose JSON (json_4x4 reader format; mm)."""
    return dumps_json({"schema_version": 1, "kind": "robot_poses", "units": "mm", **(extra or {}),
                       "poses": [{"pose": str(i), "matrix": np.asarray(M).tolist()} for i, M in zip(ids, T)]}) + "\n"


def wfs_csv(ids, zernike_thorlabs, header: dict | None = None) -> str:
    """WFS CSV text (the ``wfs_csv`` reader's format) of Thorlabs-ordered coefficients (um)."""
    z = np.atleast_2d(np.asarray(zernike_thorlabs, dtype=float))
    lines = ["# lensforge WFS Zernike export: um of wavefront, Thorlabs modes (k = OSA j + 1)"]
    for k, v in (header or {}).items():
        lines.append(f"# {k}: " + ", ".join(repr(float(a)) for a in np.atleast_1d(v)))
    lines.append(",".join(["pose"] + [f"Z{k}" for k in range(1, z.shape[1] + 1)]))
    lines += [",".join([str(i)] + [repr(float(c)) for c in row]) for i, row in zip(ids, z)]
    return "\n".join(lines) + "\n"


def krl_program(ids, T, name: str = "lf_calib", joints_deg=None, settle_s: float = 2.0) -> dict:
    """KUKA KRL module (``name.src`` + ``name.dat``) visiting the flange poses T (mm).

    .dat: one ``DECL E6POS XP<i>={X, Y, Z, A, B, C, E1..E6}`` per pose: X, Y, Z in mm
    and A, B, C in deg (R = Rz(A) Ry(B) Rx(C)) of the flange in the robot base, so the
    program runs with ``$BASE = $NULLFRAME`` (base = robot root, {W}) and ``$TOOL =
    $NULLFRAME`` (TCP = flange, {E}; z out of the flange). E1..E6 (external axes)
    are 0. S and T (status and turn) are left out: the controller then keeps the
    current arm configuration, which for poses this close together is the one the
    planner checked (its joint angles are written as a comment above each point).
    .src: PTP to each point, waits ``settle_s`` and halts (``HALT``) so the operator
    (or a PLC) records the WFS frame and $POS_ACT under the point's id.
    Returns {"name.src": text, "name.dat": text}.
    """
    v = matrix_to_xyzabc(np.asarray(T))
    dat = [f"DEFDAT {name} PUBLIC", f"; lensforge calibration plan: {len(ids)} flange poses in the robot base",
           "; fields: X Y Z mm, A B C deg (KUKA R = Rz(A) Ry(B) Rx(C)), E1..E6 external axes (unused)"]
    src = [f"DEF {name}( )", "  ; lensforge calibration plan (see the .dat file for the points)",
           "  BAS(#INITMOV, 0)", "  $BASE = $NULLFRAME  ; poses are in the robot base {W}",
           "  $TOOL = $NULLFRAME  ; TCP = flange {E}", "  $VEL.CP = 0.05", "  BAS(#VEL_PTP, 10)"]
    for k, (i, row) in enumerate(zip(ids, v), start=1):
        if joints_deg is not None:
            dat.append(f"; pose {i}: joints A1..A6 (deg) " + " ".join(f"{a:.3f}" for a in joints_deg[k - 1]))
        fields = ",".join(f"{n} {_fmt(c, 4)}" for n, c in zip("XYZABC", row))
        dat.append(f"DECL E6POS XP{k}={{{fields},E1 0.0,E2 0.0,E3 0.0,E4 0.0,E5 0.0,E6 0.0}}")
        src += [f"  ; pose id {i}", f"  PTP XP{k}", f"  WAIT SEC {settle_s:g}",
                f"  HALT  ; record WFS Zernikes and $POS_ACT as pose {i}"]
    dat.append("ENDDAT")
    src.append("END")
    return {f"{name}.src": "\n".join(src) + "\n", f"{name}.dat": "\n".join(dat) + "\n"}


PLAN_WRITERS = {
    "csv": lambda ids, T, **kw: {"plan_xyzabc.csv": xyzabc_csv(ids, T)},
    "json": lambda ids, T, **kw: {"plan_4x4.json": pose_table_json(ids, T, kw.get("extra"))},
    "krl": lambda ids, T, **kw: krl_program(ids, T, joints_deg=kw.get("joints_deg")),
}


def easy_handeye_yaml(Z: np.ndarray, robot_base_frame: str = "base_link", robot_effector_frame: str = "tool0",
                      tracking_base_frame: str = "wfs_sensor", tracking_marker_frame: str = "lens") -> str:
    """easy_handeye (eye-on-base) calibration YAML: ``transformation`` is Z = ^W T_S
    (robot base -> sensor frame) with x, y, z in metres and a unit quaternion."""
    Z = np.asarray(Z, dtype=float)
    q = matrix_to_quaternion(Z)
    t = Z[:3, 3] / 1000.0
    lines = ["eye_on_hand: false", "freehand_robot_movement: false",
             f"robot_base_frame: {robot_base_frame}", f"robot_effector_frame: {robot_effector_frame}",
             f"tracking_base_frame: {tracking_base_frame}", f"tracking_marker_frame: {tracking_marker_frame}",
             "transformation:"]
    for k, v in (("qw", q[0]), ("qx", q[1]), ("qy", q[2]), ("qz", q[3]), ("x", t[0]), ("y", t[1]), ("z", t[2])):
        lines.append(f"  {k}: {float(v)!r}")
    return "\n".join(lines) + "\n"


def write_bundle(folder, files: dict, overwrite: bool = True, drop: tuple = ()) -> dict:
    """Write {name: text | bytes} into ``folder`` all or none: the files go into a
    temporary sibling folder first, which then replaces ``folder`` (existing files
    in ``folder`` not in ``files`` are kept, except those named in ``drop``: e.g. the
    easy_handeye.yaml of an earlier run beside a calibration that failed its check).
    Returns {name: Path}."""
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    if not folder.name:  # ".", "..", "/": swap and rename need the folder's own name
        folder = folder.resolve()
    if folder.exists() and not folder.is_dir():
        raise ConfigError(f"output folder {folder}: exists and is not a folder; choose another -o")
    tmp = Path(tempfile.mkdtemp(dir=folder.parent, prefix=f".{folder.name}.", suffix=".tmp"))
    note_staging(tmp)
    try:
        if folder.exists():
            for p in folder.iterdir():
                if p.name not in files and p.name not in drop and p.is_file():
                    shutil.copy2(p, tmp / p.name)
        for name, data in files.items():
            write_atomic(tmp / name, data)
        old = None
        with committing():  # the swap completes whatever signal arrives meanwhile
            if folder.exists():
                old = folder.with_name(f".{folder.name}.old-{os.getpid()}")
                os.replace(folder, old)
            os.replace(tmp, folder)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {name: folder / name for name in files}

