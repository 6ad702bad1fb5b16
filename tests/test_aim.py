"""Ray aiming and the beam-to-sensor map's derivatives, against finite differences of
the plain trace.

The aim (``trace.aim_rays``) takes Newton steps with the exact derivatives the trace
carries along u and v (forward differentiation through both refractions, the sag's
Hessian included) and takes the last step from those derivatives. Both are checked here on a lens that uses every part of the sag:
conic, aspheric terms, polynomial freeform terms and layer ripple.
"""

import dataclasses

import numpy as np
import pytest

import lensforge as lf
from lensforge.optics.materials import Material
from lensforge.optics.surfaces import Freeform
from lensforge.optics.trace import OK, aim_rays, kernel_tangents, lens_kernel, trace_rays


def _every_term_lens():
    poly_f = np.zeros((4, 4))
    poly_f[1, 0], poly_f[0, 2], poly_f[2, 1], poly_f[0, 3] = 0.01, 0.004, -0.0015, 0.0008
    poly_b = np.zeros((4, 4))
    poly_b[0, 1], poly_b[2, 0], poly_b[1, 1], poly_b[3, 0] = -0.008, 0.003, 0.002, -0.0006
    front = Freeform(curvature=1 / 40, conic=-0.6, aspheric=(2e-4, -3e-6), poly=poly_f,
                     ripple_amplitude=2e-4, ripple_period=0.05)
    back = Freeform(curvature=-1 / 60, conic=0.4, aspheric=(-1e-4,), poly=poly_b)
    return lf.Lens(front=front, back=back, thickness=4.0, aperture=12.0, material=Material.constant(1.51))


POSES = np.array([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
                  [0.4, -0.3, 0.5, 0.02, -0.03, 0.1]])


@pytest.fixture(scope="module")
def case():
    bench = lf.Bench.default()
    lens = _every_term_lens()
    g = np.linspace(-1.2, 1.2, 7)
    uv = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    return bench, lens, uv


def test_trace_derivatives_match_finite_differences(case):
    bench, lens, uv = case
    res = trace_rays(bench, lens, POSES, uv)
    assert np.all(res.status == OK)
    values = lambda r: np.concatenate([r.xy, r.slopes], axis=-1)  # (P, N, 4): x, y, L/N, M/N
    for col, e in enumerate(np.eye(2)):
        fd = {}
        for h in (2e-5, 1e-5):  # central differences at two steps: their gap bounds the FD error
            fd[h] = (values(trace_rays(bench, lens, POSES, uv + h * e))
                     - values(trace_rays(bench, lens, POSES, uv - h * e))) / (2 * h)
        est = np.abs(fd[2e-5] - fd[1e-5])  # ~ 3x the error of the h = 1e-5 difference
        scale = np.abs(fd[1e-5]).max(axis=(0, 1))  # per row: mm/mm, rad/mm
        err = np.abs(res.derivatives[..., col] - fd[1e-5])
        # the analytic derivative sits within the FD error (plus rounding of the 1e-5 difference)
        assert np.all(err <= est + 1e-9 * scale), (col, float((err - est).max()))
    # and the rows are not trivially zero: the lens bends and magnifies the beam
    assert np.abs(res.derivatives[..., 2:, :]).max() > 1e-3


def test_aimed_rays_land_on_their_targets_with_the_trace_slopes(case):
    bench, lens, uv = case
    kern = lens_kernel(lens, bench.laser.wavelength_nm)
    targets = trace_rays(bench, lens, POSES[:1], uv).xy[0]  # points a ray reaches at nominal
    cold = aim_rays(bench, lens, POSES, targets, kernel=kern)
    # warm starts from the rays aimed at a pose one difference step away (as the Jacobians do)
    shifted = POSES + np.array([1e-3, 0, 0, 0, 1e-4, 0])
    warm = aim_rays(bench, lens, shifted, targets, u0=cold[0], kernel=kern)
    for poses, (uv_a, slopes, det, status, n) in ((POSES, cold), (shifted, warm)):
        assert np.all(status == OK)
        check = trace_rays(bench, lens, poses[:1], uv_a[0]), trace_rays(bench, lens, poses[1:], uv_a[1])
        for p, tr in enumerate(check):
            np.testing.assert_allclose(tr.xy[0], targets, rtol=0, atol=1e-11)
            np.testing.assert_allclose(slopes[p], tr.slopes[0], rtol=0, atol=1e-13)
            J = tr.derivatives[0, :, :2, :]
            # |det| is the last traced ray's, one Newton step (< 1e-10 mm) from the returned one
            np.testing.assert_allclose(det[p], np.abs(np.linalg.det(J)), rtol=1e-8)
    # exact derivatives converge quadratically: a start one difference step away (landing
    # ~1e-3 mm off) needs three traces per target (1e-3 -> 1e-7 -> 1e-14 mm), a cold one five
    assert warm[4] <= 3 * targets.shape[0] * len(POSES)
    assert cold[4] <= 5 * targets.shape[0] * len(POSES)


def test_pose_derivatives_match_finite_differences(case):
    bench, lens, uv = case
    res = trace_rays(bench, lens, POSES, uv, pose_derivatives=True)
    assert np.all(res.status == OK)
    values = lambda r: np.concatenate([r.xy, r.slopes], axis=-1)
    steps = np.array([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5])  # mm, rad
    scale = np.abs(res.pose_derivatives).max(axis=(0, 1, 3))  # per row (x, y: mm/mm; slopes: rad/mm)
    for j in range(6):
        fd = {}
        for f in (2.0, 1.0):
            e = np.eye(6)[j] * steps[j] * f
            fd[f] = (values(trace_rays(bench, lens, POSES + e, uv))
                     - values(trace_rays(bench, lens, POSES - e, uv))) / (2 * steps[j] * f)
        est = np.abs(fd[2.0] - fd[1.0])
        err = np.abs(res.pose_derivatives[..., j] - fd[1.0])
        assert np.all(err <= est + 1e-8 * scale), (j, float((err - est).max()))
    # tilting the lens steers the rays (a 4 mm thick, weakly powered lens: ~0.04 rad/rad)
    assert np.abs(res.pose_derivatives[..., 2:, 3:]).max() > 0.01


def _perturbed(lens, j, h):
    """The every-term lens moved by h along direction j (thickness, index, front
    curvature, front conic, back aspheric r^4, front poly x^2 y, back poly y, front
    ripple amplitude, front ripple period)."""
    f, b = lens.front, lens.back
    if j == 0:
        return lens.replace(thickness=lens.thickness + h)
    if j == 1:
        return lens.replace(index_offset=lens.index_offset + h)
    if j == 2:
        return lens.replace(front=dataclasses.replace(f, curvature=f.curvature + h))
    if j == 3:
        return lens.replace(front=dataclasses.replace(f, conic=f.conic + h))
    if j == 4:
        return lens.replace(back=dataclasses.replace(b, aspheric=(b.aspheric[0] + h,)))
    if j == 7:
        return lens.replace(front=dataclasses.replace(f, ripple_amplitude=f.ripple_amplitude + h))
    if j == 8:
        return lens.replace(front=dataclasses.replace(f, ripple_period=f.ripple_period + h))
    poly = np.array(f.poly if j == 5 else b.poly)
    poly[(2, 1) if j == 5 else (0, 1)] += h
    side = "front" if j == 5 else "back"
    return lens.replace(**{side: dataclasses.replace(getattr(lens, side), poly=poly)})


def test_lens_derivatives_match_finite_differences(case):
    bench, lens, uv = case
    wl = bench.laser.wavelength_nm
    steps = np.array([1e-4, 1e-5, 1e-6, 1e-4, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6])
    n = len(steps)
    lt = kernel_tangents([lens_kernel(_perturbed(lens, j, steps[j]), wl) for j in range(n)],
                         [lens_kernel(_perturbed(lens, j, -steps[j]), wl) for j in range(n)], 2 * steps)
    res = trace_rays(bench, lens, POSES, uv, lens_tangents=lt)
    assert np.all(res.status == OK) and res.lens_derivatives.shape == (2, len(uv), 4, n)
    values = lambda r: np.concatenate([r.xy, r.slopes], axis=-1)
    scale = np.abs(res.lens_derivatives).max(axis=(0, 1))  # (4, n): per row and direction
    for j in range(n):
        fd = {}
        for f in (2.0, 1.0):
            fd[f] = (values(trace_rays(bench, _perturbed(lens, j, f * steps[j]), POSES, uv))
                     - values(trace_rays(bench, _perturbed(lens, j, -f * steps[j]), POSES, uv))) / (2 * f * steps[j])
        est = np.abs(fd[2.0] - fd[1.0])
        err = np.abs(res.lens_derivatives[..., j] - fd[1.0])
        assert np.all(err <= est + 1e-7 * scale[:, j]), (j, float((err - est).max()))
        assert scale[:, j].max() > 0  # every direction moves the rays
