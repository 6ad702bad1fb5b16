"""STEP (AP214) export of a lens as an exact B-spline solid, built with OCP (OpenCascade).

Each sag surface becomes a bicubic B-spline that interpolates the analytic sag on a
regular x-y grid (GeomAPI_PointsToBSplineSurface, parametrised along x and y, so the
patch is a graph z(x, y)). A cylinder of the edge diameter is split by the two
patches and the piece holding the lens centre is the solid; handling features are
OCC booleans with the same boxes the mesh uses. The grid is refined until the
measured deviation of the B-spline from the analytic sag, at points half-way
between grid nodes, is within the goal (default 10 nm). The written file is read
back and checked (valid solid, volume within 1e-6 relative of the exact integral).

Lens frame {O}, mm. The STL never goes through OCC (see mesh.py).
"""

from __future__ import annotations

from os import PathLike

import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, LensforgeError, MissingDependencyError
from ..fileio import write_atomic
from ..optics.lens import Lens
from .features import Box, FeatureSpec, feature_boxes, feature_volume_change, lens_volume
from .mesh import features_from_args

# Every line below needs OCP, so a missing CAD stack fails the import itself, with one line naming the
# extra (the importers, report.export_lens and the package's lazy ``export_step``, import it only for a
# STEP). mesh.py instead binds an ExceptionWrapper: it also holds numpy-only helpers others import.
CAD_STACK_MISSING = "STEP export needs the CAD stack: pip install 'lensforge[export]'"
try:  # the `export` extra (cadquery's OCP, with vtk): only STEP export imports this module
    from OCP.APIHeaderSection import APIHeaderSection_MakeHeader
    from OCP.BRep import BRep_Tool
    from OCP.BRepAlgoAPI import BRepAlgoAPI_Cut, BRepAlgoAPI_Fuse, BRepAlgoAPI_Splitter
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace, BRepBuilderAPI_Transform
    from OCP.BRepCheck import BRepCheck_Analyzer
    from OCP.BRepClass3d import BRepClass3d_SolidClassifier
    from OCP.BRepGProp import BRepGProp
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox, BRepPrimAPI_MakeCylinder
    from OCP.GeomAPI import GeomAPI_PointsToBSplineSurface
    from OCP.GProp import GProp_GProps
    from OCP.gp import gp_Ax1, gp_Ax2, gp_Dir, gp_Pnt, gp_Trsf
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.Interface import Interface_Static
    from OCP.Message import Message, Message_Gravity
    from OCP.ShapeUpgrade import ShapeUpgrade_UnifySameDomain
    from OCP.STEPControl import STEPControl_AsIs, STEPControl_Reader, STEPControl_Writer
    from OCP.TCollection import TCollection_HAsciiString
    from OCP.TColStd import TColStd_Array2OfReal
    from OCP.TopAbs import TopAbs_IN, TopAbs_SHELL, TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS, TopoDS_Shape
    from OCP.TopTools import TopTools_ListOfShape
except ImportError as _exc:
    raise MissingDependencyError(CAD_STACK_MISSING) from _exc

__all__ = ["SagPatch", "StepSolid", "StepExport", "sag_patch", "build_step_solid", "solid_report", "read_step",
           "export_step"]

MAX_GRID = 801  # nodes per side


def _sag_on_square(surface, z0: float, r_ext: float):
    """Callable (x, y) -> z0 + sag, continued C1 along the radius where the conic is undefined."""
    cs = surface.canonical()

    def f(x, y):
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        z = np.array(cs.sag(x, y), dtype=float)
        bad = ~np.isfinite(z)
        if np.any(bad):
            r = np.hypot(x[bad], y[bad])
            s = r_ext / r
            xe, ye = x[bad] * s, y[bad] * s
            ze, gx, gy = cs.sag_and_gradient(xe, ye)
            dzdr = (gx * xe + gy * ye) / r_ext
            z[bad] = ze + (r - r_ext) * dzdr
        return z0 + z

    return f


@dataclass(frozen=True)
class SagPatch:
    """A B-spline patch interpolating z0 + sag on an n x n grid over [-h, h]^2 (mm)."""

    surface: object  # Geom_BSplineSurface
    n: int
    half_width_mm: float
    max_deviation_mm: float  # measured between the grid nodes, inside the edge disc


def _patch(f, hw: float, n: int):
    xs = np.linspace(-hw, hw, n)
    d = xs[1] - xs[0]
    Z = f(xs[:, None], xs[None, :])
    arr = TColStd_Array2OfReal(1, n, 1, n)
    for i in range(n):
        for j in range(n):
            arr.SetValue(i + 1, j + 1, float(Z[i, j]))
    api = GeomAPI_PointsToBSplineSurface()
    api.Interpolate(arr, -hw, d, -hw, d)
    if not api.IsDone():
        raise LensforgeError("step: B-spline interpolation of the sag failed; please report this")
    return api.Surface(), xs


def _deviation(surf, f, xs: np.ndarray, radius: float) -> float:
    """Max |B-spline z - analytic z| (mm) at cell centres and edge midpoints inside `radius`."""
    n = len(xs)
    u0, u1, v0, v1 = surf.Bounds()
    # parameter of node i: linear map from x (the interpolation is parametrised along x and y)
    pu = u0 + (u1 - u0) * (np.arange(n) / (n - 1))
    pv = v0 + (v1 - v0) * (np.arange(n) / (n - 1))
    mu = 0.5 * (pu[1:] + pu[:-1])
    mv = 0.5 * (pv[1:] + pv[:-1])
    mx = 0.5 * (xs[1:] + xs[:-1])
    samples = []
    for a, ax in ((mu, mx), (pu, xs)):
        for b, bx in ((mv, mx), (pv, xs)):
            if a is pu and b is pv:
                continue  # the nodes themselves are interpolated exactly
            A, B = np.meshgrid(np.arange(len(a)), np.arange(len(b)), indexing="ij")
            keep = ax[A] ** 2 + bx[B] ** 2 <= radius * radius
            samples.append((a[A[keep]], b[B[keep]]))
    worst = 0.0
    for us, vs in samples:
        pts = np.empty((len(us), 3))
        for k, (u, v) in enumerate(zip(us, vs)):
            p = surf.Value(float(u), float(v))
            pts[k] = (p.X(), p.Y(), p.Z())
        if len(pts):
            worst = max(worst, float(np.max(np.abs(pts[:, 2] - f(pts[:, 0], pts[:, 1])))))
    return worst


def sag_patch(surface, z0: float, radius: float, goal_mm: float = 1e-5, n: int | None = None) -> SagPatch:
    """B-spline patch of z0 + sag(x, y) covering the disc of `radius` (mm), refined to `goal_mm`.

    n: force the grid size (nodes per side) instead of refining.
    """
    hw = 1.05 * radius + 0.5
    f = _sag_on_square(surface, z0, radius * 1.02)
    grid = int(n) if n is not None else 33  # 33 x 33 meets 10 nm on the paper lenses
    for _ in range(6):
        hw_n = hw + 2 * (2 * hw / (grid - 1))  # two cells beyond the trimmed region
        surf, xs = _patch(f, hw_n, grid)
        dev = _deviation(surf, f, xs, radius)
        if n is not None or dev <= goal_mm:
            break
        if grid >= MAX_GRID:
            break
        grid = min(MAX_GRID, int(np.ceil((grid - 1) * (dev / goal_mm) ** 0.25 * 1.15)) + 1)
    return SagPatch(surf, grid, hw_n, dev)


def _box_shape(b: Box) -> TopoDS_Shape:
    box = BRepPrimAPI_MakeBox(gp_Pnt(b.u0, -0.5 * b.size[1], b.z0), *map(float, b.size)).Shape()
    tr = gp_Trsf()
    tr.SetRotation(gp_Ax1(gp_Pnt(0, 0, 0), gp_Dir(0, 0, 1)), float(b.angle))
    return BRepBuilderAPI_Transform(box, tr, True).Shape()


def _solids(shape: TopoDS_Shape) -> list:
    out = []
    ex = TopExp_Explorer(shape, TopAbs_SOLID)
    while ex.More():
        out.append(TopoDS.Solid_s(ex.Current()))
        ex.Next()
    return out


@dataclass(frozen=True)
class StepSolid:
    """The lens solid in OCC and how well it matches the analytic part."""

    shape: TopoDS_Shape
    front: SagPatch
    back: SagPatch
    analytic_volume_mm3: float
    features: tuple

    @property
    def max_deviation_mm(self) -> float:
        return max(self.front.max_deviation_mm, self.back.max_deviation_mm)


def build_step_solid(lens: Lens, features: FeatureSpec | None = None, deviation_goal_mm: float = 1e-5,
                     grid: int | None = None) -> StepSolid:
    """Closed B-spline solid of `lens` (plus features) in {O}, mm."""
    goal = float(deviation_goal_mm)
    if not np.isfinite(goal) or goal <= 0:
        raise ConfigError(f"deviation_goal_mm: must be a finite number > 0 mm, got {deviation_goal_mm}")
    if grid is not None and int(grid) < 4:
        raise ConfigError(f"grid: need at least 4 nodes per side, got {grid}")
    lens.validate()
    R = 0.5 * lens.edge_diameter
    half = 0.5 * lens.thickness
    pf = sag_patch(lens.front, -half, R, goal, grid)
    pb = sag_patch(lens.back, half, R, goal, grid)
    boxes = feature_boxes(lens, features or FeatureSpec())
    # cylinder tall enough to be cut by both patches everywhere
    rr = R * np.sqrt(np.linspace(0, 1, 24))[:, None]
    pp = np.linspace(0, 2 * np.pi, 96, endpoint=False)[None, :]
    x, y = rr * np.cos(pp), rr * np.sin(pp)
    zlo = float(np.min(lens.front.sag(x, y))) - half - 1.0
    zhi = float(np.max(lens.back.sag(x, y))) + half + 1.0
    cyl = BRepPrimAPI_MakeCylinder(gp_Ax2(gp_Pnt(0, 0, zlo), gp_Dir(0, 0, 1)), R, zhi - zlo).Shape()
    tools = TopTools_ListOfShape()
    for p in (pf, pb):
        tools.Append(BRepBuilderAPI_MakeFace(p.surface, 1e-9).Face())
    args = TopTools_ListOfShape()
    args.Append(cyl)
    sp = BRepAlgoAPI_Splitter()
    sp.SetArguments(args)
    sp.SetTools(tools)
    sp.SetRunParallel(True)
    sp.Build()
    if not sp.IsDone():
        raise LensforgeError("step: splitting the edge cylinder by the surfaces failed; please report this")
    # a point surely in the glass: halfway between the two surfaces on the axis (the {O}
    # origin is not, when piston/defocus terms move a surface off its vertex plane)
    z_in = 0.5 * ((-half + float(lens.front.sag(0.0, 0.0))) + (half + float(lens.back.sag(0.0, 0.0))))
    inside = []
    for s in _solids(sp.Shape()):
        cls = BRepClass3d_SolidClassifier(s, gp_Pnt(0, 0, z_in), 1e-7)
        if cls.State() == TopAbs_IN:
            inside.append(s)
    if len(inside) != 1:
        raise LensforgeError(f"step: expected one lens body between the surfaces, found {len(inside)}")
    shape = inside[0]
    for b in boxes:
        op = BRepAlgoAPI_Cut(shape, _box_shape(b)) if b.op == "cut" else BRepAlgoAPI_Fuse(shape, _box_shape(b))
        if not op.IsDone():
            raise LensforgeError(f"step: boolean for feature {b.name!r} failed; please report this")
        shape = op.Shape()
    if boxes:
        uni = ShapeUpgrade_UnifySameDomain(shape, True, True, False)
        uni.Build()
        shape = uni.Shape()
    v_exact = lens_volume(lens) + feature_volume_change(lens, boxes)
    return StepSolid(shape, pf, pb, float(v_exact), tuple(boxes))


def solid_report(shape: TopoDS_Shape) -> dict:
    """Validity (BRepCheck), closed shells, number of solids and volume (mm^3) of an OCC shape."""
    solids = _solids(shape)
    closed = True
    ex = TopExp_Explorer(shape, TopAbs_SHELL)
    n_shells = 0
    while ex.More():
        n_shells += 1
        closed &= bool(BRep_Tool.IsClosed_s(ex.Current()))
        ex.Next()
    props = GProp_GProps()
    BRepGProp.VolumeProperties_s(shape, props, 1e-10, True)
    return {"valid": bool(BRepCheck_Analyzer(shape).IsValid()), "closed": bool(closed and n_shells > 0),
            "solids": len(solids), "volume_mm3": float(props.Mass())}


def read_step(path) -> TopoDS_Shape:
    """Read a STEP file into one OCC shape."""
    with _quiet_occ():
        rd = STEPControl_Reader()
        if rd.ReadFile(str(path)) != IFSelect_RetDone:
            raise ConfigError(f"STEP file {path}: cannot be read")
        rd.TransferRoots()
        return rd.OneShape()


@contextmanager
def _quiet_occ():
    """Keep OCC's transfer statistics off stdout (the CLI's --json owns stdout)."""
    printers = Message.DefaultMessenger_s().Printers()
    saved = []
    for i in range(1, printers.Size() + 1):
        pr = printers.Value(i)
        saved.append((pr, pr.GetTraceLevel()))
        pr.SetTraceLevel(Message_Gravity.Message_Fail)
    try:
        yield
    finally:
        for pr, level in saved:
            pr.SetTraceLevel(level)


def _ascii(text: str) -> str:
    """STEP strings are ISO 10303-21 ASCII: keep printable ASCII, drop quotes."""
    return "".join(c if 32 <= ord(c) < 127 and c not in "'\\" else "?" for c in text)


def _name_product(model, name: str, file_name: str) -> None:
    """Lens name and units in the STEP PRODUCT entity and the file header."""
    label = _ascii(name or "lens")
    desc = f"lensforge lens {label}; lengths in mm; lens frame {{O}}: origin on the axis midway between the vertices, +z front to back"
    for i in range(1, model.NbEntities() + 1):
        e = model.Value(i)
        if e.DynamicType().Name() == "StepBasic_Product":
            e.SetId(TCollection_HAsciiString(_ascii(Path(file_name).stem)))
            e.SetName(TCollection_HAsciiString(label))
            e.SetDescription(TCollection_HAsciiString(desc))
    h = APIHeaderSection_MakeHeader(model)
    h.SetName(TCollection_HAsciiString(_ascii(file_name)))
    h.SetDescriptionValue(1, TCollection_HAsciiString(desc))
    h.SetOriginatingSystem(TCollection_HAsciiString("lensforge"))


def _step_bytes(shape: TopoDS_Shape, name: str = "lens", file_name: str = "lens.step") -> bytes:
    with _quiet_occ():
        Interface_Static.SetCVal_s("write.step.schema", "AP214IS")
        Interface_Static.SetCVal_s("write.step.unit", "MM")
        w = STEPControl_Writer()
        w.Transfer(shape, STEPControl_AsIs)
        _name_product(w.Model(), name, file_name)
        with tempfile.TemporaryDirectory() as tmp:
            p = Path(tmp) / "lens.step"
            if w.Write(str(p)) != IFSelect_RetDone:
                import shutil

                if shutil.disk_usage(tmp).free < 64 * 2**20:  # OCC says only "failed": name the likely cause
                    raise LensforgeError(f"step: the temporary folder {tempfile.gettempdir()} (TMPDIR) is full; free "
                                         "space there or set TMPDIR to a folder with room")
                raise LensforgeError("step: OCC could not write the STEP file")
            return p.read_bytes()


@dataclass(frozen=True)
class StepExport:
    """Result of :func:`export_step` (lengths mm, volumes mm^3, times s)."""

    path: Path
    max_deviation_mm: float
    deviation_goal_mm: float
    grid: tuple  # nodes per side (front, back)
    valid: bool
    closed: bool
    analytic_volume_mm3: float
    volume_mm3: float
    reimport_valid: bool
    reimport_volume_mm3: float
    reimport_volume_rel_error: float
    file_bytes: int
    wall_s: float
    features: tuple = ()

    @property
    def ok(self) -> bool:
        return self.valid and self.closed and self.reimport_valid and abs(self.reimport_volume_rel_error) <= 1e-6

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "features"}
        d["path"] = str(self.path)
        d["grid"] = list(self.grid)
        d["features"] = [b.name for b in self.features]
        d["ok"] = self.ok
        return d


def export_step(lens: Lens, path: str | PathLike[str], fiducial: bool | str = False, tab: bool = False,
                features: FeatureSpec | None = None, deviation_goal_mm: float = 1e-5,
                grid: int | None = None) -> StepExport:
    """Write the lens as an AP214 STEP solid (atomically) and verify it by reading it back.

    Parameters
    ----------
    lens : Lens
        The lens ({O}, mm).
    path : str or os.PathLike
        Destination file.
    fiducial : bool or str
        False, True (= 'flat'), 'flat' or 'notch'.
    tab : bool
        Add a gripper tab.
    features : FeatureSpec, optional
        A full feature spec (overrides fiducial and tab).
    deviation_goal_mm : float
        Largest allowed B-spline deviation from the analytic sag, mm (default 10 nm).
    grid : int, optional
        Force the interpolation grid (nodes per side).

    Returns
    -------
    StepExport
        Path, measured deviation (mm), grid, validity, volumes (mm^3) and the re-import
        volume error (goal |error| <= 1e-6).

    Raises
    ------
    LensforgeError
        The solid is not valid and closed.
    """
    t0 = time.perf_counter()
    spec = features if features is not None else features_from_args(fiducial, tab)
    sol = build_step_solid(lens, spec, deviation_goal_mm, grid)
    rep = solid_report(sol.shape)
    if not (rep["valid"] and rep["closed"] and rep["solids"] == 1):
        raise LensforgeError(f"step: the lens solid is not a single valid closed solid ({rep}); file not written")
    path = Path(path)
    data = _step_bytes(sol.shape, lens.name or path.stem, path.name)
    write_atomic(path, data)
    back = solid_report(read_step(path))
    v = sol.analytic_volume_mm3
    return StepExport(path, sol.max_deviation_mm, float(deviation_goal_mm), (sol.front.n, sol.back.n),
                      rep["valid"], rep["closed"], v, rep["volume_mm3"],
                      back["valid"] and back["closed"] and back["solids"] == 1, back["volume_mm3"],
                      (back["volume_mm3"] - v) / v, len(data), time.perf_counter() - t0, sol.features)
