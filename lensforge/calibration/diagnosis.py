"""Name the likely mistake after a failed model check.

When a calibration (or one pose estimate) fails its chi2 model check
(``model_check.check_chi2``), the usual cause is a convention mistake in an input file,
not the bench. :func:`diagnose_session` re-reads the inputs under each usual mistake
(``SESSION_MISTAKES``), ranks the readings by a cheap screen -- the lens poses estimated
once from nominal (one batched Levenberg-Marquardt per WFS reading or design) and a
maximum-likelihood hand-eye solve per robot-file reading (milliseconds) -- and re-runs the
calibration that failed on the best reading only; it names the reading whose fit passes:

- robot units: the translations in m instead of mm (``# units:`` line or JSON "units"
  wrong), or an XYZABC file in metres;
- KUKA A, B, C given in radians (the XYZABC CSV takes degrees);
- quaternion columns in x, y, z, w order under the w, x, y, z header;
- WFS coefficients in Noll order, or OSA/ANSI order started at j = 1, instead of Thorlabs order;
- WFS coefficients in waves instead of um (the wavelength from the file's header, else the bench);
- the wavefront's sign flipped;
- the wrong design: the paper lenses and the design files beside the given one.

The screen assumes the lens as designed, so on an as-built lens even the right reading
keeps some misfit (chi2/dof ~ 10^2); the best reading must beat the inputs as given by
``SCREEN_GAIN`` and then pass the full method's own model check (e.g. the joint fit's) to be
named. Nothing here changes a file: the message says which reading makes the fit pass, and
the user fixes the file. :func:`diagnose_estimate` does the same for one pose estimate (each
reading one estimate).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import LensforgeError
from ..optics.zernike import noll_to_thorlabs
from . import formats
from .model_check import check_chi2
from .cell_plausibility import robot_file_readings

__all__ = ["Mistake", "Reading", "SESSION_MISTAKES", "WFS_MISTAKES", "candidate_readings",
           "diagnose_session", "diagnose_estimate", "SCREEN_GAIN", "Diagnosis"]

# a reading must lower the screen's hand-eye chi2/dof this much below the inputs as given to be
# confirmed with the full method (measured: the right reading of a mm file under `# units: m`
# on an as-built lens: 4.5e3 -> 157, the two-stage fit's own as-built misfit; wrong readings
# stay within a factor 2 of the inputs or fail)
SCREEN_GAIN = 10.0


@dataclass(frozen=True)
class Reading:
    """One reinterpretation of a session's inputs: name (a key), message (what it means for
    the file, in words), and the re-read inputs (wfs, poses, design; None = unchanged)."""

    name: str
    message: str
    wfs: formats.WfsData | None = None
    poses: formats.PoseTable | None = None
    design: object = None


@dataclass(frozen=True)
class Mistake:
    """The reading whose fit passes: name, message ("the fit passes if ..."), chi2/dof of the
    failed fit and of the fit under this reading."""

    name: str
    message: str
    chi2_dof_before: float
    chi2_dof_after: float
    partial: bool = False  # the reading lowers the misfit by SCREEN_GAIN or more, but the fit still fails


def _fin(v):
    return float(v) if v is not None and math.isfinite(v) else None


# ----------------------------------------------------------------------------- pose-file readings


def _pose_readings(poses: formats.PoseTable, path) -> list[Reading]:
    return [Reading(name, f"the fit passes if {condition}", poses=table)
            for name, condition, table in robot_file_readings(poses, path)]


# ----------------------------------------------------------------------------- WFS readings


def _noll_as_thorlabs(z: np.ndarray) -> np.ndarray:
    """Thorlabs-ordered coefficients of rows whose column k held Noll mode k."""
    n, K = z.shape
    out = np.zeros_like(z)
    for k in range(1, K + 1):
        t = noll_to_thorlabs(k)
        if t <= K:
            out[:, t - 1] = z[:, k - 1]
    return out


def _osa_from_one(z: np.ndarray) -> np.ndarray:
    """Rows whose column Zk held OSA/ANSI j = k (piston left out, every mode one column early)."""
    out = np.zeros_like(z)
    out[:, 1:] = z[:, :-1]
    return out


def _wfs_readings(wfs: formats.WfsData, path, wavelength_nm: float) -> list[Reading]:
    name = Path(path).name if path is not None else "the WFS file"
    lam_um = float(wfs.header.get("wavelength_nm", wavelength_nm)) * 1e-3
    z = wfs.zernike
    return [
        Reading("zernike noll order", f"the fit passes if the WFS file {name} is read in Noll order: it must be in "
                "Thorlabs order (mode k = OSA j + 1); re-export it from the WFS software or reorder the columns",
                wfs=replace(wfs, zernike=_noll_as_thorlabs(z))),
        Reading("zernike osa from 1", f"the fit passes if column Zk of the WFS file {name} holds OSA/ANSI j = k: "
                "Thorlabs numbering starts with piston as Z1 (k = j + 1); shift the columns by one",
                wfs=replace(wfs, zernike=_osa_from_one(z))),
        Reading("zernike waves", f"the fit passes if the WFS file {name} is read in waves (at {lam_um * 1e3:g} nm): "
                "export the coefficients in um", wfs=replace(wfs, zernike=z * lam_um)),
        Reading("zernike sign", f"the fit passes if the signs of the WFS file {name} are flipped: the wavefront "
                "convention is the opposite of lensforge's (positive OPD leading); negate the coefficients",
                wfs=replace(wfs, zernike=-z)),
    ]


def _design_readings(design, limit: int = 6) -> list[Reading]:
    """The paper lenses and up to ``limit`` design JSON files beside ``design``, other than it."""
    from ..optics.lens import PAPER_LENSES

    out = []
    here = str(design)
    for name in PAPER_LENSES:
        if here not in (name, f"paper:{name}"):
            out.append(Reading(f"design paper:{name}", f"the fit passes with the design paper:{name}: "
                               f"{here} is probably not the lens on the bench", design=f"paper:{name}"))
    p = Path(here)
    if p.suffix.lower() == ".json" and p.is_file():
        siblings = sorted(q for q in p.parent.glob("*.json") if q.resolve() != p.resolve() and q.is_file()
                          and q.stat().st_size < 1 << 20)
        for q in siblings[:limit]:
            out.append(Reading(f"design {q.name}", f"the fit passes with the design {q}: {here} is probably not the "
                               "lens on the bench", design=str(q)))
    return out


WFS_MISTAKES = ("zernike noll order", "zernike osa from 1", "zernike waves", "zernike sign")
SESSION_MISTAKES = ("robot units", "robot angles rad", "quaternion xyzw") + WFS_MISTAKES + ("design",)


def candidate_readings(design, wfs: formats.WfsData, poses: formats.PoseTable | None, *, wfs_path=None,
                       poses_path=None, wavelength_nm: float = 532.0, designs: bool = True) -> list[Reading]:
    """Every reading of the inputs to try, robot file first, then WFS file, then designs."""
    out = []
    if poses is not None and poses_path is not None:
        out += _pose_readings(poses, poses_path)
    out += _wfs_readings(wfs, wfs_path, wavelength_nm)
    if designs:
        out += _design_readings(design)
    return out


# ----------------------------------------------------------------------------- diagnosis


@dataclass(frozen=True)
class Diagnosis:
    """What the re-tries found: mistake (the Mistake, or None when no reading explains the
    data), tries [{"reading", "chi2_dof"}] (the screen's hand-eye chi2/dof, then the confirmation
    with the full method), seconds."""

    mistake: Mistake | None
    tries: tuple = ()
    seconds: float = 0.0

    def to_dict(self) -> dict:
        m = self.mistake
        return {"mistake": None if m is None else m.name, "message": None if m is None else m.message,
                "chi2_dof_before": None if m is None else _fin(m.chi2_dof_before),
                "chi2_dof_after": None if m is None else _fin(m.chi2_dof_after),
                "passes": None if m is None else not m.partial,
                "tries": list(self.tries), "seconds": round(self.seconds, 2)}


def _screen(data, A_sets) -> list[float]:
    """Hand-eye chi2/dof of the matched session ``data`` under each flange-pose set in A_sets
    (each (n, 4, 4) in data's pose order), with the lens poses estimated once from nominal
    (one batched Levenberg-Marquardt): the cheap ranking of the readings."""
    from ..optics.pose import pose_to_matrix, pose_vector_cov_to_right
    from .handeye import solve_handeye
    from .pose_estimation import estimate_poses_batch

    n = len(data.ids)
    batch = estimate_poses_batch(data.model, data.z, np.zeros((n, 6)))
    ok = np.asarray(batch.converged, bool) & np.all(np.isfinite(batch.cov.reshape(n, -1)), axis=1)
    if ok.sum() < 3:
        return [float("inf")] * len(A_sets)
    B = data.scene.T_SO_nominal @ pose_to_matrix(batch.poses[ok])
    C = np.array([pose_vector_cov_to_right(x, c) for x, c in zip(batch.poses[ok], batch.cov[ok])])
    out = []
    for A in A_sets:
        try:
            he = solve_handeye(A[ok], B, method="ml", sigma=data.robot.noise, cov_B=C, on_degenerate="warn")
            out.append(float(he.chi2_dof) if he.dof > 0 else float("inf"))
        except (LensforgeError, np.linalg.LinAlgError, ValueError):
            out.append(float("inf"))
    return out


def diagnose_session(design, measurements, robot_poses, failed, *, bench=None, robot=None, method: str = "joint",
                     tolerances="default", time_budget_s: float = 120.0, wfs_header: str = "error") -> Diagnosis:
    """The likely mistake behind a failed calibration (module docstring).

    design, measurements, robot_poses, bench, robot, method, tolerances, wfs_header: as given
    to ``session.calibrate``; failed: its CalibrationResult (valid False), or None when the
    calibration found too few lens poses to fit at all; time_budget_s: the
    screen stops trying readings after this long. The screen ranks every reading by its
    hand-eye chi2/dof (``_screen``: one batched pose estimate per WFS reading or design, a
    hand-eye solve per robot reading); the best, if it beats the inputs as given by
    ``SCREEN_GAIN``, is re-run with the method that failed and named if that fit passes."""
    from .session import calibrate, match_session

    t0 = time.monotonic()
    wfs = measurements if isinstance(measurements, formats.WfsData) else formats.read_wfs(measurements)
    poses = robot_poses if isinstance(robot_poses, formats.PoseTable) else formats.read_robot_poses(robot_poses)
    if not isinstance(wfs, formats.WfsData):  # raw spot fields: the Zernike readings do not apply
        return Diagnosis(None, (), time.monotonic() - t0)
    data = match_session(design, wfs, poses, bench=bench, robot=robot, wfs_header=wfs_header)
    lam = data.model.bench.laser.wavelength_nm
    readings = candidate_readings(design, wfs, poses, wfs_path=wfs.source or None, poses_path=poses.source or None,
                                  wavelength_nm=lam)
    robot_r = [r for r in readings if r.poses is not None]
    other_r = [r for r in readings if r.poses is None]

    def matched(table: formats.PoseTable) -> np.ndarray:
        return table.T[[table.ids.index(i) for i in data.ids]]

    tries, scores = [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            first = _screen(data, [data.A] + [matched(r.poses) for r in robot_r])
        except LensforgeError:  # the lens poses cannot be estimated as given: only WFS readings and designs can help
            first = [float("inf")] * (1 + len(robot_r))
        base = first[0]
        tries.append({"reading": "as given", "chi2_dof": _fin(base)})
        for r, c in zip(robot_r, first[1:]):
            tries.append({"reading": r.name, "chi2_dof": _fin(c)})
            scores.append((c, r))
        for r in other_r:
            if time.monotonic() - t0 > time_budget_s:
                break
            try:
                d2 = match_session(r.design or design, r.wfs or wfs, poses, bench=bench, robot=robot,
                                   wfs_header=wfs_header)
                c = _screen(d2, [d2.A])[0]
            except LensforgeError:
                c = float("inf")
            tries.append({"reading": r.name, "chi2_dof": _fin(c)})
            scores.append((c, r))
        # closest to the noise model (chi2/dof ~ 1, in log): a reading that makes the misfit absurdly
        # small (the noise model far too large for the numbers) is no explanation either
        def dist(c):
            return abs(math.log(c)) if c > 0 and math.isfinite(c) else float("inf")
        scores.sort(key=lambda t: dist(t[0]))
        if not scores or not math.isfinite(dist(scores[0][0])) or \
                not dist(scores[0][0]) + math.log(SCREEN_GAIN) <= dist(base):
            return Diagnosis(None, tuple(tries), time.monotonic() - t0)
        c, r = scores[0]
        try:
            res = calibrate(r.design or design, r.wfs or wfs, r.poses or poses, bench=bench, robot=robot,
                            method=method, tolerances=tolerances, wfs_header=wfs_header)
        except LensforgeError:
            return Diagnosis(None, tuple(tries), time.monotonic() - t0)
    tries.append({"reading": f"{r.name} ({res.method})", "chi2_dof": _fin(res.chi2_dof)})
    before = failed.chi2_dof if failed is not None else float("inf")
    if res.valid and len(res.poses_used) >= max(3, len(failed.poses_used) // 2 if failed is not None else 3):
        return Diagnosis(Mistake(r.name, r.message, before, res.chi2_dof), tuple(tries), time.monotonic() - t0)
    if failed is not None and res.chi2_dof * SCREEN_GAIN <= failed.chi2_dof:  # a large part of the misfit: say so, and what is left
        msg = r.message.replace("the fit passes if", "the misfit drops if", 1).replace("the fit passes with",
                                                                                    "the misfit drops with", 1)
        msg = (f"{msg} (chi2/dof {failed.chi2_dof:.3g} -> {res.chi2_dof:.3g}, still failing: the rest may be the lens "
               "as built" + (", which --method joint estimates" if res.method == "two-stage" else "") + ")")
        return Diagnosis(Mistake(r.name, msg, failed.chi2_dof, res.chi2_dof, partial=True), tuple(tries),
                         time.monotonic() - t0)
    return Diagnosis(None, tuple(tries), time.monotonic() - t0)


def diagnose_estimate(design, measurement, failed_chi2_dof: float, *, bench=None, pose_id=None,
                      time_budget_s: float = 60.0, wfs_header: str = "error") -> Diagnosis:
    """The likely mistake behind a pose estimate that fails its model check: the WFS
    readings and the other designs (module docstring), each one pose estimate."""
    from .session import bench_for_measurements, estimate, load_design_lens

    t0 = time.monotonic()
    wfs = measurement if isinstance(measurement, formats.WfsData) else formats.read_wfs(measurement)
    if not isinstance(wfs, formats.WfsData):  # raw spot fields: the Zernike readings do not apply
        return Diagnosis(None, (), time.monotonic() - t0)
    _, b = load_design_lens(design, bench)
    lam = bench_for_measurements(b, wfs, wfs_header).laser.wavelength_nm
    tries, best = [], None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for r in candidate_readings(design, wfs, None, wfs_path=wfs.source or None, wavelength_nm=lam):
            if time.monotonic() - t0 > time_budget_s:
                break
            try:
                e = estimate(r.design or design, r.wfs or wfs, bench=bench, pose_id=pose_id,
                             wfs_header=wfs_header)["estimate"]
            except LensforgeError:
                tries.append({"reading": r.name, "chi2_dof": None})
                continue
            tries.append({"reading": r.name, "chi2_dof": _fin(e.chi2_dof)})
            if check_chi2(e.chi2, e.dof).passed:
                return Diagnosis(Mistake(r.name, r.message, failed_chi2_dof, e.chi2_dof), tuple(tries),
                                 time.monotonic() - t0)
            if math.isfinite(e.chi2_dof) and (best is None or e.chi2_dof < best[0]):
                best = (e.chi2_dof, r)
    if best is not None and best[0] * SCREEN_GAIN <= failed_chi2_dof:  # most of the misfit (or no pose at all)
        c, r = best
        msg = r.message.replace("the fit passes if", "the misfit drops if", 1).replace("the fit passes with",
                                                                                    "the misfit drops with", 1)
        msg = f"{msg} (chi2/dof -> {c:.3g}, still failing the check: the rest may be the lens as built)"
        return Diagnosis(Mistake(r.name, msg, failed_chi2_dof, c, partial=True), tuple(tries), time.monotonic() - t0)
    return Diagnosis(None, tuple(tries), time.monotonic() - t0)
