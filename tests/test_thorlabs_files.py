"""Thorlabs WFS software exports: the reader against files in that layout, awkward ones
included, and the same session through the row-per-pose CSV and a folder of exports."""

import numpy as np
import pytest

from lensforge.calibration import thorlabs
from lensforge.calibration.formats import read_wfs, write_bundle
from lensforge.calibration.session import calibrate, match_session, plan
from lensforge.errors import ConfigError
from lensforge.optics.bench import Bench
from lensforge.verification.session_sim import simulate_session

LENS = "extended_polynomial"  # a paper freeform lens: rank 6, fast to trace
HEADER = {"wavelength_nm": 532.0, "pupil_center_mm": (0.0, 0.0), "pupil_radius_mm": 0.9}


def _z(seed=0, K=15):
    z = np.random.default_rng(seed).normal(0, 0.3, K)
    z[0] = 0.0
    return z


def _export(z=None, header=HEADER, **kw) -> str:
    return thorlabs.export_text(_z() if z is None else z, header, **kw).decode("cp1252")


def test_export_round_trip_takes_modes_by_order_and_frequency(tmp_path):
    z = _z(1)
    text = _export(z)
    lines = text.split("\r\n")
    i0 = lines.index("Index,Order,Frequency,Coefficient [µm]") + 1
    rows = lines[i0:i0 + 15]
    # shuffle the mode rows and renumber their Index column: the reader must use (n, m)
    perm = np.random.default_rng(2).permutation(15)
    shuffled = [",".join([str(k + 1)] + rows[p].split(",")[1:]) for k, p in enumerate(perm)]
    lines[i0:i0 + 15] = shuffled
    p = tmp_path / "pose_3.csv"
    p.write_bytes("\r\n".join(lines).encode("cp1252"))
    r = thorlabs.read_export(p)
    assert r["order"] == 4
    np.testing.assert_allclose(r["thorlabs"], z, rtol=0, atol=0)
    assert r["header"]["wavelength_nm"] == 532.0
    assert r["header"]["pupil_radius_mm"] == pytest.approx(0.9, abs=1e-12)
    assert r["header"]["pupil_center_mm"] == (0.0, 0.0)


@pytest.mark.parametrize("encoding,eol", [("cp1252", "\r\n"), ("latin-1", "\r\n"), ("utf-8", "\n"), ("utf-8-sig", "\r\n")])
def test_encodings_and_line_ends(tmp_path, encoding, eol):
    z = _z(3)
    text = _export(z).replace("\r\n", eol)
    p = tmp_path / "m_12.txt"
    p.write_bytes(text.encode(encoding))
    np.testing.assert_allclose(thorlabs.read_export(p)["thorlabs"], z, rtol=0, atol=0)


def test_unknown_sections_and_lines_are_skipped_missing_optional_ones_too(tmp_path):
    z = _z(4)
    text = _export(z)
    text = text.replace("*** BEAM ***", "*** SOMETHING NEW ***\r\nfoo;bar;baz\r\nrandom text line\r\n*** BEAM ***")
    text = text.replace("*** PUPIL ***", "Operator notes: lens #3, 21 °C\r\n*** PUPIL ***")
    p = tmp_path / "a_1.csv"
    p.write_bytes(text.encode("cp1252"))
    np.testing.assert_allclose(thorlabs.read_export(p)["thorlabs"], z, atol=0)
    # no pupil section, no wavelength: the reader gives what is there, the bench the rest
    lines = [ln for ln in _export(z).split("\r\n") if "Wavelength" not in ln]
    s = "\r\n".join(lines)
    a, b = s.index("*** PUPIL ***"), s.index("*** BEAM ***")
    p.write_bytes((s[:a] + s[b:]).encode("cp1252"))
    r = thorlabs.read_export(p)
    assert r["header"] == {"reference": "internal", "tilt_cancelled": False}


def test_missing_zernike_section_and_missing_modes_are_errors(tmp_path):
    p = tmp_path / "p_1.csv"
    s = _export()
    p.write_bytes(s[:s.index("*** ZERNIKE FIT ***")].encode("cp1252"))
    with pytest.raises(ConfigError, match=r"p_1.csv: no '\*\*\* ZERNIKE FIT \*\*\*' section"):
        thorlabs.read_export(p)
    p.write_bytes("\r\n".join(ln for ln in s.split("\r\n") if not ln.startswith("4,2,-2,")).encode("cp1252"))
    with pytest.raises(ConfigError, match="modes .*missing below the fit order 4"):
        thorlabs.read_export(p)


def test_comma_decimals_are_refused_clearly(tmp_path):
    s = _export(np.r_[0.0, 0.125, -0.25, np.zeros(12)])
    p = tmp_path / "p_1.csv"
    # semicolon-separated with decimal commas (a German Windows export)
    lines = s.split("\r\n")
    i0 = lines.index("Index,Order,Frequency,Coefficient [µm]")
    for i in range(i0, i0 + 16):
        f = lines[i].split(",")
        lines[i] = ";".join(f[:3] + [f[3].replace(".", ",")])
    p.write_bytes("\r\n".join(lines).encode("cp1252"))
    with pytest.raises(ConfigError, match="comma as decimal separator.*Decimal symbol"):
        thorlabs.read_export(p)
    # comma-separated with decimal commas: one field too many
    p.write_bytes(s.replace(",0.125", ",0,125").encode("cp1252"))
    with pytest.raises(ConfigError, match="comma as decimal separator"):
        thorlabs.read_export(p)


def test_pose_ids_from_file_names():
    assert thorlabs.pose_id_from_name("pose_07.csv") == "7"
    assert thorlabs.pose_id_from_name("2024-05-01_run3_pose12.txt") == "12"
    assert thorlabs.pose_id_from_name("run3_pose12_x.csv", r"run(\d+)") == "3"
    assert thorlabs.pose_id_from_name("P-A.csv", r"P-(\w)") == "A"
    with pytest.raises(ConfigError, match="no pose id in the file name"):
        thorlabs.pose_id_from_name("pose.csv")
    with pytest.raises(ConfigError, match="not a regular expression"):
        thorlabs.pose_id_from_name("pose_1.csv", "(")


def test_folder_and_glob_read_as_one_table(tmp_path):
    zs = [_z(s) for s in range(3)]
    for i, z in zip((3, 1, 12), zs):
        (tmp_path / f"pose_{i:02d}.csv").write_bytes(thorlabs.export_text(z, HEADER))
    (tmp_path / "notes.md").write_text("not a measurement")
    w = read_wfs(tmp_path)
    assert w.ids == ("1", "3", "12")  # sorted by file name (zero-padded)
    np.testing.assert_allclose(w.zernike[w.ids.index("12")], zs[2], atol=0)
    g = read_wfs(str(tmp_path / "pose_0*.csv"))
    assert g.ids == ("1", "3")
    (tmp_path / "pose_3.csv").write_bytes(thorlabs.export_text(zs[0], HEADER))
    with pytest.raises(ConfigError, match="pose id 3 also in"):
        read_wfs(tmp_path)
    with pytest.raises(ConfigError, match="matches no file"):
        read_wfs(str(tmp_path / "nothing_*.csv"))


def test_tilt_cancelled_files_are_detected(tmp_path):
    for i in range(3):
        z = _z(i)
        z[1:3] = 0.0  # Thorlabs modes 2, 3: the tilts
        (tmp_path / f"pose_{i}.csv").write_bytes(thorlabs.export_text(z, HEADER))
    with pytest.raises(ConfigError, match="tilt cancel ON; switch it OFF.*cancelWavefrontTilt=0"):
        read_wfs(tmp_path)


def test_tilt_cancelled_row_per_pose_csv_is_detected(tmp_path):
    from lensforge.calibration.formats import wfs_csv

    z = np.array([_z(i) for i in range(3)])
    z[:, 1:3] = 0.0
    (tmp_path / "w.csv").write_text(wfs_csv(["1", "2", "3"], z))
    with pytest.raises(ConfigError, match="w.csv: Zernike tilt modes Z2, Z3 are zero in every pose.*OFF"):
        read_wfs(tmp_path / "w.csv")


def test_header_against_bench_names_both_values(tmp_path):
    from lensforge.calibration.plausibility import check_wfs_header

    bench = Bench.default()
    h = {**HEADER, "instrument_file": "thorlabs_export"}
    for mode in ("error", "file"):  # an instrument file is checked in both modes
        check_wfs_header(bench, h, "f", mode)
        with pytest.raises(ConfigError, match=r"633 nm contradicts the bench's laser.wavelength_nm = 532 nm"):
            check_wfs_header(bench, {**h, "wavelength_nm": 633.0}, "f", mode)
        with pytest.raises(ConfigError, match=r"the file's 1 mm contradicts the bench's sensor.pupil_radius_mm = 0.9 mm "
                                              r"\(diameter 2 against 1.8 mm\)"):
            check_wfs_header(bench, {**h, "pupil_radius_mm": 1.0}, "f", mode)
        with pytest.raises(ConfigError, match=r"\(0.1, 0\) mm contradicts the bench's sensor.pupil_center_mm = \(0, 0\)"):
            check_wfs_header(bench, {**h, "pupil_center_mm": (0.1, 0.0)}, "f", mode)
    # within the software's printed precision: accepted; the bench's values chosen: not checked
    check_wfs_header(bench, {**h, "wavelength_nm": 532.2, "pupil_radius_mm": 0.9004}, "f")
    assert check_wfs_header(bench, {**h, "wavelength_nm": 633.0}, "f", "bench") == {}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    p = plan(LENS, n=8, seed=0)
    s = simulate_session(LENS, tolerances=None, seed=3, session_plan=p)
    folder = tmp_path_factory.mktemp("sess")
    paths = write_bundle(folder, s.files(instrument=True))
    return p, s, folder, paths


def test_a_contradicting_export_stops_the_calibration(session, tmp_path):
    p, s, folder, _ = session
    for f in (folder / "thorlabs").iterdir():
        (tmp_path / f.name).write_bytes(f.read_bytes().replace(b"Wavelength [nm]: 532.000", b"Wavelength [nm]: 633.000"))
    with pytest.raises(ConfigError, match="633 nm.* laser.wavelength_nm (= |is )532 nm"):  # both values named
        match_session(LENS, tmp_path, folder / "robot_poses.csv", robot=p.robot)


def test_integer_ids_match_as_integers(session, tmp_path):
    p, s, folder, _ = session
    text = (folder / "robot_poses.csv").read_text().split("\n")
    text = [ln if (not ln or ln[0] in "#p") else "0" + ln for ln in text]  # ids 01, 02, ...
    (tmp_path / "robot.csv").write_text("\n".join(text))
    d = match_session(LENS, folder / "thorlabs", tmp_path / "robot.csv", robot=p.robot)
    assert len(d.ids) == len(s.wfs_ids) and not d.rejected


def test_same_session_same_x_and_z_through_csv_and_export_folder(session):
    """The row-per-pose CSV and the folder of Thorlabs-layout exports hold the same
    numbers: the joint calibration gives the same X and Z to 1e-6."""
    p, s, folder, paths = session
    r_csv = calibrate(LENS, paths["wfs_zernike.csv"], paths["robot_poses.csv"], robot=p.robot)
    r_th = calibrate(LENS, folder / "thorlabs", paths["robot_poses.csv"], robot=p.robot)
    r_glob = calibrate(LENS, str(folder / "thorlabs" / "pose_*.csv"), paths["robot_poses.csv"], robot=p.robot,
                       method="two-stage")
    assert r_csv.method == r_th.method == "joint"
    assert r_csv.poses_used == r_th.poses_used
    for a, b in ((r_csv.Z, r_th.Z), (r_csv.X, r_th.X)):
        np.testing.assert_allclose(a[:3, :3], b[:3, :3], rtol=0, atol=1e-6)
        np.testing.assert_allclose(a[:3, 3], b[:3, 3], rtol=0, atol=1e-6)  # mm
    r_two = calibrate(LENS, paths["wfs_zernike.csv"], paths["robot_poses.csv"], robot=p.robot, method="two-stage")
    np.testing.assert_allclose(r_glob.Z, r_two.Z, rtol=0, atol=1e-6)


def test_cli_calibrates_a_renamed_export_folder_with_a_pose_pattern(session, tmp_path, monkeypatch, capsys):
    """`calibrate --measurements FOLDER --pose-pattern` on exports named by another scheme;
    the bundle holds the ROS 2 launch file; a contradiction is one error line, exit 2."""
    import json

    from conftest import run_cli_inprocess

    p, s, folder, paths = session
    src = tmp_path / "wfs"
    src.mkdir()
    for f in (folder / "thorlabs").iterdir():
        i = int(f.stem.split("_")[1])
        (src / f"P{i}_2026-12-01_13.csv").write_bytes(f.read_bytes())  # last integer is not the id
    code, out, err = run_cli_inprocess(monkeypatch, capsys, "calibrate", LENS, "--measurements", src,
                                       "--robot-poses", paths["robot_poses.csv"], "--pose-pattern", r"P(\d+)_",
                                       "--method", "two-stage", "-o", tmp_path / "out", "--json")
    assert code == 0, err
    d = json.loads(out)
    assert len(d["poses_used"]) == len(s.wfs_ids)
    launch = (tmp_path / "out" / "lensforge_calibration.launch.py").read_text()
    assert "static_transform_publisher" in launch and "wfs_sensor" in launch
    code, out, err = run_cli_inprocess(monkeypatch, capsys, "calibrate", LENS, "--measurements", src,
                                       "--robot-poses", paths["robot_poses.csv"], "-o", tmp_path / "out2")
    assert code == 2 and err.strip().splitlines()[-1].startswith("error: ") and "pose id 13 also in" in err


def test_user_reference_is_read_from_the_export_header(tmp_path):
    for i in range(3):
        text = _export(_z(i)).replace("Reference: internal", "Reference: user\r\nReference pose: 02")
        (tmp_path / f"pose_{i + 1}.csv").write_bytes(text.encode("cp1252"))
    w = read_wfs(tmp_path)
    assert w.header["reference"] == "user" and w.header["reference_pose"] == "02"
    from lensforge.calibration.formats import PoseTable
    from lensforge.calibration.measurement import canonical_ids

    poses = PoseTable(("1", "2", "3", "4"), np.tile(np.eye(4), (4, 1, 1)), "robot.csv")
    _, w2, ref = canonical_ids(poses, w)
    assert ref == "2" and w2.ids == w.ids  # the reference pose has its own (zero) file here


def test_simulate_session_cli_writes_the_instrument_folders(tmp_path, monkeypatch, capsys):
    from conftest import run_cli_inprocess

    code, out, err = run_cli_inprocess(monkeypatch, capsys, "simulate-session", LENS, "-t", "none", "-n", "6",
                                       "--instrument-files", "-o", tmp_path / "s")
    assert code == 0, err
    w = read_wfs(tmp_path / "s" / "wfs_zernike.csv")
    t = read_wfs(tmp_path / "s" / "thorlabs")
    f = read_wfs(tmp_path / "s" / "spot_fields")
    assert t.ids == w.ids == f.ids
    np.testing.assert_array_equal(t.zernike, w.zernike)  # repr round trip: the same numbers
    assert f.slopes.shape[0] == len(w.ids) and np.isfinite(f.slopes).sum() > 0
    # the spot fields are the slopes the Zernikes were fitted from (the same noise draw)
    from lensforge.calibration.measurement import slope_inputs
    from lensforge.calibration.session import zernike_for_model
    from lensforge.optics.lens import paper_lens
    from lensforge.optics.shack_hartmann import ForwardModel

    fm = ForwardModel(Bench.default(), paper_lens(LENS))
    meas, y, warns = slope_inputs(f, fm)
    assert not warns and meas.dropped == ()
    zc = zernike_for_model(w.zernike, fm)
    np.testing.assert_allclose(y @ fm.pupil.F.T, zc, rtol=0, atol=1e-12 * np.abs(zc).max())
