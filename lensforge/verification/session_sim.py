"""A simulated bench session: the files a real session produces, from a known truth.

``simulate_session`` plans the poses (``calibration.session.plan``), builds a true
cell (the robot file's nominal Z and X perturbed by the CAD/grasp errors of
``scenario.ScenarioConfig`` and ``initial_poses.InitialPoseModel``), prints an as-built
lens from the tolerance model, drives the robot to the planned flange poses and
records:

- ``robot_poses.csv``: the planned flange poses as the robot reports them, i.e.
  with its repeatability noise applied (A_recorded = A_true P(a), a ~ robot noise);
- ``wfs_zernike.csv``: Zernike coefficients (um, Thorlabs order, piston column 0)
  through the as-built lens at the true lens pose, with the bench's slope noise;
  poses whose pupil is not lit on the as-built lens get no row (as on the bench);
- ``truth.json``: ``Z`` and ``X`` (4x4, mm), the as-built lens, the true lens poses,
  the unlit ids and the seed.

The session is a pure function of (design, tolerances, seed, robot, n).

``record_session`` is the one session simulator under every simulated calibration
(this module's files, ``study``, ``scenario``, ``budget``): from the true cell (flange
poses as reached and as recorded, X, Z) and the lens as built it forms the true lens
poses, the noisy measurements (``ForwardModel.measure_noisy``) and the ``SessionData``
the calibration pipeline (``calibration.pipeline``) takes, as ``calibrate`` builds it
from a real session's files.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.stats import chi2 as chi2_dist

from ..calibration import formats
from ..calibration.initial_poses import InitialPoseModel
from ..calibration.robot import RobotModel
from ..calibration.formats import write_bundle
from ..calibration.robot import Scene
from ..calibration.session import Plan, calibrate, plan
from ..calibration.session_result import SCHEMA_VERSION, SessionData, frame_dict
from ..errors import ConfigError, LensforgeError
from ..fileio import dumps_json
from ..asbuilt.tolerances import resolve_tolerances, sample_as_built
from ..optics.bench import Bench
from ..optics.lens import LensSpec, resolve_lens
from ..optics.pose import invert_poses, matrix_to_pose, pose_to_matrix, rotvecs
from ..optics.shack_hartmann import ForwardModel
from ..optics.zernike import to_thorlabs_vector
from .physical_sensor import PhysicalSensor, field_max_slope, physical_measure

__all__ = ["SENSORS", "physical_config", "SimulatedSession", "simulate_session", "record_session", "RecordedSession",
           "nees", "check_sessions", "session_outcome", "summarise_sessions", "NEES_3SIGMA_6DOF", "true_focal_mm"]

SENSORS = ("model", "physical")


def physical_config(sensor: str | PhysicalSensor) -> PhysicalSensor | None:
    """The physical sensor's settings for ``sensor`` ("model": None)."""
    if isinstance(sensor, PhysicalSensor):
        return sensor
    if sensor not in SENSORS:
        raise ConfigError(f"sensor: must be one of {list(SENSORS)}, got {sensor!r}")
    return PhysicalSensor() if sensor == "physical" else None


def true_focal_mm(bench: Bench, sensor: str | PhysicalSensor) -> float:
    """The simulated lenslets' true focal length (mm): the physical sensor's ``focal_mm``, else the bench's."""
    cfg = physical_config(sensor)
    return float(bench.sensor.lenslet_focal_mm if cfg is None else cfg.focal(bench.sensor))


# ASSUMPTION (as verification/scenario.py): 1-sigma CAD error of the sensor placement Z
SENSOR_CAD_TRANSLATION_MM = 0.2
SENSOR_CAD_ROTATION_RAD = math.radians(0.2)


@dataclass(frozen=True, eq=False)
class RecordedSession:
    """What ``record_session`` returns: data (the SessionData of the lit poses, measured
    through the lens as built, modelled with the design), x_true (n, 6) true lens poses of
    every pose (mm, rad), lit (n,) which poses the sensor measured, slopes (n, lenslets, 2)
    the noisy lenslet slopes (rad) the Zernike vectors were fitted from."""

    data: SessionData
    x_true: np.ndarray
    lit: np.ndarray
    slopes: np.ndarray  # (n, lenslets, 2) rad: the noisy lenslet slopes of every pose


def record_session(nominal: ForwardModel, measured: ForwardModel, scene: Scene, A_true, A_recorded, X, Z,
                   rng: np.random.Generator, ids=None, robot: RobotModel | None = None,
                   sensor: PhysicalSensor | None = None, tick: Callable[[], None] | None = None) -> RecordedSession:
    """Simulate what the sensor and the robot record (module docstring).

    nominal: the design's model (what the calibration assumes); measured: the lens as built
    (what makes the light); scene: the robot's nominal cell (its noise is the calibration's
    robot model); A_true / A_recorded: (n, 4, 4) flange poses as reached and as the robot
    reports them (mm); X, Z: the true grasp ^E T_O and sensor ^W T_S; rng: the sensor-noise
    stream (drawn for every lenslet of every pose); ids: pose ids (default "1".."n").
    Unlit poses are left out of the data with the reason "unlit", as a bench session
    leaves them out of the WFS file. sensor: None (the measured model's slopes) or the
    physical sensor's settings: every lit pose's noise-free slopes then come from
    ``physical_sensor.physical_measure`` through the measured lens (the lit verdict stays the
    model's); ``tick()`` after each. The noise is the same draw either way."""
    A_true, A_recorded = np.asarray(A_true, dtype=float), np.asarray(A_recorded, dtype=float)
    ids = tuple(str(i + 1) for i in range(len(A_true))) if ids is None else tuple(ids)
    x_true = matrix_to_pose(invert_poses(scene.T_SO_nominal) @ invert_poses(Z) @ A_true @ X)
    if sensor is None:
        z, lit, slopes = measured.measure_noisy(x_true, rng)
    else:  # the physical sensor's noise-free slopes at the lit poses, the same noise draw
        res = measured.evaluate(x_true, check_range=False)
        lit = np.asarray(res.valid, bool)
        clean = np.array(res.slopes)
        # a sample grid fine enough for every pose's field (its rays on the lit lenslets)
        sensor = sensor.sampled_for(measured.bench, max((field_max_slope(measured, x, sensor)
                                                         for x in x_true[lit]), default=0.0))
        for i in np.flatnonzero(lit):
            clean[i] = physical_measure(measured, x_true[i], sensor).slopes
            if tick is not None:
                tick()
        slopes = measured.noisy_slopes(dataclasses.replace(res, slopes=clean), rng)
        z = measured.pupil.fit(slopes)
    rejected = tuple({"pose": i, "reason": "unlit: the pupil is not lit at this pose (no WFS measurement)",
                      "code": "unlit"} for i, ok in zip(ids, lit) if not ok)
    data = SessionData(ids=tuple(np.array(ids)[lit].tolist()), A=A_recorded[lit], z=z[lit], model=nominal,
                       robot=robot, scene=scene, rejected=rejected)
    return RecordedSession(data=data, x_true=x_true, lit=lit, slopes=slopes)


@dataclass(frozen=True, eq=False)
class SimulatedSession:
    """ids; A_recorded (n, 4, 4); A_true; wfs_ids (lit poses); zernike_thorlabs (k, K);
    Z, X: true 4x4; lens: the as-built lens; x_true: (n, 6) true lens poses; unlit: ids;
    plan: the calibration Plan; header: WFS header values."""

    ids: tuple
    A_recorded: np.ndarray
    A_true: np.ndarray
    wfs_ids: tuple
    zernike_thorlabs: np.ndarray
    Z: np.ndarray
    X: np.ndarray
    lens: object
    x_true: np.ndarray
    unlit: tuple
    plan: object
    header: dict
    seed: int
    slopes: np.ndarray | None = None  # (k, n_pupil, 2) rad: the noisy lenslet slopes behind zernike_thorlabs
    bench: Bench | None = None

    def instrument_files(self, spot_format: str = "npz") -> dict:
        """The same measurements in the instrument's own layouts (``calibration.thorlabs``):
        ``thorlabs/pose_<id>.csv`` (WFS software exports, cp1252, CRLF) and
        ``spot_fields/pose_<id>.<npz|csv>`` (SDK spot deviations in pixels over the whole
        lenslet grid, NaN outside the pupil, with the MLA data). The spot fields hold the very
        slopes the Zernikes were fitted from."""
        from ..calibration import thorlabs
        from ..optics.shack_hartmann import lenslet_pupil

        sensor = self.bench.sensor
        out = {}
        for i, z in zip(self.wfs_ids, self.zernike_thorlabs):
            out[f"thorlabs/pose_{int(i):02d}.csv" if str(i).isdigit() else f"thorlabs/pose_{i}.csv"] = \
                thorlabs.export_text(z, self.header, comment=f"lensforge simulated session, seed {self.seed}")
        n_side = int(np.floor(sensor.aperture_mm / sensor.pitch_mm + 1e-9))
        pupil = lenslet_pupil(sensor)
        ix = np.rint(pupil.centres[:, 0] / sensor.pitch_mm + 0.5 * (n_side - 1)).astype(int)
        iy = np.rint(pupil.centres[:, 1] / sensor.pitch_mm + 0.5 * (n_side - 1)).astype(int)
        f_um, px_um = sensor.lenslet_focal_mm * 1e3, sensor.pixel_mm * 1e3
        mla = {"focal_length_um": f_um, "lenslet_pitch_um": sensor.pitch_mm * 1e3, "pixel_pitch_um": px_um,
               "center_offset_mm": (0.0, 0.0)}
        head = {k: v for k, v in self.header.items()}
        for i, s in zip(self.wfs_ids, self.slopes):
            dev = np.full((n_side, n_side, 2), np.nan)
            dev[iy, ix] = s * f_um / px_um  # rad -> px: deviation = slope * focal length / pixel pitch
            name = f"spot_fields/pose_{int(i):02d}" if str(i).isdigit() else f"spot_fields/pose_{i}"
            if spot_format == "npz":
                out[name + ".npz"] = thorlabs.spot_field_npz(dev, header=head, **mla)
            else:
                out[name + ".csv"] = thorlabs.spot_field_csv(dev, header=head, **mla)
        return out

    def files(self, instrument: bool = False) -> dict:
        """{robot_poses.csv, wfs_zernike.csv, truth.json}: name -> text; instrument: also the
        instrument-layout folders (``instrument_files``)."""
        truth = {"schema_version": SCHEMA_VERSION, "kind": "session_truth", "seed": self.seed,
                 "Z": self.Z.tolist(), "X": self.X.tolist(), "lens": self.lens.to_dict(),
                 "lens_poses": {i: x for i, x in zip(self.ids, self.x_true.tolist())},
                 "unlit": list(self.unlit), "robot": self.plan.robot.name}
        out = {"robot_poses.csv": formats.xyzabc_csv(self.ids, self.A_recorded),
               "wfs_zernike.csv": formats.wfs_csv(self.wfs_ids, self.zernike_thorlabs, self.header),
               "truth.json": dumps_json(truth) + "\n"}
        return {**out, **self.instrument_files()} if instrument else out


def simulate_session(design: LensSpec, *, tolerances: Tolerances | str | Path | None = "default", seed: int = 0,
                     bench: Bench | None = None, robot: RobotModel | str | None = None, n: int = 12,
                     grasp: InitialPoseModel | None = None, session_plan: Plan | None = None,
                     sensor: str | PhysicalSensor = "model", tick: Callable[[], None] | None = None) -> SimulatedSession:
    """Simulate one bench session: the files a real session writes, to rehearse ``calibrate``
    (see the module docstring).

    Parameters
    ----------
    design : LensSpec
        Design file, paper lens name or Lens.
    tolerances : Tolerances, str, pathlib.Path or None
        Tolerances, a TOML path, "default" (the default tolerance file) or None (the lens
        exactly as designed).
    seed : int
        Everything random flows from it.
    bench : Bench, optional
        Default: the design's bench, else the built-in one.
    robot : RobotModel or str, optional
        RobotModel, registry name or TOML path (default KR 10).
    n : int
        Calibration poses.
    grasp : InitialPoseModel, optional
        How the gripper holds the lens (default: ``initial_poses``' model).
    session_plan : Plan, optional
        Reuse a Plan (else ``plan(design, robot=robot, n=n, seed=seed)``).
    sensor : str or PhysicalSensor
        What measures: "model" (lensforge's forward model), "physical" (the full-array
        physical-optics reference, ``physical_sensor``, default settings: seconds per pose) or a
        PhysicalSensor's settings.
    tick : callable, optional
        Called after each physically measured pose (a progress bar's advance).

    Returns
    -------
    SimulatedSession
        ``ids``, recorded and true flange poses ``A_recorded`` / ``A_true`` (n, 4, 4) mm,
        ``wfs_ids`` (the lit poses), ``zernike_thorlabs`` (k, K) um in Thorlabs order, the
        true ``Z`` and ``X`` (4x4, mm), the as-built ``lens``, ``x_true`` (n, 6) and the plan;
        ``files()`` gives robot_poses.csv, wfs_zernike.csv and truth.json as text.
    """
    resolved = resolve_lens(design)  # the plan keeps the design's plan box
    lens, bench = resolved.lens, resolved.bench_or(bench)
    tolerances = resolve_tolerances(tolerances)[0]
    p = session_plan or plan(resolved, bench=bench, robot=robot, n=n, seed=seed)
    scene = p.scene
    grasp = grasp or InitialPoseModel()
    ss_lens, ss_cell, ss_robot, ss_sensor = np.random.SeedSequence([seed, 11]).spawn(4)
    as_built = lens if tolerances is None else sample_as_built(lens, tolerances, np.random.default_rng(ss_lens))
    rng = np.random.default_rng(ss_cell)
    X = scene.X @ pose_to_matrix(rng.normal(size=6) * grasp.sigma)
    Z = scene.Z @ pose_to_matrix(rng.normal(size=6) * np.array([SENSOR_CAD_TRANSLATION_MM] * 3
                                                                + [SENSOR_CAD_ROTATION_RAD] * 3))
    A_true = p.A
    A_rec = A_true @ pose_to_matrix(scene.noise.sample(np.random.default_rng(ss_robot), len(p.ids)))
    measured = ForwardModel(bench, as_built, validate=False)
    # the files carry no model: the measured model stands in for the nominal one
    rec = record_session(measured, measured, scene, A_true, A_rec, X, Z, np.random.default_rng(ss_sensor), p.ids,
                         sensor=physical_config(sensor), tick=tick)
    model, lit, x_true = measured, rec.lit, rec.x_true
    zt = np.array([to_thorlabs_vector(np.concatenate([[1], model.modes]), np.concatenate([[0.0], zi]))
                   for zi in rec.data.z])
    header = {"wavelength_nm": bench.laser.wavelength_nm, "pupil_center_mm": tuple(bench.sensor.pupil_center_mm),
              "pupil_radius_mm": bench.sensor.pupil_radius_mm}
    ids = p.ids
    return SimulatedSession(ids=ids, A_recorded=A_rec, A_true=A_true, wfs_ids=tuple(np.array(ids)[lit].tolist()),
                            zernike_thorlabs=zt.reshape(int(lit.sum()), -1), Z=Z, X=X, lens=as_built, x_true=x_true,
                            unlit=tuple(np.array(ids)[~lit].tolist()), plan=p, header=header, seed=int(seed),
                            slopes=rec.slopes[lit], bench=bench)


def nees(T_true, T_est, cov) -> float:
    """Normalised estimation error squared e^T cov^-1 e of e = log(T_true^-1 T_est)
    (right perturbation, (mm, rad)); its mean over sessions is the dimension (6)."""
    e = matrix_to_pose(np.linalg.solve(T_true, T_est))
    return float(e @ np.linalg.solve(cov, e))


# 3-sigma-equivalent region of a 6-D Gaussian: the chi2(6) quantile at P(|N(0,1)| <= 3) = 0.9973
NEES_3SIGMA_6DOF = float(chi2_dist.ppf(math.erf(3 / math.sqrt(2)), 6))


def session_outcome(lens, bench: Bench, session_plan, seed: int, *, tolerances=None, method: str = "joint",
                    calibration_tolerances="default", folder: Path | None = None,
                    sensor: str | PhysicalSensor = "model", calibration_bench: Bench | None = None) -> dict:
    """Simulate the session of ``seed`` on ``session_plan``, calibrate it through the
    files a real session writes (in ``folder``, default a temporary one) and score Z.
    calibration_bench: the bench calibrate models the sensor with (default ``bench``; e.g. the
    cross-talk model, ``sensor.crosstalk = "neighbours"``, against a physical sensor).

    Returns {"seed", "failed": None or the error, "nees": e^T cov_Z^-1 e (right
    perturbation, 6 DOF), "inside_3sigma_each_axis": all six parent-frame components
    within 3 reported sigma, "chi2_dof", "p_value", "z_translation_error_mm",
    "z_rotation_error_deg", "start": the joint fit's start (or None), "sensor": the joint fit's sensor
    estimates (``session_joint.sensor_summary``, None without the gain), "lenslet_focal_true_mm": the simulated
    sensor's}."""
    s = simulate_session(lens, tolerances=tolerances, seed=seed, bench=bench, session_plan=session_plan,
                         sensor=sensor)
    with tempfile.TemporaryDirectory() as tmp:
        paths = write_bundle(Path(folder or tmp) / f"s{seed}", s.files())
        try:
            r = calibrate(lens, paths["wfs_zernike.csv"], paths["robot_poses.csv"], bench=calibration_bench or bench,
                          robot=session_plan.robot, method=method, tolerances=calibration_tolerances)
        except LensforgeError as e:
            return {"seed": int(seed), "failed": f"seed {seed}: {e}"}
    e = matrix_to_pose(invert_poses(s.Z) @ r.Z)
    std = frame_dict(r.Z, r.handeye.cov_Z)["std"]
    # an unobservable direction has no std (None): nan, so that it never counts as inside
    sig = np.array([np.nan if std[k_] is None else std[k_] for k_ in ("tx_mm", "ty_mm", "tz_mm")] +
                   [np.nan if std[k_] is None else math.radians(std[k_]) for k_ in ("rx_deg", "ry_deg", "rz_deg")])
    err_parent = np.concatenate([r.Z[:3, 3] - s.Z[:3, 3], rotvecs(r.Z[:3, :3] @ s.Z[:3, :3].T)])
    return {"seed": int(seed), "failed": None, "nees": nees(s.Z, r.Z, r.handeye.cov_Z),
            "inside_3sigma_each_axis": bool(np.all(np.abs(err_parent) <= 3 * sig)), "chi2_dof": float(r.chi2_dof),
            "p_value": float(r.p_value), "z_translation_error_mm": float(np.linalg.norm(e[:3])),
            "z_rotation_error_deg": math.degrees(float(np.linalg.norm(e[3:]))), "start": r.extra.get("start"),
            # the joint fit's focal-length estimate against the simulated lenslets' true focal length
            "sensor": r.extra.get("sensor"), "lenslet_focal_true_mm": true_focal_mm(bench, sensor)}


def summarise_sessions(outcomes) -> dict:
    """check_sessions' dict from a list of session_outcome dicts."""
    ok = [o for o in outcomes if o["failed"] is None]
    nees = np.array([o["nees"] for o in ok])
    each = [o["inside_3sigma_each_axis"] for o in ok]
    return {"nees": nees, "inside_3sigma": float(np.mean(nees <= NEES_3SIGMA_6DOF)) if len(nees) else float("nan"),
            "inside_3sigma_each_axis": float(np.mean(each)) if each else float("nan"),
            "chi2_dof": np.array([o["chi2_dof"] for o in ok]), "p_values": np.array([o["p_value"] for o in ok]),
            "z_translation_error_mm": np.array([o["z_translation_error_mm"] for o in ok]),
            "z_rotation_error_deg": np.array([o["z_rotation_error_deg"] for o in ok]),
            "seeds": np.array([o["seed"] for o in ok], dtype=int),
            "sensor": [o.get("sensor") for o in ok], "lenslet_focal_true_mm": [o.get("lenslet_focal_true_mm") for o in ok],
            "failed": [o["failed"] for o in outcomes if o["failed"] is not None]}


def extreme_poses(lens, bench: Bench, k: int) -> np.ndarray:
    """Nominal plus the k poses of the 12-pose calibration plan (seed 0, lens known) farthest from nominal in the
    bench's pose scales (k + 1, 6): where a sensor model is checked against the physical reference."""
    x = np.asarray(plan(lens, bench=bench, n=12, seed=0, tolerances=None).x)
    order = np.argsort(-np.max(np.abs(x) / np.asarray(bench.pose_scales), axis=1))
    return np.vstack([np.zeros(6), x[order[:k]]])


def check_sessions(design, n_sessions: int, *, seed: int = 0, tolerances=None, bench: Bench | None = None,
                   robot: RobotModel | str | None = None, n: int = 12, method: str = "joint",
                   calibration_tolerances="default", progress=None, plan_seed: int | None = None,
                   sensor: str | PhysicalSensor = "model", calibration_bench: Bench | None = None) -> dict:
    """Simulate ``n_sessions`` seeded sessions (seeds seed .. seed + n_sessions - 1, one
    shared plan of seed ``plan_seed``, default ``seed``), calibrate each through the
    files a real session writes, and score Z (``session_outcome``).
    method: the calibrate method ("joint", the default, or "two-stage");
    calibration_tolerances: the joint method's prior (as calibrate's ``tolerances``);
    calibration_bench: the bench calibrate models the sensor with (default the planning one).

    Returns {"nees": (k,) e^T cov_Z^-1 e of Z (right perturbation, 6 DOF), "inside_3sigma":
    fraction with NEES <= NEES_3SIGMA_6DOF (the 3-sigma-equivalent ellipsoid), "inside_3sigma_each_axis":
    fraction with all six parent-frame components within 3 reported sigma, "chi2_dof": (k,),
    "p_values": (k,) of the chi2 model check, "z_translation_error_mm", "z_rotation_error_deg",
    "seeds": (k,) of the scored sessions, "failed": sessions that raised}."""

    resolved = resolve_lens(design)
    lens, bench = resolved.lens, resolved.bench_or(bench)
    p = plan(resolved, bench=bench, robot=robot, n=n, seed=seed if plan_seed is None else plan_seed,
             tolerances=calibration_tolerances)
    outcomes = []
    for k in range(n_sessions):
        outcomes.append(session_outcome(lens, bench, p, seed + k, tolerances=tolerances, method=method,
                                        calibration_tolerances=calibration_tolerances, sensor=sensor,
                                        calibration_bench=calibration_bench))
        if progress is not None:
            progress(k + 1, n_sessions)
    return summarise_sessions(outcomes)
