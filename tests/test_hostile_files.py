"""Hostile files for every reader: success with sane values, or one ConfigError line.

Property-based (hypothesis): a valid file with one field replaced by a random type,
NaN/inf, a huge or negative number; truncated files, a UTF-8 BOM, garbage bytes.
Plus the named cases the first hostile campaign found (issue 12).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import tomli_w
from hypothesis import given, settings
from hypothesis import strategies as st

from hostile import PROFILE, assert_one_line_error, corrupt, hostile_values, leaf_paths, mutate
from lensforge.commands.handeye import load_poses
from lensforge.design.design_file import load_design
from lensforge.errors import LensforgeError
from lensforge.asbuilt.tolerances import DEFAULT_TOLERANCES_FILE, TOLERANCE_RANGES, load_tolerances
from lensforge.optics.bench import Bench, load_bench
from lensforge.optics.lens import load_lens, paper_lens
from lensforge.optics.pose import pose_to_matrix
from lensforge.input_checks import BENCH_RANGES, check_ranges, flatten

settings.load_profile(PROFILE)

BENCH_DOC = Bench.default().to_dict()
TOL_DOC = load_tolerances(DEFAULT_TOLERANCES_FILE).to_dict()
DESIGN_DOC = {"schema_version": 1, "kind": "lensforge.design", "model": "zernike", "free": [], "parameters": {},
              "bounds": {}, "lens": paper_lens("zernike").to_dict(), "bench": BENCH_DOC, "weights": [1.0, 1.0],
              "seed": 0, "n_evals": 0, "wall_time_s": 0.0}


def _poses_doc(n=6):
    rng = np.random.default_rng(0)
    A = [pose_to_matrix(np.r_[rng.normal(0, 50, 3), rng.normal(0, 0.3, 3)]).tolist() for _ in range(n)]
    B = [pose_to_matrix(np.r_[rng.normal(0, 1, 3), rng.normal(0, 0.01, 3)]).tolist() for _ in range(n)]
    return {"units": "mm", "A": A, "B": B, "sigma_B": {"translation_mm": 0.01, "rotation_rad": 1e-4}}


POSES_DOC = _poses_doc()
HOW = st.sampled_from(["none", "truncate", "bom", "garbage", "nul"])


def _read(reader, path):
    """The reader's result, or None after checking its error is one clean line."""
    try:
        return reader(path)
    except LensforgeError as e:
        assert_one_line_error(e)
        return None


def _write(tmp_path, name, data: bytes):
    p = tmp_path / name
    p.write_bytes(data)
    return p


def _toml_bytes(doc) -> bytes | None:
    try:
        return tomli_w.dumps(doc).encode()
    except (TypeError, ValueError):  # None or a mixed list: not expressible in TOML
        return None


@given(path=st.sampled_from(leaf_paths(BENCH_DOC)), value=hostile_values, how=HOW, where=st.floats(0, 1))
def test_bench_reader(tmp_path_factory, path, value, how, where):
    data = _toml_bytes(mutate(BENCH_DOC, path, value))
    if data is None:
        return
    p = _write(tmp_path_factory.mktemp("b"), "bench.toml", corrupt(data, how, where))
    b = _read(load_bench, p)
    if b is not None:  # accepted: every number is inside its physical range
        check_ranges(b.to_dict(), BENCH_RANGES, "")


@given(path=st.sampled_from(leaf_paths(TOL_DOC)), value=hostile_values, how=HOW, where=st.floats(0, 1))
def test_tolerance_reader(tmp_path_factory, path, value, how, where):
    data = _toml_bytes(mutate(TOL_DOC, path, value))
    if data is None:
        return
    p = _write(tmp_path_factory.mktemp("t"), "tol.toml", corrupt(data, how, where))
    t = _read(load_tolerances, p)
    if t is not None:
        d = t.to_dict()
        check_ranges(d, TOLERANCE_RANGES, "")
        assert all(isinstance(v, (int, float, str, list)) for v in flatten(d).values())


@given(path=st.sampled_from(leaf_paths(DESIGN_DOC)), value=hostile_values, how=HOW, where=st.floats(0, 1))
def test_design_readers(tmp_path_factory, path, value, how, where):
    doc = mutate(DESIGN_DOC, path, value)
    data = json.dumps(doc).encode()
    p = _write(tmp_path_factory.mktemp("d"), "design.json", corrupt(data, how, where))
    for reader in (load_design, load_lens):
        r = _read(reader, p)
        if r is not None:
            assert doc.get("schema_version") == 1 and type(doc["schema_version"]) is int
            assert doc.get("kind") == "lensforge.design"


@given(path=st.sampled_from(leaf_paths(POSES_DOC)), value=hostile_values, how=HOW, where=st.floats(0, 1))
def test_poses_reader(tmp_path_factory, path, value, how, where):
    doc = mutate(POSES_DOC, path, value)
    p = _write(tmp_path_factory.mktemp("p"), "poses.json", corrupt(json.dumps(doc).encode(), how, where))
    r = _read(load_poses, p)
    if r is not None:
        for key in ("A", "B"):
            assert np.isfinite(r[key]).all() and np.abs(r[key]).max() <= 1e5


@given(data=st.binary(max_size=200))
def test_garbage_files(tmp_path_factory, data):
    d = tmp_path_factory.mktemp("g")
    for reader, name in ((load_bench, "x.toml"), (load_tolerances, "x.toml"), (load_design, "x.json"),
                         (load_lens, "x.json"), (load_poses, "x.json")):
        _read(reader, _write(d, name, data))


# --- the named cases of the first campaign -----------------------------------------

@pytest.mark.parametrize("text, match", [
    ("[noise]\nslope_sigma_urad = 0\n", "noise.slope_sigma_urad: must be > 0"),
    ("[sensor]\npitch_mm = 1e-6\n", "sensor.pitch_mm"),
    ("[sensor]\naperture_mm = 1e6\n", "sensor.aperture_mm"),
    ("[sensor]\npitch_mm = 0.01\naperture_mm = 100\n", "lenslets, over the limit"),
    ("[noise]\nslope_sigma_urad = 1" + "0" * 400 + "\n", "slope_sigma_urad"),
    ("schema_version = 2\n", "schema_version must be the integer 1"),
    ("kind = \"lensforge.design\"\n", "kind must be 'lensforge.bench'"),
])
def test_bench_nonsense_refused(tmp_path, text, match):
    p = tmp_path / "b.toml"
    p.write_text(text)
    with pytest.raises(LensforgeError, match=match) as e:
        load_bench(p)
    assert "b.toml" in str(e.value)


def test_bom_accepted(tmp_path):
    p = tmp_path / "b.toml"
    p.write_bytes(b"\xef\xbb\xbf[noise]\nslope_sigma_urad = 4.0\n")
    assert load_bench(p).noise.slope_sigma_urad == 4.0
    q = tmp_path / "d.json"
    q.write_bytes(b"\xef\xbb\xbf" + json.dumps(DESIGN_DOC).encode())
    assert load_lens(q)[0].thickness == paper_lens("zernike").thickness


@pytest.mark.parametrize("text, match", [
    ("[thickness]\nsigma_mm = 50\n", r"thickness.sigma_mm: must be >= 0 and <= 1 mm, got 50; check the unit \(mm\)"),
    ("[polishing]\ndepth_mm = 25\n", "polishing.depth_mm: must be >= 0 and <= 1 mm"),
    ("[form]\nrms_mm = 1e308\n", "form.rms_mm"),
    ("[index]\nsigma = \"0.001\"\n", "expected a number, got str"),
    ("schema_version = 1.0\n", "schema_version must be the integer 1"),
])
def test_tolerance_nonsense_refused(tmp_path, text, match):
    p = tmp_path / "t.toml"
    p.write_text(text)
    with pytest.raises(LensforgeError, match=match):
        load_tolerances(p)


def test_zero_tolerances_and_version_one_files_stay_valid(tmp_path):
    p = tmp_path / "t.toml"
    p.write_text("schema_version = 1\n" + "".join(
        f"[{t}]\n" + "".join(f"{k} = 0.0\n" for k in keys) for t, keys in
        {"polishing": ("depth_mm", "depth_sigma_mm", "rolloff_mm", "rolloff_sigma_mm"), "form": ("rms_mm",),
         "thickness": ("mean_mm", "sigma_mm"), "index": ("mean", "sigma", "batch_sigma"),
         "shrinkage": ("mean", "sigma"), "ripple": ("amplitude_mm",)}.items()))
    t = load_tolerances(p)
    assert t.form_rms_mm == 0.0 and t.thickness_sigma_mm == 0.0
    assert load_tolerances(DEFAULT_TOLERANCES_FILE).thickness_sigma_mm == 0.05


@pytest.mark.parametrize("change, match", [
    ({"schema_version": 2}, "schema_version must be the integer 1, got int 2"),
    ({"schema_version": 0}, "schema_version must be the integer 1"),
    ({"schema_version": "1"}, "got str '1'"),
    ({"schema_version": None}, "schema_version must be the integer 1"),
    ({"kind": "lensforge.tolerances"}, "kind must be 'lensforge.design'"),
])
def test_design_header_checked_by_every_reader(tmp_path, change, match):
    p = tmp_path / "d.json"
    doc = {**DESIGN_DOC, **change}
    if change.get("schema_version", 1) is None:
        del doc["schema_version"]
        match = "schema_version must be the integer 1, missing"
    p.write_text(json.dumps(doc))
    for reader in (load_design, load_lens):
        with pytest.raises(LensforgeError, match=match):
            reader(p)


def test_design_without_lens_key_says_so(tmp_path):
    p = tmp_path / "d.json"
    p.write_text(json.dumps({k: v for k, v in DESIGN_DOC.items() if k != "lens"}))
    with pytest.raises(LensforgeError, match='no "lens" key') as e:
        load_lens(p)
    assert "unknown key" not in str(e.value)


@pytest.mark.parametrize("entry, match", [("1.0", "expected a number, got str '1.0'"),
                                          (1e300, r"must be >= -100000 and <= 100000 mm, got 1e\+300"),
                                          (True, "expected a number, got bool")])
def test_pose_entries_strict(tmp_path, entry, match):
    doc = mutate(POSES_DOC, ("A", 2, 0, 3), entry)
    p = tmp_path / "poses.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(LensforgeError, match=match) as e:
        load_poses(p)
    assert "nan" not in str(e.value).lower()
    assert "A[2][0][3]" in str(e.value)


def test_outlier_is_not_called_degenerate_motion():
    from lensforge.calibration.handeye import solve_handeye

    rng = np.random.default_rng(3)
    X = pose_to_matrix(np.r_[1.0, 2.0, 30.0, 0.1, 0.0, 0.2])
    Z = pose_to_matrix(np.r_[500.0, 10.0, 300.0, 0.0, 0.3, 0.0])
    A = np.stack([pose_to_matrix(np.r_[rng.normal(0, 100, 3), rng.normal(0, 0.5, 3)]) for _ in range(10)])
    B = np.stack([np.linalg.inv(Z) @ a @ X for a in A])
    A[:, :3, 3] += rng.normal(0, 0.01, (10, 3))
    A[4, 0, 3] += 5.0  # one 5 mm outlier in 10 well-spread poses
    with pytest.warns(RuntimeWarning) as w:
        r = solve_handeye(A, B, "ml")
    text = " ".join(str(x.message) for x in w) + " ".join(r.warnings)
    assert "degenerate motion" not in text and "Add poses with rotations" not in text
