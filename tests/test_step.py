"""STEP export: B-spline deviation, valid closed solid, AP214 file, volume on re-import."""

import numpy as np
import pytest

import lensforge as lf
from lensforge.errors import ConfigError
from lensforge.manufacturing.features import FeatureSpec
from lensforge.manufacturing.step import export_step, read_step, sag_patch, solid_report


@pytest.fixture(scope="module")
def zernike():
    return lf.paper_lens("zernike")


def test_step_export_valid_and_volume_on_reimport(zernike, tmp_path):
    res = export_step(zernike, tmp_path / "z.step")
    assert res.valid and res.closed and res.reimport_valid
    assert res.max_deviation_mm <= 1e-5  # goal: 10 nm
    assert abs(res.reimport_volume_rel_error) <= 1e-6
    assert res.ok
    text = (tmp_path / "z.step").read_text()
    assert text.startswith("ISO-10303-21") and "AUTOMOTIVE_DESIGN" in text  # AP214
    assert "B_SPLINE_SURFACE" in text
    rep = solid_report(read_step(tmp_path / "z.step"))
    assert rep["solids"] == 1 and rep["valid"]
    assert lf.export_step is export_step


def test_step_with_features(zernike, tmp_path):
    res = export_step(zernike.replace(edge_diameter=28.0), tmp_path / "f.step",
                      features=FeatureSpec(fiducial="notch", tab=True))
    assert res.ok, res
    assert [n for n in res.features] and {b.name for b in res.features} == {"notch", "tab"}


def test_bspline_deviation_measured_between_nodes_falls_with_grid(zernike):
    r = 0.5 * zernike.edge_diameter
    coarse = sag_patch(zernike.front, 0.0, r, n=17)
    fine = sag_patch(zernike.front, 0.0, r, n=33)
    assert coarse.max_deviation_mm > 8 * fine.max_deviation_mm  # cubic: ~16x per halving
    # independent check at random points of the fine patch (parameters = x, y)
    rng = np.random.default_rng(3)
    xy = rng.uniform(-r / np.sqrt(2), r / np.sqrt(2), size=(300, 2))
    z = np.array([fine.surface.Value(float(x), float(y)).Z() for x, y in xy])
    assert np.max(np.abs(z - zernike.front.sag(xy[:, 0], xy[:, 1]))) <= 1.5 * fine.max_deviation_mm


def test_step_bad_goal(zernike, tmp_path):
    with pytest.raises(ConfigError, match="deviation_goal_mm"):
        export_step(zernike, tmp_path / "x.step", deviation_goal_mm=0)
    assert not (tmp_path / "x.step").exists()


def test_step_lens_with_piston_terms_off_its_vertex_planes(tmp_path):
    # Zernike piston/defocus terms move both surfaces ~4 mm off their vertex planes, so the
    # {O} origin lies outside the glass; the exporter must still keep the lens body
    import lensforge as lf
    from lensforge.manufacturing.features import lens_volume
    from lensforge.manufacturing.step import export_step
    from lensforge.optics.surfaces import ZernikeSag

    lens = lf.Lens(front=ZernikeSag(coefficients=(4.0, 0.0, 0.0, -0.1), norm_radius=12.7),
                   back=ZernikeSag(coefficients=(4.5, 0.0, 0.0, -0.05), norm_radius=12.7),
                   thickness=3.0, aperture=20.0, material="Formlabs-Clear").validate()
    assert lens.front.sag(0.0, 0.0) > 1.5 + 1.0  # front surface behind the {O} origin
    r = export_step(lens, tmp_path / "p.step")
    assert r.ok and abs(r.reimport_volume_mm3 / lens_volume(lens) - 1) < 1e-6
