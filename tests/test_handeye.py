"""Hand-eye calibration A_i X = Z B_i: exactness, efficiency (CRLB), degeneracy, invariances."""

import math

import numpy as np
import pytest

from lensforge.errors import CalibrationError
from lensforge.optics.pose import matrix_to_pose, pose_to_matrix
from lensforge.calibration.handeye import METHODS, handeye_fisher, solve_handeye
from lensforge.optics.pose import adjoint, invert_poses, pose_vector_cov_to_right
from lensforge.calibration.robot import (
    RobotNoise,
    paper_scene,
    random_lens_poses,
    simulate_calibration,
)

# lens-pose noise of the order of the pose-estimation CRLB (1 um, 10 urad; ASSUMPTION for tests)
COV_B = np.diag([1e-3] * 3 + [1e-5] * 3) ** 2
NOISE = RobotNoise()


def _err(T_true, T_est):
    return matrix_to_pose(invert_poses(T_true) @ T_est)


def _data(rng, n=12, tr=1.0, rot=math.radians(1.0), noise=True, scene=None):
    scene = scene or paper_scene()
    x = random_lens_poses(rng, n, tr, rot)
    d = simulate_calibration(scene, x, rng, cov_B=COV_B if noise else None, check_reach=False)
    if noise:
        return scene, d.A, d.B, d
    return scene, d.A_true, d.B_true, d


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("rng_deg", [1.0, 15.0])
def test_noise_free_exact(method, rng_deg):
    rng = np.random.default_rng(1)
    scene, A, B, _ = _data(rng, 12, 1.0 if rng_deg < 5 else 30.0, math.radians(rng_deg), noise=False)
    r = solve_handeye(A, B, method=method)
    assert np.abs(_err(scene.X, r.X)).max() < 1e-8
    assert np.abs(_err(scene.Z, r.Z)).max() < 1e-8
    assert np.abs(r.Z[:3, 3] - scene.Z[:3, 3]).max() < 1e-8
    assert r.observable and r.method == method


def test_ml_reaches_crlb_monte_carlo():
    """>= 200 noisy calibrations of the paper scene (12 random poses, +-1 mm / +-1 deg):
    RMS error of ml within 10 % of the CRLB, chi2/dof ~ 1, predicted cov ~ observed."""
    rng = np.random.default_rng(7)
    scene = paper_scene()
    x = random_lens_poses(rng, 12)
    B_nom = simulate_calibration(scene, x, rng, check_reach=False).B_true
    F = handeye_fisher(B_nom, scene.X, NOISE, COV_B)
    crlb = np.linalg.inv(F)
    errs, chi, maha_pred = [], [], []
    for _ in range(200):
        d = simulate_calibration(scene, x, rng, cov_B=COV_B, check_reach=False)
        r = solve_handeye(d.A, d.B, "ml", sigma=NOISE, cov_B=COV_B)
        e = np.r_[_err(scene.X, r.X), _err(scene.Z, r.Z)]
        errs.append(e)
        chi.append(r.chi2_dof)
        maha_pred.append(e @ np.linalg.solve(r.cov, e))
    errs = np.array(errs)
    for sl in (slice(6, 9), slice(9, 12), slice(0, 3), slice(3, 6)):
        rms = np.sqrt(np.mean(np.sum(errs[:, sl] ** 2, axis=1)))
        bound = np.sqrt(np.trace(crlb[sl, sl]))
        assert abs(rms / bound - 1) < 0.10, (sl, rms / bound)
    maha = np.mean(np.einsum("ni,ij,nj->n", errs, F, errs))
    assert abs(maha / 12 - 1) < 0.10
    assert abs(np.mean(chi) - 1) < 0.05
    assert abs(np.mean(maha_pred) / 12 - 1) < 0.10


def test_closed_forms_are_worse_or_equal_than_ml():
    rng = np.random.default_rng(3)
    scene, A, B, _ = _data(rng)
    costs = {m: solve_handeye(A, B, m, sigma=NOISE, cov_B=COV_B).chi2 for m in METHODS}
    assert costs["ml"] <= min(costs["shah"], costs["li"]) + 1e-9


def test_permutation_invariance():
    rng = np.random.default_rng(4)
    scene, A, B, _ = _data(rng)
    p = rng.permutation(len(A))
    for m in METHODS:
        r1 = solve_handeye(A, B, m, sigma=NOISE, cov_B=COV_B)
        r2 = solve_handeye(A[p], B[p], m, sigma=NOISE, cov_B=COV_B)
        assert np.abs(_err(r1.X, r2.X) / r1.std_X).max() < 1e-5
        assert np.abs(_err(r1.Z, r2.Z) / r1.std_Z).max() < 1e-5
        # the same 1e-5 of the solution's spread, seen in the residuals (measured <= 2e-11 of a
        # 0.0115 scale under OpenBLAS Prescott and Haswell; a mis-permuted residual is O(scale))
        assert np.abs(r1.residuals[p] - r2.residuals).max() < 1e-5 * np.abs(r1.residuals).max()


def test_inverted_formulation_gives_same_answer():
    """B_i^-1 Z^-1 = X^-1 A_i^-1 is the same problem with A' = B^-1, B' = A^-1, X' = Z^-1,
    Z' = X^-1; right noise on B becomes left noise on B^-1 (covariance Ad_B Sigma Ad_B^T)."""
    rng = np.random.default_rng(5)
    scene, A, B, _ = _data(rng, n=12, tr=5.0, rot=math.radians(5.0))
    r = solve_handeye(A, B, "ml", sigma=NOISE, cov_B=COV_B)
    AdB, AdA = adjoint(B), adjoint(A)
    sig_inv = AdB @ COV_B @ np.swapaxes(AdB, 1, 2)
    covB_inv = AdA @ NOISE.cov @ np.swapaxes(AdA, 1, 2)
    ri = solve_handeye(invert_poses(B), invert_poses(A), "ml", sigma=sig_inv, cov_B=covB_inv)
    assert np.abs(_err(r.X, invert_poses(ri.Z)) / r.std_X).max() < 1e-3
    assert np.abs(_err(r.Z, invert_poses(ri.X)) / r.std_Z).max() < 1e-3
    assert abs(ri.chi2 / r.chi2 - 1) < 1e-3
    # closed forms on exact data
    _, A0, B0, _ = _data(rng, noise=False)
    for m in ("shah", "li"):
        q = solve_handeye(invert_poses(B0), invert_poses(A0), m)
        # exact data: round-off only. The closed forms take the rotation from an SVD null
        # space, whose error grows with eps / (singular-value gap); the translation error is
        # that rotation error times the lever arm (~1e3 mm). Measured: li ~40 eps, shah up to
        # ~8e4 eps relative (2.2e-8 mm; 1.9e-8 mm on another CPU). 4e6 eps (~1e-9 relative,
        # 1 nm here) keeps a 50x margin over any BLAS kernel and is 1e6 x below a real bug.
        scale = max(np.abs(scene.Z[:3, 3]).max(), np.abs(scene.X[:3, 3]).max(), 1.0)
        tol = 4e6 * np.finfo(float).eps * scale
        assert np.abs(_err(invert_poses(scene.Z), q.X)).max() < tol
        assert np.abs(_err(invert_poses(scene.X), q.Z)).max() < tol


def test_agrees_with_opencv_noise_free():
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(6)
    scene, A, B, _ = _data(rng, 12, 30.0, math.radians(15), noise=False)
    Ai, Bi = invert_poses(A), invert_poses(B)  # world2cam = A^-1, base2gripper = B^-1
    ours = solve_handeye(A, B, "ml")
    for m in (cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH, cv2.CALIB_ROBOT_WORLD_HAND_EYE_LI):
        R_b2w, t_b2w, R_g2c, t_g2c = cv2.calibrateRobotWorldHandEye(
            list(Ai[:, :3, :3]), list(Ai[:, :3, 3]), list(Bi[:, :3, :3]), list(Bi[:, :3, 3]), method=m)
        assert np.abs(R_b2w - ours.Z[:3, :3]).max() < 1e-8  # Z = base2world
        assert np.abs(t_b2w.ravel() - ours.Z[:3, 3]).max() < 1e-8
        assert np.abs(R_g2c - ours.X[:3, :3]).max() < 1e-8  # X = gripper2cam
        assert np.abs(t_g2c.ravel() - ours.X[:3, 3]).max() < 1e-8


def _degenerate(rng, kind):
    n = 12
    if kind == "pure translation":
        x = np.c_[rng.uniform(-1, 1, (n, 3)), np.zeros((n, 3))]
    else:  # rotations about the optical axis only
        x = np.c_[rng.uniform(-1, 1, (n, 3)), np.zeros((n, 2)), rng.uniform(-0.02, 0.02, n)]
    d = simulate_calibration(paper_scene(), x, rng, cov_B=COV_B, check_reach=False)
    return d.A, d.B


@pytest.mark.parametrize("kind,expect", [("pure translation", "translation of Z along {S} x"),
                                         ("single axis", "translation of Z along {S}")])
def test_degenerate_motion_detected(kind, expect):
    rng = np.random.default_rng(8)
    A, B = _degenerate(rng, kind)
    for m in METHODS:
        with pytest.raises(CalibrationError, match="degenerate motion"):
            solve_handeye(A, B, m, sigma=NOISE, cov_B=COV_B)
        with pytest.raises(CalibrationError, match="degenerate motion"):
            solve_handeye(A, B, m)  # noise model estimated from the data
    with pytest.warns(RuntimeWarning, match="degenerate"):
        r = solve_handeye(A, B, "ml", sigma=NOISE, cov_B=COV_B, on_degenerate="warn")
    assert not r.observable and r.warnings
    assert any(expect in s and "coupled with" in s for s in r.null_directions)
    if kind == "single axis":
        assert any("optical axis" in s for s in r.null_directions)


def test_malformed_input():
    rng = np.random.default_rng(9)
    _, A, B, _ = _data(rng, noise=False)
    with pytest.raises(CalibrationError, match="at least 3"):
        solve_handeye(A[:2], B[:2])
    with pytest.raises(CalibrationError, match="same number"):
        solve_handeye(A, B[:-1])
    bad = A.copy()
    bad[2, :3, :3] *= 1.01
    with pytest.raises(CalibrationError, match=r"A\[2\].*orthonormal"):
        solve_handeye(bad, B)
    with pytest.raises(CalibrationError, match="shape"):
        solve_handeye(A[:, :3, :], B)
    with pytest.raises(CalibrationError, match="method"):
        solve_handeye(A, B, method="tsai")
    with pytest.raises(CalibrationError, match="positive definite"):
        solve_handeye(A, B, sigma=(0.01, 0.0))


def test_pose_vector_cov_conversion():
    x = np.array([0.3, -0.2, 0.1, 0.2, -0.1, 0.3])
    C = np.diag([1.0, 2.0, 3.0, 0.1, 0.2, 0.3]) * 1e-6
    C_r = pose_vector_cov_to_right(x, C)
    # first-order map x + dx -> xi by central differences
    T0inv = invert_poses(pose_to_matrix(x))
    h = 1e-6
    M = np.stack([(matrix_to_pose(T0inv @ pose_to_matrix(x + h * e))
                   - matrix_to_pose(T0inv @ pose_to_matrix(x - h * e))) / (2 * h) for e in np.eye(6)], axis=1)
    assert np.allclose(M @ C @ M.T, C_r, rtol=1e-6, atol=1e-15)
