"""Hand-eye with a known noise model: as accurate as an independent ML solver that knows it."""

import json
import math

import numpy as np
from scipy.optimize import least_squares

from conftest import run_cli_inprocess

from lensforge.calibration.handeye import solve_handeye
from lensforge.calibration.robot import paper_scene, random_lens_poses, simulate_calibration
from lensforge.optics.pose import adjoint, invert_poses, matrix_to_pose, pose_to_matrix

SIGMA_A = np.diag([0.02] * 3 + [5e-5] * 3) ** 2  # robot: (mm, rad)


def _cov_B(rng, n):
    """Anisotropic, correlated per-pose lens covariances (mm, rad)^2."""
    out = []
    for _ in range(n):
        L = np.diag([3e-3, 6e-3, 1e-2, 2e-4, 1e-4, 6e-4]) @ (np.eye(6) + 0.3 * rng.normal(size=(6, 6)))
        out.append(L @ L.T)
    return np.array(out)


def _reference_ml(A, B, C_A, C_B, X0, Z0):
    """Independent ML: minimise sum e_i^T S_i^-1 e_i, e_i = log((Z B_i)^-1 A_i X), S_i = C_B,i +
    Ad_{X^-1} C_A Ad_{X^-1}^T, over (X, Z) = (X0 P(p), Z0 P(q)), numerical Jacobian."""
    def fun(p):
        X = X0 @ pose_to_matrix(p[:6])
        Z = Z0 @ pose_to_matrix(p[6:])
        Ad = adjoint(invert_poses(X))
        S = C_B + Ad @ C_A @ Ad.T
        W = np.linalg.inv(np.linalg.cholesky(S))
        e = matrix_to_pose(invert_poses(Z @ B) @ A @ X)
        return np.einsum("nij,nj->ni", W, e).ravel()

    sol = least_squares(fun, np.zeros(12), method="lm", xtol=1e-14, ftol=1e-14, x_scale="jac")
    return X0 @ pose_to_matrix(sol.x[:6]), Z0 @ pose_to_matrix(sol.x[6:])


def test_ml_with_noise_model_matches_reference_ml():
    rng = np.random.default_rng(7)
    s = paper_scene()
    ours, ref = [], []
    for _ in range(30):
        x = random_lens_poses(rng, 10, 2.0, math.radians(8.0))
        C_B = _cov_B(rng, 10)
        d = simulate_calibration(s.__class__(Z=s.Z, X=s.X, noise=s.noise), x, rng, cov_B=C_B, check_reach=False)
        # robot noise with the known anisotropic covariance
        a = rng.multivariate_normal(np.zeros(6), SIGMA_A, size=10)
        A = d.A_true @ pose_to_matrix(a)
        r = solve_handeye(A, d.B, method="ml", sigma=SIGMA_A, cov_B=C_B)
        Xr, Zr = _reference_ml(A, d.B, SIGMA_A, C_B, r.X, r.Z)
        truth = invert_poses(s.Z)
        ours.append(matrix_to_pose(truth @ r.Z))
        ref.append(matrix_to_pose(truth @ Zr))
    ours, ref = np.array(ours), np.array(ref)
    rot = np.sqrt(np.mean(np.sum(ours[:, 3:] ** 2, 1))) / np.sqrt(np.mean(np.sum(ref[:, 3:] ** 2, 1)))
    tr = np.sqrt(np.mean(np.sum(ours[:, :3] ** 2, 1))) / np.sqrt(np.mean(np.sum(ref[:, :3] ** 2, 1)))
    assert rot < 1.05 and tr < 1.05, (rot, tr)


def test_cli_noise_block_and_metres(tmp_path, monkeypatch, capsys):
    """POSES.json in metres with the per-axis noise block gives the same Z as in mm."""
    rng = np.random.default_rng(3)
    s = paper_scene()
    d = simulate_calibration(s, random_lens_poses(rng, 12, 2.0, math.radians(5)), rng,
                             cov_B=np.diag([1e-3] * 3 + [1e-4] * 3) ** 2, check_reach=False)
    noise = {"robot_sigma_trans_mm": s.noise.translation_mm, "robot_sigma_rot_deg": math.degrees(s.noise.rotation_rad),
             "lens_sigma_trans_mm": 1e-3, "lens_sigma_rot_deg": math.degrees(1e-4)}
    res = {}
    for units, k in (("mm", 1.0), ("m", 1e-3)):
        A, B = d.A.copy(), d.B.copy()
        A[:, :3, 3] *= k
        B[:, :3, 3] *= k
        p = tmp_path / f"{units}.json"
        p.write_text(json.dumps({"units": units, "A": A.tolist(), "B": B.tolist(), "noise": noise}))
        code, out, err = run_cli_inprocess(monkeypatch, capsys, "handeye", p, "--json")
        assert code == 0, err
        res[units] = json.loads(out)
        assert "A B C (deg)" in err and "quaternion" in err
    assert res["mm"]["noise_model"] == "given"
    assert np.allclose(res["mm"]["Z"], res["m"]["Z"], atol=1e-6)
    assert set(res["mm"]["frames"]["Z"]) == {"matrix", "xyzabc", "quaternion_wxyz", "std", "cov"}
