"""The full-array physical reference model of the sensor (verification/physical_sensor.py, issue 21)."""

from pathlib import Path

import numpy as np
import pytest

import lensforge as lf
from lensforge.errors import ConfigError
from lensforge.optics.shack_hartmann import ForwardModel, lenslet_pupil
from lensforge.verification.physical_sensor import PhysicalSensor, field_slopes, physical_measure, plane_field, ray_field

# coarse field samples (2 per pixel) keep these tests to seconds; the modes move by up to ~3 sigma
# from 2 to 4 samples per pixel (the default), which the checks below do not resolve
FAST = PhysicalSensor(samples_per_pixel=2)


def _noise_sigma(bench):
    pup = lenslet_pupil(bench.sensor)
    return pup, bench.noise.slope_sigma_urad * 1e-6 * np.sqrt(np.diag(pup.F @ pup.F.T))


def test_plane_wave_of_known_tilt_lands_at_f_tan(bench):
    # a uniform plane wave of slope t (tan) against the factory reference: every lenslet reports t.
    # An ideal paraxial thin lenslet maps a tilt to f tan(theta) only to first order in its
    # aperture: the mean error is ~3 t <u^2> / 2 f^2 (u over the pitch: 1.1e-4 t); cross-talk and
    # whole-pixel window placement add a spread of a few urad (slope noise: 8 urad)
    pup, _ = _noise_sigma(bench)
    t = 10 * bench.sensor.pixel_mm / bench.sensor.lenslet_focal_mm  # a 10 px spot shift
    for slope in [(t, 0.0), (0.0123, -0.0047)]:
        s, cen, ref = field_slopes(plane_field(bench, FAST, pup.centres, slope=slope), bench, FAST, pup.centres)
        err = s - np.array(slope)
        np.testing.assert_array_less(np.abs(err.mean(axis=0)), 2.5e-4 * np.abs(slope) + 0.3e-6)
        assert np.abs(err).max() < 1.5 * bench.noise.slope_sigma_urad * 1e-6



@pytest.mark.parametrize("variant", [{}, {"aperture": "round"}, {"lit_stride": 3}])
def test_grids_built_in_row_chunks_give_the_one_piece_result(bench, monkeypatch, variant):
    # the reference builds and reduces its (N, N) grids a chunk of rows at a time (memory): chunks of 7 rows
    # (odd, many boundaries; pixel rows in chunks of 6) give what one chunk gives (bitwise here; to 1e-12 of the
    # values, as a BLAS may round a 7-row product apart from a whole one, while a misplaced row moves them ~1e-3)
    import lensforge.verification.physical_sensor as ps

    m = ForwardModel(bench, lf.paper_lens("polynomial"))
    pose = np.r_[0.1, -0.2, 0.3, 0.01, 0.02, -0.01]
    cfg = PhysicalSensor(samples_per_pixel=2, **variant)
    out = []
    for rows in (10**6, 7):
        monkeypatch.setattr(ps, "_CHUNK_ROWS", rows)
        ps._reference_cached.cache_clear()
        r = physical_measure(m, pose, cfg)
        sph = field_slopes(plane_field(bench, cfg, m.pupil.centres, curvature_mm=60.0, gaussian=True), bench, cfg,
                           m.pupil.centres)[0]
        out.append((r.centroids_mm, r.reference_mm, sph))
    for a, b in zip(*out):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(a).max())


def test_fresnel_propagation_reads_sin_where_the_exact_one_reads_tan(bench):
    # the diagnostic 'fresnel' transfer function puts a plane wave of direction cosine L at f L, not f tan
    # (tan - sin ~ t^3 / 2), and drops the thin lenslet's own non-paraxial gain t p^2 / 6 f^2 (the fast model's
    # correction): a 0.05 tilt reads 69 urad less; a bad name is refused
    pup, _ = _noise_sigma(bench)
    t = 0.05
    out = {}
    for prop in ("exact", "fresnel"):
        cfg = PhysicalSensor(samples_per_pixel=2, propagation=prop)
        out[prop] = field_slopes(plane_field(bench, cfg, pup.centres, slope=(t, 0.0)), bench, cfg, pup.centres)[0]
    d = (out["fresnel"] - out["exact"]).mean(axis=0)
    p, f = bench.sensor.pitch_mm, bench.sensor.lenslet_focal_mm
    np.testing.assert_allclose(d[0], -(0.5 * t**3 + t * p * p / (6 * f * f)), rtol=0.03)
    assert abs(d[1]) < 1e-6
    with pytest.raises(ConfigError, match="propagation"):
        PhysicalSensor(propagation="paraxial")


def test_a_true_focal_length_off_the_devices_scales_every_slope(bench):
    # the device divides spot displacements by its stored focal length (the bench's): lenslets 1.5 % longer
    # put a tilt's spots 1.5 % farther out, and the reported slopes are 1.015 t (the gain calibrate estimates)
    pup, _ = _noise_sigma(bench)
    t = 8 * bench.sensor.pixel_mm / bench.sensor.lenslet_focal_mm
    cfg = PhysicalSensor(samples_per_pixel=2, focal_mm=1.015 * bench.sensor.lenslet_focal_mm)
    s, _, _ = field_slopes(plane_field(bench, cfg, pup.centres, slope=(t, -0.5 * t)), bench, cfg, pup.centres)
    g = s.mean(axis=0) / np.array([t, -0.5 * t])
    np.testing.assert_allclose(g, 1.015, rtol=5e-4)
    for bad in (0.0, -5.2, float("nan")):
        with pytest.raises(ConfigError, match="focal_mm"):
            PhysicalSensor(focal_mm=bad)

@pytest.mark.parametrize("R", [40.0, -60.0])
def test_pure_defocus_gives_the_known_z4(bench, R):
    # a spherical wave converging to a point R after the lenslets (R < 0: diverging) has slopes
    # -x/R and, over the pupil of radius a, Z4 = -a^2 / (4 sqrt(3) R) (mm of OPD, Noll RMS); the
    # physical sensor reproduces it to 2e-4 relative (the lenslets' own mapping, above), and no
    # other mode beyond 3.5 sigma
    pup, sig = _noise_sigma(bench)
    s, _, _ = field_slopes(plane_field(bench, FAST, pup.centres, curvature_mm=R), bench, FAST, pup.centres)
    z = pup.fit(s)
    a = bench.sensor.pupil_radius_mm
    z4 = -1e3 * a * a / (4 * np.sqrt(3) * R)
    j4 = list(pup.modes).index(4)
    assert abs(z[j4] - z4) < 2e-4 * abs(z4)
    others = np.delete((z - np.where(pup.modes == 4, z4, 0.0)) / sig, j4)
    assert np.abs(others).max() < 3.5


def test_cross_talk_is_the_main_disagreement(bench):
    # the whole array lit at once against every 3rd lenslet lit at a time (no cross-talk): on the
    # paper's polynomial lens at nominal the fast model misses Z4 by ~50 sigma with cross-talk and by
    # < 10 sigma without (issue 21: 48-87 sigma; 3-7 sigma without cross-talk)
    model = ForwardModel(bench, lf.paper_lens("polynomial"))
    sig = np.sqrt(np.diag(model.noise_cov))
    z = model.evaluate(np.zeros(6)).z[0]
    j4 = list(model.modes).index(4)
    full = physical_measure(model, np.zeros(6), FAST)
    alone = physical_measure(model, np.zeros(6), PhysicalSensor(samples_per_pixel=2, lit_stride=3))
    assert full.valid and full.potential_residual_urad[1] < 1e-3
    assert (full.z[j4] - z[j4]) / sig[j4] < -30
    assert np.abs((alone.z - z) / sig).max() < 10


def test_round_apertures_and_the_beam_reference_run(bench):
    model = ForwardModel(bench, lf.paper_lens("extended_polynomial"))
    for cfg in (PhysicalSensor(samples_per_pixel=2, aperture="round"),
                PhysicalSensor(samples_per_pixel=2, reference="beam", threshold=0.05)):
        r = physical_measure(model, np.zeros(6), cfg)
        assert np.all(np.isfinite(r.z)) and r.slopes.shape == (model.pupil.n_lenslets, 2)


def test_round_and_square_lenslets_against_a_direct_fresnel_integral():
    """The reference's lenslet apertures against an independent computation: a saddle-and-curvature wave (K up to
    10.7 mrad/mm) through a steep Gaussian beam (2.6 mm waist, 2 mm off), five pupil lenslets and the reference's
    whole lit box, both with the Fresnel kernel; ``physical_optics.block_fresnel_centroids`` integrates each disc with
    its smooth rim by Gauss-Legendre nodes (no sampling grid, no anti-aliased edges) and each square cell alike,
    into the same windows. Measured (urad, slope noise 8): round 140 um, 8 samples per pixel, worst 0.82 (2.7 at
    4); square 1.6 (0.93 at 16). The round lenslets' own effect, round - square, reaches 87 urad here; the
    reference's is within 1.8 urad of the direct one's."""
    from physical_optics import block_fresnel_centroids, quadratic_beam_field

    from lensforge.verification.physical_sensor import lit_box

    bench = lf.Bench.default().replace(sensor={"pupil_radius_mm": 0.2, "zernike_order": 1},
                                       laser={"beam_diameter_mm": 5.25})
    s = bench.sensor
    c = lenslet_pupil(s).centres
    assert len(c) == 5
    H = np.array([[-8e-3, -10.7e-3], [-10.7e-3, 5e-3]])
    bo, wl = (0.7, -2.0), bench.laser.wavelength_nm
    field = quadratic_beam_field(bo, 0.5 * bench.laser.beam_diameter_mm, H, wl)

    def plane(X, Y):
        return np.ones_like(X) + 0j

    pix, W = s.pixel_mm, s.centroid_window_px
    edge0 = s.camera_offset_px * pix

    def window(pos):  # the window the tracking rule stands on at a converged centroid
        return np.floor((pos - edge0) / pix - 0.5 * W + 0.5)

    out = {}
    for aperture in ("square", "round"):
        cfg = PhysicalSensor(aperture=aperture, propagation="fresnel", margin_lenslets=3, samples_per_pixel=8)
        slopes, cen, ref = field_slopes(plane_field(bench, cfg, c, (0.0, 0.0), True, None, bo, H), bench, cfg, c)
        cx, cy = lit_box(s, cfg, c)
        lit = np.stack(np.meshgrid(cx, cy, indexing="xy"), -1).reshape(-1, 2)
        dia = cfg.shape(s)[1] if aperture == "round" else None
        direct = (block_fresnel_centroids(field, c, window(cen), s, wl, n_nodes=160, diameter=dia, lit=lit)
                  - block_fresnel_centroids(plane, c, window(ref), s, wl, n_nodes=160, diameter=dia, lit=lit))
        out[aperture] = (slopes, direct / s.lenslet_focal_mm)
    sigma = bench.noise.slope_sigma_urad * 1e-6
    for aperture, (ref_s, direct_s) in out.items():
        assert np.abs(ref_s - direct_s).max() < (0.15 if aperture == "round" else 0.25) * sigma, aperture
    effect_ref, effect_direct = out["round"][0] - out["square"][0], out["round"][1] - out["square"][1]
    assert np.abs(effect_direct).max() > 2.0 * sigma  # the apertures' shape is what is checked
    assert np.abs(effect_ref - effect_direct).max() < 0.05 * np.abs(effect_direct).max()


def test_settings_are_checked(bench):
    with pytest.raises(ConfigError, match="aperture"):
        PhysicalSensor(aperture="hexagonal")
    with pytest.raises(ConfigError, match="window"):
        PhysicalSensor(window_px=0).window(bench.sensor)


def _max_sigma(model, z_phys, pose):
    sig = np.sqrt(np.diag(model.noise_cov))
    return np.abs((z_phys - model.evaluate(pose).z[0]) / sig).max()


def test_crosstalk_model_closes_most_of_the_gap(bench):
    # sensor.crosstalk = 'neighbours' (optics/centroid.py): on the paper's polynomial lens at nominal the
    # fast model moves from ~50 sigma off the physical sensor to a few sigma (measured on the default
    # design with 4 samples per pixel: 59-70 sigma -> 3.2-8.3 sigma at nominal and 4 calibration poses)
    lens = lf.paper_lens("polynomial")
    old = ForwardModel(bench, lens)
    new = ForwardModel(bench.replace(sensor={"crosstalk": "neighbours"}), lens)
    r = physical_measure(old, np.zeros(6), FAST)
    before, after = _max_sigma(old, r.z, np.zeros(6)), _max_sigma(new, r.z, np.zeros(6))
    assert before > 30 and after < 0.2 * before


def test_crosstalk_model_jacobian_is_exact():
    # the complex step through the cross-talk kernel against central differences of the model (a small
    # pupil keeps it cheap; steps small enough that no window moves by a pixel between them)
    b = lf.Bench.default().replace(sensor={"crosstalk": "neighbours", "pupil_radius_mm": 0.5, "zernike_order": 3})
    model = ForwardModel(b, lf.paper_lens("polynomial"))
    x0 = np.array([0.1, -0.2, 0.3, 0.01, -0.02, 0.015])
    J, _, _ = model.jacobians(x0[None])
    h = np.array([1e-5] * 3 + [1e-6] * 3)
    fd = np.stack([(model.evaluate(x0 + e * hi).z[0] - model.evaluate(x0 - e * hi).z[0]) / (2 * hi)
                   for e, hi in zip(np.eye(6), h)], axis=1)
    scale = np.abs(fd).max(axis=0)
    np.testing.assert_array_less(np.abs(J[0] - fd).max(axis=0), 1e-5 * scale + 1e-9)


def test_crosstalk_setting_is_checked(bench):
    with pytest.raises(ConfigError, match="sensor.crosstalk"):
        bench.replace(sensor={"crosstalk": "all"})


def test_simulate_session_rejects_an_unknown_sensor():
    from conftest import run_cli

    r = run_cli("simulate-session", "polynomial", "--sensor", "camera", "-o", "/tmp/never", "-t", "none")
    assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].startswith("error: --sensor")


def test_a_session_measured_by_the_physical_sensor(bench):
    # the session simulator's physical path (coarse settings: the plumbing, not the numbers): every lit
    # pose is measured by the physical sensor, which reads a different defocus than the model
    from lensforge.verification.session_sim import simulate_session

    cheap = PhysicalSensor(samples_per_pixel=2, margin_lenslets=1, potential_knot_mm=0.3, ray_grid=80)
    ticks = []
    s_phys = simulate_session("polynomial", tolerances=None, seed=3, n=4, sensor=cheap, tick=lambda: ticks.append(1))
    s_model = simulate_session("polynomial", tolerances=None, seed=3, n=4, session_plan=s_phys.plan)
    assert len(ticks) == len(s_phys.wfs_ids) > 0
    assert np.all(np.isfinite(s_phys.zernike_thorlabs))
    from lensforge.optics.zernike import from_thorlabs_vector

    def z4(rows):
        out = []
        for row in rows:
            noll, c = from_thorlabs_vector(row)
            out.append(c[list(noll).index(4)])
        return np.array(out)

    dz4 = np.abs(z4(s_phys.zernike_thorlabs) - z4(s_model.zernike_thorlabs))
    assert np.median(dz4) > 0.002 and np.all(dz4 > 5e-4), dz4  # a few nm (coarse settings: 1.4-8 nm)


def test_session_study_runs_combine(tmp_path):
    # the session study split over runs (one seed a run) is reported as one: lists joined, fractions weighted,
    # the physical / model Z error ratio over the seeds both measured; a seed read twice or a NaN is refused
    import json
    import subprocess
    import sys

    def run(name, sensor, seeds, nees, err_mm, inside):
        k = len(seeds)
        rec = {"nees": nees, "inside_3sigma": inside, "inside_3sigma_each_axis": inside, "chi2_dof": [1.0] * k,
               "p_values": [0.5] * k, "z_translation_error_mm": err_mm, "z_rotation_error_deg": [0.05] * k,
               "seeds": seeds, "sensor": [None] * k, "lenslet_focal_true_mm": [5.2] * k, "failed": [], "seconds": 1.0}
        (tmp_path / name).write_text(json.dumps({sensor: rec}))
        return str(tmp_path / name)

    files = [run("p0.json", "physical", [0], [12.0], [0.030], 0.0), run("p1.json", "physical", [1, 2], [3.0, 6.0],
             [0.020, 0.040], 1.0), run("m.json", "model", [0, 1, 2, 3], [6.0] * 4, [0.01, 0.02, 0.02, 0.5], 1.0)]
    script = [sys.executable, str(Path(__file__).parents[1] / "benchmarks" / "bench_sensor_physics.py"), "--combine"]
    out = subprocess.run(script + files + ["--json", str(tmp_path / "all.json")], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "physical  3 sessions | NEES median   6.00 mean/6  1.17" in out.stdout
    assert "inside 3 sigma 0.67" in out.stdout
    assert "over the 3 seeds both measured: translation 1.50" in out.stdout  # 30 um / 20 um
    merged = json.loads((tmp_path / "all.json").read_text())
    assert merged["physical"]["seeds"] == [0, 1, 2] and merged["physical"]["seconds"] == 2.0
    twice = subprocess.run(script + [files[0], files[0]], capture_output=True, text=True)
    assert twice.returncode == 2 and twice.stderr.startswith("error: ") and "seeds [0]" in twice.stderr
    (tmp_path / "nan.json").write_text('{"physical": {"nees": [NaN]}}')
    bad = subprocess.run(script + [str(tmp_path / "nan.json")], capture_output=True, text=True)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "nan.json" in bad.stderr
    # --validate's assumed sensor settings: a known numeric one, finite
    for wrong in ("pitch_mm=0.15", "centroid_threshold=nan", "centroid_threshold=-0.1", "centroid_threshold"):
        r = subprocess.run(script[:-1] + ["--validate", "x.json", "--assume", wrong], capture_output=True, text=True)
        assert r.returncode == 2 and "--assume" in r.stderr, (wrong, r.stderr)
    # --cut-scan's cuts are fractions of the spot peak; --estimate-mc's draws and pupil positive
    for wrong, name in ((["--cut-scan", "--cuts", "0.1,nan"], "--cuts"), (["--cut-scan", "--cut-ref", "1.5"], "--cut-ref"),
                        (["--estimate-mc", "-1"], "--estimate-mc"), (["--estimate-mc", "3", "--pupil", "0"], "--pupil"),
                        (["--estimate-mc", "3", "--zernike-order", "0"], "--zernike-order")):
        r = subprocess.run(script[:-1] + wrong, capture_output=True, text=True)
        assert r.returncode == 2 and name in r.stderr, (wrong, r.stderr)


@pytest.mark.slow
def test_physical_sessions_calibrate_honestly():
    # >= 10 sessions of 12 poses measured by the full-array sensor (4 samples per pixel, 5 lit rings), calibrated
    # with the lens known on the 'cells' model: mean NEES / 6 in [0.6, 1.6] and chi2 passing at its nominal rate.
    # Measured one seed a run (`bench_sensor_physics.py --design polynomial --sessions 1 --seed S --sensors physical
    # --calibration-crosstalk cells --calibration-tolerances none --json S.json`, the same plan, seeds and sensor
    # settings as here, merged by `--combine`), seeds 0-9 with the exact covariance: NEES 2.0-13.8 (mean / 6 1.18),
    # chi2/dof 0.72-1.20 (none p < 0.05), Z inside 3 sigma in 10 of 10 (42-61 min a session, two or three runs
    # sharing two cores; the 'neighbours' model gave NEES / 6 5.2 and chi2/dof 3.5-7.6)
    from lensforge.calibration.session import load_design_lens
    from lensforge.verification.session_sim import check_sessions

    cells = load_design_lens("polynomial")[1].replace(sensor={"crosstalk": "cells"})
    r = check_sessions("polynomial", 10, tolerances=None, calibration_tolerances=None, sensor=PhysicalSensor(),
                       calibration_bench=cells)
    assert 0.6 <= np.mean(r["nees"]) / 6 <= 1.6
    assert np.mean(r["p_values"] < 0.05) <= 0.2


CODESIGN = Path(__file__).parent / "data" / "codesign-zernike.json"  # `lensforge design --model zernike --seed 0`
CORNER = np.r_[-0.5, -0.5, -0.5, np.radians([-5.0, 5.0, -5.0])]  # a corner of its calibration plan's box


@pytest.fixture(scope="module")
def codesign_model():
    from lensforge.optics.lens import resolve_lens

    r = resolve_lens(CODESIGN)
    return ForwardModel(r.bench_or(None), r.lens)


def test_field_is_fitted_over_the_lit_lenslets_only(codesign_model):
    # the co-designed bench's 3.5 mm pupil: the lit box's corners lie where the lens's edge bends the
    # rays steeply; fitted with them the eikonal was off by 0.65 mrad RMS (21 mrad max) at this pose
    f = ray_field(codesign_model, CORNER, PhysicalSensor(margin_lenslets=3))  # 5 reaches 221 mrad rays: spp 8
    assert f.residual_rms < 5e-6 and f.residual_max < 1e-4, (f.residual_rms, f.residual_max)


def test_a_sample_grid_that_aliases_the_field_is_refused(codesign_model):
    # ~100 mrad slopes over 3 rings: 2 samples per pixel alias the phase (Z4 was 2600 sigma off; 4, 6 and 8 agree);
    # 5 rings reach the lens edge's 221 mrad rays, which need 8
    with pytest.raises(ConfigError, match="samples_per_pixel 2 under-samples.*>= 4"):
        physical_measure(codesign_model, CORNER, PhysicalSensor(samples_per_pixel=2, margin_lenslets=3))
    with pytest.raises(ConfigError, match="samples_per_pixel 4 under-samples.*221 mrad.*>= 8"):
        physical_measure(codesign_model, CORNER, PhysicalSensor(samples_per_pixel=4))
    # what the session simulator uses instead: raised to the need, never lowered
    bench = codesign_model.bench
    assert PhysicalSensor(samples_per_pixel=2).sampled_for(bench, 0.11).samples_per_pixel == 4
    assert PhysicalSensor(samples_per_pixel=2).sampled_for(bench, 0.02).samples_per_pixel == 2
    assert PhysicalSensor(samples_per_pixel=6).sampled_for(bench, 0.11).samples_per_pixel == 6


def test_crosstalk_derivatives_along_the_kernel_inputs_are_exact():
    # crosstalk_slope_derivatives chains a complex step along the kernel's 8 inputs per lenslet; it must
    # equal the complex step along the directions themselves (rounding), on a curved, tilted field with
    # an irradiance gradient (K, ln I gradient and the spot all move) and a 5 % noise cut
    from lensforge.optics.centroid import (centroid_slopes, crosstalk_slope_derivatives, crosstalk_slopes,
                                           quadrature_rule, window_gain)
    sensor = lf.Bench.default().replace(sensor={"centroid_threshold": 0.05}).sensor
    p, wl = sensor.pitch_mm, 532.0
    r = np.arange(-3, 4) * p
    centres = np.stack(np.meshgrid(r, r), axis=-1).reshape(-1, 2)
    off, w = quadrature_rule(4)
    X = centres[:, None, :] + p * off[None]  # (n, q, 2)
    rng = np.random.default_rng(3)

    def field(c):  # slopes: tilt + curvature + a cubic term; irradiance: a Gaussian beam off axis
        sq = c[0] + X @ np.array([[c[1], c[2]], [c[2], c[3]]]) + c[4] * X**3
        wi = w * np.exp(-((X - c[5]) ** 2).sum(axis=-1) / 1.2**2)
        return sq[None], wi[None]

    c0 = np.array([0.004, 0.03, -0.01, 0.02, 0.05, 0.3])
    dirs = rng.standard_normal((3, 6))
    sq, wi = field(c0)
    gains = window_gain(sensor, wl)
    h = 1e-30
    ref = np.stack([crosstalk_slopes(centroid_slopes(*field(c0 + 1j * h * d), off, w, gains), *field(c0 + 1j * h * d),
                                     off, w, centres, sensor, wl).imag / h for d in dirs], axis=-1)
    eps = 1e-7  # the field is polynomial in c: the direction derivatives by a complex step too
    dsq = np.stack([field(c0 + 1j * eps * d)[0].imag / eps for d in dirs], axis=-1)
    dwi = np.stack([field(c0 + 1j * eps * d)[1].imag / eps for d in dirs], axis=-1)
    got = crosstalk_slope_derivatives(sq, wi, dsq, dwi, off, w, gains, centres, sensor, wl)
    scale = np.abs(ref).max()
    assert scale > 0
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * scale)


def test_sub_aperture_curvature_closes_the_zernike_lens_gap(bench):
    # the paper's Zernike lens converges strongly: with flat sub-apertures the cross-talk model missed its
    # Z4 by 18-24 sigma (4 samples per pixel), with each sub-aperture's own curvature by 0.5-4.4 (at 2
    # samples per pixel here: the reference itself moves by ~3 sigma)
    lens = lf.paper_lens("zernike")
    model = ForwardModel(bench.replace(sensor={"crosstalk": "neighbours"}), lens)
    r = physical_measure(ForwardModel(bench, lens), np.zeros(6), PhysicalSensor(samples_per_pixel=3))
    sig = np.sqrt(np.diag(model.noise_cov))
    j4 = list(model.modes).index(4)
    assert abs((r.z - model.evaluate(np.zeros(6)).z[0])[j4] / sig[j4]) < 6.0


def test_ray_field_potential_fits_a_fast_varying_field_locally():
    # the reference's eikonal from ray slopes (``_spline_fit``): a wave whose slope varies fast near one edge (a
    # square-root profile, as near a caustic just outside the box) fitted over a round patch of scattered rays.
    # The B-spline keeps its misfit local: far from the fast edge the slopes are exact to ~1e-9 rad, where a global
    # polynomial spreads it everywhere (the default design's plan pose: 39 urad RMS inside the pupil at degree 14)
    from lensforge.verification.physical_sensor import _Knots, _spline_eval, _spline_fit

    rng = np.random.default_rng(1)
    X = rng.uniform(-4.0, 4.0, (30000, 2))
    X = X[np.hypot(*X.T) < 4.0]
    c0 = 4.3  # the slope's singularity just beyond x = 4

    def grad(x):
        return np.stack([-0.05 * np.sqrt(c0 - x[:, 0]) + 0.02 * np.cos(x[:, 1]), -0.02 * x[:, 0] * np.sin(x[:, 1])], 1)

    kx, ky = (_Knots(-4.2, 4.2, 0.2, 7) for _ in range(2))
    g = grad(X)
    C, res = _spline_fit(kx, ky, X, [(g[:, 0], 1, 0), (g[:, 1], 0, 1)])
    Y = rng.uniform(-2.5, 2.5, (500, 2))  # away from the fast edge
    fit = np.stack([_spline_eval(kx, ky, C, Y, nx=1), _spline_eval(kx, ky, C, Y, ny=1)], 1)
    assert np.abs(fit - grad(Y)).max() < 1e-8 * np.abs(grad(Y)).max()
    assert np.sqrt(np.mean(res**2)) < 1e-6 * np.abs(g).max()  # and nowhere badly off
