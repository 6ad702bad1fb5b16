"""Joint as-built calibration (calibration.joint, asbuilt.lens_params).

Setup shared by the tests: the paper's polynomial lens (all six pose DOF observable
per pose, so the joint problem is well conditioned) on the default bench, the
paper scene, a 12-pose plan, a small tolerance model (form modes 4..8 only, so
that theta is small and the tests fast).
"""

import numpy as np
import pytest
from conftest import assert_exact_transforms, pose_error

from lensforge.calibration.joint import joint_calibrate, pose_chain, simulate_joint_data
from lensforge.asbuilt.lens_params import lens_space, parameterise
from lensforge.asbuilt.tolerances import Tolerances
from lensforge.optics.pose import pose_to_matrix
from lensforge.calibration.robot import flange_pose
from lensforge.verification.study import StudyConfig, calibration_plan

TOL = Tolerances(form_modes=(4, 5, 6, 7, 8))


@pytest.fixture(scope="module")
def setup(polynomial_joint_setup):
    return polynomial_joint_setup


@pytest.fixture(scope="module")
def param(setup):
    bench, lens, _, plan = setup
    return parameterise(bench, lens, TOL, plan, max_directions=3)


_err = pose_error


def test_space_reproduces_nominal_and_mean(setup):
    """p = 0 is the nominal lens (same Zernikes); the builder is additive in form."""
    bench, lens, _, plan = setup
    from lensforge.optics.shack_hartmann import ForwardModel

    sp = lens_space(lens, TOL)
    z0 = ForwardModel(bench, lens).evaluate(plan[:3]).z
    z1 = ForwardModel(bench, sp.build(np.zeros(sp.size)), validate=False).evaluate(plan[:3]).z
    assert np.max(np.abs(z1 - z0)) < 1e-9 * np.max(np.abs(z0))
    assert sp.sigma[sp.index("thickness_mm")] == TOL.thickness_sigma_mm


def test_exact_theta_jacobian_matches_differences_of_the_model(setup, param):
    """dh/dtheta (lens tangents through the trace) against central differences of the
    model over theta at two steps (their gap bounds the difference error), at an
    as-built theta; the same for the elementary deviations the parameterisation uses."""
    from lensforge.calibration.joint import JointProblem
    from lensforge.asbuilt.lens_params import elementary_jacobian
    from lensforge.optics.shack_hartmann import ForwardModel

    bench, lens, scene, plan = setup
    theta = np.array([0.8, -1.1, 0.5])[:param.k]
    pb = JointProblem(bench, param, np.zeros((len(plan), 1)), np.zeros((len(plan), 4, 4)), scene.T_SO_nominal,
                      scene.noise.cov, True)
    base = pb.model(theta).evaluate(plan, check_range=False)
    _, Jt = pb.jacobians(theta, plan, base.uv)
    Li = pb.Li

    def diff(h):
        cols = []
        for j in range(param.k):
            e = np.eye(param.k)[j] * h
            z = [ForwardModel(bench, param.build(theta + sg * e), validate=False).evaluate(
                plan, uv0=base.uv, check_range=False).z for sg in (1.0, -1.0)]
            cols.append((z[0] - z[1]) @ Li.T / (2 * h))
        return np.stack(cols, axis=-1)

    fd1, fd2 = diff(0.01), diff(0.02)
    col = np.linalg.norm(Jt, axis=1)  # (n, k) whitened: noise sigmas per prior sigma
    assert np.all(col.max(axis=0) > 0.1)  # each direction is seen (the parameterisation kept it)
    err = np.linalg.norm(Jt - fd1, axis=1)
    est = np.linalg.norm(fd2 - fd1, axis=1)
    assert np.all(err <= est + 1e-6 * col.max()), (err / col.max(), est / col.max())
    # elementary deviations: the parameterisation's whole Jacobian, against differences
    space = param.space
    Je = elementary_jacobian(bench, space, plan[:3])
    Lm = ForwardModel(bench, space.build(space.mean), validate=False)
    for j in np.flatnonzero(space.sigma > 0)[::3]:
        e = np.zeros(space.size)
        e[j] = 0.01 * space.sigma[j]
        z = [Lm.__class__(bench, space.build(space.mean + sg * e), validate=False).evaluate(plan[:3]).z
             for sg in (1.0, -1.0)]
        fd = (z[0] - z[1]) @ Li.T / 0.02
        assert np.allclose(Je[..., j], fd, rtol=0, atol=1e-4 * np.abs(Je).max() + 1e-3 * np.abs(fd).max()), space.names[j]


def test_noise_free_exactness(setup, param):
    """theta, X and Z recovered to 1e-8 relative from noise-free data of the lens of theta."""
    bench, lens, scene, plan = setup
    rng = np.random.default_rng(1)
    theta = rng.standard_normal(param.k)
    X = scene.X @ pose_to_matrix([0.1, -0.2, 0.15, 0.003, -0.002, 0.004])
    A = flange_pose(scene, plan, check_reach=False)
    z = simulate_joint_data(bench, param, theta, A, X, scene.Z, scene.T_SO_nominal)
    X0 = X @ pose_to_matrix([0.05, 0.05, -0.05, 1e-3, 1e-3, -1e-3])
    Z0 = scene.Z @ pose_to_matrix([-0.05, 0.05, 0.05, -1e-3, 1e-3, 1e-3])
    res = joint_calibrate(bench, param, z, A, scene.T_SO_nominal, X0, Z0, scene.noise.cov, theta_prior=False)
    assert res.converged and res.used.all()
    assert np.max(np.abs(res.theta - theta)) <= 1e-8 * np.max(np.abs(theta))
    assert_exact_transforms(((X, res.X), (scene.Z, res.Z)))
    assert res.chi2 < 1e-10 * res.dof


def _mc_trial(bench, param, scene, A_cmd, rng):
    """One Monte Carlo draw: theta ~ prior, robot errors ~ RobotNoise, slope noise."""
    theta = rng.standard_normal(param.k)
    A_true = A_cmd @ pose_to_matrix(scene.noise.sample(rng, len(A_cmd)))
    z = simulate_joint_data(bench, param, theta, A_true, scene.X, scene.Z, scene.T_SO_nominal, rng=rng)
    X0 = scene.X @ pose_to_matrix(rng.standard_normal(6) * ([0.05] * 3 + [1e-3] * 3))
    Z0 = scene.Z @ pose_to_matrix(rng.standard_normal(6) * ([0.05] * 3 + [1e-3] * 3))
    res = joint_calibrate(bench, param, z, A_cmd, scene.T_SO_nominal, X0, Z0, scene.noise.cov)
    e = np.r_[_err(scene.X, res.X), _err(scene.Z, res.Z), res.theta - theta]
    return e, res


def _mc(setup, param, n, seed):
    bench, _, scene, plan = setup
    A_cmd = flange_pose(scene, plan, check_reach=False)
    rng = np.random.default_rng(seed)
    errs, covs, chi = [], [], []
    for _ in range(n):
        e, res = _mc_trial(bench, param, scene, A_cmd, rng)
        errs.append(e)
        covs.append(res.cov)
        chi.append(res.chi2 / res.dof)
    return np.array(errs), np.array(covs), np.array(chi)


def _check_crlb(errs, covs, rel):
    """Mean NEES of (X, Z, theta) per dimension and the Z block's trace ratio within rel."""
    n, d = errs.shape
    C = covs.mean(axis=0)
    nees = np.einsum("ni,nij,nj->n", errs, np.linalg.inv(covs), errs) / d
    assert abs(nees.mean() - 1) < rel, nees.mean()
    emp = errs[:, 6:12].T @ errs[:, 6:12] / n
    for blk in (slice(0, 3), slice(3, 6)):
        ratio = np.trace(emp[blk, blk]) / np.trace(C[6:12, 6:12][blk, blk])
        assert abs(ratio - 1) < 2.5 * rel, ratio


def test_monte_carlo_at_joint_crlb_small(setup, param):
    """A small Monte Carlo (CI): NEES and Z scatter agree with the joint CRLB within
    3 sigma of a 30-draw estimate (NEES mean: sd sqrt(2 / (30 d)))."""
    errs, covs, chi = _mc(setup, param, 30, 7)
    d = errs.shape[1]
    _check_crlb(errs, covs, 3 * np.sqrt(2 / (30 * d)) + 0.02)
    assert abs(chi.mean() - 1) < 0.1


@pytest.mark.slow
def test_monte_carlo_at_joint_crlb(setup, param):
    """The issue's Monte Carlo: empirical error covariance at the joint CRLB within 10 %."""
    errs, covs, _ = _mc(setup, param, 200, 11)
    _check_crlb(errs, covs, 0.10)


def test_mismatch_flagged(setup, param):
    """A lens with a form error outside theta's span (spherical aberration Z11, not in
    the tolerance model's modes) is flagged by the chi^2 test; in-span data are not."""
    bench, lens, scene, plan = setup
    from lensforge.asbuilt.lens_params import LensSpace

    rng = np.random.default_rng(5)
    A = flange_pose(scene, plan, check_reach=False)
    theta = rng.standard_normal(param.k)
    sp = param.space
    wide = LensSpace(lens=sp.lens, names=sp.names + ("front_Z11_mm",), mean=np.r_[sp.mean, 0.0],
                     sigma=np.r_[sp.sigma, 1e-3], form_modes=sp.form_modes + (11,), rolloff_power=sp.rolloff_power)
    p = np.r_[param.elementary(theta), 2e-3]  # 2 um of spherical on the front surface

    class Outside:
        k = param.k

        @staticmethod
        def build(_theta):
            return wide.build(p)

    z_bad = simulate_joint_data(bench, Outside, theta, A, scene.X, scene.Z, scene.T_SO_nominal, rng=rng)
    z_ok = simulate_joint_data(bench, param, theta, A, scene.X, scene.Z, scene.T_SO_nominal, rng=rng)
    kw = dict(T_SO_nominal=scene.T_SO_nominal, X0=scene.X, Z0=scene.Z, robot_cov=scene.noise.cov)
    bad = joint_calibrate(bench, param, z_bad, A, **kw)
    ok = joint_calibrate(bench, param, z_ok, A, **kw)
    assert bad.mismatch and bad.p_value < 1e-6
    assert not ok.mismatch


def test_pose_chain_matches_scene(setup):
    """B = Z^-1 A X of the commanded flange poses is the planned lens pose."""
    _, _, scene, plan = setup
    A = flange_pose(scene, plan, check_reach=False)
    _, x = pose_chain(A, scene.X, scene.Z, np.zeros((len(A), 6)), scene.T_SO_nominal)
    assert np.max(np.abs(x - plan)) < 1e-9


def test_study_stores_both_calibrations(tmp_path):
    """verify(calibration="joint") shows the joint errors in ``summary`` and keeps the
    two-stage ones; the CLI rejects an unknown calibration in one line."""
    import subprocess
    import sys

    from lensforge.verification.study import verify

    cfg = StudyConfig(n_poses=8, calibration="joint")
    res = verify("zernike", Tolerances.zero(), 2, 0, config=cfg, workers=0, progress=False)
    d = res.to_dict()
    assert d["summary"]["calibration"] == "joint" and d["joint_summary"] is d["summary"]
    assert d["two_stage_summary"]["n_lenses"] == 2
    rec = res.records[0]
    assert rec["ok"] and rec["joint"]["ok"]
    assert res.trans_err_mm[0] == rec["joint"]["trans_err_mm"]
    assert d["summary"]["joint"]["nees_dof"] > 0
    exe = [sys.executable, "-c", "from lensforge.cli import main; main()"]
    r = subprocess.run(exe + ["study", "zernike", "--lenses", "1", "--calibration", "both", "-o", str(tmp_path)],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "calibration" in r.stderr


def test_joint_design_beats_random_and_matches_estimator(setup, param):
    """The Ds-optimal joint design predicts a smaller Z uncertainty than the random plan
    of the same size, and the prediction equals the estimator's own covariance at
    noise-free data on the nominal lens (same information)."""
    from lensforge.calibration.joint_design import box_candidates, design_joint_poses, predicted_joint_uncertainty

    bench, lens, scene, plan = setup
    A = flange_pose(scene, plan, check_reach=False)
    z = simulate_joint_data(bench, param, np.zeros(param.k), A, scene.X, scene.Z, scene.T_SO_nominal)
    res = joint_calibrate(bench, param, z, A, scene.T_SO_nominal, scene.X, scene.Z, scene.noise.cov)
    pred = predicted_joint_uncertainty(bench, param, scene, plan)
    assert pred["n_lit"] == len(plan)
    np.testing.assert_allclose(np.sqrt(np.diag(pred["cov"])), np.sqrt(np.diag(res.cov)), rtol=1e-3)
    span = np.r_[0.2, 0.2, 2.0, np.radians([6.0] * 3)]
    cand = box_candidates(np.random.default_rng(0), span, 60)
    d = design_joint_poses(bench, param, scene, len(plan), cand, compare=plan, check_reach=False, max_passes=2)
    assert d.chosen["Z_rotation_deg"] < d.random["Z_rotation_deg"]
    assert d.chosen["Z_translation_mm"] < d.random["Z_translation_mm"]


def _noisy_data(setup, param, seed):
    """(commanded flange poses, noisy Zernikes of a lens drawn from theta's prior with robot
    pose noise, X0, Z0 started 0.3-0.4 mm / 0.5 deg off) on the test plan."""
    bench, _, scene, plan = setup
    A_cmd = flange_pose(scene, plan, check_reach=False)
    rng = np.random.default_rng(seed)
    theta = rng.standard_normal(param.k)
    A_true = A_cmd @ pose_to_matrix(scene.noise.sample(rng, len(A_cmd)))
    z = simulate_joint_data(bench, param, theta, A_true, scene.X, scene.Z, scene.T_SO_nominal, rng=rng)
    X0 = scene.X @ pose_to_matrix([0.3, -0.2, 0.25, 5e-3, -4e-3, 6e-3])
    Z0 = scene.Z @ pose_to_matrix([-0.25, 0.3, 0.2, -6e-3, 5e-3, 4e-3])
    return A_cmd, z, X0, Z0


def test_reused_jacobians_reach_the_same_minimum(setup, param):
    """The solver reuses its Jacobians across iterations; relinearising at every step
    instead gives the same estimate (within 0.05 of its 1-sigma: both stop when the
    remaining step is below 0.01 sigma) and the same covariance (rel 1e-3: both take
    fresh Jacobians at the estimate). Which is cheaper depends on theta's size
    (benchmarks/bench_joint.py)."""
    bench, _, scene, _ = setup
    A_cmd, z, X0, Z0 = _noisy_data(setup, param, 21)
    kw = dict(T_SO_nominal=scene.T_SO_nominal, X0=X0, Z0=Z0, robot_cov=scene.noise.cov)
    fast = joint_calibrate(bench, param, z, A_cmd, **kw)
    full = joint_calibrate(bench, param, z, A_cmd, refresh_ratio=0.0, **kw)
    assert fast.converged and full.converged
    sd = np.sqrt(np.diag(full.cov))
    d = np.r_[_err(full.X, fast.X), _err(full.Z, fast.Z), fast.theta - full.theta]
    assert np.max(np.abs(d) / sd) < 0.05
    np.testing.assert_allclose(np.sqrt(np.diag(fast.cov)), sd, rtol=1e-3)
    assert abs(fast.chi2 - full.chi2) < 0.01 * np.sqrt(2 * full.dof)


def test_a_pose_darkened_on_the_way_leaves_the_problem(setup, param, monkeypatch):
    """A pose lit at the start that a descending step would darken (at the pupil's edge)
    is dropped, and the fit ends where a fit without it from the start ends (within the
    0.01-sigma stopping tolerance), instead of stalling at the start."""
    from lensforge.calibration import joint as joint_mod

    bench, _, scene, plan = setup
    A_cmd, z, X0, Z0 = _noisy_data(setup, param, 5)
    kw = dict(T_SO_nominal=scene.T_SO_nominal, robot_cov=scene.noise.cov)
    without = joint_calibrate(bench, param, z[1:], A_cmd[1:], X0=X0, Z0=Z0, **kw)

    residuals = joint_mod.JointProblem.residuals

    def edge(self, X, Z, theta, a, uv0=None):  # pose 0 goes dark once the state leaves the start
        r, lit, B, x, uv, zm = residuals(self, X, Z, theta, a, uv0)
        if uv0 is not None and self.n == len(plan):
            lit = lit.copy()
            lit[0] = False
        return r, lit, B, x, uv, zm

    monkeypatch.setattr(joint_mod.JointProblem, "residuals", edge)
    res = joint_calibrate(bench, param, z, A_cmd, X0=X0, Z0=Z0, **kw)
    assert res.converged and not res.used[0] and res.used[1:].all()
    assert res.robot_errors.shape == (len(plan) - 1, 6) and res.dof == without.dof
    sd = np.sqrt(np.diag(without.cov))
    d = np.r_[_err(without.X, res.X), _err(without.Z, res.Z), res.theta - without.theta]
    assert np.max(np.abs(d) / sd) < 0.05
    assert not res.mismatch


def test_study_takes_a_pose_plan(tmp_path):
    """verify(plan=...) runs the given poses (they are the hashed plan, n_poses follows);
    `study --pose-plan` rejects a malformed plan file in one line, exit 2."""
    import json
    import subprocess
    import sys

    from lensforge.verification.study import load_plan, verify

    plan = calibration_plan(StudyConfig(n_poses=7))[:6]
    f = tmp_path / "plan.json"
    f.write_text(json.dumps({"poses": plan.tolist()}))
    np.testing.assert_array_equal(load_plan(f), plan)
    res = verify("zernike", Tolerances.zero(), 1, 0, workers=0, progress=False, plan=load_plan(f))
    assert res.config["config"]["n_poses"] == 6 and np.array_equal(res.config["plan"], plan.tolist())
    rec = res.records[0]  # every planned pose is accounted for
    assert rec["n_used"] + rec["n_pupil_lost"] + rec["n_not_converged"] == 6
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"poses": [[0, 0, 0, 0, 0]] * 4}))
    exe = [sys.executable, "-c", "from lensforge.cli import main; main()"]
    r = subprocess.run(exe + ["study", "zernike", "-n", "1", "--pose-plan", str(bad), "-o", str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "bad.json" in r.stderr, r.stderr


def test_pose_plan_in_wrong_units_is_refused():
    """A plan pose outside the bench's pose range (e.g. um or m written for mm) is a unit
    mistake: refused before any trial runs, with the unit named."""
    from lensforge.errors import ConfigError
    from lensforge.verification.study import verify

    plan = calibration_plan(StudyConfig(n_poses=6))
    plan[2, 2] = 500.0  # mm: far outside the bench's +-5 mm
    with pytest.raises(ConfigError, match=r"pose plan: .*exceeds bench.pose_limits.*mm and rad"):
        verify("zernike", Tolerances.zero(), 1, 0, workers=0, progress=False, plan=plan)


def test_window_passes_stand_at_the_least_objective():
    """The joint fit's window passes on a cross-talk model (``joint.WindowPasses``): it goes on while the tracking
    rule places windows not had before, stops where they are the frozen ones (consistent), come back (a cycle) or
    the passes run out, and stands at the state of least objective chi2(x, windows(x)), not the last one."""
    from lensforge.calibration.joint import WindowPasses

    w = [np.full((2, 3, 2), i) for i in range(4)]
    p = WindowPasses(4)
    assert not p.settle(w[0], w[0], 5.0, "a") and p.best == "a" and p.best_objective == 5.0
    p = WindowPasses(4)  # a cycle: the second minimum's windows are the first's; the better point stands
    assert p.settle(w[0], w[1], 10.0, "a") and not p.settle(w[1], w[0], 8.0, "b") and p.best == "b"
    p = WindowPasses(4)  # a three-set cycle whose first point is the best
    assert p.settle(w[0], w[1], 3.0, "a") and p.settle(w[1], w[2], 9.0, "b")
    assert not p.settle(w[2], w[1], 7.0, "c") and p.best == "a" and p.passes == 2
    p = WindowPasses(2)  # the limit: every set new, two passes, then the best of the three minima
    assert p.settle(w[0], w[1], 6.0, "a") and p.settle(w[1], w[2], 4.0, "b")
    assert not p.settle(w[2], w[3], 5.0, "c") and p.best == "b" and p.best_objective == 4.0
    p = WindowPasses(4)  # an unlit objective never stands over a lit one
    assert p.settle(w[0], w[1], np.inf, "a") and not p.settle(w[1], w[1], 2.0, "b") and p.best == "b"


@pytest.mark.slow
def test_joint_fit_on_the_cells_model_reports_its_objective(polynomial_joint_setup):
    """The joint fit on the 'cells' cross-talk model (windows frozen within a fit, placed again by the tracking
    rule at its minimum; the focal-length gain estimated, lens known): the reported chi2 is the objective at the
    reported state, chi2 with the windows the rule places there, the fit is not worse than the truth, and the
    gain and Z are within their reported sigmas. A small pupil (0.5 mm, order 3) and four poses of the plan keep
    it to minutes."""
    from lensforge.calibration.joint import JointProblem

    bench0, lens, scene, plan = polynomial_joint_setup
    bench = bench0.replace(sensor={"crosstalk": "cells", "pupil_radius_mm": 0.5, "zernike_order": 3})
    plan = plan[[0, 3, 6, 9]]
    param = parameterise(bench, lens, TOL, plan, as_designed=True)
    rng = np.random.default_rng(5)
    A_cmd = flange_pose(scene, plan, check_reach=False)
    a_true = scene.noise.sample(rng, len(A_cmd))
    g, gs = 1.012, 0.01
    # the sensor's lenslets at f g: on a cross-talk bench the light itself changes with f, beyond the gain
    bench_g = bench.replace(sensor={"lenslet_focal_mm": bench.sensor.lenslet_focal_mm * g})
    z = g * simulate_joint_data(bench_g, param, np.zeros(0), A_cmd @ pose_to_matrix(a_true), scene.X, scene.Z,
                                scene.T_SO_nominal, rng=rng)
    X0 = scene.X @ pose_to_matrix([0.03, -0.02, 0.04, 5e-4, -4e-4, 6e-4])
    Z0 = scene.Z @ pose_to_matrix([-0.04, 0.03, 0.02, -5e-4, 3e-4, 4e-4])
    res = joint_calibrate(bench, param, z, A_cmd, scene.T_SO_nominal, X0, Z0, scene.noise.cov, gain_sigma=gs)
    assert res.converged and res.used.all()
    pb = JointProblem(bench, param, z, A_cmd, scene.T_SO_nominal, scene.noise.cov, True, gain_sigma=gs)
    r, lit, *_ = pb.residuals(res.X, res.Z, res.theta, res.robot_errors, place_windows=True)
    assert lit.all() and res.chi2 == pytest.approx(pb.cost(r, res.robot_errors, res.theta), rel=1e-9)
    r, *_ = pb.residuals(scene.X, scene.Z, np.array([(g - 1) / gs]), a_true, place_windows=True)
    assert res.chi2 <= pb.cost(r, a_true, np.array([(g - 1) / gs]))  # the minimum, not a frozen-window one
    assert abs(res.sensor_gain - g) < 4 * res.sensor_gain_std
    e = pose_error(scene.Z, res.Z)
    assert e @ np.linalg.solve(res.cov_Z, e) < 22.5  # chi2_6's 99.9th percentile
