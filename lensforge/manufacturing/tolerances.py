"""As-built tolerance model of a printed (and polished) lens, and its sampler.

Components (names as in the TOML tables and in :meth:`Tolerances.component_names`):

- ``polishing``: material removed from each polished surface, a uniform depth plus a
  radial roll-off toward the edge, removal(r) = depth + rolloff (r / R_a)^power with
  R_a the clear-aperture radius. Depths are non-negative: drawn from a gamma
  distribution with the given mean and standard deviation.
- ``form``: random low-order form error per surface, Noll Zernike modes (RMS
  normalised over the clear aperture) with total RMS ``rms_mm`` split equally.
- ``thickness``: centre-thickness error (normal), split equally between the vertices.
- ``index``: refractive-index offset, normal; defaults are the material's
  index_sigma (absolute uncertainty) and batch_sigma (batch to batch).
- ``shrinkage``: isotropic linear cure shrinkage f (normal, material default); the
  whole lens scales about the origin of {O} by s = 1 - f.
- ``ripple``: residual layer staircase on *unpolished* surfaces, modelled as
  z = sag + a sin(2 pi sag / h) (layers of constant sag: optical axis along the
  build direction, the worst case).

The as-built lens keeps the nominal frame {O}: removals are sag changes relative to
the nominal vertex planes (a constant term of the surface), the thickness error
moves both vertices by half of it. Random numbers are drawn in a fixed order and
number whatever the values, so ``only(name)`` samples with the same seed share the
draws of the full model (common random numbers for variance budgets).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.special import gammaincinv

from ..errors import ConfigError
from ..fileio import read_toml, write_atomic
from ..schema import TOLERANCE_RANGES, check_header, check_ranges
from ..optics.lens import Lens
from ..optics.materials import Material
from ..optics.surfaces import CanonicalSurface, Freeform
from ..optics.zernike import zernike_monomials

__all__ = ["Tolerances", "load_tolerances", "save_tolerances", "sample_as_built", "scale_canonical",
           "COMPONENTS", "COMPONENT_SPECS", "ToleranceComponent", "DEFAULT_TOLERANCES_FILE"]

DEFAULT_TOLERANCES_FILE = Path(__file__).with_name("tolerances-default.toml")
SCHEMA_VERSION = 1
MATERIAL = "material"  # TOML value meaning "take it from the lens material"


@dataclass(frozen=True)
class ToleranceComponent:
    """One tolerance component, everything about it in one place.

    table: its TOML table, {TOML key: Tolerances field}; non_negative: fields that
    must be >= 0 (validation); scaled: the magnitudes its budget scale factor
    multiplies (shape parameters are left alone); main: (field, unit) naming its size
    in the budget table (after ``Tolerances.resolved``); draw(rng, tolerances): the
    standard random numbers one as-built lens takes from it (a fixed count whatever
    the values, for common random numbers); draw_rank: its place in the draw order
    (fixed: changing it changes every seeded study).
    """

    name: str
    table: dict
    scaled: tuple
    main: tuple
    non_negative: tuple = ()
    draw: Callable = field(default=lambda rng, t: np.empty(0), compare=False)
    draw_rank: int = 99


# The registry, in the order of the TOML file. A new component: its Tolerances fields,
# one entry here, and its effect in sample_as_built.
COMPONENT_SPECS = {c.name: c for c in (
    ToleranceComponent(
        "polishing",
        {"depth_mm": "polish_depth_mm", "depth_sigma_mm": "polish_depth_sigma_mm", "rolloff_mm": "polish_rolloff_mm",
         "rolloff_sigma_mm": "polish_rolloff_sigma_mm", "rolloff_power": "polish_rolloff_power",
         "surfaces": "polished_surfaces"},
        scaled=("polish_depth_mm", "polish_depth_sigma_mm", "polish_rolloff_mm", "polish_rolloff_sigma_mm"),
        main=("polish_depth_mm", "mm"),
        non_negative=("polish_depth_mm", "polish_depth_sigma_mm", "polish_rolloff_mm", "polish_rolloff_sigma_mm"),
        draw=lambda rng, t: rng.uniform(size=(2, 2)), draw_rank=1),  # (surface, depth/rolloff)
    ToleranceComponent(
        "form", {"rms_mm": "form_rms_mm", "modes": "form_modes"}, scaled=("form_rms_mm",),
        main=("form_rms_mm", "mm RMS"), non_negative=("form_rms_mm",),
        draw=lambda rng, t: rng.standard_normal((2, len(t.form_modes))), draw_rank=0),
    ToleranceComponent(
        "thickness", {"mean_mm": "thickness_mean_mm", "sigma_mm": "thickness_sigma_mm"},
        scaled=("thickness_mean_mm", "thickness_sigma_mm"), main=("thickness_sigma_mm", "mm (1 sigma)"),
        non_negative=("thickness_sigma_mm",), draw=lambda rng, t: rng.standard_normal(1), draw_rank=2),
    ToleranceComponent(
        "index", {"mean": "index_mean", "sigma": "index_sigma", "batch_sigma": "index_batch_sigma",
                  "factor": "index_factor"},
        scaled=("index_mean", "index_sigma", "index_batch_sigma"), main=("index_sigma", "(1 sigma)"),
        non_negative=("index_sigma", "index_batch_sigma", "index_factor"),
        draw=lambda rng, t: rng.standard_normal(2), draw_rank=3),  # (absolute, batch)
    ToleranceComponent(
        "shrinkage", {"mean": "shrinkage_mean", "sigma": "shrinkage_sigma", "factor": "shrinkage_factor"},
        scaled=("shrinkage_mean", "shrinkage_sigma"), main=("shrinkage_sigma", "(1 sigma, linear)"),
        non_negative=("shrinkage_sigma", "shrinkage_factor"),
        draw=lambda rng, t: rng.standard_normal(1), draw_rank=4),
    ToleranceComponent(
        "ripple", {"amplitude_mm": "ripple_amplitude_mm", "period_mm": "ripple_period_mm"},
        scaled=("ripple_amplitude_mm",), main=("ripple_amplitude_mm", "mm"), non_negative=("ripple_amplitude_mm",)),
)}
COMPONENTS = tuple(COMPONENT_SPECS)
_TABLES = {n: c.table for n, c in COMPONENT_SPECS.items()}  # TOML table -> {TOML key: dataclass field}
_TOML_NAME = {f: f"{t}.{k}" for t, m in _TABLES.items() for k, f in m.items()}
_SCALED = {n: c.scaled for n, c in COMPONENT_SPECS.items()}
_NON_NEGATIVE = tuple(f for c in COMPONENT_SPECS.values() for f in c.non_negative)
_MAX_MODE = 66  # Noll modes up to radial order 10


@dataclass(frozen=True)
class Tolerances:
    """As-built tolerances (lengths mm; 1-sigma values). Each default says where it comes from.

    None in the index and shrinkage fields means "the lens material's value"
    (Material.index_sigma, batch_sigma, shrinkage, shrinkage_sigma), multiplied by
    index_factor / shrinkage_factor.
    """

    # Polishing. SOURCED: the paper's printed lens was sanded and polished on both
    # surfaces (Optics Express 30(9) 14368, Sec. 4.3). ASSUMPTION: about one 25 um
    # layer is removed to clear the staircase (mean 25 um, sd 10 um), with 5 um
    # (sd 3 um) extra removal at the clear-aperture edge growing as r^4 (hand
    # polishing rolls the edge off).
    polish_depth_mm: float = 0.025
    polish_depth_sigma_mm: float = 0.010
    polish_rolloff_mm: float = 0.005
    polish_rolloff_sigma_mm: float = 0.003
    polish_rolloff_power: int = 4
    polished_surfaces: tuple = ("front", "back")
    # Form error. ASSUMPTION: 2 um RMS per surface over Noll modes 2..11 (tilt to
    # primary spherical), typical of hand-polished SLA optics.
    form_rms_mm: float = 0.002
    form_modes: tuple = tuple(range(2, 12))
    # Centre thickness. ASSUMPTION: 50 um sd, about two Form 2 layers, no bias.
    thickness_mean_mm: float = 0.0
    thickness_sigma_mm: float = 0.05
    # Refractive index offset. SOURCED via the material file (materials/*.toml).
    index_mean: float = 0.0
    index_sigma: float | None = None
    index_batch_sigma: float | None = None
    index_factor: float = 1.0
    # Cure shrinkage (linear fraction). From the material file (an ASSUMPTION there).
    shrinkage_mean: float | None = None
    shrinkage_sigma: float | None = None
    shrinkage_factor: float = 1.0
    # Layer ripple on unpolished surfaces. SOURCED: the paper printed 25 um layers.
    # ASSUMPTION: amplitude 25 um / pi, the fundamental of an unsmoothed 25 um sawtooth.
    ripple_amplitude_mm: float = 0.025 / math.pi
    ripple_period_mm: float = 0.025

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            name = _TOML_NAME[f.name]
            if f.name == "polished_surfaces":
                v = (v,) if isinstance(v, str) else v
                if not isinstance(v, (tuple, list)) or any(s not in ("front", "back") for s in v):
                    raise ConfigError(f"{name}: must list surfaces out of 'front', 'back', got {v!r}")
                object.__setattr__(self, f.name, tuple(dict.fromkeys(v)))
                continue
            if f.name == "form_modes":
                if not isinstance(v, (tuple, list)) or any(isinstance(j, bool) or not isinstance(j, (int, np.integer))
                                                          or not 2 <= j <= _MAX_MODE for j in v):
                    raise ConfigError(f"{name}: Noll indices must be integers 2..{_MAX_MODE} (no piston), got {v!r}")
                if len(set(v)) != len(v):
                    raise ConfigError(f"{name}: Noll indices must not repeat, got {list(v)}")
                object.__setattr__(self, f.name, tuple(int(j) for j in v))
                continue
            if f.name == "polish_rolloff_power":
                if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v not in range(2, 17, 2):
                    raise ConfigError(f"{name}: must be an even integer 2..16 (r^power), got {v!r}")
                object.__setattr__(self, f.name, int(v))
                continue
            if v is None and f.name in ("index_sigma", "index_batch_sigma", "shrinkage_mean", "shrinkage_sigma"):
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise ConfigError(f"{name}: must be a number, got {v!r}")
            v = float(v)
            if not math.isfinite(v):
                raise ConfigError(f"{name}: must be a finite number, got {v}")
            if f.name in _NON_NEGATIVE and v < 0:
                raise ConfigError(f"{name}: must be >= 0, got {v}")
            object.__setattr__(self, f.name, v)
        if self.ripple_period_mm <= 0:
            raise ConfigError(f"ripple.period_mm: must be > 0 mm, got {self.ripple_period_mm}")
        if self.shrinkage_mean is not None and not -0.5 < self.shrinkage_mean < 0.5:
            raise ConfigError(f"shrinkage.mean: linear fraction must lie in (-0.5, 0.5), got {self.shrinkage_mean}")
        for mean, sd in (("polish_depth_mm", "polish_depth_sigma_mm"), ("polish_rolloff_mm", "polish_rolloff_sigma_mm")):
            if getattr(self, sd) > 0 and getattr(self, mean) == 0:
                raise ConfigError(f"{_TOML_NAME[sd]}: a removal depth cannot scatter around a zero mean; "
                                  f"set {_TOML_NAME[mean]} > 0 or the sigma to 0")

    # --- construction helpers -------------------------------------------------
    @classmethod
    def zero(cls) -> "Tolerances":
        """No deviation at all: sample_as_built returns the nominal lens."""
        return cls(polish_depth_mm=0.0, polish_depth_sigma_mm=0.0, polish_rolloff_mm=0.0,
                   polish_rolloff_sigma_mm=0.0, form_rms_mm=0.0, thickness_mean_mm=0.0, thickness_sigma_mm=0.0,
                   index_mean=0.0, index_sigma=0.0, index_batch_sigma=0.0, shrinkage_mean=0.0,
                   shrinkage_sigma=0.0, ripple_amplitude_mm=0.0)

    @staticmethod
    def component_names() -> tuple:
        """The tolerance components, in the order of the TOML file."""
        return COMPONENTS

    @staticmethod
    def _check_component(name: str) -> str:
        if name not in COMPONENTS:
            raise ConfigError(f"tolerance component: unknown {name!r}; use one of {list(COMPONENTS)}")
        return name

    def only(self, name: str) -> "Tolerances":
        """These tolerances with every component except `name` set to zero."""
        self._check_component(name)
        z = Tolerances.zero()
        keep = {f: getattr(self, f) for f in _TABLES[name].values()}
        return replace(z, **keep)

    def scaled(self, name: str, factor: float) -> "Tolerances":
        """These tolerances with the magnitudes of component `name` multiplied by `factor` (>= 0).

        Means and standard deviations scale together; material-derived values
        (None) scale through index_factor / shrinkage_factor.
        """
        self._check_component(name)
        factor = float(factor)
        if not math.isfinite(factor) or factor < 0:
            raise ConfigError(f"scale factor for {name!r}: must be a finite number >= 0, got {factor}")
        ch = {}
        for f in _SCALED[name]:
            v = getattr(self, f)
            if v is None:
                fac = f"{name}_factor"
                ch[fac] = getattr(self, fac) * factor
            else:
                ch[f] = v * factor
        return replace(self, **ch)

    def resolved(self, material: Material) -> "Tolerances":
        """A copy with every material-derived value (None) filled in from `material`."""
        ch = {}
        for f, attr, fac in (("index_sigma", "index_sigma", "index_factor"),
                             ("index_batch_sigma", "batch_sigma", "index_factor"),
                             ("shrinkage_mean", "shrinkage", "shrinkage_factor"),
                             ("shrinkage_sigma", "shrinkage_sigma", "shrinkage_factor")):
            if getattr(self, f) is None:
                ch[f] = float(getattr(material, attr)) * getattr(self, fac)
        if ch:
            ch["index_factor"] = 1.0 if "index_sigma" in ch or "index_batch_sigma" in ch else self.index_factor
            ch["shrinkage_factor"] = 1.0 if "shrinkage_mean" in ch or "shrinkage_sigma" in ch else self.shrinkage_factor
        return replace(self, **ch)

    # --- I/O ------------------------------------------------------------------
    def to_dict(self) -> dict:
        """Nested dict in the TOML layout ("material" marks material-derived values)."""
        out = {"schema_version": SCHEMA_VERSION}
        for table, keys in _TABLES.items():
            out[table] = {}
            for k, f in keys.items():
                v = getattr(self, f)
                out[table][k] = MATERIAL if v is None else (list(v) if isinstance(v, tuple) else v)
        return out

    @classmethod
    def from_dict(cls, d: dict, where: str = "tolerances") -> "Tolerances":
        """Strictly validated tolerances from the TOML layout; missing keys keep their defaults."""
        check_header(d, where, kind="lensforge.tolerances")
        check_ranges(d, TOLERANCE_RANGES, where)
        kw = {}
        for table, body in d.items():
            if table in ("schema_version", "kind", "description"):
                continue
            if table not in _TABLES:
                raise ConfigError(f"{where}: unknown tolerance component [{table}]; use one of {list(COMPONENTS)}")
            if not isinstance(body, dict):
                raise ConfigError(f"{where}.{table}: expected a table [{table}] of keys")
            for k, v in body.items():
                if k not in _TABLES[table]:
                    raise ConfigError(f"{where}: unknown key {table}.{k}; allowed: {sorted(_TABLES[table])}")
                f = _TABLES[table][k]
                if isinstance(v, str):
                    if v == MATERIAL and f in ("index_sigma", "index_batch_sigma", "shrinkage_mean", "shrinkage_sigma"):
                        v = None
                    elif f != "polished_surfaces":
                        raise ConfigError(f"{where}: {table}.{k} must be a number, got {v!r}")
                if isinstance(v, list):
                    v = tuple(v)
                kw[f] = v
        sv = d.get("schema_version", SCHEMA_VERSION)
        if sv != SCHEMA_VERSION:
            raise ConfigError(f"{where}.schema_version: expected {SCHEMA_VERSION}, got {sv!r}")
        try:
            return cls(**kw)
        except ConfigError as e:
            raise ConfigError(f"{where}: {e}") from None

    def save(self, path) -> Path:
        """Write the tolerances as TOML (atomically)."""
        return save_tolerances(self, path)


def load_tolerances(path) -> Tolerances:
    """Tolerances from a TOML file (missing keys keep the documented defaults)."""
    p = Path(path)
    return Tolerances.from_dict(read_toml(p, "tolerances file"), where=f"tolerances file {p.name}")


def save_tolerances(tol: Tolerances, path) -> Path:
    """Write `tol` as TOML (atomically)."""
    import tomli_w

    return write_atomic(path, tomli_w.dumps(tol.to_dict()))


# ---------------------------------------------------------------------------
# Sampling


def scale_canonical(cs: CanonicalSurface, s: float) -> CanonicalSurface:
    """The surface of a part scaled by s about the vertex frame origin (exact).

    s'(x, y) = s * sag(x/s, y/s): c -> c/s, alpha_i -> alpha_i / s^(2i-1),
    P[p, q] -> P[p, q] / s^(p+q-1); ripple amplitude and period scale by s.
    """
    i = np.arange(1, len(cs.alpha) + 1)
    d = cs.poly.shape[0]
    pq = np.add.outer(np.arange(d), np.arange(d))
    return CanonicalSurface(cs.c / s, cs.k, cs.alpha / s ** (2 * i - 1), cs.poly / s ** (pq - 1.0),
                            cs.ripple_amplitude * s, cs.ripple_period * s)


def _add_poly(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    n = max(a.shape[0], b.shape[0])
    out = np.zeros((n, n))
    out[: a.shape[0], : a.shape[1]] += a
    out[: b.shape[0], : b.shape[1]] += b
    return out


def _form_poly(modes, coeffs, radius: float) -> np.ndarray:
    """Monomial array of sum_j a_j Z_j(x/R, y/R) (mm)."""
    out = np.zeros((1, 1))
    for j, a in zip(modes, coeffs):
        if a == 0.0:
            continue
        m = np.asarray(zernike_monomials(j), float)
        pq = np.add.outer(np.arange(m.shape[0]), np.arange(m.shape[1]))
        out = _add_poly(out, a * m / radius ** pq)
    return out


def _gamma(mean: float, sd: float, u: float) -> float:
    """Gamma-distributed value with the given mean and sd, from a uniform u (inverse CDF)."""
    if sd == 0.0:
        return mean
    k = (mean / sd) ** 2
    return float(sd * sd / mean * gammaincinv(k, u))


def sample_as_built(lens: Lens, tolerances: Tolerances, rng: np.random.Generator, validate: bool = True) -> Lens:
    """One as-built lens drawn from the tolerance model (see the module notes).

    Returns a Lens (changed surfaces become Freeform surfaces holding the perturbed
    canonical form) that the tracer uses like any other; with zero tolerances the
    nominal lens itself. validate: run Lens.validate() on the draw (about 10 ms;
    raises LensGeometryError if the draw is not a physical lens).
    """
    if not isinstance(rng, np.random.Generator):
        raise ConfigError("rng: pass a numpy Generator, e.g. np.random.default_rng(seed)")
    t = tolerances.resolved(lens.material_data)
    nm = len(t.form_modes)
    # fixed draw order and count, whatever the values
    d = {c.name: c.draw(rng, t) for c in sorted(COMPONENT_SPECS.values(), key=lambda c: c.draw_rank)}
    z_form, u_polish = d["form"], d["polishing"]
    (z_thick,), (z_index, z_batch), (z_shrink,) = d["thickness"], d["index"], d["shrinkage"]

    s = 1.0 - (t.shrinkage_mean + t.shrinkage_sigma * z_shrink)
    if s <= 0:
        raise ConfigError("shrinkage: the draw shrinks the lens to nothing; check shrinkage.mean/sigma")
    Ra = 0.5 * lens.aperture
    mode_sd = t.form_rms_mm / math.sqrt(nm) if nm else 0.0
    surfaces = {}
    changed_any = False
    for k, side in enumerate(("front", "back")):
        surf = getattr(lens, side)
        cs = surf.canonical()
        changed = False
        poly, alpha = cs.poly, cs.alpha.copy()
        ra, rp = cs.ripple_amplitude, cs.ripple_period
        if mode_sd > 0:
            poly = _add_poly(poly, _form_poly(t.form_modes, mode_sd * z_form[k], Ra))
            changed = True
        polished = side in t.polished_surfaces
        if not polished and t.ripple_amplitude_mm > 0:
            ra, rp = t.ripple_amplitude_mm, t.ripple_period_mm
            changed = True
        cs = CanonicalSurface(cs.c, cs.k, alpha, poly, ra, rp)
        if s != 1.0:
            cs = scale_canonical(cs, s)
            changed = True
        if polished:
            depth = _gamma(t.polish_depth_mm, t.polish_depth_sigma_mm, u_polish[k, 0])
            roll = _gamma(t.polish_rolloff_mm, t.polish_rolloff_sigma_mm, u_polish[k, 1])
            sign = 1.0 if side == "front" else -1.0  # removal moves the surface into the material
            if depth or roll:
                poly = cs.poly.copy()
                poly[0, 0] += sign * depth
                alpha = cs.alpha.copy()
                alpha[t.polish_rolloff_power // 2 - 1] += sign * roll / (s * Ra) ** t.polish_rolloff_power
                cs = CanonicalSurface(cs.c, cs.k, alpha, poly, cs.ripple_amplitude, cs.ripple_period)
                changed = True
        surfaces[side] = Freeform.from_canonical(cs) if changed else surf
        changed_any |= changed
    dt = t.thickness_mean_mm + t.thickness_sigma_mm * z_thick
    dn = t.index_mean + t.index_sigma * z_index + t.index_batch_sigma * z_batch
    if not changed_any and dt == 0.0 and dn == 0.0:
        return lens
    out = lens.replace(front=surfaces["front"], back=surfaces["back"],
                       thickness=lens.thickness * s + dt, aperture=lens.aperture * s,
                       edge_diameter=float(lens.edge_diameter * s), index_offset=lens.index_offset + dn)
    return out.validate() if validate else out
