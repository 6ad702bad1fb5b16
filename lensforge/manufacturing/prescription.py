"""Files other optical tools open: an optiland bench model and an OpticStudio prescription.

* :func:`optiland_model` / :func:`write_optiland`: the bench (collimated beam, lens at
  its nominal place, sensor plane) as an optiland ``Optic`` in optiland's own JSON
  layout, so that ``optiland.fileio.load_optiland_file`` opens it. lensforge does not
  import optiland for this (optiland is a test dependency); the test loads the file
  with optiland and compares sags and traced rays with lensforge's.
* :func:`opticstudio_prescription` / :func:`format_prescription`: the lens as rows of
  OpticStudio surface types and parameter names (Standard, Even Asphere, Zernike
  Standard Sag, Extended Polynomial), for typing a design into OpticStudio.
* :func:`lens_conventions`: the facts another tool needs to read lensforge's numbers
  (Zernike order and normalisation, coefficient units, index at the design wavelength).

Zernike convention: lensforge's Zernike Standard Sag uses Noll order and Noll (RMS)
normalisation, which is OpticStudio's "Zernike Standard" and optiland's
``zernike_type="noll"``. optiland's default (``"standard"``) is a different ordering:
typed into it, the same coefficients give a different surface.

optiland frame: global z = 0 is the beam plane (the stop, ``gap_mm`` before the front
vertex), +z the beam direction; a point of the sensor frame {S} is at
(x_S - beam offset, y_S - beam offset, z_S + z_sensor) with ``z_sensor`` stored in the
file's ``lensforge`` block. Lengths in mm, wavelength in um (optiland's unit).
"""

from __future__ import annotations

from os import PathLike

import json
import math
from pathlib import Path

import numpy as np

from ..errors import LensforgeError
from ..fileio import json_default, write_atomic
from ..optics.bench import Bench
from ..optics.lens import Lens, lens_conventions
from ..optics.surfaces import (Conic, ExtendedPolynomial, Freeform, Surface, ZernikeSag,
                               extended_monomial_exponents)

__all__ = ["optiland_model", "write_optiland", "opticstudio_prescription",
           "format_prescription", "write_prescription", "OPTILAND_NEWTON_TOL_MM"]

OPTILAND_NEWTON_TOL_MM = 1e-12  # optiland's Newton-Raphson intersection tolerance in the written file


# --------------------------------------------------------------------------- canonical helpers

def _asphere_as_monomials(alpha: np.ndarray, deg: int) -> np.ndarray:
    """sum_i alpha_i r^(2i) as a monomial array (deg+1, deg+1) in x, y (exact)."""
    out = np.zeros((deg + 1, deg + 1))
    for i, a in enumerate(alpha, start=1):
        if a == 0.0:
            continue
        for k in range(i + 1):  # (x^2 + y^2)^i = sum_k C(i,k) x^(2k) y^(2(i-k))
            out[2 * k, 2 * (i - k)] += a * math.comb(i, k)
    return out


def _full_monomials(surface: Surface) -> tuple[float, float, np.ndarray]:
    """(curvature, conic, monomials incl. the even asphere) of a surface; raises for layer ripple."""
    cs = surface.canonical()
    if cs.ripple_amplitude:
        raise LensforgeError(f"{surface.kind}: a layer-ripple term has no equivalent in other tools; "
                             "export the nominal design instead of an as-built lens")
    n_alpha = int(np.max(np.nonzero(cs.alpha)[0], initial=-1)) + 1
    deg = max(cs.poly.shape[0] - 1, 2 * n_alpha)
    poly = np.zeros((deg + 1, deg + 1))
    poly[: cs.poly.shape[0], : cs.poly.shape[1]] += cs.poly
    poly += _asphere_as_monomials(cs.alpha[:n_alpha], deg)
    return cs.c, cs.k, poly


def _radius(c: float) -> float:
    return math.inf if c == 0.0 else 1.0 / c


# --------------------------------------------------------------------------- optiland

def _cs(x: float, y: float, z: float) -> dict:
    return {"x": x, "y": y, "z": z, "rx": 0.0, "ry": 0.0, "rz": 0.0, "reference_cs": None}


def _optiland_geometry(surface: Surface | None, cs: dict) -> dict:
    """optiland geometry dict of a lensforge surface (None: a plane)."""
    newton = {"tol": OPTILAND_NEWTON_TOL_MM, "max_iter": 100}
    if surface is None:
        return {"type": "Plane", "cs": cs, "radius": math.inf}
    if isinstance(surface, ZernikeSag) and not any(surface.aspheric):
        return {"type": "ZernikePolynomialGeometry", "cs": cs, "radius": _radius(surface.curvature),
                "conic": surface.conic, **newton, "coefficients": list(surface.coefficients),
                "zernike_type": "noll", "norm_radius": surface.norm_radius}
    if surface.is_rotationally_symmetric() and not isinstance(surface, Freeform):
        if not any(surface.aspheric):
            if surface.curvature == 0.0:
                return {"type": "Plane", "cs": cs, "radius": math.inf}
            return {"type": "StandardGeometry", "cs": cs, "radius": _radius(surface.curvature),
                    "conic": surface.conic}
        return {"type": "EvenAsphere", "cs": cs, "radius": _radius(surface.curvature), "conic": surface.conic,
                **newton, "coefficients": list(surface.aspheric)}
    c, k, poly = _full_monomials(surface)
    return {"type": "PolynomialGeometry", "cs": cs, "radius": _radius(c), "conic": k, **newton,
            "coefficients": poly.tolist()}


def _material(index: float) -> dict:
    return {"type": "IdealMaterial", "propagation_model": {"class": "HomogeneousPropagation"},
            "index": float(index), "absorp": 0.0}


def _surface(geometry: dict, thickness: float, index: float, comment: str, is_stop: bool = False) -> dict:
    return {"type": "Surface", "thickness": thickness, "geometry": geometry, "material_post": _material(index),
            "is_stop": is_stop, "aperture": None, "comment": comment,
            "interaction_model": {"type": "RefractiveReflectiveModel", "is_reflective": False, "coating": None,
                                  "bsdf": None}}


def optiland_model(lens: Lens, bench: Bench, gap_mm: float = 5.0) -> dict:
    """The bench as an optiland ``Optic`` dict: beam plane (stop, EPD = beam diameter), lens
    front and back at the nominal placement, sensor (image) plane.

    Parameters
    ----------
    lens : Lens
        The lens.
    bench : Bench
        The bench (an on-axis collimated beam).
    gap_mm : float
        Distance from the beam plane to the front vertex, mm.

    Returns
    -------
    dict
        optiland's JSON layout (``optiland.fileio.load_optiland_file`` opens it), with a
        ``lensforge`` block of frames and conventions.
    """
    lens.validate()
    if any(bench.laser.slope):
        raise LensforgeError("bench.laser.slope: the optiland export models an on-axis collimated beam; "
                             "set the beam slope to (0, 0) or tilt the lens instead")
    wl_nm = bench.laser.wavelength_nm
    n = lens.index(wl_nm)
    l = lens.thickness
    d = bench.placement.distance_mm
    back_to_sensor = d - 0.5 * l
    if back_to_sensor <= 0:
        raise LensforgeError(f"bench.placement.distance_mm: {d} mm puts the lens back vertex behind the sensor")
    ox, oy = (-float(v) for v in bench.laser.offset_mm)  # lens axis relative to the beam centre
    z_front = gap_mm
    z_back = z_front + l
    z_sensor = z_back + back_to_sensor
    name = lens.name or "lens"
    surfaces = [
        {"type": "ObjectSurface", "geometry": {"type": "Plane", "cs": _cs(0.0, 0.0, -math.inf), "radius": math.inf},
         "material_post": _material(1.0), "comment": "collimated laser (object at infinity)"},
        _surface(_optiland_geometry(None, _cs(0.0, 0.0, 0.0)), gap_mm, 1.0, "beam plane (stop)", is_stop=True),
        _surface(_optiland_geometry(lens.front, _cs(ox, oy, z_front)), l, n, f"{name}: front ({lens.front.kind})"),
        _surface(_optiland_geometry(lens.back, _cs(ox, oy, z_back)), back_to_sensor, 1.0,
                 f"{name}: back ({lens.back.kind})"),
        _surface(_optiland_geometry(None, _cs(0.0, 0.0, z_sensor)), 0.0, 1.0, "Shack-Hartmann lenslet plane"),
    ]
    return {
        "version": 1.0,
        "name": name,
        "aperture": {"type": "EPD", "value": float(bench.laser.beam_diameter_mm)},
        "fields": {"fields": [{"x": 0.0, "y": 0.0, "vx": 0.0, "vy": 0.0, "weight": 1.0}], "telecentric": False,
                   "field_definition": {"field_type": "AngleField"}},
        "wavelengths": {"wavelengths": [{"value": wl_nm / 1000.0, "is_primary": True, "unit": "um", "weight": 1.0}],
                        "polarization": "ignore"},
        "apodization": None,
        "pickups": [],
        "solves": {"solves": []},
        "surface_group": {"surfaces": surfaces},
        "ray_tracer": {"ray_aiming_config": {"mode": "paraxial", "max_iter": 10, "tol": 1e-06}},
        "lensforge": {
            "note": "written by lensforge; optiland ignores this block",
            "frame": "optiland global = sensor frame {S} shifted: x_opt = x_S - beam_offset_x, "
                     "y_opt = y_S - beam_offset_y, z_opt = z_S + z_sensor_mm",
            "z_sensor_mm": z_sensor,
            "beam_offset_mm": [float(v) for v in bench.laser.offset_mm],
            "lens_frame_origin_z_mm": z_front + 0.5 * l,
            "conventions": lens_conventions(lens, wl_nm),
        },
    }


def write_optiland(lens: Lens, bench: Bench, path: str | PathLike[str], gap_mm: float = 5.0) -> Path:
    """Write :func:`optiland_model` as optiland JSON (atomically; planes carry ``Infinity``
    radii as optiland itself writes them).

    Parameters
    ----------
    lens : Lens
        The lens.
    bench : Bench
        The bench.
    path : str or os.PathLike
        Destination file.
    gap_mm : float
        Distance from the beam plane to the front vertex, mm.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    text = json.dumps(optiland_model(lens, bench, gap_mm), indent=2, default=json_default)
    return write_atomic(path, text + "\n")


# --------------------------------------------------------------------------- OpticStudio

def _fmt(v: float) -> str:
    return "Infinity" if not math.isfinite(v) else f"{v:.12g}"


def _os_surface(surface: Surface, semi_diameter: float) -> dict:
    """One lens surface in OpticStudio's names: type, Radius, Conic, parameters, extra data."""
    row: dict = {"radius": _radius(surface.curvature), "conic": surface.conic, "semi_diameter": semi_diameter}
    if isinstance(surface, ZernikeSag):
        row["type"] = "Zernike Standard Sag"
        row["parameters"] = {"Extrapolate": 1, **{f"Par {i} (r^{2 * i})": a
                                                  for i, a in enumerate(surface.aspheric, start=1) if a}}
        row["extra_data"] = {"Number of Terms": len(surface.coefficients), "Norm Radius": surface.norm_radius,
                             **{f"Zernike {j}": a for j, a in enumerate(surface.coefficients, start=1)}}
        return row
    if surface.is_rotationally_symmetric() and not isinstance(surface, Freeform):
        if any(surface.aspheric):
            row["type"] = "Even Asphere"
            row["parameters"] = {f"Par {i} (r^{2 * i})": a for i, a in enumerate(surface.aspheric, start=1)}
        else:
            row["type"] = "Standard"
        return row
    # every other freeform: Extended Polynomial over its own monomials (aspheric terms folded in, exact)
    c, k, poly = _full_monomials(surface)
    rn = surface.norm_radius if isinstance(surface, ExtendedPolynomial) else 1.0
    if poly[0, 0] != 0.0:
        row["note"] = (f"constant term {poly[0, 0]:.12g} mm has no Extended Polynomial coefficient: "
                       "add it to the preceding thickness")
    deg = poly.shape[0] - 1
    n_terms = (deg + 1) * (deg + 2) // 2 - 1
    coeffs = {}
    for i, (p, q) in enumerate(extended_monomial_exponents(n_terms), start=1):
        a = poly[p, q] * rn ** (p + q) if p < poly.shape[0] and q < poly.shape[1] else 0.0
        coeffs[f"Coeff {i} (x^{p} y^{q})"] = float(a)
    last = max([i for i, v in enumerate(coeffs.values(), start=1) if v != 0.0], default=0)
    row.update(type="Extended Polynomial", radius=_radius(c), conic=k)
    row["extra_data"] = {"Maximum Term #": last, "Norm Radius": rn,
                         **{k_: v for i, (k_, v) in enumerate(coeffs.items(), start=1) if i <= last}}
    return row


def opticstudio_prescription(lens: Lens, bench: Bench) -> dict:
    """The bench as OpticStudio Lens Data Editor rows (lens units mm, sequential, +z).

    Surfaces: OBJ (infinity), STO (beam plane, Entrance Pupil Diameter = beam diameter),
    lens front, lens back, IMA (lenslet plane). Zernike surfaces are "Zernike Standard
    Sag" (Noll order, as OpticStudio's Zernike Standard coefficients); other freeforms
    "Extended Polynomial" with terms x, y, x^2, xy, y^2, ...

    Parameters
    ----------
    lens : Lens
        The lens.
    bench : Bench
        The bench.

    Returns
    -------
    dict
        ``lens`` (name), ``system`` (aperture, lens units, wavelength in um, field), ``surfaces``
        (one row per surface: type, radius, thickness, material, semi-diameter, parameters; mm)
        and ``conventions`` (:func:`lensforge.lens_conventions`).
    """
    lens.validate()
    wl_nm = bench.laser.wavelength_nm
    n = lens.index(wl_nm)
    sd = 0.5 * lens.aperture
    front = _os_surface(lens.front, sd)
    back = _os_surface(lens.back, sd)
    front.update(surface="2 (lens front)", thickness=lens.thickness,
                 material=f"model glass nd = {n:.6f} at {wl_nm:g} nm (Abbe: not used, monochromatic)")
    back.update(surface="3 (lens back)", thickness=bench.placement.distance_mm - 0.5 * lens.thickness, material="")
    rows = [
        {"surface": "OBJ", "type": "Standard", "radius": math.inf, "thickness": math.inf, "material": ""},
        {"surface": "1 STO (beam plane)", "type": "Standard", "radius": math.inf, "thickness": 5.0, "material": "",
         "semi_diameter": 0.5 * bench.laser.beam_diameter_mm},
        front, back,
        {"surface": "IMA (Shack-Hartmann lenslet plane)", "type": "Standard", "radius": math.inf, "thickness": 0.0,
         "material": ""},
    ]
    return {
        "lens": lens.name or "lens",
        "system": {"Aperture Type": "Entrance Pupil Diameter", "Aperture Value": bench.laser.beam_diameter_mm,
                   "Lens Units": "Millimeters", "Wavelength (um)": wl_nm / 1000.0, "Field Type": "Angle",
                   "Field 1": 0.0},
        "surfaces": rows,
        "conventions": lens_conventions(lens, wl_nm),
    }


def format_prescription(p: dict) -> str:
    """Plain-text table of :func:`opticstudio_prescription` (one block per surface)."""
    lines = [f"# OpticStudio prescription of {p['lens']} (written by lensforge)",
             "# System: " + ", ".join(f"{k} = {v}" for k, v in p["system"].items()),
             "# Zernike Standard Sag coefficients are OpticStudio 'Zernike Standard' (Noll order, RMS-normalised), "
             "in lens units (mm).",
             f"# Glass index {p['conventions']['index_at_design_wavelength']:.6f} at "
             f"{p['conventions']['design_wavelength_nm']:g} nm (material {p['conventions']['material']}).", ""]
    for s in p["surfaces"]:
        lines.append(f"Surface {s['surface']}: {s['type']}")
        lines.append(f"  Radius = {_fmt(s['radius'])}   Thickness = {_fmt(s['thickness'])}"
                     + (f"   Conic = {_fmt(s['conic'])}" if "conic" in s else "")
                     + (f"   Semi-Diameter = {_fmt(s['semi_diameter'])}" if "semi_diameter" in s else "")
                     + (f"   Material = {s['material']}" if s.get("material") else ""))
        for block in ("parameters", "extra_data"):
            if s.get(block):
                title = "Parameters" if block == "parameters" else "Extra Data"
                lines.append(f"  {title}:")
                lines.extend(f"    {k} = {_fmt(float(v))}" for k, v in s[block].items())
        if s.get("note"):
            lines.append(f"  Note: {s['note']}")
    return "\n".join(lines) + "\n"


def write_prescription(lens: Lens, bench: Bench, path: str | PathLike[str]) -> Path:
    """Write the OpticStudio prescription table (:func:`opticstudio_prescription`) as text
    (atomically).

    Parameters
    ----------
    lens : Lens
        The lens.
    bench : Bench
        The bench.
    path : str or os.PathLike
        Destination file.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    return write_atomic(path, format_prescription(opticstudio_prescription(lens, bench)))
