"""Form 2 profile checks and the PrusaSlicer verdict, with negative controls."""

import numpy as np
import pytest
import trimesh

import lensforge as lf
from lensforge.errors import ConfigError
from lensforge.manufacturing.features import FeatureSpec, feature_boxes
from lensforge.manufacturing.mesh import build_lens_mesh
from lensforge.manufacturing.printer import (
    FORM2,
    check_layer,
    fitting_orientations,
    printability,
    small_features,
    staircase,
    surface_staircase,
)
from lensforge.manufacturing.slicer import find_prusa_slicer, parse_info, slicer_check

HAS_SLICER = find_prusa_slicer() is not None
needs_slicer = pytest.mark.skipif(not HAS_SLICER, reason="prusa-slicer not installed (.ci/install-slicer.sh)")


def test_form2_profile_and_layers():
    assert FORM2.build_volume_mm == (145.0, 145.0, 175.0)
    assert FORM2.layer_heights_mm == (0.025, 0.05, 0.1) and FORM2.laser_wavelength_nm == 405.0
    assert "xy_spot_mm" in FORM2.assumptions
    assert check_layer(0.05) == 0.05
    with pytest.raises(ConfigError, match="layer"):
        check_layer(0.03)


def test_staircase_model():
    st = staircase(np.array([1.0, np.cos(np.radians(45)), 0.0]), 0.025)
    assert st["cusp_mm"] == pytest.approx([0.025, 0.025 / np.sqrt(2), 0.0])
    assert np.isinf(st["tread_mm"][0]) and st["tread_mm"][1] == pytest.approx(0.025)
    assert st["tread_mm"][2] == 0.0


def test_fits_and_orientation():
    assert fitting_orientations((25.4, 25.4, 7.0))
    assert not fitting_orientations((200.0, 10.0, 10.0))
    lens = lf.paper_lens("zernike")
    lm = build_lens_mesh(lens, chord_tol_mm=0.01)
    rep = printability(lens, lm.mesh.vertices, 0.025)
    assert rep.fits and rep.extents_mm[0] == pytest.approx(lens.edge_diameter, abs=0.01)
    # nearly flat optical surfaces: layers parallel to the optical axis minimise the cusp height
    assert rep.orientation.tilt_deg == 90.0
    assert rep.orientation.rms_cusp_mm < 0.5 * rep.staircase_axis_vertical[0].rms_cusp_mm
    steep = [s.max_slope_deg for s in surface_staircase(lens, 0.025)]
    assert steep[0] > steep[1]  # the curved front is steeper than the near-plane back
    assert rep.to_dict()["orientation"]["layers"] > 0


def test_small_features_flagged():
    lens = lf.paper_lens("zernike").replace(edge_diameter=28.0)
    boxes = feature_boxes(lens, FeatureSpec(fiducial="notch", notch_width_mm=0.1))
    flagged = {f["feature"] for f in small_features(lens, boxes)}
    assert flagged == {"notch width"}
    assert small_features(lens, feature_boxes(lens, FeatureSpec(fiducial="notch"))) == []


def test_parse_info():
    d = parse_info("[x.stl]\nmanifold = yes\nnumber_of_parts =  1\nvolume = 12.5\nedges_fixed = 4\n")
    assert d == {"manifold": "yes", "number_of_parts": 1, "volume": 12.5, "edges_fixed": 4}


def test_slicer_not_available(tmp_path, monkeypatch):
    import lensforge.manufacturing.slicer as sl

    monkeypatch.setattr(sl, "find_prusa_slicer", lambda: None)
    res = sl.slicer_check(tmp_path / "none.stl")
    assert not res.available and res.verdict == "not available" and not res.ok


@pytest.fixture(scope="module")
def small_stl(tmp_path_factory):
    lens = lf.paper_lens("zernike")
    lm = build_lens_mesh(lens, chord_tol_mm=0.02)
    d = tmp_path_factory.mktemp("stl")
    lm.mesh.export(d / "good.stl")
    return lm, d


@needs_slicer
def test_slicer_accepts_the_lens(small_stl):
    lm, d = small_stl
    res = slicer_check(d / "good.stl", layer_mm=0.1, expected_volume_mm3=lm.mesh.volume)
    assert res.ok, res.verdict
    assert res.info_line == "manifold = yes" and res.parts == 1 and res.repairs == {}
    assert res.sliced and res.layers >= 60  # about 6.9 mm / 0.1 mm


@needs_slicer
def test_slicer_negative_controls(small_stl):
    lm, d = small_stl
    m = lm.mesh
    keep = np.ones(len(m.faces), bool)
    keep[::40] = False  # holes
    trimesh.Trimesh(m.vertices, m.faces[keep], process=False).export(d / "holes.stl")
    f = m.faces.copy()
    f[:50] = f[:50, ::-1]  # inconsistent winding: PrusaSlicer repairs it silently and still says manifold
    trimesh.Trimesh(m.vertices, f, process=False).export(d / "flipped.stl")
    for name in ("holes", "flipped"):
        res = slicer_check(d / f"{name}.stl", layer_mm=0.1, expected_volume_mm3=m.volume, slice_sla=False)
        assert res.available and not res.ok, name
        assert res.verdict.startswith("failed")
    assert "open_edges" in slicer_check(d / "holes.stl", slice_sla=False).repairs
    assert "facets_reversed" in slicer_check(d / "flipped.stl", slice_sla=False).repairs
