"""Printer profile (Formlabs Form 2) and the printability checks that need no slicer.

Checks: the part fits the build volume, a suggested print orientation, the layer
staircase each optical surface carries (from its local slope and the layer height)
and features smaller than the laser spot. Lengths in mm, angles in rad inside
(reports add *_deg keys).

Staircase model (cusp height, Dolenc & Maekelae, Computer-Aided Design 26(2) 119,
1994): layers are planes normal to the build direction d; a surface whose normal n
makes the angle theta with d carries steps of height h along d, a cusp of height
h |cos theta| along its normal and treads h / tan(theta) wide.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from ..optics.lens import Lens

__all__ = ["PrinterProfile", "FORM2", "check_layer", "staircase", "SurfaceStaircase", "surface_staircase",
           "Orientation", "suggest_orientation", "fitting_orientations", "small_features", "PrintReport",
           "printability"]


@dataclass(frozen=True)
class PrinterProfile:
    """An SLA printer (mm, nm).

    Form 2 values from the Formlabs Form 2 technical specifications: build volume
    145 x 145 x 175 mm, layer heights 25/50/100 um, 405 nm laser. xy_spot_mm = 0.140:
    ASSUMPTION (the laser spot size commonly quoted for the Form 2; Formlabs gives
    no official XY resolution).
    """

    name: str = "Formlabs Form 2"
    build_volume_mm: tuple = (145.0, 145.0, 175.0)
    layer_heights_mm: tuple = (0.025, 0.05, 0.1)
    laser_wavelength_nm: float = 405.0
    xy_spot_mm: float = 0.140
    assumptions: tuple = ("xy_spot_mm",)

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


FORM2 = PrinterProfile()


def check_layer(layer_mm: float, profile: PrinterProfile = FORM2) -> float:
    """The layer height (mm) if the printer offers it, else ConfigError naming the choices."""
    for h in profile.layer_heights_mm:
        if np.isclose(layer_mm, h, rtol=0, atol=1e-9):
            return float(h)
    um = ", ".join(f"{1000 * h:g}" for h in profile.layer_heights_mm)
    raise ConfigError(f"layer: {profile.name} prints layers of {um} um only, got {1000 * layer_mm:g} um")


def staircase(cos_theta, layer_mm: float) -> dict:
    """Staircase of a surface whose normal makes angle theta with the build direction.

    cos_theta: |n . d| (array); returns cusp height along the normal (mm), tread width
    (mm, inf where the surface lies in a layer) and the step along d (= layer, mm).
    """
    c = np.clip(np.abs(np.asarray(cos_theta, float)), 0.0, 1.0)
    s = np.sqrt(1.0 - c * c)
    with np.errstate(divide="ignore"):
        tread = np.where(s > 0, layer_mm * c / np.where(s > 0, s, 1.0), np.inf)
    return {"cusp_mm": layer_mm * c, "tread_mm": tread, "step_mm": np.full_like(c, layer_mm)}


def _aperture_points(lens: Lens, n_r: int = 24, n_phi: int = 72):
    """Equal-area polar samples of the clear aperture (mm)."""
    R = 0.5 * lens.aperture
    r = R * np.sqrt((np.arange(n_r) + 0.5) / n_r)
    p = 2 * np.pi * np.arange(n_phi) / n_phi
    return (r[:, None] * np.cos(p)).ravel(), (r[:, None] * np.sin(p)).ravel()


def _normals(surface, x, y) -> np.ndarray:
    gx, gy = surface.gradient(x, y)
    n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


@dataclass(frozen=True)
class SurfaceStaircase:
    """Layer staircase on one optical surface over the clear aperture (mm, deg)."""

    surface: str
    layer_mm: float
    max_slope_deg: float  # steepest angle between the surface and the layers
    min_tread_mm: float
    max_cusp_mm: float
    rms_cusp_mm: float

    def to_dict(self) -> dict:
        d = dict(self.__dict__)
        d["min_tread_mm"] = None if not np.isfinite(self.min_tread_mm) else self.min_tread_mm
        return d


def surface_staircase(lens: Lens, layer_mm: float, build_dir=(0.0, 0.0, 1.0)) -> list[SurfaceStaircase]:
    """Staircase on the front and back surfaces for a build direction given in {O}."""
    d = np.asarray(build_dir, float)
    d = d / np.linalg.norm(d)
    x, y = _aperture_points(lens)
    out = []
    for name in ("front", "back"):
        c = np.abs(_normals(getattr(lens, name), x, y) @ d)
        st = staircase(c, layer_mm)
        out.append(SurfaceStaircase(name, float(layer_mm), float(np.degrees(np.arccos(np.min(c)))),
                                    float(np.min(st["tread_mm"])), float(np.max(st["cusp_mm"])),
                                    float(np.sqrt(np.mean(st["cusp_mm"] ** 2)))))
    return out


def fitting_orientations(extents_mm, profile: PrinterProfile = FORM2) -> list[tuple]:
    """Axis permutations (part x, y, z -> printer axes) under which the box fits the build volume."""
    from itertools import permutations

    e = np.asarray(extents_mm, float)
    vol = np.asarray(profile.build_volume_mm, float)
    return [p for p in permutations(range(3)) if np.all(e[list(p)] <= vol)]


@dataclass(frozen=True)
class Orientation:
    """A print orientation: build direction in {O} and what it costs (mm, deg)."""

    build_direction: tuple
    tilt_deg: float  # angle between the optical axis and the build direction
    azimuth_deg: float
    rms_cusp_mm: float  # over both clear apertures
    max_cusp_mm: float
    height_mm: float
    layers: int
    fits: bool
    note: str = ""

    def to_dict(self) -> dict:
        d = dict(self.__dict__)
        d["build_direction"] = list(self.build_direction)
        return d


def _extent_along(vertices: np.ndarray, d: np.ndarray) -> tuple[float, float, float]:
    """(height along d, the two widths across d) of the vertices (mm)."""
    h = vertices @ d
    a = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(d, a)
    w1 = np.ptp(vertices @ a)
    w2 = np.ptp(vertices @ b)
    return float(np.ptp(h)), float(w1), float(w2)


def suggest_orientation(lens: Lens, vertices: np.ndarray, layer_mm: float,
                        profile: PrinterProfile = FORM2) -> tuple[Orientation, list[Orientation]]:
    """Build direction minimising the RMS cusp height on the optical surfaces, among tilts
    0..90 deg (15 deg steps) and azimuths 0..135 deg, that fits the build volume.

    vertices: (N, 3) part vertices in {O} (mm) for the size checks.
    Returns (best, all candidates).
    """
    x, y = _aperture_points(lens)
    nf, nb = _normals(lens.front, x, y), _normals(lens.back, x, y)
    cands = []
    for tilt in np.radians(np.arange(0, 91, 15)):
        for az in (np.radians([0, 45, 90, 135]) if tilt > 0 else [0.0]):
            d = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
            c = np.abs(np.concatenate([nf @ d, nb @ d]))
            cusp = layer_mm * c
            hgt, w1, w2 = _extent_along(vertices, d)
            fits = hgt <= profile.build_volume_mm[2] and max(w1, w2) <= min(profile.build_volume_mm[:2])
            cands.append(Orientation(tuple(float(v) for v in np.round(d, 12) + 0.0), float(np.degrees(tilt)), float(np.degrees(az)),
                                     float(np.sqrt(np.mean(cusp ** 2))), float(np.max(cusp)), hgt,
                                     int(np.ceil(hgt / layer_mm)), bool(fits)))
    ok = [c for c in cands if c.fits] or cands
    best = min(ok, key=lambda c: (round(c.rms_cusp_mm, 9), c.tilt_deg, c.azimuth_deg))
    note = ("optical axis tilted {:.0f} deg from the build direction; put supports on the edge or the tab, "
            "never on the optical surfaces").format(best.tilt_deg)
    best = Orientation(**{**best.__dict__, "note": note})
    return best, cands


def small_features(lens: Lens, boxes=(), profile: PrinterProfile = FORM2) -> list[dict]:
    """Features narrower than the XY laser spot (they will not print as drawn)."""
    items = [("edge thickness", lens.edge_thickness)]
    for b in boxes:
        if b.name == "notch":
            items.append(("notch width", b.size[1]))
        if b.op == "cut":
            items.append((f"{b.name} depth", b.size[0] - 1.0))
        if b.name == "tab":
            items.append(("tab thickness", b.size[2]))
    return [{"feature": n, "size_mm": float(v), "limit_mm": profile.xy_spot_mm}
            for n, v in items if v < profile.xy_spot_mm]


@dataclass(frozen=True)
class PrintReport:
    """What the Form 2 will make of the part (mm)."""

    printer: str
    layer_mm: float
    bounding_box_mm: tuple
    extents_mm: tuple
    fits: bool
    orientation: Orientation
    staircase: tuple  # SurfaceStaircase for the suggested orientation
    staircase_axis_vertical: tuple  # optical axis along the build direction (the ripple model's case)
    small_features: tuple
    assumptions: tuple = field(default=())

    def to_dict(self) -> dict:
        return {
            "printer": self.printer,
            "layer_mm": self.layer_mm,
            "bounding_box_mm": [list(c) for c in self.bounding_box_mm],
            "extents_mm": list(self.extents_mm),
            "fits": self.fits,
            "orientation": self.orientation.to_dict(),
            "staircase": [s.to_dict() for s in self.staircase],
            "staircase_axis_vertical": [s.to_dict() for s in self.staircase_axis_vertical],
            "small_features": list(self.small_features),
            "assumptions": list(self.assumptions),
        }


def printability(lens: Lens, vertices: np.ndarray, layer_mm: float = 0.025, boxes=(),
                 profile: PrinterProfile = FORM2) -> PrintReport:
    """Fit, orientation, staircase and small-feature checks for a part with these vertices (mm)."""
    layer = check_layer(layer_mm, profile)
    v = np.asarray(vertices, float)
    lo, hi = v.min(axis=0), v.max(axis=0)
    ext = hi - lo
    best, _ = suggest_orientation(lens, v, layer, profile)
    fits = bool(fitting_orientations(ext, profile)) or best.fits
    d = np.asarray(best.build_direction)
    return PrintReport(profile.name, layer, (tuple(map(float, lo)), tuple(map(float, hi))), tuple(map(float, ext)),
                       fits, best, tuple(surface_staircase(lens, layer, d)),
                       tuple(surface_staircase(lens, layer, (0.0, 0.0, 1.0))),
                       tuple(small_features(lens, boxes, profile)),
                       tuple(f"{a} (ASSUMPTION)" for a in profile.assumptions))
