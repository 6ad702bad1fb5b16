"""Sub-aperture centroid model and the sensor's spot-assignment range (lensforge/optics/sensor_range.py)."""

import numpy as np
import pytest

import lensforge as lf
from lensforge.errors import ConfigError
from lensforge.optics.centroid import quadrature_rule
from lensforge.optics.sensor_range import spot_guard_mm
from lensforge.optics.shack_hartmann import ForwardModel


def test_quadrature_rule_integrates_bicubics_exactly():
    off, w = quadrature_rule(2)
    assert w.sum() == pytest.approx(1.0)
    # mean of x^2 y^2 over the unit square [-1/2, 1/2]^2 is (1/12)^2; of x^3 y it is 0
    assert np.sum(w * off[:, 0] ** 2 * off[:, 1] ** 2) == pytest.approx(1 / 144, rel=1e-12)
    assert abs(np.sum(w * off[:, 0] ** 3 * off[:, 1])) < 1e-15
    np.testing.assert_allclose(quadrature_rule(1)[0], 0.0)


def test_subaperture_quadrature_converges(bench):
    # 2x2 Gauss-Legendre is within 0.2 sigma of the 4x4 rule per mode; the centre sample is far off
    lens = lf.paper_lens("extended_polynomial")
    zs = {q: ForwardModel(bench.replace(sensor={"subaperture_quadrature": q}), lens).evaluate(np.zeros(6)).z[0]
          for q in (1, 2, 4)}
    sig = np.sqrt(np.diag(ForwardModel(bench, lens).noise_cov))
    assert np.max(np.abs(zs[2] - zs[4]) / sig) < 0.2
    assert np.max(np.abs(zs[1] - zs[4]) / sig) > 5.0


def test_uniform_tilt_gives_exact_slope_and_fixed_window_limit(bench):
    # a flat plate tilted by the beam: every lenslet sees the same slope; the fixed window holds the spot
    # until f * slope = p/2 - lambda f / p
    sen = bench.sensor
    g = spot_guard_mm(sen, bench.laser.wavelength_nm)
    limit = (0.5 * sen.pitch_mm - g) / sen.lenslet_focal_mm
    for frac, ok in ((0.9, True), (1.1, False)):
        b = bench.replace(laser={"slope": (frac * limit, 0.0)}, sensor={"spot_assignment": "fixed"},
                          placement={"distance_mm": 20.0})
        m = ForwardModel(b, _flat_plate())
        res = m.evaluate(np.zeros(6))
        np.testing.assert_allclose(res.slopes[0, :, 0], frac * limit, rtol=1e-9)
        assert bool(res.valid[0]) is ok
        assert m.sensor_range().lenslets_out == (0 if ok else m.pupil.n_lenslets)


def _flat_plate():
    from lensforge.optics.lens import Lens
    from lensforge.optics.surfaces import Surface

    return Lens(front=Surface(), back=Surface(), thickness=2.0, aperture=10.0, name="flat plate")


def test_tracking_limit_is_the_spot_overlap_curvature(bench):
    # tracking: neighbouring spots of a converging wave overlap when f * p / q > p - 2 lambda f / p,
    # q the distance to focus: the spherical lens is in range at 20 mm and out of range close to its focus
    lens = lf.paper_lens("spherical")
    m = ForwardModel(bench, lens)
    assert m.sensor_range().ok
    sen = bench.sensor
    g = spot_guard_mm(sen, bench.laser.wavelength_nm)
    q_min = sen.lenslet_focal_mm * sen.pitch_mm / (sen.pitch_mm - 2 * g)
    n = lens.index(532.0)
    f = 25.8 / (n - 1)
    d_focus = lens.thickness / 2 + f - lens.thickness / n  # lens-sensor distance that puts the focus on the sensor
    far = ForwardModel(bench.replace(placement={"distance_mm": d_focus - 1.5 * q_min}), lens)
    near = ForwardModel(bench.replace(placement={"distance_mm": d_focus - 0.7 * q_min}), lens)
    assert far.sensor_range().ok
    r = near.sensor_range()
    assert not r.ok and r.lenslets_out > 0


def test_spot_assignment_is_a_checked_bench_setting(bench, tmp_path):
    with pytest.raises(ConfigError, match="sensor.spot_assignment"):
        bench.replace(sensor={"spot_assignment": "magic"})
    with pytest.raises(ConfigError, match="sensor.lenslet_focal_mm"):
        bench.replace(sensor={"lenslet_focal_mm": 0.0})
    b = bench.replace(sensor={"spot_assignment": "fixed", "lenslet_focal_mm": 4.1})
    lf.save_bench(b, tmp_path / "b.toml")
    assert lf.load_bench(tmp_path / "b.toml") == b


def test_design_constraint_keeps_spots_assignable_with_margin(bench):
    from lensforge.design.constraints import Constraints, check_design

    lens = lf.paper_lens("polynomial")
    ok = check_design(bench, lens, Constraints())
    assert "sensor_range" not in [v.constraint for v in ok.violations]
    fixed = bench.replace(sensor={"spot_assignment": "fixed"})
    bad = check_design(fixed, lens, Constraints())
    v = [v for v in bad.violations if v.constraint == "sensor_range"]
    assert v and v[0].value > v[0].limit == pytest.approx(0.8) and "range_margin" in v[0].message
    with pytest.raises(ConfigError, match="range_margin"):
        Constraints(range_margin=1.0)


def test_bench_geometry_scan_finds_the_measurable_distances(bench):
    from lensforge.design.sensor_bench import best_distance, measurable_geometry

    fixed = bench.replace(sensor={"spot_assignment": "fixed"})
    rows = measurable_geometry(fixed, lf.paper_lens("polynomial"), [10.0, 20.0], [0.6, 0.9])
    best = best_distance(rows)
    assert best[0.9] is None  # radius 0.9 mm: 16 spots leave their windows at 20 mm, more at 10 mm
    assert best[0.6] is not None and 20.0 in best[0.6]["measurable_mm"]


def test_evaluate_reports_sensor_range_and_no_metrics_out_of_range(bench, tmp_path):
    from lensforge.commands.evaluate import evaluate_lenses

    lf.save_bench(bench.replace(sensor={"spot_assignment": "fixed"}), tmp_path / "fixed.toml")
    ok, = evaluate_lenses(["polynomial"])
    out, = evaluate_lenses(["polynomial"], str(tmp_path / "fixed.toml"))
    assert ok["sensor_range"]["ok"] and ok["rank"] == 6
    assert ok["sensor_range"]["max_slope_mrad"] == pytest.approx(13.46, abs=0.05)
    assert not out["sensor_range"]["ok"] and out["sensor_range"]["lenslets_out"] == 16 and out["rank"] is None
