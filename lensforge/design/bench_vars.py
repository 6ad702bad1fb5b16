"""Bench variables of a design: beam expander, Zernike pupil and lens-sensor distance.

A lens is measured on a bench; lensforge designs both. :class:`BenchVariables` says which
bench quantities are free and within which limits; :class:`CoDesignParameterisation`
appends them to a lens :class:`~lensforge.design.parameterisation.Parameterisation`, so
the optimisers see one unit box. Names (in the design file's ``parameters``):

* ``bench.expander``: index into ``expanders`` (rounded; the catalogue of real
  expanders, ``expanders.py``), or with ``expanders = ()`` the continuous magnification
  ``bench.magnification``. The laser's own beam times the magnification must fit the
  WFS aperture; the beam at the lens is ``laser.beam_diameter_mm``.
* ``bench.pupil_radius_mm``, ``bench.pupil_center_x_mm``, ``bench.pupil_center_y_mm``:
  the Zernike pupil (it must fit the sensor; the design constraints keep it lit).
* ``bench.distance_mm``: the nominal lens-sensor distance.

Default limits (ASSUMPTIONS, lensforge choices): pupil radius 0.9-4.0 mm (from today's
pupil up to 70 % of the WFS40's 5.63 mm half-aperture), centre within +-1 mm of the axis;
distance 12-40 mm: the lens (up to 10 mm thick) keeps >= 7 mm between its back vertex
and the lenslet plane for the WFS40's front housing (not sourced) at the near end, and
the far end bounds the arm's lever between lens and sensor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..optics.bench import Bench
from ..optics.lens import Lens
from .expanders import expander, fitting_expanders
from .parameterisation import BoxBounds, Parameterisation

__all__ = ["BENCH_VARIABLES", "BenchVariables", "CoDesignParameterisation", "bench_summary", "bench_label"]

BENCH_VARIABLES = ("expander", "pupil_radius", "pupil_center", "distance")


@dataclass(frozen=True)
class BenchVariables:
    """Which bench quantities a design may change (``free``, a subset of BENCH_VARIABLES) and
    their limits: expanders (catalogue names to choose from; () = continuous magnification in
    ``magnification``), pupil_radius_mm (lo, hi), pupil_center_mm (half-width of the box
    about the axis), distance_mm (lo, hi)."""

    free: tuple = BENCH_VARIABLES
    expanders: tuple = ("none", "GBE02-A", "GBE03-A", "GBE05-A")
    magnification: tuple = (1.0, 3.2)
    pupil_radius_mm: tuple = (0.9, 4.0)
    pupil_center_mm: float = 1.0
    distance_mm: tuple = (12.0, 40.0)

    def __post_init__(self):
        free = tuple(self.free)
        object.__setattr__(self, "free", free)
        bad = set(free) - set(BENCH_VARIABLES)
        if bad:
            raise ConfigError(f"bench variables: unknown {sorted(bad)}; use some of {', '.join(BENCH_VARIABLES)}")
        for n in self.expanders:
            expander(n)
        for name in ("magnification", "pupil_radius_mm", "distance_mm"):
            lo, hi = (float(v) for v in getattr(self, name))
            if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo <= hi):
                raise ConfigError(f"bench variables: {name} needs 0 < lo <= hi, got {getattr(self, name)!r}")
        if not (np.isfinite(self.pupil_center_mm) and self.pupil_center_mm >= 0):
            raise ConfigError(f"bench variables: pupil_center_mm must be >= 0, got {self.pupil_center_mm!r}")

    def to_dict(self) -> dict:
        return {"free": list(self.free), "expanders": list(self.expanders), "magnification": list(self.magnification),
                "pupil_radius_mm": list(self.pupil_radius_mm), "pupil_center_mm": self.pupil_center_mm,
                "distance_mm": list(self.distance_mm)}

    @classmethod
    def none(cls) -> "BenchVariables":
        return cls(free=())

    @classmethod
    def parse(cls, spec: str | None) -> "BenchVariables":
        """From the CLI's --bench-free: 'all', 'none' or a comma list of BENCH_VARIABLES."""
        key = (spec or "all").strip().lower()
        if key == "all":
            return cls()
        if key == "none":
            return cls.none()
        return cls(free=tuple(s.strip() for s in key.split(",") if s.strip()))


def _laser_beam(bench: Bench) -> float:
    """The laser's own beam diameter (mm): the beam at the lens over the expander's magnification."""
    return bench.laser.beam_diameter_mm / bench.laser.expander_magnification


@dataclass(frozen=True)
class CoDesignParameterisation(BoxBounds):
    """A lens parameterisation followed by the free bench variables on a base bench.

    Same interface as ``Parameterisation`` (n, names, lo, hi, to_unit, from_unit, in_bounds,
    to_lens, from_lens, bounds_dict, labels, template, model) plus to_bench(p, base)."""

    lens_par: Parameterisation
    variables: BenchVariables
    base: Bench
    bench_names: tuple
    bench_lower: tuple
    bench_upper: tuple
    expanders: tuple

    @classmethod
    def build(cls, lens_par: Parameterisation, variables: BenchVariables, base: Bench) -> "CoDesignParameterisation":
        names, lo, hi = [], [], []
        v = variables
        exp = ()
        if "expander" in v.free:
            if v.expanders:
                exp = fitting_expanders(_laser_beam(base), base.sensor.aperture_mm, v.expanders)
                if not exp:
                    raise ConfigError(f"bench variables: no expander of {list(v.expanders)} keeps the "
                                      f"{_laser_beam(base):g} mm laser beam inside the {base.sensor.aperture_mm} mm sensor")
                names.append("bench.expander")
                lo.append(-0.5)
                hi.append(len(exp) - 0.5)
            else:
                top = min(v.magnification[1], base.sensor.aperture_mm / _laser_beam(base))
                if top < v.magnification[0]:
                    raise ConfigError("bench variables: the smallest magnification over-fills the sensor aperture")
                names.append("bench.magnification")
                lo.append(float(v.magnification[0]))
                hi.append(float(top))
        if "pupil_radius" in v.free:
            names.append("bench.pupil_radius_mm")
            lo.append(float(v.pupil_radius_mm[0]))
            hi.append(float(min(v.pupil_radius_mm[1], 0.5 * base.sensor.aperture_mm)))
        if "pupil_center" in v.free and v.pupil_center_mm > 0:
            for axis in "xy":
                names.append(f"bench.pupil_center_{axis}_mm")
                lo.append(-float(v.pupil_center_mm))
                hi.append(float(v.pupil_center_mm))
        if "distance" in v.free:
            names.append("bench.distance_mm")
            lo.append(float(v.distance_mm[0]))
            hi.append(float(v.distance_mm[1]))
        return cls(lens_par, v, base, tuple(names), tuple(lo), tuple(hi), exp)

    # the Parameterisation interface -------------------------------------------------
    @property
    def model(self) -> str:
        return self.lens_par.model

    @property
    def template(self) -> Lens:
        return self.lens_par.template

    @property
    def names(self) -> tuple:
        return self.lens_par.names + self.bench_names

    @property
    def lower(self) -> tuple:
        return self.lens_par.lower + self.bench_lower

    @property
    def upper(self) -> tuple:
        return self.lens_par.upper + self.bench_upper

    def labels(self) -> dict:
        lab = self.lens_par.labels()
        text = {"bench.expander": f"beam expander (index into {list(self.expanders)})",
                "bench.magnification": "beam expander magnification",
                "bench.pupil_radius_mm": "Zernike pupil radius (mm)",
                "bench.pupil_center_x_mm": "Zernike pupil centre x (mm)",
                "bench.pupil_center_y_mm": "Zernike pupil centre y (mm)",
                "bench.distance_mm": "lens-sensor distance (mm)"}
        return {**lab, **{n: text[n] for n in self.bench_names}}

    def split(self, p) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(p, dtype=float)
        k = self.lens_par.n
        return p[:k], p[k:]

    def to_lens(self, p) -> Lens:
        return self.lens_par.to_lens(self.split(p)[0])

    def to_bench(self, p, base: Bench | None = None) -> Bench:
        """The bench of parameter vector p (ConfigError if it is not a valid bench)."""
        base = self.base if base is None else base
        vals = dict(zip(self.bench_names, self.split(p)[1]))
        laser, sensor, placement = {}, {}, {}
        beam0 = _laser_beam(base)
        if "bench.expander" in vals:
            e = expander(self.expanders[int(np.clip(np.rint(vals["bench.expander"]), 0, len(self.expanders) - 1))])
            laser = {"expander": "" if e.name == "none" else e.name, "expander_magnification": e.magnification,
                     "beam_diameter_mm": beam0 * e.magnification}
        elif "bench.magnification" in vals:
            mag = float(vals["bench.magnification"])
            laser = {"expander": "continuous", "expander_magnification": mag, "beam_diameter_mm": beam0 * mag}
        if "bench.pupil_radius_mm" in vals:
            sensor["pupil_radius_mm"] = float(vals["bench.pupil_radius_mm"])
        if "bench.pupil_center_x_mm" in vals:
            sensor["pupil_center_mm"] = (float(vals["bench.pupil_center_x_mm"]), float(vals["bench.pupil_center_y_mm"]))
        if "bench.distance_mm" in vals:
            placement["distance_mm"] = float(vals["bench.distance_mm"])
        return base.replace(**{k: v for k, v in (("laser", laser), ("sensor", sensor), ("placement", placement)) if v})

    def bench_vector(self, bench: Bench) -> np.ndarray:
        """The bench variables of ``bench`` (clipped into the bounds)."""
        out = []
        for n in self.bench_names:
            if n == "bench.expander":
                name = bench.laser.expander or "none"
                out.append(float(self.expanders.index(name)) if name in self.expanders else 0.0)
            elif n == "bench.magnification":
                out.append(bench.laser.expander_magnification)
            elif n == "bench.pupil_radius_mm":
                out.append(bench.sensor.pupil_radius_mm)
            elif n == "bench.pupil_center_x_mm":
                out.append(bench.sensor.pupil_center_mm[0])
            elif n == "bench.pupil_center_y_mm":
                out.append(bench.sensor.pupil_center_mm[1])
            elif n == "bench.distance_mm":
                out.append(bench.placement.distance_mm)
        return np.clip(np.array(out, dtype=float), self.bench_lower, self.bench_upper)

    def from_lens(self, lens: Lens, bench: Bench | None = None) -> np.ndarray:
        return np.concatenate([self.lens_par.from_lens(lens), self.bench_vector(self.base if bench is None else bench)])


def bench_summary(bench: Bench) -> dict:
    """The design-relevant bench in a few numbers (for evaluate/compare and the design file)."""
    return {"expander": bench.laser.expander or "none", "magnification": bench.laser.expander_magnification,
            "beam_diameter_mm": bench.laser.beam_diameter_mm, "pupil_radius_mm": bench.sensor.pupil_radius_mm,
            "pupil_center_mm": list(bench.sensor.pupil_center_mm), "distance_mm": bench.placement.distance_mm,
            "spot_assignment": bench.sensor.spot_assignment}


def bench_label(bench: Bench) -> str:
    """'GBE02-A 7 mm / pupil 2.5 mm @ (0, 0) / 20 mm' style one-liner."""
    s = bench_summary(bench)
    cx, cy = s["pupil_center_mm"]
    centre = "" if cx == 0 and cy == 0 else f" @ ({cx:.2f}, {cy:.2f})"
    return (f"{s['expander']} {s['beam_diameter_mm']:.3g} mm beam, pupil r {s['pupil_radius_mm']:.3g} mm{centre}, "
            f"d {s['distance_mm']:.3g} mm")


