"""Forward model z = h(x, p), sensitivity matrix and metrics."""

import numpy as np
import pytest

import lensforge as lf
from lensforge.errors import (
    ConfigError,
    LensGeometryError,
    PoseRangeError,
    PupilError,
    TraceError,
)
from lensforge.optics.materials import Material
from lensforge.optics.shack_hartmann import ForwardModel, lenslet_pupil
from lensforge.optics.surfaces import Conic, ZernikeSag

FREEFORMS = ["polynomial", "extended_polynomial", "zernike"]


def test_slope_fit_recovers_known_coefficients(bench, rng):
    pupil = lenslet_pupil(bench.sensor)
    z_true = rng.normal(0, 1.0, len(pupil.modes))
    s = pupil.G @ z_true
    slopes = np.stack([s[: pupil.n_lenslets], s[pupil.n_lenslets :]], axis=1)
    np.testing.assert_allclose(pupil.fit(slopes), z_true, atol=1e-10)
    b10 = bench.replace(sensor={"zernike_order": 10, "pupil_radius_mm": 1.5})
    p10 = lenslet_pupil(b10.sensor)
    assert len(p10.modes) == 65
    z_true = rng.normal(0, 1.0, 65)
    s = p10.G @ z_true
    np.testing.assert_allclose(p10.fit(np.stack([s[: p10.n_lenslets], s[p10.n_lenslets :]], 1)), z_true, atol=1e-9)


def test_defocus_of_spherical_lens_matches_geometry(bench):
    # A converging beam of focus distance q gives W = -r^2 / (2 q) (paraxially) -> Noll Z4 = -a^2 / (4 sqrt(3) q)
    lens = lf.paper_lens("spherical")
    z = lf.measure(bench, lens)
    n = lens.index(532.0)
    f = 25.8 / (n - 1)
    # thick lens, convex side first: the back principal plane lies t/n before the plane (back) vertex,
    # so the focus is f - t/n behind the back vertex, which sits at z = -d + t/2 in {S}
    t = lens.thickness
    q = -bench.placement.distance_mm + t / 2 + f - t / n  # distance from sensor to focus
    a_um = bench.sensor.pupil_radius_mm * 1e3
    q_um = q * 1e3
    expected = -(a_um**2) / (4 * np.sqrt(3) * q_um)
    assert z[2] == pytest.approx(expected, rel=0.01)  # modes start at Noll 2: index 2 is Z4
    # only defocus and spherical, plus cos 4phi (Z14): each lenslet averages the slope over its *square*
    # sub-aperture, which gives a rotationally symmetric wavefront square symmetry at O(pitch^2 d3W/dr3)
    # (~3e-5 um here, far below the 1e-3 um noise level); with centre sampling it was ~1e-8 um (grid aliasing)
    np.testing.assert_allclose(np.delete(z, [2, 9, 12]), 0.0, atol=1e-6)
    assert abs(z[12]) < 1e-4


def test_paper_lenses_measurable_and_rank(bench):
    sph = lf.metrics(bench, lf.paper_lens("spherical"))
    assert sph.rank == 5
    col = np.linalg.norm(sph.S, axis=0)
    assert col[5] / col.max() < 1e-8
    assert not np.isfinite(sph.crlb_std[5])
    for name in FREEFORMS:
        m = lf.metrics(bench, lf.paper_lens(name))
        assert m.rank == 6, name
        assert np.all(np.isfinite(m.crlb_std))
        assert m.J == pytest.approx(m.kappa + 1 / m.sigma_min)


def test_sensitivity_matches_independent_fd(bench):
    lens = lf.paper_lens("polynomial")
    model = ForwardModel(bench, lens)
    S = lf.sensitivity(bench, lens)
    for i, h in enumerate([2e-3, 2e-3, 2e-3, 2e-4, 2e-4, 2e-4]):
        e = np.zeros(6)
        e[i] = h
        col = (model.zernike(e) - model.zernike(-e)) / (2 * h)
        np.testing.assert_allclose(S[:, i], col, rtol=1e-4, atol=1e-6 * np.abs(S).max())


def test_crlb_equals_inverse_fisher(bench):
    m = lf.metrics(bench, lf.paper_lens("extended_polynomial"))
    F = m.S.T @ np.linalg.solve(m.R, m.S)
    np.testing.assert_allclose(m.crlb, np.linalg.inv(F), rtol=1e-8)
    np.testing.assert_allclose(m.crlb_std, np.sqrt(np.diag(np.linalg.inv(F))), rtol=1e-8)


def test_measured_noise_matches_covariance(bench):
    lens = lf.paper_lens("zernike")
    model = ForwardModel(bench, lens)
    rng = np.random.default_rng(7)
    z0 = model.zernike(np.zeros(6))
    zs = np.array([model.zernike(np.zeros(6), rng=rng) for _ in range(400)]) - z0
    var = zs.var(axis=0)
    # 400 samples: relative std of a variance estimate ~ sqrt(2/400) = 7 %
    np.testing.assert_allclose(var, np.diag(model.noise_cov), rtol=0.3)


def test_batched_model_equals_loop(bench, rng):
    model = ForwardModel(bench, lf.paper_lens("zernike"))
    poses = np.column_stack([rng.uniform(-0.3, 0.3, (5, 3)), rng.uniform(-0.005, 0.005, (5, 3))])
    zb = model.zernike(poses)
    for p in range(5):
        np.testing.assert_allclose(model.zernike(poses[p]), zb[p], rtol=0, atol=1e-12)


# --- one clear error per bad input -------------------------------------------------

def test_bad_bench_toml(tmp_path):
    p = tmp_path / "b.toml"
    p.write_text("[sensor]\npitch_mm = 0.15\nfoo = 1\n")
    with pytest.raises(ConfigError, match=r"bench.sensor: unknown key"):
        lf.load_bench(p)
    p.write_text('[laser]\nwavelength_nm = "green"\n')
    with pytest.raises(ConfigError, match=r"laser.wavelength_nm: expected a number"):
        lf.load_bench(p)
    p.write_text("[placement]\ndistance_mm = nan\n")
    with pytest.raises(ConfigError, match=r"placement.distance_mm: nan is not a finite number"):
        lf.load_bench(p)
    p.write_text("[placement\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        lf.load_bench(p)
    p.write_text("[sensor]\nzernike_order = 11\n")
    with pytest.raises(ConfigError, match="zernike_order"):
        lf.load_bench(p)


def test_bench_toml_round_trip(tmp_path):
    b = lf.Bench.default().replace(sensor={"zernike_order": 6}, placement={"distance_mm": 25.0})
    lf.save_bench(b, tmp_path / "b.toml")
    assert lf.load_bench(tmp_path / "b.toml") == b


def test_bad_lens_geometry():
    with pytest.raises(LensGeometryError, match="thickness"):
        lf.Lens(front=Conic(), back=Conic(), thickness=-1.0).validate()
    with pytest.raises(LensGeometryError, match="thickness"):
        lf.Lens(front=Conic(), back=Conic(), thickness=0.0).validate()
    # biconvex too thin: edge thickness negative
    with pytest.raises(LensGeometryError, match="edge thickness"):
        lf.Lens(front=Conic(curvature=1 / 20), back=Conic(curvature=-1 / 20), thickness=3.0).validate()
    # surfaces cross inside the aperture but not at the edge (wavy back surface)
    wavy = ZernikeSag(coefficients=(0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1.0), norm_radius=12.7)  # dips at rho^2 = 1/2
    with pytest.raises(LensGeometryError, match="cross"):
        lf.Lens(front=Conic(), back=wavy, thickness=1.0).validate()
    with pytest.raises(LensGeometryError, match="undefined"):
        lf.Lens(front=Conic(curvature=1 / 10), back=Conic(), thickness=5.0, aperture=25.4).validate()


def test_tir_pose_range_and_pupil_errors(bench):
    steep = ZernikeSag(coefficients=(0.0, 0.5), norm_radius=1.0)
    lens = lf.Lens(front=Conic(), back=steep, thickness=14.0, material=Material.constant(1.5))
    with pytest.raises(TraceError, match="total internal reflection"):
        lf.measure(bench, lens)
    zer = lf.paper_lens("zernike")
    with pytest.raises(PoseRangeError, match="translation"):
        lf.measure(bench, zer, [6.0, 0, 0, 0, 0, 0])
    with pytest.raises(PoseRangeError, match="rotation"):
        lf.measure(bench, zer, [0, 0, 0, 0.3, 0, 0])
    off = bench.replace(sensor={"pupil_center_mm": (4.0, 0.0)})
    with pytest.raises(PupilError, match="pupil"):
        lf.measure(off, zer)
    big = bench.replace(sensor={"pupil_radius_mm": 2.5})
    with pytest.raises(PupilError, match="under-filled"):
        lf.measure(big, zer)


@pytest.mark.parametrize("gains", [(0.871, 0.949), (0.9, 0.9), (1.0, 1.0)])
def test_centroid_derivatives_match_a_complex_step(gains):
    """The closed-form forward derivative of the pixel-window centroid (what the exact Jacobians
    use without the cross-talk model) against a complex step through centroid_slopes itself."""
    from lensforge.optics.centroid import centroid_slope_derivatives, centroid_slopes, quadrature_rule

    rng = np.random.default_rng(3)
    off, wt = quadrature_rule(2)
    sq = rng.normal(0, 0.05, (3, 7, 4, 2))
    wi = rng.uniform(0.2, 1.0, (3, 7, 4)) * wt
    dsq, dwi = rng.normal(size=(3, 7, 4, 2, 5)), rng.normal(size=(3, 7, 4, 5)) * wt[:, None]
    d = centroid_slope_derivatives(sq, wi, dsq, dwi, off, wt, gains)
    eps = 1e-30
    ref = np.stack([centroid_slopes(sq + 1j * eps * dsq[..., k], wi + 1j * eps * dwi[..., k], off, wt, gains).imag / eps
                    for k in range(5)], axis=-1)
    assert d.shape == (3, 7, 2, 5)
    np.testing.assert_allclose(d, ref, rtol=1e-12, atol=1e-14 * np.abs(ref).max())
