"""The cross-talk kernel's pieces against independent numerical integrals (issue 21).

``aperture.square_aperture_moments`` against a 400-node Gauss-Legendre rule, and
``centroid.crosstalk_shift`` against a brute-force Fresnel integral of the whole 7 x 7 block of
lenslets lit by a quadratic wavefront (with K_xy), sampled node by node: it shares none of the
kernel's separable algebra (aperture moments, the K_xy series, the neighbours' spot positions).
"""

import numpy as np
import pytest

from lensforge.optics import centroid
from lensforge.optics.aperture import square_aperture_moments
from lensforge.optics.bench import Sensor


def _gl(n):
    t, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * t, 0.5 * w


def test_aperture_moments_and_their_derivatives_are_the_integrals():
    # M_r = int_{-1/2}^{1/2} t^r exp(i alpha t^2 - i beta t) dt, r <= 12 (the K_xy series' reach), on both sides of the series / Fresnel
    # switch and of the beta split, up to curvatures beyond the co-designed bench's (|alpha| <= 6.6)
    t, w = _gl(400)
    beta = np.array([0.0, 0.3, 5.0, 9.99, 10.01, 30.0, -47.0, 170.0, -200.0])
    R = 12
    for alpha in (0.0, 1e-3, -1.0, 1.99, 2.0, -6.6, 12.0, 40.0):
        E = np.exp(1j * alpha * t[None] ** 2 - 1j * beta[:, None] * t[None])
        ref = np.stack([(E * t**r) @ w for r in range(R + 3)], axis=-1)
        tol = 1e-12 + 2e-15 * np.exp(abs(alpha) / 4)  # the alpha series' cancellation, e^(|alpha| / 4)
        re, im = square_aperture_moments(beta, alpha, R)
        np.testing.assert_allclose(re + 1j * im, ref[:, : R + 1], rtol=0, atol=tol)
        # a complex step along beta and alpha: dM_r/dbeta = -i M_(r+1), dM_r/dalpha = i M_(r+2)
        h = 1e-30
        re, im = square_aperture_moments(beta + 1j * h * 0.7, alpha + 1j * h * 0.3, R)
        got = (re.imag + 1j * im.imag) / h
        want = 0.7 * (-1j * ref[:, 1: R + 2]) + 0.3 * (1j * ref[:, 2: R + 3])
        np.testing.assert_allclose(got, want, rtol=0, atol=tol)
    re, im = (v[:, 0] for v in square_aperture_moments(beta, 0.0, 0))  # flat: the sinc
    np.testing.assert_allclose(re, np.sinc(beta / (2 * np.pi)), rtol=0, atol=1e-14)
    assert np.all(im == 0)


def test_aperture_moments_of_repeated_rows_are_each_rows():
    # a complex step repeats a lenslet's real inputs in consecutive rows (one per direction), and the kernel runs
    # once per run of equal rows: each row's moments and derivative are exactly what the row alone gives
    rng = np.random.default_rng(7)
    base = rng.uniform(-40, 40, (3, 5, 2)), rng.uniform(-3, 3, (3, 1, 2)), rng.uniform(-1, 1, (3, 1, 2))
    rows = [0, 0, 0, 1, 2, 2, 0]  # runs of equal rows, and a row equal to one that is not its neighbour
    steps = rng.standard_normal((len(rows), 5, 2))
    beta, alpha, gamma = (v[rows] for v in base)
    re, im = square_aperture_moments(beta + 1e-30j * steps, alpha, 4, gamma, 0.01)
    for i, k in enumerate(rows):
        r1, i1 = square_aperture_moments(base[0][k] + 1e-30j * steps[i], base[1][k], 4, base[2][k], 0.01)
        np.testing.assert_array_equal(re[i], r1)
        np.testing.assert_array_equal(im[i], i1)


def test_aperture_moments_with_an_amplitude_gradient_and_curvature_are_the_integrals():
    # M_r = int t^r exp(gamma t + delta t^2 + i alpha t^2 - i beta t) dt: the amplitude's gradient (up to e^2.6 across
    # a sub-aperture) and curvature (the Gaussian beam's ln I curvature is ~0.01), with their complex-step jets
    t, w = _gl(400)
    beta = np.array([0.0, 0.3, 9.99, 10.01, -47.0, 170.0])
    R = 8
    for alpha in (0.0, -1.0, 2.5, 12.0):
        for gamma, delta in ((0.0, 0.05), (1.3, 0.0), (-1.0, 0.05), (0.5, -0.2)):
            E = np.exp((gamma * t + delta * t**2)[None] + 1j * alpha * t[None] ** 2 - 1j * beta[:, None] * t[None])
            ref = np.stack([(E * t**r) @ w for r in range(R + 3)], axis=-1)
            # the series' high moments come from the upward recursion above |beta| = 10, whose rounding grows by
            # m / |beta| a step: 1e-12 here, 1e-9 at |gamma| = 1, delta = 0.2, 1e-7 at 2 or 3, 0 (measured)
            tol = 1e-9
            re, im = square_aperture_moments(beta, alpha, R, gamma, delta)
            np.testing.assert_allclose(re + 1j * im, ref[:, : R + 1], rtol=0, atol=tol)
            h = 1e-30
            re, im = square_aperture_moments(beta, alpha, R, gamma + 1j * h * 0.6, delta - 1j * h * 0.8)
            got = (re.imag + 1j * im.imag) / h
            np.testing.assert_allclose(got, 0.6 * ref[:, 1: R + 2] - 0.8 * ref[:, 2: R + 3], rtol=0, atol=tol)


def test_aperture_moments_of_interleaved_amplitude_pairs_are_each_pairs_own():
    # the kernel keeps the Taylor coefficients of the last two (gamma, delta) pairs: interleaved pairs (x and y of
    # one sub-aperture, then a third evicting one, zeros between) give bitwise what each element gives alone
    rng = np.random.default_rng(3)
    pairs = np.array([(0.7, 0.02), (-1.1, 0.0), (0.0, 0.05), (0.0, 0.0), (2.0, -0.1)])
    order = np.array([0, 1, 0, 1, 2, 0, 3, 1, 4, 4, 0, 2, 3, 3, 1, 0])
    gamma, delta = pairs[order, 0], pairs[order, 1]
    beta, alpha = rng.uniform(-30, 30, order.size), rng.uniform(-8, 8, order.size)
    re, im = square_aperture_moments(beta, alpha, 3, gamma, delta)
    for i in range(order.size):
        r1, i1 = square_aperture_moments(beta[i:i + 1], alpha[i], 3, gamma[i], delta[i])
        np.testing.assert_array_equal(re[i], r1[0])
        np.testing.assert_array_equal(im[i], i1[0])


def _brute_force_centroid(spot, K, g, sensor, wl_nm, sub, nodes=160):
    """Window centroid of the 7 x 7 block's coherent field, integrated node by node over each sub-aperture:
    U(x) = sum_b exp(-i k |c_b|^2 / 2f) int_b E(X) exp(i k X . (c_b - x) / f) dX, E = exp(g.c_b / 2 + i k W),
    W = s . X + X K X / 2 about the own lenslet's centre (0), s = spot / f (the amplitude is constant over
    each sub-aperture: its own irradiance weighting is the fast model's centroid_slopes, not the kernel's)."""
    f, p, pix, Wpx = sensor.lenslet_focal_mm, sensor.pitch_mm, sensor.pixel_mm, sensor.centroid_window_px
    k = 2 * np.pi / (wl_nm * 1e-6)
    s = spot / f
    edge0 = sensor.camera_offset_px * pix
    st = np.floor((spot - edge0) / pix - 0.5 * Wpx + 0.5)
    xs = edge0 + (st[:, None] + (np.arange(Wpx * sub) + 0.5)[None] / sub) * pix  # (2, S) camera samples
    t, w = _gl(nodes)
    Ks = 0.5 * (K + K.T)
    U = np.zeros((Wpx * sub, Wpx * sub), complex)
    for ex in range(-3, 4):
        for ey in range(-3, 4):
            c = p * np.array([ex, ey], float)
            X, Y = np.meshgrid(c[0] + p * t, c[1] + p * t, indexing="xy")  # (Y nodes, X nodes)
            Wf = s[0] * X + s[1] * Y + 0.5 * (Ks[0, 0] * X * X + 2 * Ks[0, 1] * X * Y + Ks[1, 1] * Y * Y)
            P = np.exp(0.5 * (g @ c) + 1j * k * Wf) * np.outer(w, w) * p * p
            Gx = np.exp(1j * k * np.outer(c[0] - xs[0], c[0] + p * t) / f)  # (S, nodes)
            Gy = np.exp(1j * k * np.outer(c[1] - xs[1], c[1] + p * t) / f)
            U += np.exp(-1j * k * (c @ c) / (2 * f)) * (Gy @ P @ Gx.T)
    inten = (np.abs(U) ** 2).reshape(Wpx, sub, Wpx, sub).sum(axis=(1, 3))
    pc = edge0 + (st[:, None] + np.arange(Wpx)[None] + 0.5) * pix
    tot = inten.sum()
    return np.array([inten.sum(axis=0) @ pc[0], inten.sum(axis=1) @ pc[1]]) / tot


@pytest.mark.parametrize("K_xy", [0.0, 3e-4, 0.012])
def test_kernel_is_the_blocks_fresnel_integral(K_xy):
    # one lenslet of the default sensor under a strongly curved, obliquely astigmatic wavefront (alpha up to 4.4,
    # a = k p^2 K_xy up to 3.2: the co-designed bench's range) with an irradiance gradient, off the pixel grid.
    # K_xy = 0 and 3e-4 (a = 0.08, the block's cross-term series to r = 9) take the separable form, 0.012 the full block
    sensor = Sensor()
    wl = 532.0
    spot = np.array([0.0123, -0.0071])
    K = np.array([[0.028, K_xy], [K_xy, -0.019]])
    g = np.array([0.6, -0.4])
    sub = 2
    got = centroid.crosstalk_shift(spot[None], spot[None], K[None], g[None], sensor, wl, iterations=0, sub=sub)[0]
    want = _brute_force_centroid(spot, K, g, sensor, wl, sub) - spot
    scale = np.abs(want).max()
    assert scale > 2e-5  # the effect is there: > 20 nm
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6 * scale + 1e-12)


def test_kernel_does_not_depend_on_how_lenslets_share_a_pass():
    # the K_xy series is truncated per lenslet, so a lenslet's shift is the same alone and among others
    sensor = Sensor()
    rng = np.random.default_rng(3)
    n = 40
    spot = rng.uniform(-0.02, 0.02, (n, 2))
    K = rng.uniform(-0.03, 0.03, (n, 2, 2))
    K[::7] *= 0.01  # weakly curved lenslets next to strongly curved ones
    g = rng.uniform(-0.5, 0.5, (n, 2))
    together = centroid.crosstalk_shift(spot, spot, K, g, sensor, 532.0)
    alone = np.concatenate([centroid.crosstalk_shift(spot[i:i + 1], spot[i:i + 1], K[i:i + 1], g[i:i + 1], sensor, 532.0)
                            for i in range(n)])
    # equal to rounding (the zero-padded ranks change the matmul's summation order, not its terms)
    np.testing.assert_allclose(together, alone, rtol=0, atol=1e-10 * np.abs(alone).max())


def test_plan_on_a_cross_talk_bench_searches_on_the_own_centroid_model():
    # the candidate search does not run the ~100x dearer cross-talk model (before: > 16 min for a paper-lens plan);
    # the chosen poses are the own-centroid plan's, and their predicted Z sigma is the cross-talk model's: a few
    # percent wider (the window truncation and the neighbours' light cost information), never narrower
    from lensforge.calibration.session import load_design_lens, plan

    _, bench = load_design_lens("polynomial")
    stages_own, stages_xt = [], []
    own = plan("polynomial", bench=bench, n=3, seed=1, tolerances="none", n_candidates=20, progress=stages_own.append)
    xt = plan("polynomial", bench=bench.replace(sensor={"crosstalk": "neighbours"}), n=3, seed=1, tolerances="none",
              n_candidates=20, progress=stages_xt.append)
    # the progress bar names each stage, the cross-talk prediction (the long one) included
    assert stages_own == stages_xt[:-1] and "cross-talk" in stages_xt[-1] and len(stages_own) >= 2
    np.testing.assert_array_equal(xt.x, own.x)
    ratio = xt.z_std / own.z_std
    assert np.all(ratio > 1.0) and np.all(ratio < 1.2), ratio
    assert xt.bench.sensor.crosstalk == "neighbours"


def _xt_model():
    import lensforge as lf
    from lensforge.optics.shack_hartmann import ForwardModel

    return ForwardModel(lf.Bench.default().replace(sensor={"crosstalk": "neighbours"}), lf.paper_lens("polynomial"))


# a calibration pose of the paper polynomial lens (5 deg tilts: the block's cross term a up to 0.17, separable form)
_PLAN_POSE = np.array([[0.5, 0.5, -0.5, -0.087, -0.087, -0.087]])


def test_frozen_windows_make_the_model_smooth_and_leave_its_value():
    # whole-pixel windows make h jump where a spot crosses a half pixel (~3 whitened units, every ~25 sigma of
    # rotation); frozen at a linearisation point (the joint fit's windows) h is smooth and its exact Jacobian
    # predicts a 1e-4 rad step to its O(h^2) (8e-5), across which the free placement jumps (0.17 off)
    m = _xt_model()
    L = m.whitener
    J, _, res = m.jacobians(_PLAN_POSE)
    same = m.evaluate(_PLAN_POSE, check_range=False, windows=res.windows)
    np.testing.assert_allclose(same.z, res.z, rtol=0, atol=1e-12 * np.abs(res.z).max())
    h = 1e-4
    e = np.zeros(6)
    e[4] = h
    steps = np.concatenate([_PLAN_POSE + e, _PLAN_POSE - e])
    frozen = m.evaluate(steps, check_range=False, windows=np.concatenate([res.windows, res.windows])).z
    free = m.evaluate(steps, check_range=False)
    col = L @ J[0, :, 4]
    err_frozen = np.linalg.norm(L @ (frozen[0] - frozen[1]) / (2 * h) - col) / np.linalg.norm(col)
    err_free = np.linalg.norm(L @ (free.z[0] - free.z[1]) / (2 * h) - col) / np.linalg.norm(col)
    assert not np.array_equal(free.windows, np.concatenate([res.windows, res.windows]))  # windows did move
    assert err_frozen < 3e-4 and err_free > 100 * err_frozen, (err_frozen, err_free)


def test_pose_estimate_on_the_cross_talk_model_is_exact_without_noise():
    # the LM iterates on the own centroid's Jacobians and finishes on the exact ones: noise-free data give the pose
    from lensforge.calibration.pose_estimation import estimate_poses_batch

    m = _xt_model()
    z = m.evaluate(_PLAN_POSE, check_range=False).z
    start = _PLAN_POSE + np.array([[0.05, -0.04, 0.1, 2e-3, -1.5e-3, 4e-3]])
    est = estimate_poses_batch(m, z, start)
    assert est.converged[0] and est.status[0] in ("converged", "flat")
    sig = np.sqrt(np.diag(est.cov[0]))
    assert np.all(np.abs(est.poses[0] - _PLAN_POSE[0]) < 1e-4 * sig), (est.poses[0] - _PLAN_POSE[0]) / sig
