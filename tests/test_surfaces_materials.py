import numpy as np
import pytest

import lensforge as lf
from lensforge.errors import ConfigError
from lensforge.optics import surfaces as sf
from lensforge.optics.zernike import zernike


def _fd_check(surface, pts, h=1e-6, atol=1e-8):
    x, y = pts
    gx, gy = surface.gradient(x, y)
    np.testing.assert_allclose(gx, (surface.sag(x + h, y) - surface.sag(x - h, y)) / (2 * h), atol=atol)
    np.testing.assert_allclose(gy, (surface.sag(x, y + h) - surface.sag(x, y - h)) / (2 * h), atol=atol)


PTS = (np.array([0.0, 1.0, -2.5, 3.0]), np.array([0.0, 0.5, 1.5, -4.0]))


def test_sphere_and_conic_sag_closed_form():
    R = 25.8
    s = sf.Conic(curvature=1 / R)
    r = np.hypot(*PTS)
    np.testing.assert_allclose(s.sag(*PTS), R - np.sqrt(R * R - r * r), rtol=1e-13)
    par = sf.Conic(curvature=1 / R, conic=-1.0)  # paraboloid z = r^2 / 2R
    np.testing.assert_allclose(par.sag(*PTS), r * r / (2 * R), rtol=1e-13)
    asp = sf.Conic(curvature=0.0, aspheric=(1e-3, -2e-5))
    np.testing.assert_allclose(asp.sag(*PTS), 1e-3 * r**2 - 2e-5 * r**4, rtol=1e-13)
    for surf in (s, par, asp, sf.Conic(curvature=0.02, conic=-0.6, aspheric=(1e-4, 1e-6, -1e-8))):
        _fd_check(surf, PTS)


def test_polynomial_extended_zernike_sag():
    x, y = PTS
    p = sf.Polynomial(zeta=(0.0, -3.42e-2, 0.0, -4.24e-6), gamma=(0.0, 1.96e-2, 0.0, -7.64e-7))
    np.testing.assert_allclose(p.sag(x, y), -3.42e-2 * x**2 - 4.24e-6 * x**4 + 1.96e-2 * y**2 - 7.64e-7 * y**4, rtol=1e-13, atol=1e-15)
    assert sf.extended_monomial_exponents(9) == [(1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1), (1, 2), (0, 3)]
    A = (0.1, 0.2, 0.3, 0.4, 0.5)
    Rn = 5.0
    e = sf.ExtendedPolynomial(coefficients=A, norm_radius=Rn)
    u, v = x / Rn, y / Rn
    np.testing.assert_allclose(e.sag(x, y), A[0] * u + A[1] * v + A[2] * u * u + A[3] * u * v + A[4] * v * v, rtol=1e-13)
    coeffs = (0.01, 0.02, -0.03, 0.04, 0.05, -0.06, 0.07)
    z = sf.ZernikeSag(curvature=0.01, coefficients=coeffs, norm_radius=Rn)
    expected = sf.Conic(curvature=0.01).sag(x, y) + sum(a * zernike(j, u, v) for j, a in enumerate(coeffs, 1))
    np.testing.assert_allclose(z.sag(x, y), expected, rtol=1e-12, atol=1e-14)
    for surf in (p, e, z):
        _fd_check(surf, PTS)


def test_freeform_ripple_and_round_trip():
    base = sf.ZernikeSag(curvature=0.02, coefficients=(0, 0.01, 0.02, 0.03), norm_radius=4.0)
    ff = sf.Freeform.from_canonical(base.canonical())
    np.testing.assert_allclose(ff.sag(*PTS), base.sag(*PTS), rtol=1e-14, atol=1e-16)
    rip = ff.replace(ripple_amplitude=1e-4, ripple_period=0.025)
    s0 = base.sag(*PTS)
    np.testing.assert_allclose(rip.sag(*PTS), s0 + 1e-4 * np.sin(2 * np.pi * s0 / 0.025), rtol=1e-13)
    _fd_check(rip, PTS, h=1e-7, atol=1e-6)
    again = sf.surface_from_dict(rip.to_dict())
    assert again == rip


def test_surface_errors():
    with pytest.raises(ConfigError, match="kind"):
        sf.surface_from_dict({"kind": "spline"})
    with pytest.raises(ConfigError, match="unknown key"):
        sf.surface_from_dict({"kind": "conic", "radius": 3})
    with pytest.raises(ConfigError, match="norm_radius"):
        sf.ZernikeSag(coefficients=(1,), norm_radius=0)
    with pytest.raises(ConfigError, match="finite"):
        sf.Conic(curvature=float("nan"))


def test_material_indices():
    # SCHOTT catalogue: N-BK7 n_d = 1.51680 at 587.56 nm, n_F = 1.52238 at 486.13 nm
    bk7 = lf.load_material("N-BK7")
    assert bk7.index(587.56) == pytest.approx(1.51680, abs=2e-5)
    assert bk7.index(486.13) == pytest.approx(1.52238, abs=2e-5)
    resin = lf.load_material("Formlabs-Clear")
    assert resin.index(670) == pytest.approx(1.505, abs=1e-4)
    assert resin.index(405) == pytest.approx(1.533, abs=1e-4)
    assert 1.505 < resin.index(532) < 1.533 and resin.index_sigma > 0
    with pytest.raises(ConfigError, match="unknown material"):
        lf.load_material("unobtainium")
