"""Estimation study (Fig. 5 / Table 2 analogue) and the estimate-study CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

import lensforge as lf
from lensforge.errors import ConfigError
from lensforge.verification.estimation_study import (
    format_table,
    save_study,
    study_lens,
    study_to_dict,
)
from lensforge.calibration.initial_poses import InitialPoseModel


@pytest.fixture(scope="module")
def small_study():
    b = lf.Bench.default()
    lenses = {"spherical": lf.paper_lens("spherical"), "extended_polynomial": lf.paper_lens("extended_polynomial")}
    return [study_lens(b, lens, name, trials=12, method="lm", seed=3) for name, lens in lenses.items()]


def test_study_summary(small_study):
    sph, ext = small_study
    s = ext.summary()
    assert s["trials"] == 12 and s["succeeded"] == 12 and s["failure_rate"] == 0
    assert 1 < s["median_translation_error_um"] < 100
    assert set(s["rmse_over_crlb"]) == {"tx", "ty", "tz", "rx", "ry", "rz"}
    assert all(0.3 < v < 2.5 for v in s["rmse_over_crlb"].values())  # 12 trials: loose
    assert 0.3 < s["mean_nees_per_dof"] < 2.5
    # spherical: rz unobservable, excluded from the norms and from RMSE/CRLB
    ss = sph.summary()
    assert ss["unobservable"] == ["rz"]
    assert np.isnan(ss["rmse_over_crlb"]["rz"])
    assert np.isfinite(ss["rmse_over_crlb"]["rx"])
    table = format_table(small_study)
    assert "spherical" in table and "unobs." in table  # the one spelling of an unobservable DOF
    d = study_to_dict(small_study, seed=3)
    assert d["schema_version"] == 1
    json.dumps(d, allow_nan=False)  # NaN became null
    assert d["lenses"][0]["rmse_over_crlb"]["rz"] is None


def test_study_is_seeded():
    b = lf.Bench.default()
    lens = lf.paper_lens("polynomial")
    a = study_lens(b, lens, "p", trials=4, seed=11)
    c = study_lens(b, lens, "p", trials=4, seed=11)
    d = study_lens(b, lens, "p", trials=4, seed=12)
    assert np.array_equal(a.errors, c.errors) and np.array_equal(a.true_poses, c.true_poses)
    assert not np.allclose(a.true_poses, d.true_poses)


def test_study_counts_pupil_loss():
    """A sloppy gripper (2 mm) puts the zernike lens where the pupil is not lit."""
    b = lf.Bench.default()
    r = study_lens(b, lf.paper_lens("zernike"), "z", trials=10, seed=0,
                   initial=InitialPoseModel(grasp_translation_mm=2.0))
    s = r.summary()
    assert s["pupil_lost"] > 0
    assert s["failure_rate"] == pytest.approx((s["pupil_lost"] + s["not_converged"]) / 10)
    assert any("pupil" in m for m in r.messages)


def test_study_ukf_and_files(tmp_path):
    b = lf.Bench.default()
    r = study_lens(b, lf.paper_lens("extended_polynomial"), "ext", trials=3, method="ukf", seed=0, ukf_repeats=12)
    assert r.method == "ukf" and r.summary()["succeeded"] >= 2
    paths = save_study([r], tmp_path, method="ukf")
    assert paths["png"].read_bytes()[:4] == b"\x89PNG"
    assert json.loads(paths["json"].read_text())["lenses"][0]["method"] == "ukf"
    assert len(paths["csv"].read_text().splitlines()) == 4


def test_study_bad_args():
    b = lf.Bench.default()
    with pytest.raises(ConfigError, match="method"):
        study_lens(b, lf.paper_lens("zernike"), trials=2, method="pf")
    with pytest.raises(ConfigError, match="trials"):
        study_lens(b, lf.paper_lens("zernike"), trials=0)


from conftest import run_cli as _run


def test_cli_estimate_study_json(tmp_path):
    r = _run("estimate-study", "polynomial", "spherical", "--trials", "3", "--seed", "1", "-o", str(tmp_path),
             "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert [x["lens"] for x in d["lenses"]] == ["paper polynomial", "paper spherical"]
    assert d["trials"] == 3 and d["method"] == "lm"
    assert (tmp_path / "estimate_study.png").exists() and (tmp_path / "estimate_study.json").exists()


@pytest.mark.parametrize("args, fragment", [
    (("estimate-study", "zernike", "--method", "pf"), "--method"),
    (("estimate-study", "nonesuch", "--trials", "2"), "neither a paper lens"),
    (("estimate-study", "zernike", "--trials", "0"), "--trials"),
])
def test_cli_estimate_study_errors(tmp_path, args, fragment):
    r = _run(*args, "-o", str(tmp_path))
    assert r.returncode != 0
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and fragment in lines[0], r.stderr


def test_swing_equivalent_keeps_the_optical_axis():
    from lensforge.optics.pose import pose_to_matrix
    from lensforge.verification.estimation_study import swing_equivalent

    x = np.array([0.1, 0.2, 0.3, 0.01, -0.02, 0.015])
    y = swing_equivalent(x)
    assert abs(y[5]) < 1e-15 and np.array_equal(y[:3], x[:3])
    assert np.allclose(pose_to_matrix(x)[:3, 2], pose_to_matrix(y)[:3, 2], atol=1e-14)
