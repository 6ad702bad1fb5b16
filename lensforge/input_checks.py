"""One schema layer for every file lensforge reads: header, strict numbers, physical ranges.

Each reader parses its file (``fileio.read_json`` / ``read_toml``), then calls this
module before it builds its dataclasses:

* :func:`check_header` -- ``schema_version`` must be exactly the integer 1 (not
  ``"1"``, ``1.0`` or ``true``) and ``kind`` must name the file's kind. Files that
  lensforge writes itself (design files) must carry both; hand-written inputs
  (bench, tolerances, poses, ...) may leave them out, but when present they must be
  right.
* :func:`check_ranges` -- every number named in a range table (a dict "dotted.key"
  -> :class:`Num`) must be a real JSON/TOML number (no strings, no booleans), finite
  and inside the plausible physical range; the message names the file, the key,
  the range with its unit and the value.
* :func:`number` / :func:`number_array` -- the same rule for one value or an array
  of a given shape (matrices in pose files).

Adopting it in a new reader (e.g. robot poses, WFS measurements, robot TOML)::

    data = read_toml(path, "robot file")                  # BOM-tolerant, one-line errors
    where = f"robot file {Path(path).name}"
    check_header(data, where, kind="lensforge.robot")     # optional header, checked if present
    check_ranges(data, ROBOT_RANGES, where)               # {"joint.offset_deg": Num(-360, 360, "deg")}
    T = number_array(data["T"], f"{where}:T", (4, 4), Num(-1e5, 1e5, "mm"))

The ranges are what real hardware has (sources and assumptions next to each
table); they are deliberately wide: they catch wrong units and typos, not design
choices. This module sits at the bottom of the import graph (errors only).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .errors import ConfigError

__all__ = ["Num", "number", "number_array", "field_number", "check_header", "check_ranges", "flatten",
           "BENCH_RANGES", "LENS_RANGES", "POSE_TRANSLATION", "SCHEMA_VERSION",
           "MAX_LENSLETS", "DESIGN_KIND", "MAX_SAG_COEFFICIENTS"]

SCHEMA_VERSION = 1
DESIGN_KIND = "lensforge.design"  # the kind of a design file (design/design_file.py writes it)


@dataclass(frozen=True)
class Num:
    """A plausible range [lo, hi] (``lo_open``: lo excluded) in ``unit``; ``integer``: whole numbers only."""

    lo: float
    hi: float
    unit: str = ""
    lo_open: bool = False
    integer: bool = False

    def describe(self) -> str:
        u = f" {self.unit}" if self.unit else ""
        lo = f"> {self.lo:g}" if self.lo_open else f">= {self.lo:g}"
        return f"{lo} and <= {self.hi:g}{u}"


def _finite(f: float, where: str, shown: str) -> float:
    if not math.isfinite(f):
        raise ConfigError(f"{where}: {shown} is not a finite number (NaN/inf)")
    return f


def _plain_number(v, where: str, integer: bool = False) -> float:
    """v as a float if it is a real number (int/float, numpy scalars too), else ConfigError."""
    if isinstance(v, bool) or not hasattr(v, "__float__") or isinstance(v, (str, bytes)):
        raise ConfigError(f"{where}: expected a number, got {type(v).__name__} {_short(v)}")
    if type(v).__module__ == "numpy" and getattr(v, "ndim", 0) != 0:
        raise ConfigError(f"{where}: expected a number, got an array")
    try:
        f = _finite(float(v), where, repr(v))
    except OverflowError:
        raise ConfigError(f"{where}: number {_short(v)} is too large") from None
    if integer and f != int(f):
        raise ConfigError(f"{where}: expected a whole number, got {v!r}")
    return f


def field_number(source, row: int, field: str, text: str) -> float:
    """A text table's field as a finite float, else a ConfigError naming the file, row and
    field (the CSV readers of robot poses, WFS data and instrument exports)."""
    t = text.strip()
    where = f"{source}: row {row}, field {field}"
    try:
        v = float(t)
    except ValueError:
        raise ConfigError(f"{where}: {t!r} is not a number") from None
    return _finite(v, where, t)


def _short(v, n: int = 40) -> str:
    s = repr(v)
    return s if len(s) <= n else s[: n - 3] + "..."


def number(v, where: str, rng: Num | None = None) -> float:
    """One strict number inside ``rng``; ConfigError naming ``where``, the range and its unit."""
    f = _plain_number(v, where, integer=bool(rng and rng.integer))
    if rng is not None:
        low = f <= rng.lo if rng.lo_open else f < rng.lo
        if low or f > rng.hi:
            raise ConfigError(f"{where}: must be {rng.describe()}, got {v!r}"
                              + (f"; check the unit ({rng.unit.strip('()')})" if rng.unit else ""))
    return f


def number_array(v, where: str, shape: tuple, rng: Num | None = None):
    """A float array of ``shape`` (None = any length on that axis) with every entry strict."""
    import numpy as np

    def walk(x, depth, path):
        if depth == len(shape):
            return number(x, f"{where}{path}", rng)
        if not isinstance(x, (list, tuple)):
            raise ConfigError(f"{where}{path}: expected a list ({len(shape) - depth}-deep nesting "
                              f"of numbers, shape {_shape_text(shape)}), got {type(x).__name__}")
        if shape[depth] is not None and len(x) != shape[depth]:
            raise ConfigError(f"{where}{path}: expected {shape[depth]} entries (shape {_shape_text(shape)}), "
                              f"got {len(x)}")
        return [walk(e, depth + 1, f"{path}[{i}]") for i, e in enumerate(x)]

    return np.asarray(walk(v, 0, ""), dtype=float)


def _shape_text(shape) -> str:
    return "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"


def check_header(data: dict, where: str, kind: str | tuple, required: bool = False,
                 versions: tuple = (SCHEMA_VERSION,)) -> None:
    """schema_version exactly an integer in ``versions`` and ``kind`` equal to ``kind``.

    required: both keys must be present (files lensforge writes); otherwise each is
    checked only when present (hand-written inputs).
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a table/object at the top level, got {type(data).__name__}")
    kinds = (kind,) if isinstance(kind, str) else tuple(kind)
    if "schema_version" in data or required:
        v = data.get("schema_version")
        if isinstance(v, bool) or not isinstance(v, int) or v not in versions:
            got = "missing" if "schema_version" not in data else f"got {type(v).__name__} {_short(v)}"
            raise ConfigError(f"{where}: schema_version must be the integer {' or '.join(map(str, versions))}, "
                              f"{got}; this lensforge reads schema_version {versions[-1]} files")
    if "kind" in data or required:
        k = data.get("kind")
        if k not in kinds:
            got = "missing" if "kind" not in data else f"got {_short(k)}"
            raise ConfigError(f"{where}: kind must be {' or '.join(map(repr, kinds))}, {got}; "
                              "is this the right file?")


def flatten(d: dict, prefix: str = "") -> dict:
    """{"a": {"b": 1}} -> {"a.b": 1} (lists stay values)."""
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "."))
        else:
            out[key] = v
    return out


def check_ranges(data: dict, ranges: dict, where: str, skip=("material",)) -> None:
    """Every key of ``ranges`` present in (nested) ``data`` is a strict number in its range.

    A list value checks each element. Values in ``skip`` (e.g. the tolerance file's
    "material" marker) are left to the reader.
    """
    flat = flatten(data) if isinstance(data, dict) else {}
    for key, rng in ranges.items():
        if key not in flat:
            continue
        v = flat[key]
        name = f"{where}: {key}" if where else key
        if isinstance(v, str) and v in skip:
            continue
        if isinstance(v, (list, tuple)):
            for i, e in enumerate(v):
                number(e, f"{name}[{i}]", rng)
        else:
            number(v, name, rng)


# --- physical ranges ---------------------------------------------------------------

# Bench. Real Shack-Hartmann sensors: lenslet pitch 30 um .. 1 mm (Thorlabs WFS: 150 um,
# 300 um; Imagine Optic HASO: 110 um .. 1 mm); apertures up to ~40 mm (ASSUMPTION: allow
# 0.5 .. 100 mm). Lasers: UV to mid-IR. The noise must be > 0: the estimator whitens
# by it (a noise of 0 makes every covariance singular).
BENCH_RANGES = {
    "laser.wavelength_nm": Num(200.0, 20000.0, "nm"),
    "laser.beam_diameter_mm": Num(0.0, 100.0, "mm", lo_open=True),
    "laser.offset_mm": Num(-100.0, 100.0, "mm"),
    "laser.slope": Num(-1.0, 1.0, "(dx/dz)"),
    "placement.distance_mm": Num(0.0, 1000.0, "mm", lo_open=True),
    "sensor.pitch_mm": Num(0.01, 2.0, "mm"),
    "sensor.aperture_mm": Num(0.5, 100.0, "mm"),
    "sensor.pupil_radius_mm": Num(0.0, 50.0, "mm", lo_open=True),
    "sensor.pupil_center_mm": Num(-50.0, 50.0, "mm"),
    "sensor.zernike_order": Num(1, 10, "", integer=True),
    "sensor.irradiance_threshold": Num(0.0, 0.999, "(fraction of the beam peak)"),
    # lenslet arrays: f = 1.6 .. 40 mm (Thorlabs MLA, Edmund); cameras: 1 .. 25 um pixels (ASSUMPTION: wider)
    "sensor.lenslet_focal_mm": Num(0.5, 100.0, "mm"),
    "sensor.pixel_mm": Num(0.0005, 0.1, "mm"),
    "sensor.subaperture_quadrature": Num(1, 16, "(rays per lenslet side)", integer=True),  # n^2 rays per lenslet
    "sensor.centroid_window_px": Num(0, 4096, "px", integer=True),
    "sensor.centroid_threshold": Num(0.0, 0.999, "(fraction of the spot peak)"),
    "sensor.focal_length_rel_sigma": Num(0.0, 0.5, "relative 1-sigma"),
    "noise.slope_sigma_urad": Num(0.0, 1e5, "urad", lo_open=True),
    "pose_limits.translation_mm": Num(0.0, 100.0, "mm", lo_open=True),
    "pose_limits.rotation_rad": Num(0.0, math.pi / 2, "rad", lo_open=True),
    "fd_steps": Num(0.0, 1.0, "(mm or rad)", lo_open=True),
    "pose_scales": Num(0.0, 1000.0, "(mm or rad)", lo_open=True),
    "rank_rtol": Num(0.0, 0.1, "", lo_open=True),
}
# Lenslets over the sensor aperture, (aperture / pitch)^2: real sensors have up to a few
# hundred per side (ASSUMPTION: 512 x 512 bounds every catalogue part); more would only
# exhaust memory in the tracer.
MAX_LENSLETS = 512 * 512
# Coefficients of one sag term list (Zernike, extended polynomial, polynomial): 231 is every
# Zernike mode up to radial order 20 (OpticStudio's Zernike Standard Sag allows 231 terms) and
# every monomial up to degree 20; more is no lens but a memory and time bomb in the tracer.
MAX_SAG_COEFFICIENTS = 231

# Lens (design / lens JSON): what a printer or a catalogue lens can be.
LENS_RANGES = {
    "thickness": Num(0.0, 100.0, "mm", lo_open=True),
    "aperture": Num(0.0, 300.0, "mm", lo_open=True),
    "edge_diameter": Num(0.0, 500.0, "mm", lo_open=True),
    "index_offset": Num(-0.5, 0.5, ""),
}

# Tolerances: each component's ranges live in its entry of asbuilt.tolerances.COMPONENT_SPECS
# (TOLERANCE_RANGES there), beside its default and draw.

# Pose matrices: translations within a robot cell (ASSUMPTION: 100 m), rotation entries |r| <= 1.
POSE_TRANSLATION = Num(-1e5, 1e5, "mm")
