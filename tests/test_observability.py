"""The one Jacobian and the one observability rule (DESIGN.md: a direction is
unobservable when it is numerically null or its predicted 1-sigma exceeds its scale)."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

import lensforge as lf
from lensforge.calibration.handeye import solve_handeye
from lensforge.calibration.pose_estimation import WeakObservabilityWarning, estimate_pose_model
from lensforge.calibration.robot import RobotNoise, paper_scene, random_lens_poses, simulate_calibration
from lensforge.design.design_file import load_design
from lensforge.optics.sensitivity import jacobian, metrics, observability
from lensforge.optics.shack_hartmann import ForwardModel

DEMO = Path(__file__).parent / "data" / "demo-zernike.json"  # `lensforge demo`'s design (CMA-ES, A, seed 0, 800 evals)


def difference_jacobian(model: ForwardModel, x, scale: float = 1.0) -> np.ndarray:
    """Central differences of the model, dz/dx (P, m, 6) at poses x (P, 6), with steps
    scale * bench.fd_steps: the independent check of the exact ``jacobian`` (DESIGN.md:
    differences of h exist only in tests; 12 evaluated poses per pose, rays warm-started from x)."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    base = model.evaluate(x, check_range=False)
    h = scale * np.asarray(model.bench.fd_steps, dtype=float)
    cols = []
    for j in range(6):
        e = np.eye(6)[j] * h[j]
        zp = model.evaluate(x + e, uv0=base.uv, check_range=False).z
        zm = model.evaluate(x - e, uv0=base.uv, check_range=False).z
        cols.append((zp - zm) / (2 * h[j]))
    return np.stack(cols, axis=-1)


@pytest.fixture(scope="module")
def bench():
    return lf.Bench.default()


@pytest.mark.parametrize("name, rz", [("spherical", False), ("zernike", False), ("polynomial", True),
                                      ("extended_polynomial", True)])
def test_paper_lenses_rz(bench, name, rz):
    ob = metrics(bench, lf.paper_lens(name)).observability
    assert bool(ob.observable[5]) is rz
    assert ob.observable[:5].all()
    if name == "spherical":  # numerically null: 1-sigma inf, never a finite number
        assert ob.null_names == ("rz",) and math.isinf(ob.std[5])
    if name == "zernike":  # rank 6, yet rz 1-sigma ~ 11 deg > 1 deg
        assert ob.rank == 6 and ob.null_names == ()
        # 10.6 deg with the old lenslet-centre slopes, 11.0 deg with the spot-centroid sensor model
        assert math.degrees(ob.std[5]) == pytest.approx(11.0, rel=0.02)


def test_demo_design_fully_observable():
    d = load_design(DEMO)
    ob = metrics(d.bench, d.lens).observability
    assert ob.observable.all() and ob.all_observable


def test_rule_on_a_diagonal_jacobian():
    # whitened Jacobian diag(10, 2, 0.5, 1e-12): 1-sigma 0.1, 0.5, 2, null
    J = np.diag([10.0, 2.0, 0.5, 1e-12])
    ob = observability(J, np.ones(4), 1e-9, names=("a", "b", "c", "d"))
    assert ob.observable.tolist() == [True, True, False, False]
    assert np.allclose(ob.std[:3], [0.1, 0.5, 2.0]) and math.isinf(ob.std[3])
    assert ob.rank == 3 and ob.null_names == ("d",) and ob.unobservable == ("c", "d")
    # scales: the same direction is fine when the scale allows 2-sigma
    assert observability(J, [1, 1, 4, 1], 1e-9).observable[2]


def test_batched_jacobian_matches_per_pose(bench):
    model = ForwardModel(bench, lf.paper_lens("polynomial"))
    x = np.array([[0.0] * 6, [0.2, -0.1, 0.05, 0.002, -0.003, 0.004]])
    J, complete, _ = jacobian(model, x)
    assert complete.all() and J.shape == (2, len(model.modes), 6)
    for p in range(2):
        Jp = jacobian(model, x[p:p + 1])[0][0]
        assert np.allclose(J[p], Jp, rtol=1e-9, atol=1e-12 * np.abs(Jp).max())


@pytest.mark.parametrize("name", ["polynomial", "extended_polynomial", "zernike", "spherical"])
def test_exact_jacobian_matches_central_differences_of_the_model(bench, name):
    # central differences of the model at two steps: their gap (~3x the error of the smaller)
    # bounds the difference error; the exact Jacobian must sit within it
    model = ForwardModel(bench, lf.paper_lens(name))
    x = np.array([[0.0] * 6, [0.3, -0.2, 0.4, 0.004, -0.006, 0.05]])
    J, complete, _ = jacobian(model, x)
    assert complete.all()
    W = lambda A: np.einsum("ij,pjk->pik", model.whitener, A)  # whitened: 1/sigma per unit
    fd1, fd2 = W(difference_jacobian(model, x)), W(difference_jacobian(model, x, scale=2.0))
    # rounding floor: 1e-7 of the pose's largest column (a null column, e.g. rz of the
    # rotationally symmetric spherical lens, is all rounding in both)
    floor = 1e-7 * np.linalg.norm(W(J), axis=1).max(axis=1, keepdims=True)  # (P, 1)
    est = np.linalg.norm(fd2 - fd1, axis=1)
    err = np.linalg.norm(W(J) - fd1, axis=1)
    assert np.all(err <= est + floor), (name, err, est, floor)


@pytest.mark.parametrize("name", ["polynomial", "zernike"])
def test_iteration_jacobian_is_close_to_the_exact_one(bench, name):
    """exact=False (the joint fit's iteration Jacobians) leaves out only the change of det J in
    the irradiance weights: a small part of each whitened column, never the whole."""
    model = ForwardModel(bench, lf.paper_lens(name))
    x = np.array([[0.0] * 6, [0.3, -0.2, 0.4, 0.004, -0.006, 0.05]])
    J, _, res = model.jacobians(x)
    Ja, _, res_a = model.jacobians(x, exact=False)
    assert np.array_equal(res.z, res_a.z)  # the model itself is the same
    W = lambda A: np.einsum("ij,pjk->pik", model.whitener, A)
    col = np.linalg.norm(W(J), axis=1)  # (P, 6)
    rel = np.linalg.norm(W(Ja) - W(J), axis=1) / col
    big = col > 1e-3 * col.max()  # rz of a near-symmetric lens is all rounding
    assert np.all(rel[big] < 2e-2) and rel[big].max() > 1e-8, rel


def test_pose_estimation_warns_weak_rz_and_still_solves(bench):
    model = ForwardModel(bench, lf.paper_lens("zernike"))
    xt = np.array([0.1, -0.05, 0.02, 0.001, 0.0, 0.0])
    with pytest.warns(WeakObservabilityWarning, match="rz"):
        est = estimate_pose_model(model, model.zernike(xt))
    assert est.converged and not est.observable[5] and est.unobservable == ()
    assert np.isfinite(est.cov[5, 5])
    assert np.allclose(est.pose, xt, atol=1e-6)


def test_handeye_noisy_problem_is_solved_and_warned_not_refused():
    rng = np.random.default_rng(3)
    scene = paper_scene()
    x = random_lens_poses(rng, 12, 5.0, math.radians(5.0))
    cov_B = np.diag([1e-3] * 3 + [1e-5] * 3) ** 2 * 1e6  # large but honest noise (1 mm, 10 mrad)
    d = simulate_calibration(scene, x, rng, cov_B=cov_B, check_reach=False)
    with pytest.warns(RuntimeWarning, match="weakly observable"):
        r = solve_handeye(d.A, d.B, "ml", sigma=RobotNoise(), cov_B=cov_B)
    assert not r.observable and r.warnings and np.all(np.isfinite(r.std_Z))
    err = np.linalg.solve(scene.Z, r.Z)
    assert np.linalg.norm(err[:3, 3]) < 5 * np.linalg.norm(r.std_Z[:3])  # finite and consistent with its 1-sigma
    # a looser, settable limit calls the same data observable
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        r2 = solve_handeye(d.A, d.B, "ml", sigma=RobotNoise(), cov_B=cov_B, obs_limits=(100.0, 1.0))
    assert r2.observable and np.allclose(r2.Z, r.Z)


def test_handeye_degenerate_motion_gets_inf_sigma():
    rng = np.random.default_rng(8)
    x = np.c_[rng.uniform(-1, 1, (12, 3)), np.zeros((12, 3))]  # pure translations
    cov_B = np.diag([1e-3] * 3 + [1e-5] * 3) ** 2
    d = simulate_calibration(paper_scene(), x, rng, cov_B=cov_B, check_reach=False)
    with pytest.warns(RuntimeWarning, match="degenerate"):
        r = solve_handeye(d.A, d.B, "ml", sigma=RobotNoise(), cov_B=cov_B, on_degenerate="warn")
    assert np.isinf(r.std_Z[:3]).all() and np.isinf(r.std_X[:3]).all()
    assert np.isfinite(r.std_Z[3:]).all()
    assert r.to_dict()["std_Z"][:3] == [None, None, None]


def test_design_constraint_observable(bench):
    from lensforge.design.constraints import Constraints, check_design

    c = Constraints(observable=True, range_mm=0.0, range_rad=0.0, max_slope_deg=90.0)
    z = check_design(bench, lf.paper_lens("zernike"), c)
    assert not z.ok and [v.constraint for v in z.violations] == ["observable"] and "rz" in z.message()
    assert check_design(bench, lf.paper_lens("extended_polynomial"), c).ok
    assert Constraints.from_dict(c.to_dict()).observable and "observable" not in Constraints().to_dict()


def test_cli_evaluate_json_reports_observability(tmp_path):
    import json
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "lensforge", "evaluate", "spherical", "paper:zernike", "polynomial",
                        "--json"], capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    rows = {row["lens"]: row for row in json.loads(r.stdout)["lenses"]}
    for name, rz in (("spherical", False), ("paper:zernike", False), ("polynomial", True)):
        obs = rows[name]["observable"]
        assert list(obs) == ["tx", "ty", "tz", "rx", "ry", "rz"] and obs["rz"] is rz
        assert all(obs[d] for d in ("tx", "ty", "tz", "rx", "ry"))
        assert ("rz" in rows[name]["unobservable"]) is (not rz)
        assert len(rows[name]["unobservable_directions"]) == (0 if rz else 1)


def test_no_poses_give_empty_results(bench):
    # a study lens whose every pose is unlit estimates nothing: the model and its Jacobian
    # take zero poses (the joint budget with loose tolerances found this)
    model = ForwardModel(bench, lf.paper_lens("polynomial"))
    res = model.evaluate(np.zeros((0, 6)))
    assert res.z.shape == (0, len(model.modes)) and res.valid.shape == (0,)
    J, complete, _ = jacobian(model, np.zeros((0, 6)))
    assert J.shape == (0, len(model.modes), 6) and complete.shape == (0,)
    J, complete, _ = jacobian(model, np.zeros((0, 6)), uv=np.zeros((0, model.targets.shape[0], 2)))
    assert J.shape == (0, len(model.modes), 6)
