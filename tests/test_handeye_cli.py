"""``lensforge handeye POSES.json``."""

import json
import math

import numpy as np
from conftest import check_json_output
import pytest

from conftest import run_cli_inprocess

from lensforge.calibration.robot import (
    flange_pose,
    paper_scene,
    random_lens_poses,
    simulate_calibration,
)

COV_B = np.diag([1e-3] * 3 + [1e-5] * 3) ** 2


def _run(monkeypatch, capsys, *args):
    return run_cli_inprocess(monkeypatch, capsys, *args)


def _poses(tmp_path, **extra):
    rng = np.random.default_rng(0)
    s = paper_scene()
    d = simulate_calibration(s, random_lens_poses(rng, 12, 5.0, math.radians(5)), rng, cov_B=COV_B,
                             check_reach=False)
    data = {"units": "mm", "A": d.A.tolist(), "B": d.B.tolist(),
            "sigma_A": {"translation_mm": s.noise.translation_mm, "rotation_rad": s.noise.rotation_rad},
            "cov_B": COV_B.tolist()}
    data.update(extra)
    p = tmp_path / "poses.json"
    p.write_text(json.dumps(data))
    return p, s, data


@pytest.mark.parametrize("method", ["ml", "shah", "li"])
def test_cli_json_happy_path(tmp_path, monkeypatch, capsys, method):
    p, s, _ = _poses(tmp_path)
    code, out, err = _run(monkeypatch, capsys, "handeye", p, "--method", method, "--json")
    assert code == 0, err
    res = check_json_output("handeye", out)
    for k in ("X", "Z", "cov_X", "cov_Z", "chi2_dof", "residuals", "observable", "null_directions", "method"):
        assert k in res
    assert res["method"] == method and res["observable"] is True
    assert np.abs(np.array(res["Z"])[:3, 3] - s.Z[:3, 3]).max() < 0.5
    assert np.array(res["cov_Z"]).shape == (6, 6)
    assert len(res["residuals"]) == 12
    assert "chi2/dof" in err


def _bad(tmp_path, data):
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(data))
    return p


def test_cli_bad_files(tmp_path, monkeypatch, capsys):
    p, _, data = _poses(tmp_path)
    A, B = data["A"], data["B"]
    notortho = [row[:] for row in A]
    notortho[1] = (np.array(A[1]) * [[1.1, 1, 1, 1], [1, 1, 1, 1], [1, 1, 1, 1], [1, 1, 1, 1]]).tolist()
    cases = {
        "orthonormal": {"units": "mm", "A": notortho, "B": B},
        "shape": {"units": "mm", "A": [r[:3] for r in A], "B": B},
        "has 12 poses but B has 11": {"units": "mm", "A": A, "B": B[:11]},
        "at least 3": {"units": "mm", "A": A[:2], "B": B[:2]},
        "units": {"units": "inch", "A": A, "B": B},
        "sigma_A": {"units": "mm", "A": A, "B": B, "sigma_A": {"translation_mm": 0.01}},
    }
    for needle, d in cases.items():
        code, out, err = _run(monkeypatch, capsys, "handeye", _bad(tmp_path, d), "--json")
        assert code != 0, needle
        assert err.startswith("error: ") and err.count("\n") == 1, err
        assert needle in err, (needle, err)
        assert out == ""
    (tmp_path / "broken.json").write_text("{not json")
    code, _, err = _run(monkeypatch, capsys, "handeye", tmp_path / "broken.json")
    assert code != 0 and "not valid JSON" in err


def test_cli_degenerate_motion(tmp_path, monkeypatch, capsys):
    rng = np.random.default_rng(1)
    x = np.c_[rng.uniform(-1, 1, (12, 3)), np.zeros((12, 3))]
    d = simulate_calibration(paper_scene(), x, rng, cov_B=COV_B, check_reach=False)
    p = _bad(tmp_path, {"units": "mm", "A": d.A.tolist(), "B": d.B.tolist(),
                        "sigma_B": {"translation_mm": 1e-3, "rotation_rad": 1e-5}})
    code, out, err = _run(monkeypatch, capsys, "handeye", p, "--json")
    assert code != 0 and "degenerate motion" in err
    # the file declares the lens noise only (the simulated robot noise is not in it): the chi2 model
    # check rejects the fit (exit 3, issue 23); this test is about the degenerate directions
    code, out, err = _run(monkeypatch, capsys, "handeye", p, "--json", "--allow-degenerate")
    assert code == 3 and json.loads(out)["valid"] is False, err
    code, out, err = _run(monkeypatch, capsys, "handeye", p, "--json", "--allow-degenerate", "--accept-failed-check")
    assert code == 0
    res = json.loads(out)
    assert res["observable"] is False and res["null_directions"]
    assert "warning" in err
    # the directions the motion lacks get a null 1-sigma, never a tiny finite number
    std = res["frames"]["Z"]["std"]
    assert None in std.values() and all(v is None or v > 0 for v in std.values())


def test_cli_exactly_degenerate_motion_has_null_sigma(tmp_path, monkeypatch, capsys):
    """Noise-free pure translations: rotation of Z about the motion-free axes is not
    determined at all; its 1-sigma is null (infinite), not a tiny pseudo-inverse number."""
    rng = np.random.default_rng(2)
    x = np.c_[rng.uniform(-1, 1, (12, 3)), np.zeros((12, 3))]
    s = paper_scene()
    A = flange_pose(s, x, check_reach=False)
    B = np.linalg.inv(s.Z) @ A @ s.X
    p = _bad(tmp_path, {"units": "mm", "A": A.tolist(), "B": B.tolist(),
                        "noise": {"robot_sigma_trans_mm": 0.005, "robot_sigma_rot_deg": 0.001,
                                  "lens_sigma_trans_mm": 0.001, "lens_sigma_rot_deg": 0.001}})
    code, out, err = _run(monkeypatch, capsys, "handeye", p, "--json", "--allow-degenerate", "-o", tmp_path / "he")
    assert code == 0, err
    res = json.loads(out)
    assert res["observable"] is False
    assert None in res["frames"]["Z"]["std"].values()
    assert (tmp_path / "he" / "handeye.json").exists() and (tmp_path / "he" / "easy_handeye.yaml").exists()
