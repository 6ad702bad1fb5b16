"""Ray trace against closed-form optics."""

import numpy as np
import pytest

import lensforge as lf
from lensforge.optics.materials import Material
from lensforge.optics.surfaces import Conic, ZernikeSag
from lensforge.optics.trace import OK, TIR, trace_rays

N_GLASS = 1.5


def _lens(front, back, t, n=N_GLASS, aperture=25.4):
    return lf.Lens(front=front, back=back, thickness=t, aperture=aperture, material=Material.constant(n))


@pytest.mark.parametrize("theta_deg", [0.5, 3.0, 7.0, 9.5])
@pytest.mark.parametrize("axis", ["x", "y"])
def test_tilted_plate_lateral_shift(bench, theta_deg, axis):
    t, th = 5.0, np.radians(theta_deg)
    plate = _lens(Conic(), Conic(), t)
    pose = np.zeros(6)
    pose[3 if axis == "x" else 4] = th
    uv = np.array([[0.0, 0.0], [0.7, -0.4], [-1.1, 0.9]])
    res = trace_rays(bench, plate, pose, uv)
    assert np.all(res.status == OK)
    expected = t * np.sin(th) * (1 - np.cos(th) / np.sqrt(N_GLASS**2 - np.sin(th) ** 2))
    shift = res.xy[0] - uv
    # the exit ray is parallel to the beam; the shift lies in the plane of tilt
    np.testing.assert_allclose(res.direction[0], np.tile([0, 0, 1.0], (3, 1)), atol=1e-14)
    moved = np.linalg.norm(shift, axis=1)
    np.testing.assert_allclose(moved, expected, atol=1e-9)
    other = shift[:, 1] if axis == "y" else shift[:, 0]
    np.testing.assert_allclose(other, 0.0, atol=1e-12)


@pytest.mark.parametrize("slope", [0.01, 0.1, 0.4, 0.8])
def test_wedge_deviation_snell(bench, slope):
    # back surface = plane tilted by a Zernike tilt term: sag = A * 2 x / R_n -> slope 2A/R_n
    Rn = 4.0
    back = ZernikeSag(coefficients=(0.0, slope * Rn / 2.0), norm_radius=Rn)
    wedge = _lens(Conic(), back, 6.0)
    res = trace_rays(bench, wedge, np.zeros(6), np.array([[0.0, 0.0], [0.5, 0.3]]))
    assert np.all(res.status == OK)
    alpha = np.arctan(slope)
    expected = np.arcsin(N_GLASS * np.sin(alpha)) - alpha  # deviation towards the thick end
    L, M, N = res.direction[0].T
    np.testing.assert_allclose(np.arctan2(L, N), expected, atol=1e-9)
    np.testing.assert_allclose(M, 0.0, atol=1e-14)


def test_wedge_total_internal_reflection(bench):
    Rn = 1.0
    back = ZernikeSag(coefficients=(0.0, 0.5), norm_radius=Rn)  # slope 1.0 -> 45 deg > critical 41.8 deg
    res = trace_rays(bench, _lens(Conic(), back, 10.0), np.zeros(6), np.array([[0.0, 0.0]]))
    assert res.status[0, 0] == TIR


def _paraxial_efl(bench, lens, h=0.01):
    res = trace_rays(bench, lens, np.zeros(6), np.array([[h, 0.0]]))
    L, _, N = res.direction[0, 0]
    return -h / (L / N)


def test_plano_convex_focal_length(bench):
    R, t = 25.8, 5.3
    lens = _lens(Conic(curvature=1 / R), Conic(), t)
    f_thick = 1.0 / ((N_GLASS - 1) * (1 / R))
    assert _paraxial_efl(bench, lens) == pytest.approx(f_thick, rel=1e-3)
    # flipped (plano side first): same EFL
    flipped = _lens(Conic(), Conic(curvature=-1 / R), t)
    assert _paraxial_efl(bench, flipped) == pytest.approx(f_thick, rel=1e-3)


def test_biconvex_thick_lens_formula(bench):
    R1, R2, t = 30.0, -45.0, 7.0
    lens = _lens(Conic(curvature=1 / R1), Conic(curvature=1 / R2), t)
    c1, c2, n = 1 / R1, 1 / R2, N_GLASS
    power = (n - 1) * (c1 - c2 + (n - 1) * t * c1 * c2 / n)
    assert _paraxial_efl(bench, lens) == pytest.approx(1 / power, rel=1e-3)


def test_catalogue_spherical_lens_focal_length(bench):
    # Thorlabs LA1131-A: f = 50.0 mm at 588 nm; at 532 nm the N-BK7 index is higher -> f slightly shorter
    lens = lf.paper_lens("spherical")
    efl = _paraxial_efl(bench, lens)
    n = lens.index(532.0)
    assert efl == pytest.approx(25.8 / (n - 1), rel=1e-3)
    assert 49.0 < efl < 50.0


def test_batched_poses_equal_loop(bench, rng):
    lens = lf.paper_lens("extended_polynomial")
    poses = np.column_stack([rng.uniform(-0.5, 0.5, (7, 3)), rng.uniform(-0.01, 0.01, (7, 3))])
    uv = rng.uniform(-1.5, 1.5, (50, 2))
    batch = trace_rays(bench, lens, poses, uv)
    for p in range(len(poses)):
        one = trace_rays(bench, lens, poses[p], uv)
        np.testing.assert_array_equal(one.xy[0], batch.xy[p])
        np.testing.assert_array_equal(one.direction[0], batch.direction[p])
