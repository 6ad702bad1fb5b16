"""SDK spot fields: the reader, the slope measurement model, the likelihood on the
slopes against the one on the 14-mode fit, and user-reference measurements."""

import numpy as np
import pytest

from lensforge.calibration import thorlabs
from lensforge.calibration.formats import read_wfs, write_bundle
from lensforge.calibration.joint import chain_jacobians, joint_information
from lensforge.calibration.measurement import (Measurement, joint_crlb, measurement, referenced_information,
                                               slope_inputs, _jacobians)
from lensforge.calibration.session import calibrate, match_session, plan
from lensforge.calibration.session_joint import resolve_tolerances
from lensforge.asbuilt.lens_params import parameterise
from lensforge.errors import ConfigError
from lensforge.optics.bench import Bench
from lensforge.optics.lens import paper_lens
from lensforge.optics.pose import invert_poses, matrix_to_pose
from lensforge.optics.shack_hartmann import ForwardModel
from lensforge.verification.session_sim import simulate_session

LENS = "extended_polynomial"
MLA = {"focal_length_um": 5200.0, "lenslet_pitch_um": 150.0, "pixel_pitch_um": 5.5, "center_offset_mm": (0.0, 0.0)}


def _field(rng, ny=9, nx=11):
    d = rng.normal(0.0, 0.5, (ny, nx, 2))
    d[0, 0] = np.nan
    return d


@pytest.mark.parametrize("fmt", ["npz", "csv"])
def test_spot_field_round_trip_pixels_to_slopes(tmp_path, fmt):
    rng = np.random.default_rng(0)
    d = _field(rng)
    head = {"wavelength_nm": 532.0, "pupil_radius_mm": 0.9}
    data = (thorlabs.spot_field_npz(d, header=head, **MLA) if fmt == "npz"
            else thorlabs.spot_field_csv(d, header=head, **MLA).replace("\n", "\r\n").encode("cp1252"))
    p = tmp_path / f"pose_4.{fmt}"
    p.write_bytes(data)
    r = thorlabs.read_spot_field(p)
    k = 5.5 / 5200.0  # rad per pixel: pixel pitch / lenslet focal length
    np.testing.assert_allclose(r["slopes"], d * k, rtol=1e-15, equal_nan=True)
    assert np.isnan(r["slopes"][0, 0]).all()
    # [Y][X]: row iy is y, column ix is x, centred grid at the offset
    assert r["centres"][0, 0].tolist() == pytest.approx([-5 * 0.15, -4 * 0.15])
    assert r["centres"][8, 10].tolist() == pytest.approx([5 * 0.15, 4 * 0.15])
    assert r["header"] == head


def test_spot_field_errors(tmp_path):
    rng = np.random.default_rng(1)
    p = tmp_path / "pose_1.csv"
    text = thorlabs.spot_field_csv(_field(rng), **MLA)
    p.write_text(text.replace("# focal_length_um: 5200.0\n", ""))
    with pytest.raises(ConfigError, match="field focal_length_um: missing; save the MLA data of WFS_GetMlaData"):
        thorlabs.read_spot_field(p)
    p.write_text(text.replace("0,0,", "0;0;", 1).replace(",", ";"))
    thorlabs.read_spot_field(p)  # semicolons are a separator
    semi = [ln if ln.startswith("#") else ln.replace(",", ";").replace(".", ",") for ln in text.split("\n")]
    p.write_text("\n".join(semi))  # a German-locale export: ';' separators, decimal commas
    with pytest.raises(ConfigError, match="comma as decimal separator"):
        thorlabs.read_spot_field(p)
    # tilt cancelled: every pose's mean deviation is zero
    for i in range(3):
        d = _field(np.random.default_rng(i))
        d -= np.nanmean(d.reshape(-1, 2), axis=0)
        (tmp_path / f"f_{i}.npz").write_bytes(thorlabs.spot_field_npz(d, **MLA))
    with pytest.raises(ConfigError, match="mean spot deviations .* tilt cancel ON"):
        read_wfs(str(tmp_path / "f_*.npz"))


def test_slope_model_is_the_fit_s_input_exactly():
    """z = F s: the slope model's values and exact Jacobian map through the fit matrix to
    the Zernike model's, for every pose and lens direction (no difference anywhere)."""
    bench = Bench.default()
    fm = ForwardModel(bench, paper_lens(LENS))
    sm = measurement("slopes").model(fm)
    x = np.array([[0.1, -0.2, 0.05, 0.01, -0.02, 0.03], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    Jz, _, rz = fm.jacobians(x)
    Js, _, rs = sm.jacobians(x)
    F = fm.pupil.F
    np.testing.assert_allclose(rs.z @ F.T, rz.z, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.einsum("ij,pjk->pik", F, Js), Jz, rtol=1e-10, atol=1e-12 * np.abs(Jz).max())
    sigma = bench.noise.slope_sigma_urad * 1e-6
    np.testing.assert_allclose(sm.noise_cov, sigma**2 * np.eye(2 * fm.pupil.n_lenslets), rtol=1e-15)
    assert np.array_equal(rs.valid, rz.valid)


def test_missing_spots_drop_their_lenslet_from_every_pose(tmp_path):
    bench = Bench.default()
    fm = ForwardModel(bench, paper_lens(LENS))
    n_side = int(np.floor(bench.sensor.aperture_mm / bench.sensor.pitch_mm + 1e-9))
    rng = np.random.default_rng(5)
    for i in range(3):
        d = rng.normal(0, 1.0, (n_side, n_side, 2))
        if i == 1:
            d[37, 37] = np.nan  # the centre lenslet (pupil centre) lost in one pose
        (tmp_path / f"pose_{i}.npz").write_bytes(thorlabs.spot_field_npz(d, **MLA))
    f = read_wfs(tmp_path)
    meas, y, warns = slope_inputs(f, fm)
    n = fm.pupil.n_lenslets
    assert len(meas.dropped) == 1 and y.shape == (3, 2 * (n - 1)) and "left out of every pose" in warns[0]
    c = fm.pupil.centres[meas.dropped[0]]
    assert np.abs(c).max() < 1e-12
    sm = meas.model(fm)
    assert sm.evaluate(np.zeros(6)).z.shape == (1, 2 * (n - 1))
    bad = dict(MLA, lenslet_pitch_um=100.0)
    (tmp_path / "pose_0.npz").write_bytes(thorlabs.spot_field_npz(rng.normal(0, 1, (n_side, n_side, 2)), **bad))
    with pytest.raises(ConfigError, match="lenslet grid differs|lenslet_pitch_um"):
        read_wfs(tmp_path)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    p = plan(LENS, n=8, seed=0)
    s = simulate_session(LENS, tolerances=None, seed=3, session_plan=p)
    folder = tmp_path_factory.mktemp("sess")
    paths = write_bundle(folder, s.files(instrument=True))
    return p, s, folder, paths


def test_spot_fields_give_the_zernike_z_within_the_crlb_ratio(session):
    """The same simulated session (the spot fields hold the slopes the Zernikes were fitted
    from): Z from the slopes' likelihood is at least as precise, and differs from the
    Zernike Z by what the extra information allows (the difference of two efficient
    estimators of nested data has covariance cov_Zernike - cov_slopes)."""
    p, s, folder, paths = session
    r_z = calibrate(LENS, paths["wfs_zernike.csv"], paths["robot_poses.csv"], robot=p.robot)
    r_s = calibrate(LENS, folder / "spot_fields", paths["robot_poses.csv"], robot=p.robot)
    assert r_s.method == r_z.method == "joint" and r_s.poses_used == r_z.poses_used
    sz, ss = np.sqrt(np.diag(r_z.handeye.cov_Z)), np.sqrt(np.diag(r_s.handeye.cov_Z))
    # (at the two estimates; the same-point bound is exact, test_referenced_information_and_fit)
    assert np.all(ss <= sz * (1 + 1e-3))
    d = matrix_to_pose(invert_poses(r_z.Z) @ r_s.Z)
    extra = np.sqrt(np.clip(sz**2 - ss**2, 0, None))
    assert np.all(np.abs(d) <= 4 * extra + 0.05 * sz), (d, extra, sz)
    # both near the truth (3 sigma per axis)
    e = matrix_to_pose(invert_poses(s.Z) @ r_s.Z)
    assert np.all(np.abs(e) <= 3 * ss)
    assert 0.5 < r_s.chi2_dof < 1.5


def test_referenced_information_and_fit(session):
    """Absolute information equals the joint module's; referencing to one pose costs
    information (never gains); the referenced fit on referenced data finds Z within 3 sigma."""
    p, s, folder, paths = session
    lens = paper_lens(LENS)
    bench = Bench.default()
    tol, _ = resolve_tolerances("default")
    param = parameterise(bench, lens, tol, p.x)
    S, Jt, dX, dZ, dA = _jacobians(bench, param, p.scene, p.x, p.robot.noise.cov, None)
    B = p.scene.T_SO_nominal @ __import__("lensforge.optics.pose", fromlist=["pose_to_matrix"]).pose_to_matrix(p.x)
    I_joint = joint_information(S, B, p.x, p.scene.X, Jt, p.robot.noise.cov)
    I_abs = referenced_information(S, Jt, dX, dZ, dA, p.robot.noise.cov, None)
    np.testing.assert_allclose(I_abs, I_joint, rtol=1e-8, atol=1e-8 * np.abs(I_joint).max())
    I_ref = referenced_information(S, Jt, dX, dZ, dA, p.robot.noise.cov, 0)
    ev = np.linalg.eigvalsh(I_abs - I_ref)
    assert ev.min() > -1e-8 * ev.max()
    c = joint_crlb(bench, param, p.scene, p.x, p.robot.noise.cov, reference=0)
    assert set(c) == {"zernike", "zernike_referenced", "slopes", "slopes_referenced"}
    for k in ("zernike", "slopes"):
        assert c[f"{k}_referenced"]["Z_translation_mm"] >= c[k]["Z_translation_mm"]
    assert c["slopes"]["Z_translation_mm"] <= c["zernike"]["Z_translation_mm"] * (1 + 1e-9)
    # referenced data: every pose relative to pose 0's measurement (both noisy)
    from lensforge.calibration.formats import WfsData

    y = s.zernike_thorlabs - s.zernike_thorlabs[0]
    wfs = WfsData(s.wfs_ids, y, 4, s.header, "ref.csv")
    r = calibrate(LENS, wfs, paths["robot_poses.csv"], robot=p.robot, reference_pose=s.wfs_ids[0])
    assert r.method == "joint-referenced" and r.extra["reference_pose"] == s.wfs_ids[0]
    e = matrix_to_pose(invert_poses(s.Z) @ r.Z)
    sig = np.sqrt(np.diag(r.handeye.cov_Z))
    assert np.all(np.abs(e) <= 3 * sig), (e, sig)
    assert r.dof == (len(s.wfs_ids) - 1) * 14 - 12 and 0.5 < r.chi2_dof < 1.6
    # the reference pose without its own file: a zero row is implied
    wfs2 = WfsData(s.wfs_ids[1:], y[1:], 4, {**s.header, "reference_pose": s.wfs_ids[0]}, "ref.csv")
    r2 = calibrate(LENS, wfs2, paths["robot_poses.csv"], robot=p.robot)
    np.testing.assert_allclose(r2.Z, r.Z, rtol=0, atol=1e-6)
    with pytest.raises(ConfigError, match="reference pose '99' has no robot pose"):
        match_session(LENS, wfs, paths["robot_poses.csv"], robot=p.robot, reference_pose="99")


def test_referenced_spot_fields_calibrate(session):
    """Spot fields relative to a user reference at pose 1 (the reference named in the
    fields): the referenced slope fit finds Z within 3 sigma and writes the whole bundle."""
    from dataclasses import replace

    p, s, folder, paths = session
    f = read_wfs(folder / "spot_fields")
    k = f.ids.index("1")
    ref = replace(f, slopes=f.slopes - f.slopes[k], header={**f.header, "reference_pose": "1"})
    r = calibrate(LENS, ref, paths["robot_poses.csv"], robot=p.robot)
    assert r.method == "joint-referenced" and r.extra["measurement"] == "slopes"
    e = matrix_to_pose(invert_poses(s.Z) @ r.Z)
    assert np.all(np.abs(e) <= 3 * np.sqrt(np.diag(r.handeye.cov_Z)))
    assert 0.8 < r.chi2_dof < 1.2  # ~1570 DOF
    assert "lensforge_calibration.launch.py" in r.files()
