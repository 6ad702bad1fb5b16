"""Lens mesh: watertight/manifold at several resolutions, measured chord error, volume, features."""

import manifold3d as m3
import numpy as np
import pytest
import trimesh

import lensforge as lf
from lensforge.errors import ConfigError, LensGeometryError
from lensforge.manufacturing.features import FeatureSpec, lens_volume
from lensforge.manufacturing.mesh import (
    build_lens_mesh,
    check_mesh,
    disc_triangulation,
    export_stl,
)


@pytest.fixture(scope="module")
def zernike():
    return lf.paper_lens("zernike")


@pytest.mark.parametrize("name", ["zernike", "polynomial"])
@pytest.mark.parametrize("n_rings", [3, 8, 24])
def test_watertight_and_manifold_at_several_resolutions(name, n_rings):
    lm = build_lens_mesh(lf.paper_lens(name), chord_tol_mm=0.01, n_rings=n_rings)
    c = check_mesh(lm.mesh, lm.analytic_volume_mm3, lm.volume_bound_mm3)
    assert c.watertight and c.winding_consistent
    assert c.manifold_status == "NoError" and c.genus == 0 and c.bodies == 1
    assert c.volume_ok and c.volume_mm3 > 0  # outward normals: positive volume
    assert c.ok


def test_disc_triangulation_covers_the_polygon():
    xy, tris, rim = disc_triangulation(2.0, 5, 40)
    p = xy[tris]
    a, b = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = 0.5 * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    assert np.all(area > 0)  # all counter-clockwise, none degenerate
    assert np.isclose(area.sum(), 0.5 * 40 * 4.0 * np.sin(2 * np.pi / 40))
    assert len(rim) == 40 and np.allclose(np.hypot(*xy[rim].T), 2.0)


@pytest.mark.parametrize("name", ["zernike", "spherical", "extended_polynomial"])
def test_default_tolerance_met(name):
    lm = build_lens_mesh(lf.paper_lens(name))
    assert lm.chord_error_mm <= 1e-3
    assert max(lm.surface_chord_error_mm) > 0.2e-3  # not absurdly over-refined


def test_chord_error_measurement_is_not_undersampled(zernike):
    """Dense random sampling inside every triangle finds no larger deviation than reported."""
    lm = build_lens_mesh(zernike, chord_tol_mm=0.01, n_rings=10)
    rng = np.random.default_rng(0)
    v, f = lm.mesh.vertices, lm.mesh.faces
    nz = v[f][:, :, 2]
    front = np.all(np.isclose(nz, -0.5 * zernike.thickness + zernike.front.sag(v[f][..., 0], v[f][..., 1])), axis=1)
    tri = v[f[front]]
    b = rng.dirichlet(np.ones(3), size=(len(tri), 40))
    pts = np.einsum("tkc,tcd->tkd", b, tri)
    dev = np.abs(pts[..., 2] + 0.5 * zernike.thickness - zernike.front.sag(pts[..., 0], pts[..., 1]))
    assert dev.max() <= lm.surface_chord_error_mm[0] * (1 + 1e-9)
    assert dev.max() > 0.8 * lm.surface_chord_error_mm[0]


def test_chord_error_falls_with_resolution(zernike):
    errs = [build_lens_mesh(zernike, chord_tol_mm=0.1, n_rings=n).surface_chord_error_mm[0] for n in (8, 16, 32)]
    assert errs[0] > 2.5 * errs[1] > 2.5 ** 2 * errs[2]  # about 4x per doubling
    lm = build_lens_mesh(zernike, chord_tol_mm=2e-4)
    assert lm.chord_error_mm <= 2e-4


def test_analytic_volume_matches_closed_form():
    lens = lf.paper_lens("spherical")  # plano-convex: V = pi R^2 l - spherical cap over the disc
    R, Rc, l = 12.7, 25.8, 5.3
    cap = np.pi * R**2 * Rc - 2 * np.pi / 3 * (Rc**3 - (Rc**2 - R**2) ** 1.5)
    assert lens_volume(lens) == pytest.approx(np.pi * R**2 * l - cap, rel=1e-12)


def test_bad_tolerance_rejected(zernike):
    with pytest.raises(ConfigError, match="chord_tol_mm"):
        build_lens_mesh(zernike, chord_tol_mm=-1)


def _clear_aperture_part(mesh, radius, zlo=-20, zhi=20):
    man = m3.Manifold(m3.Mesh64(vert_properties=np.ascontiguousarray(mesh.vertices),
                                tri_verts=np.ascontiguousarray(mesh.faces, dtype=np.uint64)))
    cyl = m3.Manifold.cylinder(zhi - zlo, radius, radius, 512).translate([0, 0, zlo])
    return (man ^ cyl).volume()


@pytest.mark.parametrize("spec", [FeatureSpec(fiducial="flat"), FeatureSpec(fiducial="notch"),
                                  FeatureSpec(tab=True), FeatureSpec(fiducial="notch", tab=True)],
                         ids=["flat", "notch", "tab", "notch+tab"])
def test_features_watertight_and_outside_clear_aperture(zernike, spec):
    lens = zernike.replace(edge_diameter=28.0)
    plain = build_lens_mesh(lens, chord_tol_mm=0.01)
    lm = build_lens_mesh(lens, chord_tol_mm=0.01, features=spec)
    c = check_mesh(lm.mesh, lm.analytic_volume_mm3, lm.volume_bound_mm3)
    assert c.ok, c
    sign = 1 if spec.tab and spec.fiducial is None else -1 if not spec.tab else 0
    if sign:
        assert np.sign(c.volume_mm3 - check_mesh(plain.mesh).volume_mm3) == sign
    # inside the clear aperture (slightly inside, away from the rim polygon) the parts are identical
    r = 0.5 * lens.aperture - 0.01
    assert _clear_aperture_part(lm.mesh, r) == pytest.approx(_clear_aperture_part(plain.mesh, r), rel=1e-12)


def test_features_need_room_outside_the_clear_aperture(zernike):
    with pytest.raises(LensGeometryError, match="edge_diameter"):
        build_lens_mesh(zernike, features=FeatureSpec(fiducial="flat"))
    with pytest.raises(ConfigError, match="tab_angle"):
        build_lens_mesh(zernike.replace(edge_diameter=28.0),
                        features=FeatureSpec(fiducial="flat", tab=True, tab_angle=0.1))


def test_export_stl_binary_and_reloads_watertight(zernike, tmp_path):
    res = export_stl(zernike.replace(edge_diameter=27.0), tmp_path / "lens.stl", chord_tol_mm=0.005, fiducial=True)
    data = (tmp_path / "lens.stl").read_bytes()
    assert len(data) == 84 + 50 * res.triangles == res.file_bytes  # binary STL
    m = trimesh.load(tmp_path / "lens.stl")
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume == pytest.approx(res.volume_mm3, rel=1e-6)
    assert res.watertight and res.manifold and res.genus == 0 and res.chord_error_mm <= 0.005
    assert not list(tmp_path.glob(".*tmp"))  # no temp file left behind
    assert lf.export_stl is export_stl
