"""The paper's calibration procedure simulated: Z error against its predicted bound."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
from conftest import check_json_output
import pytest

import lensforge as lf
from lensforge.errors import CalibrationError, ConfigError
from lensforge.calibration.robot import PAPER_Z, flange_pose
from lensforge.verification.scenario import (
    ScenarioConfig,
    compare_pose_designs,
    format_comparison,
    plan_poses,
    run_calibration,
    scenario_scene,
)

FAST = ScenarioConfig(n_convergence=4)


@pytest.fixture(scope="module")
def ext():
    return lf.paper_lens("extended_polynomial")


def test_side_grasp_scene_is_reachable(bench):
    sc = scenario_scene(bench)
    x = np.array([[0.5, -0.5, 0.5, 0.17, -0.17, 0.17], [-0.5, 0.5, -0.5, -0.17, 0.17, -0.17]])
    flange_pose(sc, x, check_reach=True)  # raises if not
    assert np.allclose(sc.Z, PAPER_Z)
    with pytest.raises(ConfigError, match="grasp"):
        scenario_scene(bench, "under")


def test_plan_poses_lit_and_in_box(bench, ext):
    cfg = ScenarioConfig()
    for design in ("random", "oed"):
        x, pred = plan_poses(bench, ext, design, np.random.default_rng(1), cfg)
        assert x.shape == (12, 6)
        assert np.all(np.abs(x[:, :3]) <= cfg.work_translation_mm + 1e-12)
        assert np.all(np.abs(x[:, 3:]) <= cfg.work_rotation_rad + 1e-12)
        assert pred["Z_translation_mm"] > 0 and pred["Z_rotation_rad"] > 0
    with pytest.raises(ConfigError, match="design"):
        plan_poses(bench, ext, "grid", np.random.default_rng(1))


def test_noise_free_calibration_is_exact(bench, ext):
    """No sensor or robot noise, no CAD/grasp error: Z and X come back exactly."""
    from lensforge.calibration.initial_poses import InitialPoseModel
    from lensforge.calibration.robot import RobotNoise

    quiet = bench.replace(noise={"slope_sigma_urad": 1e-6})
    sc = scenario_scene(quiet)
    sc = type(sc)(Z=sc.Z, X=sc.X, distance_mm=sc.distance_mm, noise=RobotNoise(1e-9, 1e-12))
    cfg = ScenarioConfig(n_convergence=0, sensor_cad_translation_mm=0.0, sensor_cad_rotation_rad=0.0,
                         grasp=InitialPoseModel(0.0, 0.0, 0.0, 0.0))
    x, _ = plan_poses(quiet, ext, "random", np.random.default_rng(0), cfg, sc)
    run = run_calibration(quiet, ext, x, np.random.default_rng(0), cfg, sc)
    assert run.n_used == 12 and run.pupil_lost == 0
    assert run.z_translation_error_mm < 1e-5 and run.z_rotation_error_rad < 1e-7


def test_calibration_error_matches_prediction(bench, ext):
    """A few noisy runs: the Z error is of the size the solver predicts (NEES ~ 1 per DOF)."""
    rep = compare_pose_designs(bench, ext, FAST, designs=("random", "oed"), runs=4, seed=2)
    for d in ("random", "oed"):
        s = rep["designs"][d]
        assert s["runs"] == 4 and s["pupil_lost"] == 0
        assert 0.1 < s["mean_nees_Z_per_dof"] < 3.0, s
        assert 0.5 < s["mean_chi2_dof"] < 2.0, s
        assert 0.3 < s["Z_translation_error_rms_um"] / s["Z_translation_predicted_rms_um"] < 2.5
    # the chosen poses promise a smaller bound than random ones
    assert rep["designs"]["oed"]["Z_design_bound_rotation_urad"] < rep["designs"]["random"]["Z_design_bound_rotation_urad"]
    assert "oed" in format_comparison(rep)
    json.dumps(rep, allow_nan=False)


def test_spherical_lens_cannot_calibrate(bench):
    with pytest.raises(CalibrationError, match="rank"):
        plan_poses(bench, lf.paper_lens("spherical"), "random", np.random.default_rng(0))


def test_config_checks():
    with pytest.raises(ConfigError, match="estimator"):
        ScenarioConfig(estimator="ekf")
    with pytest.raises(ConfigError, match="n_calibration"):
        ScenarioConfig(n_calibration=2)


def test_cli_scenario(tmp_path):
    r = subprocess.run([sys.executable, "-m", "lensforge", "scenario", "extended_polynomial", "--runs", "1",
                        "--poses", "oed", "-o", str(tmp_path), "--json"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    d = check_json_output("scenario", r.stdout)
    assert set(d["designs"]) == {"oed"} and d["designs"]["oed"]["runs"] == 1
    r = subprocess.run([sys.executable, "-m", "lensforge", "scenario", "zernike", "--poses", "grid",
                        "-o", str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and r.stderr.strip().startswith("error:") and "--poses" in r.stderr
