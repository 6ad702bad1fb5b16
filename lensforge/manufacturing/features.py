"""Handling features on the lens edge: orientation fiducial (flat or notch) and gripper tab.

A feature is described once, backend-neutrally, as a list of boxes to cut or to add
(:class:`Box`, lens frame {O}, mm); the mesh route applies them with manifold3d and
the STEP route with OCC booleans, so both files carry the same part. Every feature
lies in the ring between the clear aperture and the mechanical edge (or beyond the
edge), never inside the clear aperture.

The analytic volume change of the features (:func:`feature_volume_change`) lets the
exporters check their solids against an exact integral.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, LensGeometryError
from ..optics.lens import Lens

__all__ = ["FeatureSpec", "Box", "feature_boxes", "feature_volume_change", "lens_volume", "with_flange",
           "DEFAULT_FLANGE_MM"]

FIDUCIAL_KINDS = ("flat", "notch")

# ASSUMPTION: a 1 mm wide mechanical edge (flange) around the clear aperture. It holds the
# default 0.5 mm fiducial with its 0.1 mm clearance and the tab's 0.5 mm overlap, and gives
# a holder or gripper something to touch that is not optical surface.
DEFAULT_FLANGE_MM = 1.0


def with_flange(lens: Lens, flange_mm: float = DEFAULT_FLANGE_MM) -> Lens:
    """The lens with a mechanical edge at least ``flange_mm`` (radial, mm) beyond the clear
    aperture: its surfaces continue outward to edge_diameter = aperture + 2 flange_mm. A lens
    whose edge is already that wide is returned unchanged."""
    f = float(flange_mm)
    if not np.isfinite(f) or f < 0:
        raise ConfigError(f"flange: must be a finite width >= 0 mm, got {flange_mm}")
    want = lens.aperture + 2.0 * f
    if lens.edge_diameter >= want:
        return lens
    wide = lens.replace(edge_diameter=want)
    try:
        return wide.validate()
    except LensGeometryError as e:
        raise LensGeometryError(f"flange: continuing the surfaces {f:g} mm beyond the clear aperture fails ({e}); "
                                "choose a narrower flange (CLI: --flange) or --edge-diameter") from None


@dataclass(frozen=True)
class FeatureSpec:
    """Optional handling features (lengths in mm, angles in rad about +z of {O}). The default
    sizes are ASSUMPTIONS (a 6 mm wide tab suits a small parallel gripper; 0.5 mm flat/notch
    depth is several Form 2 laser spots, so it prints and is visible).

    Parameters
    ----------
    fiducial : str or None
        None, "flat" or "notch": a flat or a rectangular slot on the edge that makes the
        roll of the lens visible.
    fiducial_angle : float
        Direction of the fiducial's centre, rad.
    fiducial_depth_mm : float
        How far it reaches in from the edge, mm.
    notch_width_mm : float
        Slot width, mm.
    tab : bool
        Add a rectangular gripper tab.
    tab_angle : float
        Its direction, rad.
    tab_width_mm, tab_length_mm : float
        Its width and its reach beyond the edge, mm.
    tab_thickness_mm : float
        Its thickness along z, mm (clipped to 80 % of the local edge thickness).
    clearance_mm : float
        Minimum gap kept to the clear aperture, mm.
    """

    fiducial: str | None = None
    fiducial_angle: float = 0.0
    fiducial_depth_mm: float = 0.5
    notch_width_mm: float = 1.0
    tab: bool = False
    tab_angle: float = 0.5 * np.pi
    tab_width_mm: float = 6.0
    tab_length_mm: float = 8.0
    tab_thickness_mm: float = 2.0
    clearance_mm: float = 0.1

    def __post_init__(self):
        if self.fiducial not in (None,) + FIDUCIAL_KINDS:
            raise ConfigError(f"fiducial: must be one of {FIDUCIAL_KINDS} or None, got {self.fiducial!r}")
        for name in ("fiducial_depth_mm", "notch_width_mm", "tab_width_mm", "tab_length_mm", "tab_thickness_mm"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise ConfigError(f"features.{name}: must be a finite number > 0 mm, got {v}")
        if not np.isfinite(self.clearance_mm) or self.clearance_mm < 0:
            raise ConfigError(f"features.clearance_mm: must be >= 0 mm, got {self.clearance_mm}")
        for name in ("fiducial_angle", "tab_angle"):
            if not np.isfinite(getattr(self, name)):
                raise ConfigError(f"features.{name}: must be a finite angle in rad")

    @property
    def any(self) -> bool:
        return self.fiducial is not None or self.tab


@dataclass(frozen=True)
class Box:
    """An axis-aligned box rotated by `angle` (rad) about +z, then centred at `center`.

    op: "cut" or "add"; size: (radial, tangential, axial) extents in mm in the
    feature's own frame (u along the direction `angle`, v tangential, z axial);
    u0: the box spans u in [u0, u0 + size[0]]; z0: lower z face.
    """

    op: str
    angle: float
    u0: float
    size: tuple
    z0: float
    name: str = ""

    @property
    def center(self) -> np.ndarray:
        """Box centre in {O} (mm)."""
        uc = self.u0 + 0.5 * self.size[0]
        return np.array([uc * np.cos(self.angle), uc * np.sin(self.angle), self.z0 + 0.5 * self.size[2]])


def _z_extent(lens: Lens, margin: float = 1.0) -> tuple[float, float]:
    r = 0.5 * lens.edge_diameter
    rr = r * np.sqrt(np.linspace(0, 1, 24))[:, None]
    pp = np.linspace(0, 2 * np.pi, 96, endpoint=False)[None, :]
    x, y = rr * np.cos(pp), rr * np.sin(pp)
    zf = -0.5 * lens.thickness + lens.front.sag(x, y)
    zb = 0.5 * lens.thickness + lens.back.sag(x, y)
    return float(np.nanmin(zf)) - margin, float(np.nanmax(zb)) + margin


def _angle_gap(a: float, b: float) -> float:
    d = (a - b) % (2 * np.pi)
    return min(d, 2 * np.pi - d)


def feature_boxes(lens: Lens, spec: FeatureSpec) -> list[Box]:
    """The boxes that realise `spec` on `lens`; raises if a feature would enter the clear aperture."""
    if not spec.any:
        return []
    R = 0.5 * lens.edge_diameter
    Ra = 0.5 * lens.aperture
    margin = R - Ra - spec.clearance_mm
    zlo, zhi = _z_extent(lens)
    boxes: list[Box] = []
    if spec.fiducial is not None:
        d = spec.fiducial_depth_mm
        if d > margin + 1e-12:
            need = lens.aperture + 2 * (d + spec.clearance_mm)
            raise LensGeometryError(
                f"lens.edge_diameter: the {spec.fiducial} fiducial ({d} mm deep, {spec.clearance_mm} mm clearance) "
                f"would enter the {lens.aperture} mm clear aperture; set edge_diameter >= {need:.3f} mm "
                "(CLI: --edge-diameter) or reduce the fiducial depth"
            )
        width = 2 * R + 2.0 if spec.fiducial == "flat" else spec.notch_width_mm
        if spec.fiducial == "notch" and spec.notch_width_mm >= 2 * R:
            raise ConfigError(f"features.notch_width_mm: {spec.notch_width_mm} mm is wider than the lens")
        boxes.append(Box("cut", spec.fiducial_angle, R - d, (d + 1.0, width, zhi - zlo), zlo, spec.fiducial))
    if spec.tab:
        if margin < 0.2:
            need = lens.aperture + 2 * (0.2 + spec.clearance_mm)
            raise LensGeometryError(
                f"lens.edge_diameter: the gripper tab needs at least 0.2 mm of edge outside the clear aperture "
                f"(+{spec.clearance_mm} mm clearance); set edge_diameter >= {need:.3f} mm (CLI: --edge-diameter)"
            )
        if spec.tab_width_mm >= 2 * R:
            raise ConfigError(f"features.tab_width_mm: {spec.tab_width_mm} mm is wider than the lens")
        if spec.fiducial is not None:
            half = np.arcsin(min(1.0, 0.5 * spec.tab_width_mm / R))
            if spec.fiducial == "flat":
                fhalf = np.arccos((R - spec.fiducial_depth_mm) / R)
            else:
                fhalf = np.arcsin(min(1.0, 0.5 * spec.notch_width_mm / R))
            if _angle_gap(spec.tab_angle, spec.fiducial_angle) < half + fhalf + 0.05:
                raise ConfigError("features.tab_angle: the tab overlaps the fiducial; choose angles further apart")
        overlap = min(0.5, margin)
        u0 = R - overlap
        # z range that stays inside the lens over the part of the tab inside the edge
        hw = 0.5 * spec.tab_width_mm
        v = np.linspace(-hw, hw, 41)
        u = np.linspace(u0, R, 11)
        uu, vv = np.meshgrid(u, v, indexing="ij")
        inside = uu * uu + vv * vv <= R * R
        uu, vv = uu[inside], vv[inside]
        ca, sa = np.cos(spec.tab_angle), np.sin(spec.tab_angle)
        x, y = uu * ca - vv * sa, uu * sa + vv * ca
        zf_max = float(np.max(-0.5 * lens.thickness + lens.front.sag(x, y)))
        zb_min = float(np.min(0.5 * lens.thickness + lens.back.sag(x, y)))
        room = zb_min - zf_max
        if room <= 0:
            raise LensGeometryError("lens: no edge thickness left for a gripper tab at tab_angle; choose another angle")
        t = min(spec.tab_thickness_mm, 0.8 * room)
        zc = 0.5 * (zf_max + zb_min)
        boxes.append(Box("add", spec.tab_angle, u0, (overlap + spec.tab_length_mm, spec.tab_width_mm, t), zc - 0.5 * t, "tab"))
    return boxes


# ---------------------------------------------------------------------------
# Analytic volumes (exact to quadrature accuracy; smooth integrands only)


def lens_volume(lens: Lens, n_r: int = 64, n_phi: int = 256) -> float:
    """Volume (mm^3) of the plain lens: integral of thickness_at over the edge disc.

    Gauss-Legendre in r (exact for the polynomial terms) times the periodic
    trapezoid rule in phi (spectrally accurate for smooth periodic integrands).
    """
    R = 0.5 * lens.edge_diameter
    t, w = np.polynomial.legendre.leggauss(n_r)
    r = 0.5 * R * (t + 1.0)
    wr = 0.5 * R * w * r
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    x = r[:, None] * np.cos(phi)[None, :]
    y = r[:, None] * np.sin(phi)[None, :]
    th = lens.thickness_at(x, y)
    return float(np.sum(wr[:, None] * th) * (2 * np.pi / n_phi))


def _segment_volume(lens: Lens, angle: float, u_in: float, half_width: float, n: int = 48) -> float:
    """Integral of thickness over {u > u_in, |v| < half_width} inside the edge disc (mm^3)."""
    return _segment_integral(0.5 * lens.edge_diameter, angle, u_in, half_width, lens.thickness_at, n)


def _segment_integral(R: float, angle: float, u_in: float, half_width: float, f, n: int = 48) -> float:
    """Integral of f(x, y) over {u > u_in, |v| < half_width} inside the disc of radius R,
    (u, v) rotated by ``angle`` from (x, y); Gauss-Legendre in both directions."""
    c = np.sqrt(max(R * R - u_in * u_in, 0.0))
    vmax = min(half_width, c)
    if vmax <= 0:
        return 0.0
    tm = np.arcsin(vmax / c)
    g, gw = np.polynomial.legendre.leggauss(n)
    th = tm * g  # v = c sin(theta) keeps the integrand smooth at the circle
    wth = tm * gw
    v = c * np.sin(th)
    dv = c * np.cos(th) * wth
    umax = np.sqrt(R * R - v * v)
    uu = u_in + 0.5 * (umax - u_in)[:, None] * (g[None, :] + 1.0)
    wu = 0.5 * (umax - u_in)[:, None] * gw[None, :]
    ca, sa = np.cos(angle), np.sin(angle)
    vv = v[:, None]
    x, y = uu * ca - vv * sa, uu * sa + vv * ca
    return float(np.sum(dv[:, None] * wu * f(x, y)))


def _disc_rect_area(R: float, u_in: float, half_width: float, n: int = 64) -> float:
    """Area of {u > u_in, |v| < half_width} inside the disc of radius R (mm^2)."""
    return _segment_integral(R, 0.0, u_in, half_width, lambda x, y: np.ones_like(x), n)


def feature_volume_change(lens: Lens, boxes: list[Box]) -> float:
    """Volume (mm^3) the feature boxes add (positive) or remove (negative) from the lens."""
    R = 0.5 * lens.edge_diameter
    dv = 0.0
    for b in boxes:
        if b.op == "cut":
            dv -= _segment_volume(lens, b.angle, b.u0, 0.5 * b.size[1])
        else:  # tab: box volume minus the part already inside the lens (it lies wholly inside in z)
            inside = _disc_rect_area(R, b.u0, 0.5 * b.size[1])
            dv += b.size[2] * (b.size[0] * b.size[1] - inside)
    return dv
