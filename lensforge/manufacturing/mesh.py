"""Watertight triangle mesh of a lens and its binary STL export.

Each sag surface is triangulated on concentric rings (uniform radial spacing, the
number of points per ring growing with radius), the two surfaces are joined by a
side wall on the edge cylinder, and optional handling features are applied with
manifold3d booleans. The ring count follows from a chord-error tolerance: the
deviation of the triangles from the analytic sag is *measured* (at 12 points per
triangle) and the mesh refined until it is within the tolerance; the edge polygon
is fine enough that its sagitta to the true cylinder is within the tolerance too.

Lens frame {O}, mm. The STL carries the lens in {O}: optical axis along +z.
"""

from __future__ import annotations

from os import PathLike

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError, ExceptionWrapper, LensforgeError, MissingDependencyError
from ..fileio import write_atomic
from ..optics.lens import Lens
from .features import Box, FeatureSpec, feature_boxes, feature_volume_change, lens_volume

MESH_STACK_MISSING = "STL/3MF export needs trimesh and manifold3d: pip install 'lensforge[export]'"
try:  # the `export` extra: calibrating a robot does not need the mesh stack installed
    import manifold3d as m3
    import trimesh
except ImportError as _exc:
    m3 = trimesh = ExceptionWrapper(MissingDependencyError(MESH_STACK_MISSING), _exc)

__all__ = [
    "disc_triangulation",
    "surface_chord_error",
    "LensMesh",
    "MeshCheck",
    "StlExport",
    "build_lens_mesh",
    "check_mesh",
    "export_stl",
    "save_stl",
    "apply_features",
    "features_from_args",
    "orient_mesh",
    "save_3mf",
    "stl_header",
]

MAX_RINGS = 3000  # about 5e7 triangles: beyond this the tolerance is not meant for printing
_BARY = np.array([(i, j, 4 - i - j) for i in range(5) for j in range(5 - i)
                  if max(i, j, 4 - i - j) < 4], dtype=float) / 4.0  # 12 points, no corners


def _zipper(inner: np.ndarray, outer: np.ndarray) -> np.ndarray:
    """Triangles (counter-clockwise seen from +z) joining two closed rings by angle order.

    inner, outer: vertex indices of each ring, ordered by increasing angle from phi = 0.
    """
    m, n = len(inner), len(outer)
    keys = np.concatenate([np.arange(1, m + 1) / m, np.arange(1, n + 1) / n])
    is_inner = np.concatenate([np.ones(m, bool), np.zeros(n, bool)])
    order = np.lexsort((is_inner, keys))  # at equal angle advance the outer ring first
    step_inner = is_inner[order]
    j = np.cumsum(step_inner) - step_inner
    k = np.cumsum(~step_inner) - ~step_inner
    a = inner[j % m]
    b = outer[k % n]
    c = np.where(step_inner, inner[(j + 1) % m], outer[(k + 1) % n])
    return np.stack([a, b, c], axis=1)


def disc_triangulation(radius: float, n_rings: int, n_rim: int):
    """Concentric-ring triangulation of a disc.

    Returns (xy (V, 2) mm, triangles (T, 3) counter-clockwise seen from +z, rim indices
    ordered by angle). Ring i (1..n_rings) sits at r = radius i / n_rings with
    max(6, ceil(n_rim i / n_rings)) points, the rim ring exactly n_rim.
    """
    if n_rings < 1 or n_rim < 6:
        raise ConfigError("mesh resolution: need n_rings >= 1 and n_rim >= 6")
    xy = [np.zeros((1, 2))]
    rings = [np.array([0])]
    start = 1
    for i in range(1, n_rings + 1):
        cnt = n_rim if i == n_rings else max(6, int(np.ceil(n_rim * i / n_rings)))
        phi = 2 * np.pi * np.arange(cnt) / cnt
        r = radius * i / n_rings
        xy.append(np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1))
        rings.append(np.arange(start, start + cnt))
        start += cnt
    first = rings[1]
    tris = [np.stack([np.zeros(len(first), int), first, np.roll(first, -1)], axis=1)]
    for i in range(1, n_rings):
        tris.append(_zipper(rings[i], rings[i + 1]))
    return np.concatenate(xy), np.concatenate(tris).astype(np.int64), rings[-1]


def surface_chord_error(sag, xy: np.ndarray, z: np.ndarray, tris: np.ndarray) -> float:
    """Max |planar triangle - analytic sag| (mm), sampled at 12 barycentric points per triangle.

    sag: callable (x, y) -> z (mm); xy, z: vertex positions; tris: (T, 3) indices.
    The deviation is measured along z (an upper bound of the normal distance).
    """
    P = xy[tris]  # (T, 3, 2)
    Z = z[tris]
    pts = np.einsum("kc,tcd->tkd", _BARY, P)
    zl = np.einsum("kc,tc->tk", _BARY, Z)
    dev = np.abs(zl - sag(pts[..., 0], pts[..., 1]))
    return float(np.nanmax(dev)) if dev.size else 0.0


def _max_curvature(lens: Lens) -> float:
    """Largest |second derivative| of either sag over the edge disc (1/mm), by differences."""
    R = 0.5 * lens.edge_diameter
    r = R * np.sqrt(np.linspace(0, 1, 32))[:, None]
    p = np.linspace(0, 2 * np.pi, 64, endpoint=False)[None, :]
    x, y = (r * np.cos(p)).ravel(), (r * np.sin(p)).ravel()
    h = 1e-4 * R
    kmax = 0.0
    for surf in (lens.front, lens.back):
        cs = surf.canonical()
        gx1, gy1 = cs.gradient(x + h, y)
        gx0, gy0 = cs.gradient(x - h, y)
        hx1, hy1 = cs.gradient(x, y + h)
        hx0, hy0 = cs.gradient(x, y - h)
        hess = np.stack([(gx1 - gx0), (gy1 - gy0), (hx1 - hx0), (hy1 - hy0)]) / (2 * h)
        kmax = max(kmax, float(np.nanmax(np.abs(hess))))
    return kmax


def _rim_count(radius: float, tol: float) -> int:
    """Points on the edge polygon so that its sagitta to the circle is <= tol."""
    return int(np.ceil(np.pi / np.arccos(max(-1.0, 1.0 - tol / radius))))


@dataclass(frozen=True)
class LensMesh:
    """A lens mesh and how it was made (lengths mm, volumes mm^3)."""

    mesh: trimesh.Trimesh
    n_rings: int
    n_rim: int
    chord_tol_mm: float
    surface_chord_error_mm: tuple  # (front, back), measured
    rim_chord_error_mm: float  # sagitta of the edge polygon
    analytic_volume_mm3: float  # plain lens + features, exact integral
    volume_bound_mm3: float  # the largest |mesh - analytic| the chord errors allow
    features: tuple = ()
    lens_name: str = ""
    transform: tuple | None = None  # 4x4 applied to the {O} coordinates (None: the mesh is in {O})

    @property
    def chord_error_mm(self) -> float:
        """Largest measured deviation of the mesh from the analytic part (mm)."""
        return max(max(self.surface_chord_error_mm), self.rim_chord_error_mm)

    @property
    def triangles(self) -> int:
        return int(len(self.mesh.faces))


def _surface_meshes(lens: Lens, n_rings: int, n_rim: int):
    R = 0.5 * lens.edge_diameter
    xy, tris, rim = disc_triangulation(R, n_rings, n_rim)
    zf_s = lens.front.sag(xy[:, 0], xy[:, 1])
    zb_s = lens.back.sag(xy[:, 0], xy[:, 1])
    ef = surface_chord_error(lens.front.sag, xy, zf_s, tris)
    eb = surface_chord_error(lens.back.sag, xy, zb_s, tris)
    return xy, tris, rim, zf_s, zb_s, (ef, eb)


def _assemble(lens: Lens, xy, tris, rim, zf_s, zb_s) -> tuple[np.ndarray, np.ndarray]:
    nv = len(xy)
    half = 0.5 * lens.thickness
    verts = np.concatenate([
        np.column_stack([xy, zf_s - half]),
        np.column_stack([xy, zb_s + half]),
    ])
    front = tris[:, ::-1]  # outward normal towards -z
    back = tris + nv
    a, a1 = rim, np.roll(rim, -1)
    b, b1 = rim + nv, np.roll(rim, -1) + nv
    wall = np.concatenate([np.stack([a, a1, b], 1), np.stack([a1, b1, b], 1)])
    return verts, np.concatenate([front, back, wall])


def _to_manifold(verts: np.ndarray, faces: np.ndarray) -> m3.Manifold:
    return m3.Manifold(m3.Mesh64(vert_properties=np.ascontiguousarray(verts, dtype=np.float64),
                                 tri_verts=np.ascontiguousarray(faces, dtype=np.uint64)))


def _box_manifold(b: Box) -> m3.Manifold:
    cube = m3.Manifold.cube(list(b.size), False)
    return cube.translate([b.u0, -0.5 * b.size[1], b.z0]).rotate([0.0, 0.0, float(np.degrees(b.angle))])


def apply_features(verts: np.ndarray, faces: np.ndarray, boxes) -> tuple[np.ndarray, np.ndarray]:
    """Cut/add the feature boxes with manifold3d booleans; returns (vertices, faces)."""
    man = _to_manifold(verts, faces)
    if man.status() != m3.Error.NoError:
        raise LensforgeError(f"mesh: manifold3d rejected the lens mesh ({man.status()}); please report this")
    for b in boxes:
        box = _box_manifold(b)
        man = man - box if b.op == "cut" else man + box
    out = man.to_mesh64()
    return np.asarray(out.vert_properties)[:, :3].copy(), np.asarray(out.tri_verts, dtype=np.int64)


def build_lens_mesh(lens: Lens, chord_tol_mm: float = 1e-3, features: FeatureSpec | None = None,
                    n_rings: int | None = None) -> LensMesh:
    """Watertight mesh of `lens` whose measured chord error is <= chord_tol_mm.

    n_rings: force a ring count (the rim polygon still follows chord_tol_mm) instead of
    refining automatically. features: optional fiducial/tab (see FeatureSpec).
    """
    tol = float(chord_tol_mm)
    if not np.isfinite(tol) or tol <= 0:
        raise ConfigError(f"chord_tol_mm: must be a finite number > 0 mm, got {chord_tol_mm}")
    lens.validate()
    R = 0.5 * lens.edge_diameter
    if n_rings is None:
        kappa = _max_curvature(lens)
        h = np.sqrt(6.0 * tol / kappa) if kappa > 0 else R
        n = int(np.clip(np.ceil(R / h), 8, MAX_RINGS))
    else:
        n = int(n_rings)
        if n < 1:
            raise ConfigError(f"n_rings: must be >= 1, got {n_rings}")
    rim_min = _rim_count(R, tol)
    for _ in range(8):
        n_rim = max(rim_min, int(np.ceil(2 * np.pi * n)), 6)
        xy, tris, rim, zf_s, zb_s, errs = _surface_meshes(lens, n, n_rim)
        err = max(errs)
        if n_rings is not None or err <= tol:
            break
        if n >= MAX_RINGS:
            raise ConfigError(
                f"chord_tol_mm: {tol} mm needs more than {MAX_RINGS} rings (measured {err:.3g} mm); "
                "use a larger tolerance (the Form 2 prints 25 um layers)"
            )
        n = min(MAX_RINGS, int(np.ceil(n * np.sqrt(err / tol) * 1.05)) + 1)
    verts, faces = _assemble(lens, xy, tris, rim, zf_s, zb_s)
    rim_err = R * (1 - np.cos(np.pi / n_rim))
    spec = features or FeatureSpec()
    boxes = feature_boxes(lens, spec)
    v_exact = lens_volume(lens) + feature_volume_change(lens, boxes)
    poly_area = 0.5 * n_rim * R * R * np.sin(2 * np.pi / n_rim)
    t_max = float(np.max(zb_s[rim] - zf_s[rim])) + lens.thickness
    bound = (errs[0] + errs[1]) * np.pi * R * R + (np.pi * R * R - poly_area) * t_max
    for b in boxes:  # each box edge crossing the rim polygon adds at most sagitta x height x width
        bound += 2 * rim_err * b.size[2] * b.size[1] if b.op == "add" else 2 * rim_err * t_max * min(b.size[1], 2 * R)
    if boxes:
        verts, faces = apply_features(verts, faces, boxes)
    mesh = trimesh.Trimesh(vertices=verts, faces=faces, process=False)
    return LensMesh(mesh, n, n_rim, tol, (float(errs[0]), float(errs[1])), float(rim_err),
                    float(v_exact), float(bound), tuple(boxes), lens.name)


def orient_mesh(lm: LensMesh, build_direction) -> LensMesh:
    """The mesh turned so that ``build_direction`` (in {O}) points along +z of the printer,
    centred in x and y and resting on z = 0. The 4x4 transform is kept on the result."""
    from scipy.spatial.transform import Rotation

    d = np.asarray(build_direction, float)
    d = d / np.linalg.norm(d)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(d, z)
    s, c = np.linalg.norm(axis), float(d @ z)
    if s < 1e-15:
        R = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        R = Rotation.from_rotvec(axis / s * np.arctan2(s, c)).as_matrix()
    v = lm.mesh.vertices @ R.T
    lo, hi = v.min(axis=0), v.max(axis=0)
    t = -np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    mesh = trimesh.Trimesh(vertices=v + t, faces=lm.mesh.faces, process=False)
    return dataclasses.replace(lm, mesh=mesh, transform=tuple(map(tuple, T.tolist())))


@dataclass(frozen=True)
class MeshCheck:
    """Validation of a closed mesh by trimesh and manifold3d (volumes mm^3, box mm)."""

    watertight: bool
    winding_consistent: bool
    volume_mm3: float
    analytic_volume_mm3: float
    volume_rel_error: float
    volume_ok: bool
    manifold_status: str
    genus: int | None
    bodies: int
    triangles: int
    bounding_box_mm: tuple  # ((xmin, ymin, zmin), (xmax, ymax, zmax))

    @property
    def ok(self) -> bool:
        return (self.watertight and self.winding_consistent and self.volume_ok
                and self.manifold_status == "NoError" and self.genus == 0 and self.bodies == 1)

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["bounding_box_mm"] = [list(map(float, c)) for c in self.bounding_box_mm]
        d["ok"] = self.ok
        return d


def check_mesh(mesh: trimesh.Trimesh, analytic_volume_mm3: float | None = None,
               volume_bound_mm3: float | None = None) -> MeshCheck:
    """Watertight, consistent winding, volume vs the analytic value, manifold3d status and genus."""
    m = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, process=True)  # merge coincident vertices
    vol = float(m.volume)
    if analytic_volume_mm3 is None:
        rel, ok, exact = float("nan"), True, float("nan")
    else:
        exact = float(analytic_volume_mm3)
        rel = (vol - exact) / exact
        bound = abs(volume_bound_mm3) if volume_bound_mm3 is not None else 1e-3 * abs(exact)
        ok = abs(vol - exact) <= bound
    man = _to_manifold(m.vertices, m.faces)
    status = man.status()
    status_name = getattr(status, "name", str(status).split(".")[-1])
    genus = int(man.genus()) if status == m3.Error.NoError else None
    bodies = len(man.decompose()) if status == m3.Error.NoError else int(m.body_count)
    lo, hi = m.bounds
    return MeshCheck(bool(m.is_watertight), bool(m.is_winding_consistent), vol, exact, float(rel), bool(ok),
                     status_name, genus, bodies, int(len(m.faces)), (tuple(map(float, lo)), tuple(map(float, hi))))


@dataclass(frozen=True)
class StlExport:
    """Result of :func:`export_stl` (lengths mm, volume mm^3, times s, sizes bytes)."""

    path: Path
    triangles: int
    chord_error_mm: float
    chord_tol_mm: float
    surface_chord_error_mm: tuple
    rim_chord_error_mm: float
    n_rings: int
    n_rim: int
    volume_mm3: float
    analytic_volume_mm3: float
    watertight: bool
    manifold: bool
    genus: int | None
    bounding_box_mm: tuple
    file_bytes: int
    wall_s: float
    check: MeshCheck
    features: tuple = field(default=())

    def to_dict(self) -> dict:
        return {
            "path": str(self.path),
            "triangles": self.triangles,
            "chord_error_mm": self.chord_error_mm,
            "chord_tol_mm": self.chord_tol_mm,
            "surface_chord_error_mm": list(self.surface_chord_error_mm),
            "rim_chord_error_mm": self.rim_chord_error_mm,
            "n_rings": self.n_rings,
            "n_rim": self.n_rim,
            "volume_mm3": self.volume_mm3,
            "analytic_volume_mm3": self.analytic_volume_mm3,
            "watertight": self.watertight,
            "manifold": self.manifold,
            "genus": self.genus,
            "bounding_box_mm": [list(c) for c in self.bounding_box_mm],
            "file_bytes": self.file_bytes,
            "wall_s": self.wall_s,
            "features": [b.name for b in self.features],
            "check": self.check.to_dict(),
        }


def features_from_args(fiducial=False, tab=False, **kw) -> FeatureSpec:
    """FeatureSpec from the export arguments: fiducial False/True/'flat'/'notch', tab bool."""
    kind = None
    if fiducial is True:
        kind = "flat"
    elif fiducial:
        kind = str(fiducial)
    return FeatureSpec(fiducial=kind, tab=bool(tab), **kw)


def export_stl(lens: Lens, path: str | PathLike[str], chord_tol_mm: float = 1e-3, fiducial: bool | str = False, tab: bool = False,
               features: FeatureSpec | None = None, n_rings: int | None = None) -> StlExport:
    """Write the lens as a binary STL (atomically) after validating the mesh.

    Parameters
    ----------
    lens : Lens
        The lens ({O}, mm).
    path : str or os.PathLike
        Destination file.
    chord_tol_mm : float
        Largest allowed deviation of the triangles from the analytic part, mm.
    fiducial : bool or str
        False, True (= 'flat'), 'flat' or 'notch'.
    tab : bool
        Add a gripper tab.
    features : FeatureSpec, optional
        A full feature spec (overrides fiducial and tab).
    n_rings : int, optional
        Force the ring count of the triangulation.

    Returns
    -------
    StlExport
        Path, triangle count, chord errors (mm), volumes (mm^3), watertight/manifold checks.

    Raises
    ------
    LensforgeError
        The mesh is not watertight, manifold and of genus 0.
    MissingDependencyError
        trimesh/manifold3d are not installed (``pip install 'lensforge[export]'``).
    """
    t0 = time.perf_counter()
    spec = features if features is not None else features_from_args(fiducial, tab)
    lm = build_lens_mesh(lens, chord_tol_mm, spec, n_rings=n_rings)
    return save_stl(lm, path, t0)


def save_3mf(lm: LensMesh, path) -> Path:
    """Write a validated lens mesh as 3MF (mm units; trimesh's exporter, needs networkx)."""
    chk = check_mesh(lm.mesh, lm.analytic_volume_mm3, lm.volume_bound_mm3)
    if not chk.ok:
        raise LensforgeError(f"mesh: validation failed ({chk.to_dict()}); the 3MF was not written")
    mesh = lm.mesh.copy()
    mesh.units = "millimeters"
    mesh.metadata["name"] = lm.lens_name or Path(path).stem
    return write_atomic(path, trimesh.exchange.export.export_mesh(mesh, None, file_type="3mf"))


def stl_header(name: str, frame: str = "lens frame {O}") -> bytes:
    """The 80-byte binary-STL header: lens name, units and frame (ASCII, never starting with 'solid')."""
    text = f"lensforge lens {name}; units mm; {frame}"
    raw = text.encode("ascii", "replace")[:80]
    return raw.ljust(80, b" ")


def save_stl(lm: LensMesh, path, t0: float | None = None) -> StlExport:
    """Validate a built lens mesh and write it as a binary STL (atomically).

    t0: perf_counter() at the start of the export, for the reported wall time.
    """
    t0 = time.perf_counter() if t0 is None else t0
    chk = check_mesh(lm.mesh, lm.analytic_volume_mm3, lm.volume_bound_mm3)
    if not chk.ok:
        raise LensforgeError(f"mesh: validation failed ({chk.to_dict()}); the STL was not written")
    path = Path(path)
    frame = "lens frame {O}" if lm.transform is None else "print orientation, build direction +z"
    data = stl_header(lm.lens_name or path.stem, frame) + trimesh.exchange.stl.export_stl(lm.mesh)[80:]
    write_atomic(path, data)
    return StlExport(path, lm.triangles, lm.chord_error_mm, lm.chord_tol_mm, lm.surface_chord_error_mm,
                     lm.rim_chord_error_mm, lm.n_rings, lm.n_rim, chk.volume_mm3, lm.analytic_volume_mm3,
                     chk.watertight, chk.manifold_status == "NoError", chk.genus, chk.bounding_box_mm,
                     len(data), time.perf_counter() - t0, chk, lm.features)
