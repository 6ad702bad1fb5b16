"""Manufacturability and measurability constraints of a design.

* thickness: axial glass thickness >= ``min_center_mm`` on the axis and
  >= ``min_edge_mm`` everywhere else on the edge diameter (printable; default 1 mm).
* no total internal reflection for any beam ray (a grid over the beam's 1/e^2 disc at
  the nominal pose) nor for any lenslet's aimed ray over the working range.
* working range: every lenslet of the SH pupil stays traced and lit (irradiance
  above the sensor threshold) at the nominal pose and at a batch of axis and corner
  poses of the working range (default +-1 mm, +-1 deg), so the robot can move the
  lens during estimation and calibration. The batch is one ``ForwardModel.evaluate``
  call: 12 axis poses (each DOF at +-range) and the 16 corners of
  (tx, ty, rx, ry) at +-range -- lateral beam walk comes from those four DOF.
* sensor range: over the same poses every pupil lenslet's spot stays assignable by
  the sensor (``sensor.spot_assignment``, see ``optics/sensor_range.py``) with a margin:
  the largest fraction of the assignment limit used is at most 1 - ``range_margin``.
* sensor model: over the same poses every pupil lenslet's slope stays within the range
  where the sensor model is validated (``sensor.validated_slope_mrad``; 0 = unbounded).
* calibration plan (``plan_mm`` / ``plan_rad`` > 0): the sensor-range and sensor-model
  checks also hold at the extreme poses of the calibration plan's box (``plan_poses``:
  +-plan on each DOF alone and the four (rx, ry) corners) wherever the pupil is lit there
  (``lensforge plan`` only chooses lit poses).
* observability (opt-in, ``observable=True``): every pose DOF observable at the
  nominal pose by DESIGN.md's statistical rule (``optics.sensitivity.observability``:
  not numerically null and predicted 1-sigma within the bench's pose scale).

``violation`` is a non-negative number (0 = feasible) that the optimisers use as a
penalty; ``check_design`` reports which constraint is violated and by how much.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError, DesignError, LensforgeError
from ..optics.bench import Bench
from ..optics.lens import Lens, polar_grid
from ..optics.sensitivity import metrics_from_S, sensitivity_from_model
from ..optics.shack_hartmann import ForwardModel
from ..optics.trace import OK, TIR, trace_rays

__all__ = ["PLAN_BOX_MM", "PLAN_BOX_DEG", "Constraints", "Violation", "Feasibility", "working_poses", "plan_poses", "check_design", "require_feasible"]


#: The calibration plan's box a design is checked over and ``lensforge plan`` then draws from (half-widths
#: of the lens pose about nominal). +-1.5 mm: a wider translation span separates the as-built lens from the
#: sensor's rotation (measured on the co-designed default design, ``lensforge plan -n 24``: rotation 1-sigma
#: lens free / lens known 1.41 at +-0.5 mm, 1.29 at +-1 mm, 1.24 at +-1.5 mm, 1.23 at +-2 mm; +-10 deg
#: instead of +-5 deg: 1.36). Neither the default nor the paper-bench design changes with it.
PLAN_BOX_MM = 1.5
PLAN_BOX_DEG = 5.0


@dataclass(frozen=True)
class Constraints:
    """Design constraints (mm, rad).

    min_center_mm / min_edge_mm: minimum axial thickness on the axis / elsewhere;
    range_mm / range_rad: half-width of the working pose range per DOF (0 disables the
    range check, the nominal pose is always checked); tir: forbid total internal
    reflection; max_slope_deg: steepest surface slope allowed inside the clear aperture
    (ASSUMPTION: 50 deg -- steeper surfaces are hard to hand-polish and to measure
    with a profilometer, and their SLA staircase grows as tan(slope); the paper's
    polynomial lens, printed and polished there, reaches 46.8 deg at its back rim).
    90 disables the check. range_margin: fraction of the sensor's spot-assignment limit
    kept free over the working range (ASSUMPTION 0.2: room for as-built deviations and
    poses between the checked ones). observable: require every pose DOF observable at the
    nominal pose (the statistical rule; off by default, the criteria already
    penalise lost rank). plan_mm / plan_rad: half-width of the calibration plan's box of
    lens poses (``lensforge design`` sets ``PLAN_BOX_MM`` / ``PLAN_BOX_DEG``, and ``lensforge plan`` draws from
    the box the design records); 0 = no plan check.
    """

    min_center_mm: float = 1.0
    min_edge_mm: float = 1.0
    range_mm: float = 1.0
    range_rad: float = math.radians(1.0)
    tir: bool = True
    max_slope_deg: float = 50.0
    range_margin: float = 0.2
    observable: bool = False
    plan_mm: float = 0.0
    plan_rad: float = 0.0

    def __post_init__(self):
        if not (isinstance(self.max_slope_deg, (int, float)) and 0 < self.max_slope_deg <= 90):
            raise ConfigError(f"constraints.max_slope_deg: must be in (0, 90] deg, got {self.max_slope_deg!r}")
        if isinstance(self.range_margin, bool) or not isinstance(self.range_margin, (int, float)) \
                or not 0 <= self.range_margin < 1:
            raise ConfigError(f"constraints.range_margin: must be in [0, 1), got {self.range_margin!r}")
        for f in ("min_center_mm", "min_edge_mm", "range_mm", "range_rad", "plan_mm", "plan_rad"):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"constraints.{f}: must be a finite number >= 0, got {v!r}")
            object.__setattr__(self, f, float(v))

    def check_bench(self, bench: Bench) -> None:
        """ConfigError if the working range exceeds the bench's pose limits."""
        lim = bench.pose_limits
        if self.range_mm > lim.translation_mm:
            raise ConfigError(
                f"constraints.range_mm: {self.range_mm} mm exceeds bench.pose_limits.translation_mm = "
                f"{lim.translation_mm}; shrink the working range or widen the limit"
            )
        if self.range_rad * math.sqrt(2) > lim.rotation_rad:
            raise ConfigError(
                f"constraints.range_rad: corners of +-{math.degrees(self.range_rad):.3g} deg exceed "
                f"bench.pose_limits.rotation_rad = {lim.rotation_rad:.4g} rad; shrink the range or widen the limit"
            )

    def to_dict(self) -> dict:
        d = {"min_center_mm": self.min_center_mm, "min_edge_mm": self.min_edge_mm,
             "range_mm": self.range_mm, "range_rad": self.range_rad, "tir": self.tir,
             "range_margin": self.range_margin}
        if self.plan_mm > 0 or self.plan_rad > 0:
            d.update(plan_mm=self.plan_mm, plan_rad=self.plan_rad)
        return {**d, "observable": True} if self.observable else d

    @classmethod
    def from_dict(cls, d: dict) -> "Constraints":
        if not isinstance(d, dict):
            raise ConfigError("constraints: expected an object")
        allowed = {"min_center_mm", "min_edge_mm", "range_mm", "range_rad", "tir", "range_margin", "observable",
                   "plan_mm", "plan_rad"}
        unknown = set(d) - allowed
        if unknown:
            raise ConfigError(f"constraints: unknown key(s) {sorted(unknown)}; allowed: {sorted(allowed)}")
        return cls(**d)


@dataclass(frozen=True)
class Violation:
    """One violated constraint: name, measured value, limit, one-line message."""

    constraint: str
    value: float
    limit: float
    message: str


@dataclass(frozen=True)
class Feasibility:
    """Result of checking a design: ok, violations, and the penalty measure (0 if ok)."""

    ok: bool
    violations: tuple = ()
    violation: float = 0.0
    min_thickness_mm: float = float("nan")
    center_thickness_mm: float = float("nan")
    model: ForwardModel | None = field(default=None, repr=False, compare=False)
    nominal_uv: np.ndarray | None = field(default=None, repr=False, compare=False)

    def message(self) -> str:
        return "; ".join(v.message for v in self.violations)

    def to_dict(self) -> dict:
        return {"feasible": self.ok, "violations": [v.constraint for v in self.violations],
                "message": self.message(), "min_thickness_mm": self.min_thickness_mm,
                "center_thickness_mm": self.center_thickness_mm}


def working_poses(c: Constraints) -> np.ndarray:
    """(P, 6) poses checked for the working range: nominal, 12 axis, 16 corners."""
    a, b = c.range_mm, c.range_rad
    scale = np.array([a, a, a, b, b, b])
    rows = [np.zeros(6)]
    if a > 0 or b > 0:
        for i in range(6):
            for s in (1.0, -1.0):
                e = np.zeros(6)
                e[i] = s * scale[i]
                rows.append(e)
        for sx, sy, srx, sry in itertools.product((1.0, -1.0), repeat=4):
            rows.append(np.array([sx * a, sy * a, 0.0, srx * b, sry * b, 0.0]))
    poses = np.unique(np.array(rows), axis=0)
    order = np.argsort(np.abs(poses).sum(axis=1), kind="stable")  # nominal first
    return poses[order]


def plan_poses(c: Constraints) -> np.ndarray:
    """(Q, 6) extreme poses of the calibration plan's box: +-plan on each DOF alone and the
    four (rx, ry) corners; (0, 6) without a plan box."""
    if not (c.plan_mm > 0 or c.plan_rad > 0):
        return np.zeros((0, 6))
    a, b = c.plan_mm, c.plan_rad
    rows = []
    for i, v in enumerate((a, a, a, b, b, b)):
        for s in (1.0, -1.0):
            e = np.zeros(6)
            e[i] = s * v
            rows.append(e)
    for srx, sry in itertools.product((1.0, -1.0), repeat=2):
        rows.append(np.array([0.0, 0.0, 0.0, srx * b, sry * b, 0.0]))
    return np.unique(np.array(rows), axis=0)


def _beam_grid(bench: Bench, n: int = 9) -> np.ndarray:
    """Beam rays (u, v) on a square grid inside the 1/e^2 disc (mm)."""
    w = 0.5 * bench.laser.beam_diameter_mm
    g = np.linspace(-w, w, n)
    U, V = np.meshgrid(g, g)
    inside = U**2 + V**2 <= w * w
    return np.stack([U[inside], V[inside]], axis=1)


def check_design(bench: Bench, lens: Lens, c: Constraints, poses: np.ndarray | None = None,
                 fast: bool = False) -> Feasibility:
    """Check every constraint; never raises for a non-physical lens (reported instead).

    fast: skip ``Lens.validate`` (inside optimisers; the returned design is always
    re-checked with fast=False).
    """
    vs: list[Violation] = []
    if not fast:
        try:
            lens.validate()
        except LensforgeError as e:
            return Feasibility(False, (Violation("geometry", float("nan"), 0.0, str(e)),), 1e3)
    # thickness: centre and the rest of the edge diameter (polar grid incl. the rim)
    t_c = float(lens.thickness_at(0.0, 0.0))
    x, y = polar_grid(0.5 * lens.edge_diameter)  # the grid Lens.min_thickness uses
    t_all = lens.thickness_at(x, y)
    if not np.all(np.isfinite(t_all)):
        return Feasibility(False, (Violation("geometry", float("nan"), 0.0,
                                             "lens: a conic surface is undefined inside the edge diameter; "
                                             "reduce the curvature"),), 1e3)
    t_min = float(np.min(t_all[1:]))
    pen = 0.0
    if t_c < c.min_center_mm:
        vs.append(Violation("center_thickness", t_c, c.min_center_mm,
                            f"centre thickness {t_c:.3f} mm < {c.min_center_mm} mm (constraints.min_center_mm); "
                            "raise the thickness bound"))
        pen += (c.min_center_mm - t_c) / max(c.min_center_mm, 1e-3)
    if t_min < c.min_edge_mm:
        vs.append(Violation("edge_thickness", t_min, c.min_edge_mm,
                            f"edge/minimum thickness {t_min:.3f} mm < {c.min_edge_mm} mm (constraints.min_edge_mm); "
                            "raise the thickness or reduce the surface sags"))
        pen += (c.min_edge_mm - t_min) / max(c.min_edge_mm, 1e-3)
    if c.max_slope_deg < 90.0:
        xa, ya = polar_grid(0.5 * lens.aperture)
        limit = math.tan(math.radians(c.max_slope_deg))
        for side in ("front", "back"):
            gx, gy = getattr(lens, side).gradient(xa, ya)
            steepest = float(np.max(np.hypot(gx, gy)))
            if steepest > limit:
                vs.append(Violation(f"{side}_slope", math.degrees(math.atan(steepest)), c.max_slope_deg,
                                    f"{side} surface slope {math.degrees(math.atan(steepest)):.1f} deg > "
                                    f"{c.max_slope_deg} deg inside the clear aperture (constraints.max_slope_deg); "
                                    "reduce the curvature/freeform terms or relax the limit"))
                pen += steepest / limit - 1.0
    if vs:
        return Feasibility(False, tuple(vs), 10.0 + pen, t_min, t_c)
    model = ForwardModel(bench, lens, validate=False)
    if c.tir:
        tr = trace_rays(bench, lens, np.zeros((1, 6)), _beam_grid(bench), kernel=model.kernel)
        n_tir = int(np.sum(tr.status == TIR))
        if n_tir:
            vs.append(Violation("tir", n_tir, 0, f"total internal reflection for {n_tir} beam rays at the nominal "
                                "pose; reduce surface slopes"))
            pen += n_tir / tr.status.size
    P = working_poses(c) if poses is None else poses
    res = model.evaluate(P[:1], check_range=False)
    uv0 = res.uv[0] if res.valid[0] else None
    status, irr, use = res.status, res.irradiance, res.range_use
    if len(P) > 1:
        # the whole working batch in one call, warm-started from the nominal aim
        warm = None if uv0 is None else np.broadcast_to(uv0, (len(P) - 1,) + uv0.shape)
        res2 = model.evaluate(P[1:], uv0=warm, check_range=False)
        status = np.concatenate([status, res2.status])
        irr = np.concatenate([irr, res2.irradiance])
        use = np.concatenate([use, res2.range_use])
    valid = np.all(status == OK, axis=1) & np.all(irr >= res.threshold, axis=1)
    if c.tir and np.any(status == TIR):
        n_tir = int(np.sum(np.any(status == TIR, axis=1)))
        vs.append(Violation("tir", n_tir, 0, f"total internal reflection of pupil rays at {n_tir} of {len(P)} "
                            "working-range poses; reduce surface slopes"))
        pen += float(np.mean(status == TIR))
    if not valid.all():
        bad = np.flatnonzero(~valid)
        worst = bad[0]
        not_ok = float(np.mean(status != OK))
        thr = res.threshold
        short = float(np.mean(np.clip((thr - np.where(status == OK, irr, 0.0)) / thr, 0.0, 1.0)))
        where = "the nominal pose" if worst == 0 else f"working-range pose {np.round(P[worst], 4).tolist()} (mm, rad)"
        # reason text of the first bad pose
        st = status[worst]
        if np.any(st != OK):
            why = f"{int(np.sum(st != OK))} of {st.size} pupil lenslets not reached"
        else:
            why = f"pupil under-filled (min irradiance {irr[worst].min():.3g} < threshold {thr:.3g})"
        vs.append(Violation("pupil_lit", float(len(bad)), 0.0,
                            f"SH pupil not fully lit at {len(bad)} of {len(P)} working-range poses (the beam leaves "
                            f"part of the sensor's Zernike pupil dark there, so those poses cannot be measured), first "
                            f"at {where}: {why}; reduce surface power/tilt or shrink the working range "
                            f"(constraints.range_mm/range_rad; CLI --range-mm/--range-deg)"))
        pen += 1.0 + not_ok + short
    else:
        pen += _range_checks(bench, c, model, P, use, res.slopes if len(P) == 1 else
                             np.concatenate([res.slopes, res2.slopes]), uv0, vs)
    if c.observable and not vs:
        S, z0, _ = sensitivity_from_model(model, raise_invalid=False)
        ob = None if S is None else metrics_from_S(S, model.noise_cov, bench, z0).observability
        if ob is not None and not ob.observable.all():
            excess = np.minimum(ob.std / np.asarray(bench.pose_scales, dtype=float), 1e3)
            vs.append(Violation("observable", float(np.sum(~ob.observable)), 0.0,
                                f"pose DOF {', '.join(ob.unobservable)} unobservable at the nominal pose (predicted "
                                "1-sigma above the bench's pose scale); break the lens's symmetry or drop "
                                "constraints.observable"))
            pen += 1.0 + float(np.sum(np.log10(excess[~ob.observable])))
    return Feasibility(not vs, tuple(vs), pen, t_min, t_c, model, uv0)


def _range_checks(bench: Bench, c: Constraints, model: ForwardModel, P, use, slopes, uv0, vs: list) -> float:
    """Sensor range (with margin) and sensor-model slope bound over the working poses P and
    the lit plan poses; appends violations to vs and returns their penalty."""
    pen = 0.0
    Q = plan_poses(c)
    labels = ["working-range"] * len(P)
    if len(Q):
        warm = None if uv0 is None else np.broadcast_to(uv0, (len(Q),) + uv0.shape)
        rq = model.evaluate(Q, uv0=warm, check_range=False)
        lit = np.all(rq.status == OK, axis=1) & np.all(rq.irradiance >= rq.threshold, axis=1)
        use = np.concatenate([use, rq.range_use[lit]])
        slopes = np.concatenate([slopes, rq.slopes[lit]])
        P = np.concatenate([P, Q[lit]])
        labels += ["calibration-plan"] * int(lit.sum())
    if bench.sensor.spot_assignment != "none":
        worst_use = np.max(use, axis=1)
        allowed = 1.0 - c.range_margin
        if np.any(worst_use > allowed):
            k = int(np.argmax(worst_use))
            where = "the nominal pose" if k == 0 else f"{labels[k]} pose {np.round(P[k], 4).tolist()} (mm, rad)"
            vs.append(Violation("sensor_range", float(worst_use[k]), allowed,
                                f"spots use up to {worst_use[k]:.3g} x the sensor's '{bench.sensor.spot_assignment}' "
                                f"spot-assignment limit (allowed {allowed:.3g} with constraints.range_margin = "
                                f"{c.range_margin}) at {where}; weaken the surface power, move the lens closer "
                                "(placement.distance_mm) or shrink the working range"))
            pen += float(worst_use[k] - allowed) + float(np.mean(np.clip(worst_use - allowed, 0, None)))
    bound = bench.sensor.validated_slope_mrad * 1e-3
    if bound > 0:
        worst = np.max(np.abs(slopes), axis=(1, 2))
        if np.any(worst > bound):
            k = int(np.argmax(worst))
            where = "the nominal pose" if k == 0 else f"{labels[k]} pose {np.round(P[k], 4).tolist()} (mm, rad)"
            vs.append(Violation("sensor_model", float(worst[k] * 1e3), bench.sensor.validated_slope_mrad,
                                f"lenslet slopes reach {worst[k] * 1e3:.4g} mrad at {where}, beyond the "
                                f"{bench.sensor.validated_slope_mrad:g} mrad where the sensor model is validated "
                                "(sensor.validated_slope_mrad); weaken the surface power or shrink the pupil"))
            pen += float(worst[k] / bound - 1.0) + float(np.mean(np.clip(worst / bound - 1.0, 0, None)))
    return pen


def require_feasible(f: Feasibility, what: str = "design") -> None:
    """Raise DesignError naming the violated constraint(s)."""
    if not f.ok:
        names = ", ".join(sorted({v.constraint for v in f.violations}))
        raise DesignError(f"{what} is infeasible ({names}): {f.message()}")
