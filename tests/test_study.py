"""As-built study: noise-only equivalence, thickness bias physics, determinism, bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
from conftest import check_json_output
import pytest

from lensforge.errors import ConfigError
from lensforge.asbuilt.tolerances import Tolerances
from lensforge.optics.shack_hartmann import ForwardModel
from lensforge.calibration.pose_estimation import estimate_pose_model, estimate_poses_batch
from lensforge.verification.study import StudyConfig, verify

CFG = StudyConfig(n_poses=8, min_poses=4)


def test_zero_tolerances_give_the_noise_only_result():
    a = verify("extended_polynomial", Tolerances.zero(), 3, 11, config=CFG, workers=0, progress=False)
    b = verify("extended_polynomial", None, 3, 11, config=CFG, workers=0, progress=False)
    assert a.records == b.records  # bit-identical: the as-built stream does not touch the noise draws
    assert a.ok.all()
    # noise only: the mean pose error is within the noise of a mean over the used poses
    for r in a.records:
        sem = np.asarray(r["bias_std"]) / np.sqrt(r["n_used"] - 1)
        assert np.all(np.abs(r["bias"]) < 5 * sem)


def test_thicker_lens_shifts_apparent_tz_towards_the_laser():
    # Zernike-sag paper lens: convex front (R 25.8 mm), near-plano back. With {O} at the
    # mid-thickness, a thickness change dl moves the back focus (in {O}) by
    # d/dl [l/2 - l/n + R/(n-1)] = 1/2 - 1/n = -0.160 dl (n = 1.5145): the nominal model
    # explains the wavefront by moving the lens along -z, so bias_tz ~ -0.16 dl.
    n_idx = 1.5145
    expect = 0.5 - 1.0 / n_idx
    for dl in (0.2, -0.2):
        tol = dataclasses.replace(Tolerances.zero(), thickness_mean_mm=dl)
        res = verify("zernike", tol, 2, 3, config=CFG, workers=0, progress=False)
        noise = verify("zernike", None, 2, 3, config=CFG, workers=0, progress=False)
        assert res.ok.all() and noise.ok.all()
        dtz = np.mean(res.bias[:, 2] - noise.bias[:, 2])  # same noise draws (CRN)
        assert np.sign(dtz) == np.sign(expect * dl)
        assert dtz == pytest.approx(expect * dl, rel=0.25)


def test_batched_estimator_matches_estimate_pose(bench):
    from lensforge.optics.lens import paper_lens

    model = ForwardModel(bench, paper_lens("extended_polynomial"))
    rng = np.random.default_rng(4)
    x = rng.uniform(-1, 1, (5, 6)) * np.r_[0.2, 0.2, 1.0, np.radians([4, 4, 4])]
    z = model.zernike(x, rng)
    x0 = x + rng.normal(size=x.shape) * np.r_[0.1, 0.1, 0.2, np.radians([0.3, 0.3, 0.3])]
    be = estimate_poses_batch(model, z, x0)
    assert be.converged.all()
    for i in range(5):
        ref = estimate_pose_model(model, z[i], x0[i])
        assert np.all(np.abs(be.poses[i] - ref.pose) <= 1e-3 * ref.std)
        assert be.chi2[i] == pytest.approx(ref.chi2, rel=1e-6)


def test_bad_tolerance_file_is_a_clear_error(tmp_path):
    p = tmp_path / "t.toml"
    p.write_text("[form]\nrms_mm = -1\n")
    with pytest.raises(ConfigError, match="form.rms_mm"):
        verify("zernike", p, 2, 0, config=CFG, workers=0, progress=False)
    p.write_text("[thickness\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        verify("zernike", p, 2, 0, config=CFG, workers=0, progress=False)
    with pytest.raises(ConfigError, match="not found"):
        verify("zernike", tmp_path / "missing.toml", 2, 0, config=CFG, workers=0, progress=False)


def test_bad_study_options():
    with pytest.raises(ConfigError, match="n_lenses"):
        verify("zernike", None, 0, 0, config=CFG, workers=0, progress=False)
    with pytest.raises(ConfigError, match="n_poses"):
        StudyConfig(n_poses=2)
    with pytest.raises(ConfigError, match="workers"):
        verify("zernike", None, 1, 0, config=CFG, workers=-1, progress=False)


def test_cli_study_and_bad_tolerances(tmp_path):
    import json
    import subprocess
    import sys

    exe = [sys.executable, "-c", "from lensforge.cli import main; main()"]
    out = tmp_path / "s"
    r = subprocess.run(exe + ["study", "zernike", "--lenses", "2", "--poses", "8", "--workers", "0",
                              "-t", str(tmp_path / "nope.toml"), "-o", str(out)], capture_output=True, text=True)
    assert r.returncode == 2 and "tolerances file" in r.stderr and "not found" in r.stderr
    (tmp_path / "zero.toml").write_text(
        "[polishing]\ndepth_mm = 0\ndepth_sigma_mm = 0\nrolloff_mm = 0\nrolloff_sigma_mm = 0\n"
        "[form]\nrms_mm = 0\n[thickness]\nsigma_mm = 0\n[index]\nsigma = 0\nbatch_sigma = 0\n"
        "[shrinkage]\nmean = 0\nsigma = 0\n[ripple]\namplitude_mm = 0\n")
    r = subprocess.run(exe + ["study", "zernike", "--lenses", "2", "--poses", "8", "--workers", "0", "--json",
                              "-t", str(tmp_path / "zero.toml"), "-o", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    d = check_json_output("study", r.stdout)
    assert d["summary"]["n_lenses"] == 2 and len(d["trials"]["ok"]) == 2
    assert (out / "summary.json").exists() and (out / "errors.png").exists() and (out / "store.sqlite").exists()
    # running again without --resume refuses to touch the store
    r = subprocess.run(exe + ["study", "zernike", "--lenses", "2", "--poses", "8", "--workers", "0",
                              "-t", str(tmp_path / "zero.toml"), "-o", str(out)], capture_output=True, text=True)
    assert r.returncode == 2 and "--resume" in r.stderr
