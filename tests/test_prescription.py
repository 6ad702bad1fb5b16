"""Interoperability: the optiland bench model opens in optiland and agrees with lensforge
(sags and traced rays to <= 1e-9 mm); the OpticStudio prescription rebuilds the surfaces."""

import math

import numpy as np
import pytest

import lensforge as lf
from lensforge.manufacturing.prescription import (format_prescription, opticstudio_prescription, optiland_model,
                                                  write_optiland)
from lensforge.optics.lens import lens_conventions
from lensforge.optics.surfaces import Conic, ExtendedPolynomial, ZernikeSag, extended_monomial_exponents
from lensforge.optics.trace import trace_rays

optiland_fileio = pytest.importorskip("optiland.fileio")

TOL_MM = 1e-9


def _freeform_zernike_lens():
    """A lens with Noll terms up to j = 11 on both sides (catches any ordering/normalisation slip)."""
    rng = np.random.default_rng(3)
    front = ZernikeSag(curvature=1 / 30.0, conic=-0.3, coefficients=tuple(2e-3 * rng.standard_normal(11)),
                       norm_radius=12.7)
    back = ZernikeSag(curvature=-1 / 80.0, coefficients=tuple(2e-3 * rng.standard_normal(11)), norm_radius=12.7)
    return lf.Lens(front=front, back=back, thickness=6.0, aperture=25.4, material="Formlabs-Clear",
                   name="test zernike").validate()


def _asphere_lens():
    return lf.Lens(front=Conic(curvature=1 / 40.0, conic=-1.2, aspheric=(1e-5, -2e-8)),
                   back=ExtendedPolynomial(curvature=-0.01, coefficients=(1e-3, -2e-3, 3e-3, 1e-3, -1e-3, 2e-4),
                                           norm_radius=5.0, aspheric=(2e-6,)),
                   thickness=5.0, aperture=20.0, material="Formlabs-Clear", name="asphere").validate()


LENSES = {
    "zernike": _freeform_zernike_lens,
    "asphere": _asphere_lens,
    "paper_extended_polynomial": lambda: lf.paper_lens("extended_polynomial"),
    "paper_polynomial": lambda: lf.paper_lens("polynomial"),
    "paper_spherical": lambda: lf.paper_lens("spherical"),
}


@pytest.mark.parametrize("which", sorted(LENSES))
def test_optiland_file_opens_and_matches_sag_and_rays(which, tmp_path):
    bench = lf.Bench.default()
    lens = LENSES[which]()
    path = write_optiland(lens, bench, tmp_path / f"{which}.optiland.json")
    optic = optiland_fileio.load_optiland_file(str(path))
    surfaces = optic.surfaces
    rng = np.random.default_rng(0)
    r = 0.5 * lens.aperture * np.sqrt(rng.uniform(0, 0.99, 400))
    phi = rng.uniform(0, 2 * np.pi, 400)
    x, y = r * np.cos(phi), r * np.sin(phi)
    for i, side in ((2, "front"), (3, "back")):
        z_opt = np.asarray(surfaces[i].geometry.sag(x, y), dtype=float)
        np.testing.assert_allclose(z_opt, getattr(lens, side).sag(x, y), rtol=0, atol=TOL_MM)
    # rays over the beam, traced by both to the lenslet plane
    P = rng.uniform(-0.95, 0.95, (2, 300))
    P = P[:, np.hypot(*P) <= 0.95]
    rays = optic.trace_generic(0.0, 0.0, P[0], P[1], bench.laser.wavelength_nm / 1000.0)
    ours = trace_rays(bench, lens, np.zeros(6), P.T * 0.5 * bench.laser.beam_diameter_mm)
    assert np.all(ours.ok)
    meta = optiland_model(lens, bench)["lensforge"]
    np.testing.assert_allclose(np.asarray(rays.z) - meta["z_sensor_mm"], 0.0, atol=TOL_MM)
    np.testing.assert_allclose(np.asarray(rays.x), ours.xy[0, :, 0], rtol=0, atol=TOL_MM)
    np.testing.assert_allclose(np.asarray(rays.y), ours.xy[0, :, 1], rtol=0, atol=TOL_MM)
    # slopes: 1e-9 mm over the 20 mm to the sensor is 5e-11 in slope
    np.testing.assert_allclose(np.asarray(rays.L) / np.asarray(rays.N), ours.slopes[0, :, 0], rtol=0, atol=5e-11)
    np.testing.assert_allclose(np.asarray(rays.M) / np.asarray(rays.N), ours.slopes[0, :, 1], rtol=0, atol=5e-11)


def test_optiland_default_zernike_convention_is_not_lensforges(tmp_path):
    """The same coefficients in optiland's default ("standard") Zernike give another surface:
    the file must say "noll"."""
    from optiland.geometries import ZernikePolynomialGeometry

    lens = _freeform_zernike_lens()
    g = optiland_model(lens, lf.Bench.default())["surface_group"]["surfaces"][2]["geometry"]
    assert g["zernike_type"] == "noll"
    g_std = ZernikePolynomialGeometry.from_dict({**g, "zernike_type": "standard"})
    x, y = np.array([3.0, -5.0, 8.0]), np.array([1.0, 6.0, -2.0])
    assert np.max(np.abs(np.asarray(g_std.sag(x, y)) - lens.front.sag(x, y))) > 1e-4


def test_opticstudio_prescription_rebuilds_the_surfaces():
    bench = lf.Bench.default()
    lens = _asphere_lens()
    p = opticstudio_prescription(lens, bench)
    front, back = p["surfaces"][2], p["surfaces"][3]
    assert front["type"] == "Even Asphere" and back["type"] == "Extended Polynomial"
    assert front["parameters"]["Par 1 (r^2)"] == 1e-5 and math.isclose(front["radius"], 40.0)
    # rebuild the extended polynomial from the table (conic part + sum A_i E_i(x/Rn, y/Rn))
    ed = back["extra_data"]
    rn = ed["Norm Radius"]
    coeffs = [v for k, v in ed.items() if k.startswith("Coeff")]
    assert len(coeffs) == ed["Maximum Term #"]
    x, y = np.array([0.0, 3.0, -7.0, 9.0]), np.array([0.0, -4.0, 2.0, 1.0])
    c = 1 / back["radius"]
    r2 = x * x + y * y
    z = c * r2 / (1 + np.sqrt(1 - (1 + back["conic"]) * c * c * r2))
    for a, (pp, qq) in zip(coeffs, extended_monomial_exponents(len(coeffs))):
        z = z + a * (x / rn) ** pp * (y / rn) ** qq
    np.testing.assert_allclose(z, lens.back.sag(x, y), rtol=0, atol=1e-12)
    # Zernike Standard Sag: coefficients as given, Noll order
    zl = _freeform_zernike_lens()
    zrow = opticstudio_prescription(zl, bench)["surfaces"][2]
    assert zrow["type"] == "Zernike Standard Sag"
    assert zrow["extra_data"]["Number of Terms"] == 11 and zrow["extra_data"]["Norm Radius"] == 12.7
    assert zrow["extra_data"]["Zernike 4"] == zl.front.coefficients[3]
    text = format_prescription(p)
    assert "Extended Polynomial" in text and "Norm Radius" in text and "Entrance Pupil Diameter" in text


def test_conventions_state_order_units_and_index():
    lens = lf.paper_lens("zernike")
    c = lens_conventions(lens, 532.0)
    assert c["zernike_order"] == "noll" and c["length_unit"] == "mm"
    assert c["index_at_design_wavelength"] == pytest.approx(lens.index(532.0), abs=0)
