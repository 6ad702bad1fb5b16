"""Export: default flange leaves room for fiducial and tab, --orient turns the mesh into the
print orientation, "overall" is OK only when every check ran, names and units in the files."""

import numpy as np
import pytest

import lensforge as lf
from lensforge.errors import LensGeometryError
from lensforge.manufacturing.features import DEFAULT_FLANGE_MM, FeatureSpec, with_flange
from lensforge.manufacturing.report import export_lens, export_steps
from lensforge.manufacturing.slicer import SlicerCheck

FAST = dict(layer_mm=0.1, chord_tol_mm=0.01, run_slicer=False)


@pytest.mark.parametrize("name", ["zernike", "extended_polynomial", "spherical"])
def test_default_flange_makes_room_for_fiducial_and_tab(name, tmp_path):
    lens = lf.paper_lens(name)
    assert lens.edge_diameter == lens.aperture  # the case the README's --fiducial --tab failed on
    rep = export_lens(lens, tmp_path, name, stl=True, step=False,
                      features=FeatureSpec(fiducial="flat", tab=True), **FAST)
    assert rep.edge_diameter_mm == pytest.approx(lens.aperture + 2 * DEFAULT_FLANGE_MM)
    assert rep.mesh_check["ok"] and {b.name for b in rep.stl.features} == {"flat", "tab"}


def test_flange_keeps_a_wider_edge_and_rejects_a_flange_the_lens_cannot_take():
    lens = lf.paper_lens("zernike").replace(edge_diameter=30.0)
    assert with_flange(lens, 1.0) is lens
    with pytest.raises(LensGeometryError, match="flange"):
        with_flange(lf.paper_lens("spherical"), 20.0)  # the R = 25.8 mm sphere ends before r = 32.7 mm


def test_orient_applies_the_suggested_build_direction(tmp_path):
    import trimesh

    lens = lf.paper_lens("zernike")
    plain = export_lens(lens, tmp_path / "a", "z", stl=True, step=False, **FAST)
    rep = export_lens(lens, tmp_path / "b", "z", stl=True, step=False, orient=True, threemf=True, **FAST)
    T = np.asarray(rep.oriented)
    d = np.asarray(rep.print_report.orientation.build_direction)
    np.testing.assert_allclose(T[:3, :3] @ d, [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    a = trimesh.load(plain.stl.path, process=False)
    b = trimesh.load(rep.stl.path, process=False)
    np.testing.assert_allclose(b.bounds[0, 2], 0.0, atol=1e-9)  # rests on the platform
    np.testing.assert_allclose(b.volume, a.volume, rtol=1e-7)  # float32 STL vertices
    # the oriented mesh is the {O} mesh moved by T, vertex for vertex
    va = np.asarray(a.vertices)
    np.testing.assert_allclose(va @ T[:3, :3].T + T[:3, 3], b.vertices, atol=1e-5)  # STL is float32
    height = np.ptp(b.vertices[:, 2])
    assert height == pytest.approx(rep.print_report.orientation.height_mm, rel=1e-5)
    assert rep.to_dict()["mesh_transform"] is not None and plain.to_dict()["mesh_transform"] is None


def test_overall_never_says_ok_for_a_check_that_did_not_run(tmp_path):
    lens = lf.paper_lens("zernike")
    rep = export_lens(lens, tmp_path, "z", stl=True, step=False, **FAST)
    assert rep.checks()["PrusaSlicer"].startswith("not run") and rep.checks()["STEP solid"].startswith("not run")
    assert rep.ok and not rep.complete
    assert "OK" not in rep.overall() and "NOT checked" in rep.overall()
    assert "overall: no problems in the checks that ran; NOT checked" in rep.summary()
    missing = rep.__class__(**{**rep.__dict__, "slicer": SlicerCheck(False, "not available")})
    assert missing.checks()["PrusaSlicer"] == "not run: prusa-slicer not installed" and "OK" not in missing.overall()
    d = rep.to_dict()
    assert d["complete"] is False and d["checks"]["mesh"] == "ok" and d["overall"] == rep.overall()
    assert "manifold yes" in rep.summary() and "NoError" not in rep.summary()


def test_names_and_units_in_stl_header_step_product_and_3mf(tmp_path):
    lens = lf.paper_lens("zernike").replace(name="my lens 7")
    rep = export_lens(lens, tmp_path, "l7", stl=True, step=True, threemf=True, **FAST)
    head = rep.stl.path.read_bytes()[:80].decode("ascii")
    assert "my lens 7" in head and "units mm" in head and not head.startswith("solid")
    text = rep.step.path.read_text()
    assert "PRODUCT('l7','my lens 7','lensforge lens my lens 7; lengths in mm" in text.replace("\n", "")
    assert "SI_UNIT(.MILLI.,.METRE.)" in text and "FILE_NAME('l7.step'" in text
    assert rep.ok and rep.step.ok


def test_export_steps_name_every_progress_step():
    seen = []
    steps = export_steps(stl=True, step=False, threemf=True, optiland=False, run_slicer=False)
    assert steps == ["mesh", "printability", "STL", "3MF"]
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        export_lens(lf.paper_lens("spherical"), tmp, "s", stl=True, step=False, threemf=True, progress=seen.append,
                    **FAST)
    assert seen == steps
