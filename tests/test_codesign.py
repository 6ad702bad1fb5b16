"""Co-design of the bench with the lens (issue 22): bench variables, the expander catalogue,
the plan-box and sensor-model constraints, the joint information below calibration, and
the design file / compare / plot carrying the bench."""

from __future__ import annotations

import math

import numpy as np
import pytest

import lensforge as lf
from lensforge.asbuilt.joint_information import pose_information, select_ds, theta_prior, z_ds, z_sigma
from lensforge.design.bench_vars import BenchVariables, CoDesignParameterisation, bench_summary
from lensforge.design.compare import compare_rows
from lensforge.design.constraints import Constraints, check_design, plan_poses
from lensforge.design.design_file import Design, load_design, save_design
from lensforge.design.expanders import EXPANDERS, fitting_expanders
from lensforge.design.optimize import optimize_design
from lensforge.design.parameterisation import parameterisation
from lensforge.errors import ConfigError


def _codesign_par(**kw):
    return CoDesignParameterisation.build(parameterisation("zernike"), BenchVariables(**kw), lf.Bench.default())


def test_expanders_must_fit_the_sensor_aperture():
    # 3.5 mm laser beam on the 11.26 mm WFS40: 1x, 2x (7 mm), 3x (10.5 mm) fit, 5x (17.5 mm) does not
    assert fitting_expanders(3.5, 11.26) == ("none", "GBE02-A", "GBE03-A")
    assert EXPANDERS["GBE03-A"].magnification == 3.0
    par = _codesign_par()
    assert par.expanders == ("none", "GBE02-A", "GBE03-A")
    with pytest.raises(ConfigError, match="expander"):
        BenchVariables(expanders=("GBE99-Z",))


def test_bench_variables_map_to_the_bench_and_back():
    par = _codesign_par()
    assert par.bench_names == ("bench.expander", "bench.pupil_radius_mm", "bench.pupil_center_x_mm",
                               "bench.pupil_center_y_mm", "bench.distance_mm")
    p = par.from_lens(par.template, lf.Bench.default())
    k = par.lens_par.n
    p[k:] = [2.2, 3.1, 0.25, -0.5, 27.0]  # index 2.2 rounds to the 3x expander
    b = par.to_bench(p)
    assert b.laser.expander == "GBE03-A" and b.laser.expander_magnification == 3.0
    assert b.laser.beam_diameter_mm == pytest.approx(10.5, rel=1e-12)
    assert b.sensor.pupil_radius_mm == 3.1 and b.sensor.pupil_center_mm == (0.25, -0.5)
    assert b.placement.distance_mm == 27.0
    # the laser's own beam is recovered from the expanded bench: a second expander does not compound
    assert np.allclose(par.bench_vector(b), [2.0, 3.1, 0.25, -0.5, 27.0])
    assert par.to_bench(par.from_lens(par.template, b), b).laser.beam_diameter_mm == pytest.approx(10.5)
    # a pupil that does not fit the sensor is not a bench
    p[k + 1], p[k + 2] = 5.0, 1.0  # outside the bounds (inside them the pupil always fits: 4 + 1 < 5.63)
    with pytest.raises(ConfigError, match="pupil"):
        par.to_bench(p)
    # continuous magnification is bounded by the aperture
    cont = _codesign_par(expanders=(), magnification=(1.0, 5.0), free=("expander",))
    assert cont.bench_names == ("bench.magnification",)
    assert cont.bench_upper[0] == pytest.approx(11.26 / 3.5)


def test_bench_roundtrip_with_expander_and_slope_bound():
    b = lf.Bench.default().replace(laser={"expander": "GBE02-A", "expander_magnification": 2.0,
                                          "beam_diameter_mm": 7.0}, sensor={"validated_slope_mrad": 120.0})
    assert lf.Bench.from_dict(b.to_dict()) == b
    with pytest.raises(ConfigError, match="laser.expander"):
        lf.Bench.from_dict({"laser": {"expander": 2}})
    with pytest.raises(ConfigError, match="validated_slope_mrad"):
        lf.Bench.default().replace(sensor={"validated_slope_mrad": -1.0})


def test_plan_poses_and_the_sensor_model_bound():
    c = Constraints(plan_mm=0.5, plan_rad=math.radians(5))
    Q = plan_poses(c)
    assert Q.shape == (16, 6)  # 12 axis poses and the 4 (rx, ry) corners
    assert np.max(np.abs(Q[:, 3:])) == pytest.approx(math.radians(5))
    assert plan_poses(Constraints()).shape == (0, 6)
    lens = lf.paper_lens("polynomial")
    bench = lf.Bench.default()
    f0 = check_design(bench, lens, Constraints(range_mm=0.0, range_rad=0.0))
    slope = f0.model.sensor_range().max_slope_mrad
    tight = bench.replace(sensor={"validated_slope_mrad": 0.5 * slope})
    f = check_design(tight, lens, Constraints(range_mm=0.0, range_rad=0.0))
    assert [v.constraint for v in f.violations] == ["sensor_model"]
    assert f.violations[0].value == pytest.approx(slope, rel=1e-9)  # the nominal pose's largest slope
    loose = bench.replace(sensor={"validated_slope_mrad": 1.01 * slope})
    assert check_design(loose, lens, Constraints(range_mm=0.0, range_rad=0.0)).ok
    # the plan box's tilted poses steepen the slopes: the same bound now fails there
    fp = check_design(loose, lens, Constraints(range_mm=0.0, range_rad=0.0, plan_mm=0.5, plan_rad=math.radians(5)))
    assert not fp.ok and "calibration-plan pose" in fp.message()


def test_joint_information_matches_a_direct_least_squares_covariance():
    """pose_information eliminates the robot error exactly: the Z block of its inverse equals the
    one of the full (X, Z, theta, a_1..a_n) information inverted at once."""
    rng = np.random.default_rng(3)
    n, m, k = 8, 14, 3
    from lensforge.optics.pose import pose_to_matrix

    x = rng.uniform(-1, 1, (n, 6)) * [0.5, 0.5, 0.5, 0.08, 0.08, 0.08]
    B = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -20.0], [0, 0, 0, 1]]) @ pose_to_matrix(x)
    X = pose_to_matrix(np.array([1.0, 2.0, 150.0, 0.1, -0.2, 0.3]))
    S = rng.standard_normal((n, m, 6)) * 50
    Jt = rng.standard_normal((n, m, k))
    cov_a = np.diag([0.005**2] * 3 + [1e-5**2] * 3)
    I = pose_information(S, Jt, B, x, X, cov_a)
    from lensforge.asbuilt.joint_information import chain_jacobians

    dX, dZ, dA = chain_jacobians(B, x, X)
    G = 12 + k
    full = np.zeros((n * m + n * 6, G + 6 * n))
    for i in range(n):
        full[i * m:(i + 1) * m, :G] = np.concatenate([S[i] @ dX[i], S[i] @ dZ[i], Jt[i]], axis=1)
        full[i * m:(i + 1) * m, G + 6 * i:G + 6 * i + 6] = S[i] @ dA[i]
        full[n * m + 6 * i:n * m + 6 * i + 6, G + 6 * i:G + 6 * i + 6] = np.linalg.inv(np.linalg.cholesky(cov_a))
    F_full = full.T @ full
    F_full[12:G, 12:G] += np.eye(k)
    C_full = np.linalg.inv(F_full)[:G, :G]
    C = np.linalg.inv(I.sum(axis=0) + theta_prior(k))
    assert np.allclose(C[6:12, 6:12], C_full[6:12, 6:12], rtol=1e-6, atol=1e-12 * np.abs(C_full[6:12, 6:12]).max())
    s = z_sigma(I.sum(axis=0) + theta_prior(k))
    assert s["Z_translation_known_lens_mm"] <= s["Z_translation_mm"] * (1 + 1e-12)
    chosen, F, eps, _ = select_ds(I, k, 4)
    assert len(chosen) == 4
    # the exchange passes leave no single swap that would improve Ds
    for pos in range(4):
        Fm = F - I[chosen[pos]]
        assert np.max(z_ds(Fm[None] + I)) <= z_ds(F) + 1e-6


def test_codesign_returns_a_feasible_design_with_its_bench(tmp_path):
    """A short co-design (small budgets) moves the bench off the paper's and keeps it in the file."""
    d = optimize_design(lf.Bench.default(), model="zernike", seed=0, criterion="A",
                        bench_vars=BenchVariables(free=("expander", "pupil_radius")), max_evals=24, lens_evals=40,
                        constraints=Constraints(plan_mm=0.5, plan_rad=math.radians(5)), progress=False)
    assert d.feasibility["feasible"]
    assert d.bench.sensor.pupil_radius_mm > 0.9 and d.bench.laser.expander_magnification > 1
    assert d.bench.sensor.subaperture_quadrature == 2  # scored on the full bench, searched on 1 point/lenslet
    assert d.settings["search_quadrature"] == 1 and d.settings["codesign"]["lens_evals"] <= 40
    assert "bench.pupil_radius_mm" in d.parameters
    assert d.parameters["bench.pupil_radius_mm"] == pytest.approx(d.bench.sensor.pupil_radius_mm)
    # the CRLB in the file is the co-designed bench's
    m = d.compute_metrics()
    assert np.sqrt(m.crlb[0, 0]) * 1e3 == pytest.approx(d.metrics["crlb_std"]["tx_um"], rel=1e-6)
    p = save_design(d, tmp_path / "co.json")
    back = load_design(p)
    assert back.bench == d.bench and isinstance(back, Design)
    rows = compare_rows([str(p), "paper:zernike"])
    assert rows[0]["bench"] == bench_summary(d.bench)
    assert rows[1]["bench"]["pupil_radius_mm"] == 0.9  # a paper lens on the default bench
    paper = compare_rows([str(p)], lf.Bench.default())
    assert paper[0]["bench"]["pupil_radius_mm"] == 0.9
    from lensforge.plots.design import plot_bench_layout
    from lensforge.plots.figure import save_figure

    png = save_figure(plot_bench_layout(d.bench, d.lens), tmp_path / "layout.png")
    assert png.stat().st_size > 10_000


def test_selfcal_information_equals_the_calibration_plans():
    """design.selfcal's joint bound (no calibration import) equals calibration.joint_design's
    for the same lens, poses, grasp and robot noise when theta spans the whole tolerance space."""
    from lensforge.asbuilt.lens_params import parameterise
    from lensforge.asbuilt.tolerances import Tolerances
    from lensforge.calibration.joint_design import predicted_joint_uncertainty
    from lensforge.calibration.robot import RobotNoise, paper_scene
    from lensforge.design.selfcal import SelfCalSpec, default_grasp, selfcal_value

    bench, lens = lf.Bench.default(), lf.paper_lens("extended_polynomial")
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, (10, 6)) * [0.3, 0.3, 0.3, 0.03, 0.03, 0.03]
    tol = Tolerances()
    spec = SelfCalSpec(tol, poses=x)
    scene = paper_scene(bench.placement.distance_mm)
    assert np.allclose(default_grasp(), scene.X) and np.allclose(spec.robot_cov, RobotNoise().cov, rtol=1e-12, atol=0)
    value, s = selfcal_value(bench, lens, spec)
    param = parameterise(bench, lens, tol, x, keep_threshold=0.0)
    ref = predicted_joint_uncertainty(bench, param, scene, x)
    assert s["n_lit"] == ref["n_lit"] == 10
    # theta free: the two differ only in the basis of theta (elementary vs its rotation V) along which
    # the packing is differenced (lens_tangents, step 1e-4); on this poorly conditioned paper lens
    # (Z to 0.6 mm over 10 small poses) that leaves ~5e-6 relative, a wrong prior or a missed
    # robot-error elimination would move it by orders of magnitude more
    assert s["Z_translation_mm"] == pytest.approx(ref["Z_translation_mm"], rel=5e-5)
    assert s["Z_rotation_deg"] == pytest.approx(ref["Z_rotation_deg"], rel=5e-5)
    assert s["Z_translation_known_lens_mm"] == pytest.approx(ref["Z_translation_known_lens_mm"], rel=1e-9)
    assert value == pytest.approx(float(np.linalg.slogdet(ref["cov"][6:12, 6:12])[1]), abs=1e-3)
