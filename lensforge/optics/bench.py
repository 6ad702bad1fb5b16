"""The measurement bench: laser, lens placement, Shack-Hartmann sensor, noise.

Defaults are the paper's hardware (sources in each field's comment); values that are
assumptions rather than sourced facts say so. A bench is a frozen dataclass and
round-trips through TOML (``load_bench`` / ``save_bench``) with strict checking:
unknown keys, wrong types and non-finite numbers are errors naming the field.
"""

from __future__ import annotations

from os import PathLike

import dataclasses
import math
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import tomli_w

from ..errors import ConfigError
from ..fileio import read_toml, write_atomic
from ..input_checks import BENCH_RANGES, MAX_LENSLETS, Num, check_header, check_ranges, number

__all__ = ["Laser", "Sensor", "Placement", "Noise", "PoseLimits", "Bench", "SPOT_ASSIGNMENTS", "CROSSTALK_MODELS", "load_bench",
           "save_bench"]


@dataclass(frozen=True)
class Laser:
    """Collimated Gaussian beam travelling along +z of {S}.

    Thorlabs CPS532-C2: 532 nm, collimated, ~3.5 mm beam (taken as the 1/e^2 diameter).
    offset_mm: beam centre (x, y) in {S}; slope: beam direction (dx/dz, dy/dz).
    beam_diameter_mm is the beam that reaches the lens, i.e. after the beam expander, if any:
    expander names it (a ``design.expanders.EXPANDERS`` entry, "" for none) and
    expander_magnification is its magnification, so the laser's own beam is
    beam_diameter_mm / expander_magnification.
    """

    wavelength_nm: float = 532.0
    beam_diameter_mm: float = 3.5
    expander: str = ""
    expander_magnification: float = 1.0
    offset_mm: tuple = (0.0, 0.0)
    slope: tuple = (0.0, 0.0)


@dataclass(frozen=True)
class Placement:
    """Nominal lens placement: {O} at z = -distance_mm in {S}, axes parallel.

    distance_mm = 20 is an ASSUMPTION (the paper does not give it): close enough that
    the f = 50 mm reference lens still fills the default pupil.
    """

    distance_mm: float = 20.0


@dataclass(frozen=True)
class Sensor:
    """Shack-Hartmann sensor (Thorlabs WFS40-7AR) and its Zernike pupil.

    pitch_mm: lenslet pitch, 150 um (Thorlabs spec); aperture_mm: 11.26 mm square
    (Thorlabs spec); pupil_radius_mm / pupil_center_mm: the fixed circular Zernike
    pupil in {S} (0.9 mm and on-axis are ASSUMPTIONS sized to the 3.5 mm beam);
    zernike_order: highest radial order fitted (4 -> 14 modes without piston; the
    instrument offers up to 10); irradiance_threshold: a lenslet is valid when its
    sub-aperture mean irradiance is at least this fraction of the input beam's peak
    (exp(-2), the 1/e^2 level; ASSUMPTION).

    What a lenslet measures (``centroid.py``): its spot centroid, i.e. the
    irradiance-weighted mean slope over its square sub-aperture, integrated by a
    ``subaperture_quadrature`` x ``subaperture_quadrature`` Gauss-Legendre rule of aimed
    rays (1 = the old lenslet-centre sample).
    lenslet_focal_mm: lenslet focal length. ASSUMPTION 5.2 mm: the Thorlabs MLA150
    microlens data of the WFS40-7AR could not be found here; values quoted for 150 um
    MLAs lie in 4.1-6.7 mm (``benchmarks/bench_sensor_range.py`` shows results over that
    span). pixel_mm: camera pixel, 5.5 um (WFS40: 2048 px over the 11.26 mm aperture).
    spot_assignment: how the software assigns a spot to its lenslet (bench setting):
    'fixed' -- each lenslet's own pitch x pitch window (lenslet-bound dynamic range,
    Akondi & Dubra, Opt. Express 29(6) 8417, 2021); 'tracking' -- spots may leave their
    window while neighbouring spots do not overlap and stay on the camera (that paper's
    optical dynamic range; ASSUMPTION that the WFS40 software tracks this far: Thorlabs
    quotes its range as a local-curvature limit, whose value was not found here);
    'none' -- no range check (the pre-issue-14 model). The default is 'tracking'.
    centroid_window_px: side of the square pixel window, centred on the spot, in which
    the centroid is taken (ASSUMPTION 27 px = one 150 um pitch; 0 = complete-spot
    centroid); centroid_threshold: noise cut as a fraction of the spot peak
    subtracted before the centroid (ASSUMPTION 0, see ``centroid.py``).
    crosstalk: 'none' (each lenslet alone, its window centred on its spot), 'neighbours'
    (``centroid.crosstalk_slopes``: the 7 x 7 neighbours' coherent spots in each whole-pixel
    window, the block's field extrapolated from the own lenslet's, against the factory reference) or
    'cells' (``centroid.cell_crosstalk_slopes``: every lit lenslet within 4 rings, each with its own
    traced field, propagated to the camera as the Rayleigh-Sommerfeld integral; issue 21); camera_offset_px: the camera pixel
    grid's offset from the lenslet array along x and y (ASSUMPTION 1/3 px: not known; 0
    puts the central row's and column's reference spots on pixel corners, a placement tie).
    focal_length_rel_sigma: relative 1-sigma uncertainty of the effective lenslet focal
    length (the software divides each spot displacement by its calibrated f, so a true f
    off by a fraction e scales every reported slope by 1 + e). 0 (default): f is known;
    > 0: the joint calibration estimates the gain with this prior (about
    ``lenslet_focal_mm``, the device's value when the user gives it) and reports the
    effective focal length with its 1-sigma. ASSUMPTION: no datasheet gives the MLA's
    calibration uncertainty; 0.01 is a cautious value for a device's own MLA data, 0.1
    for the unsourced 5.2 mm default (4.1-6.7 mm quoted for 150 um MLAs).
    validated_slope_mrad: largest lenslet slope component at which the sensor model (what a
    lenslet reports, ``centroid.py``) is trusted; designs keep every pupil lenslet within it
    over their working range and calibration plan. ASSUMPTION 200 mrad (a spot then walks
    f s = 1 mm, ~7 pitches, on the camera; neither the lenslet's off-axis aberrations nor
    the tracking software have been checked that far): a placeholder for the sensor-physics
    model's validated range, to be tightened there. 0 = no bound.
    lenslet_aperture: 'square' (fully filled pitch x pitch cells, the default) or 'round' (discs of
    ``lenslet_diameter_mm`` with opaque gaps: a chrome-masked array such as the MLA150-5C, whose spec
    sheet, as cited in issue 21, gives 140 um lenslets at 150 um pitch). Only the 'cells' model renders
    the shape (each disc as Gauss-Legendre rows with exact chords, ``centroid.disc_rows``; 30-50x the
    square cells' cost); the own-centroid and 'neighbours' models assume square cells, so a round bench
    needs ``crosstalk = 'cells'``.
    """

    pitch_mm: float = 0.150
    aperture_mm: float = 11.26
    pupil_radius_mm: float = 0.9
    pupil_center_mm: tuple = (0.0, 0.0)
    zernike_order: int = 4
    irradiance_threshold: float = math.exp(-2.0)
    lenslet_focal_mm: float = 5.2
    pixel_mm: float = 0.0055
    spot_assignment: str = "tracking"
    subaperture_quadrature: int = 2
    centroid_window_px: int = 27
    centroid_threshold: float = 0.0
    crosstalk: str = "none"
    camera_offset_px: float = 1.0 / 3.0
    validated_slope_mrad: float = 200.0
    focal_length_rel_sigma: float = 0.0
    lenslet_aperture: str = "square"
    lenslet_diameter_mm: float = 0.140


@dataclass(frozen=True)
class Noise:
    """Sensor noise: independent Gaussian noise on each lenslet slope (x and y).

    slope_sigma_urad: 1-sigma slope noise per lenslet and axis. ASSUMPTION: a spot
    centroid precision of ~1/100 pixel (WFS40: 5.5 um pixels, 2048 px over 11.26 mm)
    behind a lenslet of focal length 5.2-6.7 mm (sensor.lenslet_focal_mm, assumed) gives
    0.055 um / (5.2-6.7 mm) = 8-11 urad per frame; 8 urad is kept (1/130 px at 5.2 mm). Over the default pupil this is ~0.7 nm RMS
    of fitted wavefront, below Thorlabs' quoted sensitivity of lambda/100 (5 nm).
    """

    slope_sigma_urad: float = 8.0


@dataclass(frozen=True)
class PoseLimits:
    """Valid range of the lens pose relative to its nominal placement.

    translation_mm / rotation_rad: max |component|; larger poses are rejected.
    ASSUMPTION: +-5 mm and +-10 deg cover gripper and robot errors by a wide margin.
    """

    translation_mm: float = 5.0
    rotation_rad: float = math.radians(10.0)


@dataclass(frozen=True)
class Bench:
    """Everything the forward model needs besides the lens (frozen; TOML via load_bench/save_bench).

    Parameters
    ----------
    laser : Laser
        Wavelength (nm), beam diameter (mm), beam offset (mm) and slope in {S}.
    placement : Placement
        Nominal lens placement: {O} at z = -distance_mm in {S}, axes parallel.
    sensor : Sensor
        Shack-Hartmann sensor: pitch, aperture, pupil, Zernike order, centroid model.
    noise : Noise
        Measurement noise (slope 1-sigma per lenslet and axis, urad).
    pose_limits : PoseLimits
        Valid pose range about nominal (mm, rad).
    fd_steps : tuple of float, shape (6,)
        Steps per DOF (mm, mm, mm, rad, rad, rad) of the central differences that check
        the exact S in the tests (tests/test_observability.py).
    pose_scales : tuple of float, shape (6,)
        Expected pose uncertainty per DOF (mm, rad) that scales S for the metrics
        (1 mm and 1 deg by default, DESIGN.md).
    rank_rtol : float
        Singular values below rank_rtol * sigma_max of the scaled, whitened S count as lost rank.
    """

    laser: Laser = field(default_factory=Laser)
    placement: Placement = field(default_factory=Placement)
    sensor: Sensor = field(default_factory=Sensor)
    noise: Noise = field(default_factory=Noise)
    pose_limits: PoseLimits = field(default_factory=PoseLimits)
    fd_steps: tuple = (1e-3, 1e-3, 1e-3, 1e-4, 1e-4, 1e-4)
    pose_scales: tuple = (1.0, 1.0, 1.0, math.radians(1.0), math.radians(1.0), math.radians(1.0))
    rank_rtol: float = 1e-7

    def __post_init__(self):
        check_ranges(self.to_dict(), BENCH_RANGES, "")
        _validate(self)
        s = self.sensor
        if (s.aperture_mm / s.pitch_mm) ** 2 > MAX_LENSLETS:
            raise ConfigError(f"sensor.pitch_mm: {s.aperture_mm} mm / {s.pitch_mm} mm gives "
                              f"{(s.aperture_mm / s.pitch_mm) ** 2:.3g} lenslets, over the limit of "
                              f"{MAX_LENSLETS} (512 x 512); check the units (mm)")

    @classmethod
    def default(cls) -> "Bench":
        """The built-in default bench (paper hardware, documented assumptions)."""
        return cls()

    def to_dict(self) -> dict:
        return _to_plain(self)

    @classmethod
    def from_dict(cls, d: dict, where: str = "bench") -> "Bench":
        return _from_dict(cls, d, where)

    def own_centroid(self) -> "Bench":
        """This bench with each lenslet's own centroid (``sensor.crosstalk`` 'none', square cells): the fast proxy a
        cross-talk fit iterates on and a plan searches with."""
        if self.sensor.crosstalk == "none":
            return self
        return self.replace(sensor={"crosstalk": "none", "lenslet_aperture": "square"})

    def replace(self, **changes) -> "Bench":
        """Copy with changes; sub-tables by dict, e.g. replace(sensor={'zernike_order': 6})."""
        kw = {}
        for k, v in changes.items():
            cur = getattr(self, k)
            if dataclasses.is_dataclass(cur) and isinstance(v, dict):
                v = dataclasses.replace(cur, **v)
            kw[k] = v
        return dataclasses.replace(self, **kw)


# --- validation -----------------------------------------------------------------

_POSITIVE = {
    "laser.wavelength_nm", "laser.beam_diameter_mm", "placement.distance_mm", "sensor.pitch_mm",
    "sensor.aperture_mm", "sensor.pupil_radius_mm", "sensor.zernike_order", "pose_limits.translation_mm",
    "pose_limits.rotation_rad", "rank_rtol", "fd_steps", "pose_scales", "sensor.lenslet_focal_mm",
    "sensor.pixel_mm", "sensor.subaperture_quadrature", "laser.expander_magnification", "sensor.lenslet_diameter_mm",
}
SPOT_ASSIGNMENTS = ("fixed", "tracking", "none")
CROSSTALK_MODELS = ("none", "neighbours", "cells")
LENSLET_APERTURES = ("square", "round")
_NONNEG = {"noise.slope_sigma_urad", "sensor.irradiance_threshold", "sensor.centroid_window_px",
           "sensor.centroid_threshold", "sensor.validated_slope_mrad", "sensor.focal_length_rel_sigma"}
_LENGTHS = {"offset_mm": 2, "slope": 2, "pupil_center_mm": 2, "fd_steps": 6, "pose_scales": 6}


def _check_number(name: str, v, integer: bool = False):
    number(v, name, Num(-math.inf, math.inf, integer=integer))


def _validate(obj, prefix: str = "") -> None:
    for f in fields(obj):
        name = prefix + f.name
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            _validate(v, name + ".")
            continue
        if f.name == "spot_assignment":
            if v not in SPOT_ASSIGNMENTS:
                raise ConfigError(f"{name}: must be one of {list(SPOT_ASSIGNMENTS)}, got {v!r}")
            continue
        if f.name == "crosstalk":
            if v not in CROSSTALK_MODELS:
                raise ConfigError(f"{name}: must be one of {list(CROSSTALK_MODELS)}, got {v!r}")
            continue
        if f.name == "lenslet_aperture":
            if v not in LENSLET_APERTURES:
                raise ConfigError(f"{name}: must be one of {list(LENSLET_APERTURES)}, got {v!r}")
            continue
        if f.name == "expander":
            if not isinstance(v, str):
                raise ConfigError(f"{name}: expected a beam expander name (text, \"\" for none), got {v!r}")
            continue
        if f.name in _LENGTHS:
            if not isinstance(v, (tuple, list)) or len(v) != _LENGTHS[f.name]:
                raise ConfigError(f"{name}: expected a list of {_LENGTHS[f.name]} numbers, got {v!r}")
            for i, e in enumerate(v):
                _check_number(f"{name}[{i}]", e)
            vals = list(map(float, v))
        else:
            _check_number(name, v, integer=f.name in ("zernike_order", "subaperture_quadrature", "centroid_window_px"))
            vals = [float(v)]
        if name in _POSITIVE and min(vals) <= 0:
            raise ConfigError(f"{name}: must be > 0, got {v!r}")
        if name in _NONNEG and min(vals) < 0:
            raise ConfigError(f"{name}: must be >= 0, got {v!r}")
    if isinstance(obj, Sensor):
        if not 1 <= obj.zernike_order <= 10:
            raise ConfigError(f"sensor.zernike_order: must be 1..10 (the WFS40 reports up to order 10), got {obj.zernike_order}")
        reach = math.hypot(*obj.pupil_center_mm) + obj.pupil_radius_mm
        if max(abs(obj.pupil_center_mm[0]), abs(obj.pupil_center_mm[1])) + obj.pupil_radius_mm > obj.aperture_mm / 2:
            raise ConfigError(
                f"sensor.pupil_radius_mm: the pupil (centre {obj.pupil_center_mm}, radius {obj.pupil_radius_mm}) "
                f"does not fit the {obj.aperture_mm} mm sensor; shrink or re-centre it"
            )
        n_modes = (obj.zernike_order + 1) * (obj.zernike_order + 2) // 2 - 1
        n_lenslets = math.pi * obj.pupil_radius_mm**2 / obj.pitch_mm**2
        if 2 * n_lenslets < 2 * n_modes:
            raise ConfigError(
                f"sensor.pupil_radius_mm: ~{n_lenslets:.0f} lenslets cannot determine {n_modes} Zernike modes; "
                "enlarge the pupil or lower zernike_order"
            )
        if obj.lenslet_aperture == "round" and obj.lenslet_diameter_mm > obj.pitch_mm * (1 + 1e-12):
            raise ConfigError(f"sensor.lenslet_diameter_mm: a round lenslet of {obj.lenslet_diameter_mm} mm does not fit "
                              f"its {obj.pitch_mm} mm pitch (give the diameter in mm, e.g. 0.140)")
        if obj.lenslet_aperture == "round" and obj.crosstalk != "cells":
            raise ConfigError("sensor.lenslet_aperture: 'round' lenslets are rendered only by the 'cells' sensor model; "
                              "set sensor.crosstalk = \"cells\" (or lenslet_aperture = \"square\")")
        if obj.lenslet_aperture == "round" and obj.centroid_window_px == 0:
            raise ConfigError("sensor.lenslet_aperture: 'round' lenslets are rendered in the pixel window only; set "
                              "sensor.centroid_window_px (e.g. 27) or lenslet_aperture = \"square\"")
        if not 1 <= obj.subaperture_quadrature <= 6:
            raise ConfigError(f"sensor.subaperture_quadrature: must be 1..6 points per axis, got {obj.subaperture_quadrature}")
        if obj.centroid_threshold >= 1:
            raise ConfigError(f"sensor.centroid_threshold: must be < 1 (fraction of the spot peak), got {obj.centroid_threshold}")
        if obj.irradiance_threshold >= 1:
            raise ConfigError(f"sensor.irradiance_threshold: must be < 1 (fraction of beam peak), got {obj.irradiance_threshold}")
        del reach


def _to_plain(obj):
    if dataclasses.is_dataclass(obj):
        return {f.name: _to_plain(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, tuple):
        return [_to_plain(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    return obj


def _from_dict(cls, d, where):
    if not isinstance(d, dict):
        raise ConfigError(f"{where}: expected a table, got {type(d).__name__}")
    known = {f.name: f for f in fields(cls)}
    unknown = set(d) - set(known)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {sorted(known)}")
    kw = {}
    defaults = cls()  if cls is not Bench else None
    for name, value in d.items():
        f = known[name]
        sub = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
        if dataclasses.is_dataclass(sub):
            kw[name] = _from_dict(type(sub), value, f"{where}.{name}")
        elif isinstance(value, list):
            kw[name] = tuple(value)
        else:
            kw[name] = value
    del defaults
    try:
        return cls(**kw)
    except ConfigError as e:
        msg = str(e)
        raise ConfigError(msg if msg.startswith(where) else f"{where}.{msg}") from None


def load_bench(path: str | PathLike[str]) -> Bench:
    """Read a bench TOML file (``kind = "lensforge.bench"``); missing keys take the defaults.

    Parameters
    ----------
    path : str or os.PathLike
        The TOML file.

    Returns
    -------
    Bench
        The validated bench.

    Raises
    ------
    ConfigError
        A bad header, key, type or value (the message names the file and field).
    """
    d = read_toml(path, "bench file")
    check_header(d, f"bench file {Path(path).name}", kind="lensforge.bench")
    d.pop("schema_version", None)
    d.pop("kind", None)
    return Bench.from_dict(d, f"{Path(path).name}:bench")


def save_bench(bench: Bench, path: str | PathLike[str]) -> Path:
    """Write the bench as TOML (atomically: the file is complete or absent).

    Parameters
    ----------
    bench : Bench
        The bench to write.
    path : str or os.PathLike
        Destination file.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    return write_atomic(path, tomli_w.dumps(bench.to_dict()))
