"""A lens: two sag surfaces, centre thickness, clear aperture, material.

Lens frame {O} (DESIGN.md): origin on the axis halfway between the vertices, +z from
the front (first-hit) surface to the back surface; front vertex at z = -l/2, back
vertex at z = +l/2. Surface sags are added to their vertex planes.
"""

from __future__ import annotations

import math

from os import PathLike

from numpy.typing import ArrayLike

from dataclasses import dataclass, field, replace
from typing import Protocol, TypeAlias
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import ConfigError, LensGeometryError
from ..fileio import read_json
from ..input_checks import DESIGN_KIND, LENS_RANGES, check_header, check_ranges
from .bench import Bench
from .materials import Material, load_material
from .surfaces import Conic, ExtendedPolynomial, Polynomial, Surface, ZernikeSag, surface_from_dict

__all__ = ["Lens", "paper_lens", "PAPER_LENSES", "load_lens", "resolve_lens", "ResolvedLens", "lens_conventions"]


def polar_grid(radius: float, n_r: int = 48, n_phi: int = 96):
    """Sample points (x, y) of a disk of the given radius, uniform in area along r."""
    r = radius * np.sqrt(np.linspace(0.0, 1.0, n_r))
    phi = np.linspace(0.0, 2 * np.pi, n_phi, endpoint=False)
    rr, pp = np.meshgrid(r, phi, indexing="ij")
    return rr * np.cos(pp), rr * np.sin(pp)


@dataclass(frozen=True)
class Lens:
    """A singlet lens in its frame {O}: front vertex at z = -l/2, back vertex at z = +l/2.

    Parameters
    ----------
    front, back : Surface
        The two surfaces (sag along +z of their vertex frames): Conic, Polynomial,
        ExtendedPolynomial, ZernikeSag or Freeform.
    thickness : float
        Centre thickness l, mm.
    aperture : float
        Clear-aperture diameter, mm.
    material : str or Material
        Name of a file in ``materials/`` (or a Material).
    index_offset : float
        Added to the material's index (as-built lenses).
    edge_diameter : float or None
        Mechanical diameter of the cylindrical edge, mm (None: the aperture).
    name : str
        Free text.
    """

    front: Surface
    back: Surface
    thickness: float
    aperture: float = 25.4
    material: str = "N-BK7"
    index_offset: float = 0.0
    edge_diameter: float | None = None
    name: str = ""

    def __post_init__(self):
        for f in ("thickness", "aperture", "index_offset"):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating)) or not np.isfinite(v):
                raise ConfigError(f"lens.{f}: must be a finite number, got {v!r}")
            object.__setattr__(self, f, float(v))
        if self.edge_diameter is None:
            object.__setattr__(self, "edge_diameter", self.aperture)
        if not isinstance(self.front, Surface) or not isinstance(self.back, Surface):
            raise ConfigError("lens.front/back: must be Surface objects (see lensforge.optics.surfaces)")

    # --- optics -------------------------------------------------------------
    @cached_property
    def _material(self) -> Material:
        return self.material if isinstance(self.material, Material) else load_material(self.material)

    def index(self, wavelength_nm: float) -> float:
        """Refractive index at the wavelength (nm), including index_offset."""
        return self._material.index(wavelength_nm) + self.index_offset

    @property
    def material_data(self) -> Material:
        return self._material

    # --- geometry -----------------------------------------------------------
    def thickness_at(self, x: ArrayLike, y: ArrayLike) -> np.ndarray:
        """Axial glass thickness (mm) at lens-frame (x, y) in mm."""
        return self.thickness + self.back.sag(x, y) - self.front.sag(x, y)

    @property
    def edge_thickness(self) -> float:
        """Minimum axial thickness on the rim of the edge diameter (mm)."""
        phi = np.linspace(0, 2 * np.pi, 720, endpoint=False)
        r = 0.5 * self.edge_diameter
        return float(np.min(self.thickness_at(r * np.cos(phi), r * np.sin(phi))))

    @property
    def min_thickness(self) -> float:
        """Minimum axial thickness over the whole edge diameter (mm)."""
        x, y = polar_grid(0.5 * self.edge_diameter)
        return float(np.nanmin(self.thickness_at(x, y)))

    def validate(self) -> "Lens":
        """Raise LensGeometryError unless the lens is a physical solid; returns self."""
        if self.thickness <= 0:
            raise LensGeometryError(f"lens.thickness: centre thickness must be > 0 mm, got {self.thickness}")
        if self.aperture <= 0:
            raise LensGeometryError(f"lens.aperture: clear aperture must be > 0 mm, got {self.aperture}")
        if self.edge_diameter < self.aperture:
            raise LensGeometryError(
                f"lens.edge_diameter: {self.edge_diameter} mm is smaller than the clear aperture {self.aperture} mm"
            )
        x, y = polar_grid(0.5 * self.edge_diameter)
        for side in ("front", "back"):
            if np.any(~np.isfinite(getattr(self, side).sag(x, y))):
                raise LensGeometryError(
                    f"lens.{side}: the conic is undefined inside the {self.edge_diameter} mm diameter "
                    "(|curvature| too large for the aperture); reduce curvature or aperture"
                )
        t = self.thickness_at(x, y)
        if self.edge_thickness <= 0:
            raise LensGeometryError(
                f"lens: edge thickness {self.edge_thickness:.4g} mm <= 0; increase thickness or reduce curvature/aperture"
            )
        if np.min(t) <= 0:
            raise LensGeometryError(
                f"lens: surfaces cross inside the aperture (min thickness {np.min(t):.4g} mm); increase thickness"
            )
        n = self.index(532.0)
        if not (1.0 < n < 4.0):
            raise LensGeometryError(f"lens.index_offset: index {n:.4g} is not physical (must be in (1, 4))")
        return self

    def is_rotationally_symmetric(self) -> bool:
        return self.front.is_rotationally_symmetric() and self.back.is_rotationally_symmetric()

    # --- I/O ----------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "front": self.front.to_dict(),
            "back": self.back.to_dict(),
            "thickness": self.thickness,
            "aperture": self.aperture,
            "edge_diameter": self.edge_diameter,
            "material": self.material if isinstance(self.material, str) else self.material.name,
            "index_offset": self.index_offset,
        }

    @classmethod
    def from_dict(cls, d: dict, where: str = "lens") -> "Lens":
        if not isinstance(d, dict):
            raise ConfigError(f"{where}: expected a table/dict")
        d = dict(d)
        allowed = {"name", "front", "back", "thickness", "aperture", "edge_diameter", "material", "index_offset"}
        unknown = set(d) - allowed
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {sorted(allowed)}")
        for req in ("front", "back", "thickness"):
            if req not in d:
                raise ConfigError(f"{where}.{req}: missing")
        check_ranges(d, LENS_RANGES, where)
        d["front"] = surface_from_dict(d["front"], f"{where}.front")
        d["back"] = surface_from_dict(d["back"], f"{where}.back")
        return cls(**d)

    def replace(self, **changes) -> "Lens":
        return replace(self, **changes)


def lens_conventions(lens: Lens, wavelength_nm: float) -> dict:
    """What another tool needs to read this lens's numbers: units, Zernike order and
    normalisation, the index at the design wavelength (JSON-ready).

    Parameters
    ----------
    lens : Lens
        The lens.
    wavelength_nm : float
        Design wavelength, nm.

    Returns
    -------
    dict
        Keys ``length_unit``, ``sag_coefficient_units``, ``zernike_order``,
        ``zernike_first_index``, ``zernike_normalisation``, ``zernike_sign``,
        ``wavefront_zernike_units``, ``design_wavelength_nm``,
        ``index_at_design_wavelength``, ``material``, ``index_offset``.
    """
    return {
        "length_unit": "mm",
        "sag_coefficient_units": "mm (Zernike and extended-polynomial coefficients multiply "
                                 "dimensionless polynomials of x/R_n, y/R_n; even aspheric "
                                 "alpha_i in mm^(1-2i); polynomial zeta_i, gamma_i in mm^(1-i))",
        "zernike_order": "noll",
        "zernike_first_index": 1,
        "zernike_normalisation": "rms (Noll): Z_j = sqrt(2 (n+1)/(1+delta_m0)) R_n^|m|(rho) cos/sin(|m| phi)",
        "zernike_sign": "even Noll j: cos(m phi); odd: sin(m phi)",
        "wavefront_zernike_units": "um of wavefront (OPD), Noll order, RMS-normalised",
        "design_wavelength_nm": float(wavelength_nm),
        "index_at_design_wavelength": float(lens.index(wavelength_nm)),
        "material": lens.material if isinstance(lens.material, str) else lens.material.name,
        "index_offset": float(lens.index_offset),
    }


# ---------------------------------------------------------------------------
# The paper's lenses (Optics Express 30(9) 14368, 2022, Eqs. 11, 15, 17 and Table 1).
#
# What the paper leaves out, and what lensforge ASSUMES (all marked here):
#  * aperture: 25.4 mm (1 inch) clear aperture for all four lenses, the standard
#    size of the spherical reference lens and of 1" gripper/holder hardware.
#  * material of the freeform lenses: Formlabs Clear resin (they were printed on a
#    Form 2); index from materials/Formlabs-Clear.toml (n = 1.5145 at 532 nm).
#  * extended polynomial: normalisation radius R_n = 1 mm (so the coefficients act in
#    mm, the same units as the paper's unnormalised polynomial model); no base curvature.
#  * Zernike standard sag: the paper gives only Noll terms 1..3 (piston, x tilt, y
#    tilt) per surface, which on their own form a plane wedge; a plane wedge has no
#    optical power, so its wavefront cannot depend on translation at all. lensforge
#    therefore assumes the base sphere of the spherical reference lens (front radius
#    +25.8 mm, back plano) and a normalisation radius R_n = 12.7 mm (the semi-aperture,
#    the usual choice in Zemax). Piston terms only shift the vertex and are kept as given.
#  * polynomial: no base curvature (the x^2, y^2 terms carry the power), as in Eq. 9-10.
# ---------------------------------------------------------------------------

PAPER_LENSES = {
    # Thorlabs LA1131-A: N-BK7 plano-convex, f = 50.0 mm, R = 25.8 mm, tc = 5.3 mm,
    # diameter 25.4 mm (Thorlabs catalogue). Convex side faces the collimated beam.
    "spherical": dict(
        front=Conic(curvature=1 / 25.8),
        back=Conic(),
        thickness=5.3,
        aperture=25.4,
        material="N-BK7",
        name="spherical (Thorlabs LA1131-A, f = 50 mm plano-convex, N-BK7)",
    ),
    "polynomial": dict(
        front=Polynomial(zeta=(0.0, -3.42e-2, 0.0, -4.24e-6), gamma=(0.0, 1.96e-2, 0.0, -7.64e-7)),
        back=Polynomial(zeta=(0.0, -4.16e-2, 0.0, -9.15e-7), gamma=(0.0, 1.24e-2, 0.0, -7.45e-7)),
        thickness=6.07,
        aperture=25.4,
        material="Formlabs-Clear",
        name="polynomial (paper Eq. 11)",
    ),
    "extended_polynomial": dict(
        front=ExtendedPolynomial(coefficients=(2.94e-3, 6.43e-2, 7.73e-4, 3.54e-3, -7.13e-3), norm_radius=1.0),
        back=ExtendedPolynomial(coefficients=(-9.27e-3, 9.81e-2, -1.20e-2, 1.19e-2, -1.20e-2), norm_radius=1.0),
        thickness=5.06,
        aperture=25.4,
        material="Formlabs-Clear",
        name="extended polynomial (paper Eq. 15)",
    ),
    "zernike": dict(
        front=ZernikeSag(curvature=1 / 25.8, coefficients=(1.95e-2, 4.95e-2, -1.24e-5), norm_radius=12.7),
        back=ZernikeSag(coefficients=(-4.99e-2, 1.57e-2, 1.59e-5), norm_radius=12.7),
        thickness=6.94,
        aperture=25.4,
        material="Formlabs-Clear",
        name="Zernike standard sag (paper Eq. 17)",
    ),
}


def paper_lens(name: str) -> Lens:
    """One of the paper's four lenses (Optics Express 30(9) 14368, 2022; assumptions marked in
    ``lensforge.optics.lens``).

    Parameters
    ----------
    name : str
        'spherical', 'polynomial', 'extended_polynomial' or 'zernike' ('-' for '_' accepted).

    Returns
    -------
    Lens
        The validated lens (mm).

    Raises
    ------
    ConfigError
        An unknown name.
    """
    key = str(name).lower().replace("-", "_")
    if key not in PAPER_LENSES:
        raise ConfigError(f"lens name: unknown paper lens {name!r}; use one of {sorted(PAPER_LENSES)}")
    return Lens(**PAPER_LENSES[key]).validate()


@dataclass(frozen=True)
class ResolvedLens:
    """A lens named by the user: lens (validated), label (for tables), bench (the
    design's bench when the source stores one, else None), data (the parsed JSON,
    {} otherwise), source (the object passed in, e.g. a Design)."""

    lens: Lens
    label: str
    bench: Bench | None = None
    data: dict = field(default_factory=dict)
    source: object = None

    def bench_or(self, override: Bench | None = None) -> Bench:
        """``override`` if given, else the design's bench, else the built-in default."""
        return override or self.bench or Bench.default()

    @property
    def plan_box(self) -> tuple[float, float] | None:
        """(mm, rad) half-widths of the calibration plan's box the design was checked over
        (its constraints' plan_mm / plan_rad), or None when the source records none."""
        cons = self.data.get("constraints") if self.data else getattr(self.source, "constraints", None)
        if not isinstance(cons, dict):
            return None
        box = []
        for key in ("plan_mm", "plan_rad"):
            v = cons.get(key, 0.0)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"{self.source}: field constraints.{key}: expected a number >= 0 (the plan "
                                  f"box the design was checked over; 0 = none), got {v!r}")
            box.append(float(v))
        return (box[0], box[1]) if box[0] > 0 and box[1] > 0 else None


class HasLens(Protocol):
    """Anything carrying a lens (e.g. a ``design.Design``); a ``bench`` attribute is used too."""

    @property
    def lens(self) -> Lens: ...


#: what every function taking a design accepts (see :func:`resolve_lens`)
LensSpec: TypeAlias = "str | PathLike[str] | Lens | ResolvedLens | HasLens"


def resolve_lens(spec: LensSpec) -> ResolvedLens:
    """The one lens resolver of every command and study.

    Parameters
    ----------
    spec : LensSpec
        A paper lens name (spherical, polynomial, extended_polynomial, zernike; '-' for '_'
        accepted), 'paper:NAME', a design JSON file (lens under key "lens", bench under
        "bench"), a lens JSON file (``Lens.to_dict()``), a Lens, a ResolvedLens, or an
        object with ``.lens`` (and optionally ``.bench``, e.g. a Design).

    Returns
    -------
    ResolvedLens
        ``lens`` (validated), ``label`` (for tables), ``bench`` (the design's bench when the
        source stores one, else None), ``data`` (the parsed JSON, {} otherwise), ``source``.

    Raises
    ------
    ConfigError
        A spec that names no lens, or a bad file (the message names the fix).
    """
    if isinstance(spec, ResolvedLens):
        return spec
    if isinstance(spec, Lens):
        return ResolvedLens(spec.validate(), spec.name or "lens", source=spec)
    if not isinstance(spec, (str, Path)):
        lens = getattr(spec, "lens", None)
        if not isinstance(lens, Lens):
            raise ConfigError(f"lens: expected a paper lens name, paper:NAME, a design or lens JSON file, a Lens or "
                              f"a Design, got {type(spec).__name__}")
        bench = getattr(spec, "bench", None)
        return ResolvedLens(lens.validate(), lens.name or "lens", bench if isinstance(bench, Bench) else None,
                            source=spec)
    text = str(spec)
    explicit = isinstance(spec, str) and text.lower().startswith("paper:")
    key = (text.split(":", 1)[1] if explicit else text).lower().replace("-", "_")
    if isinstance(spec, str) and key in PAPER_LENSES:
        return ResolvedLens(paper_lens(key), f"paper {key}", source=spec)
    if explicit:
        raise ConfigError(f"lens: unknown paper lens {text!r}; use paper:{{{','.join(sorted(PAPER_LENSES))}}}")
    p = Path(spec)
    if not p.exists():
        raise ConfigError(
            f"lens: {text!r} not found: it is neither a paper lens ({', '.join(sorted(PAPER_LENSES))}) "
            "nor an existing file"
        )
    data = read_json(p, "lens file")
    if not isinstance(data, dict):
        raise ConfigError(f"lens file {p}: expected a JSON object")
    if "lens" in data or "schema_version" in data or "kind" in data:  # a design file: the whole file is
        check_header(data, f"design file {p.name}", kind=DESIGN_KIND, required=True)  # checked, whichever
        if "lens" not in data:                                                         # part a command uses
            raise ConfigError(f"design file {p.name}: no \"lens\" key; write it with `lensforge design` "
                              "or add the lens as \"lens\": {front, back, thickness, ...}")
        lens = Lens.from_dict(data["lens"], where=f"{p.name}:lens").validate()
        bench = Bench.from_dict(data["bench"], f"{p.name}:bench") if "bench" in data else None
        return ResolvedLens(lens, p.stem, bench, data, source=spec)
    if not {"front", "back", "thickness"} & set(data):
        raise ConfigError(f"lens file {p.name}: neither a design file (schema_version, kind, lens) nor a lens "
                          "(front, back, thickness); give a file written by `lensforge design`")
    return ResolvedLens(Lens.from_dict(data, where=f"{p.name}:lens").validate(), p.stem, None, data, source=spec)


def load_lens(source: "str | PathLike[str]") -> tuple[Lens, dict]:
    """The lens and parsed JSON of ``resolve_lens(source)``.

    Parameters
    ----------
    source : str or os.PathLike
        Anything :func:`resolve_lens` accepts.

    Returns
    -------
    lens : Lens
        The validated lens.
    data : dict
        The parsed JSON file, or {} when the source was not a file.
    """
    r = resolve_lens(source)
    return r.lens, r.data


