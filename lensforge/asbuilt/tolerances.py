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

Adding a component touches one place, the registry ``COMPONENT_SPECS``: one
:class:`ToleranceComponent` holds its TOML table (each :class:`ToleranceField` with
its default and where it comes from, its kind and validation range with the unit,
whether the budget's scale factor multiplies it), its draw, its effect on the
as-built lens and the budget table's size column. The TOML reader/writer, the input
ranges (``TOLERANCE_RANGES``) and the sampler are all built from the registry. The
:class:`Tolerances` dataclass declares one typed attribute per field (so that type
checkers see float, int, tuple, not Any: the package ships ``py.typed``), each taking
its default from the registry; the module checks at import that the two agree, and the
check's message gives the lines a new component adds.
"""

from __future__ import annotations

from os import PathLike

import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
from scipy.special import gammaincinv

from ..errors import ConfigError
from ..fileio import read_toml, write_atomic
from ..input_checks import Num, check_header, check_ranges
from ..optics.lens import Lens
from ..optics.materials import Material
from ..optics.surfaces import CanonicalSurface, Freeform, add_monomials
from ..optics.zernike import zernike_monomials

__all__ = ["Tolerances", "load_tolerances", "save_tolerances", "resolve_tolerances", "no_tolerance_model",
           "sample_as_built", "scale_canonical",
           "COMPONENTS", "COMPONENT_SPECS", "ToleranceComponent", "ToleranceField", "AsBuiltState",
           "TOLERANCE_RANGES", "DEFAULT_TOLERANCES_FILE"]

DEFAULT_TOLERANCES_FILE = Path(__file__).with_name("tolerances-default.toml")
SCHEMA_VERSION = 1
MATERIAL = "material"  # TOML value meaning "take it from the lens material"
SIDES = ("front", "back")
_MAX_MODE = 66  # Noll modes up to radial order 10


# --- field kinds: how a value is checked and normalised (name is its TOML name) -------------


def _number(v, name: str, non_negative: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise ConfigError(f"{name}: must be a number, got {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise ConfigError(f"{name}: must be a finite number, got {v}")
    if non_negative and v < 0:
        raise ConfigError(f"{name}: must be >= 0, got {v}")
    return v


def _surfaces(v, name: str) -> tuple:
    v = (v,) if isinstance(v, str) else v
    if not isinstance(v, (tuple, list)) or any(s not in SIDES for s in v):
        raise ConfigError(f"{name}: must list surfaces out of 'front', 'back', got {v!r}")
    return tuple(dict.fromkeys(v))


def _noll_modes(v, name: str) -> tuple:
    if not isinstance(v, (tuple, list)) or any(isinstance(j, bool) or not isinstance(j, (int, np.integer))
                                              or not 2 <= j <= _MAX_MODE for j in v):
        raise ConfigError(f"{name}: Noll indices must be integers 2..{_MAX_MODE} (no piston), got {v!r}")
    if len(set(v)) != len(v):
        raise ConfigError(f"{name}: Noll indices must not repeat, got {list(v)}")
    return tuple(int(j) for j in v)


def _even_power(v, name: str) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v not in range(2, 17, 2):
        raise ConfigError(f"{name}: must be an even integer 2..16 (r^power), got {v!r}")
    return int(v)


@dataclass(frozen=True)
class ToleranceField:
    """One value of a component: attribute ``attr`` of Tolerances, ``key`` in its TOML table.

    default: the documented default (its source is in the registry's comment);
    range: validation range and unit of the TOML value (None: checked by ``check``);
    check(value, toml_name) -> normalised value (default: a finite number, >= 0 when
    ``non_negative``); material: the Material attribute a None value stands for (the
    TOML value "material"), scaled by the component's ``factor`` field; scaled: the
    budget's scale factor multiplies it; zero: its value in ``Tolerances.zero()``
    (None: keeps the default, e.g. shape parameters); text: the TOML value may be a
    string (not "material").
    """

    attr: str
    key: str
    default: Any
    range: Num | None = None
    check: Callable | None = None
    non_negative: bool = False
    material: str | None = None
    scaled: bool = False
    zero: Any = None
    text: bool = False

    def normalise(self, v, toml_name: str):
        if v is None and self.material is not None:
            return None
        if self.check is not None:
            return self.check(v, toml_name)
        return _number(v, toml_name, self.non_negative)


@dataclass
class AsBuiltState:
    """The as-built lens while the components' effects build it (working state of one draw).

    surfaces: side -> CanonicalSurface; changed: side -> bool; radius: the nominal
    clear-aperture radius R_a (mm); scale: linear shrinkage factor s (the lens, its
    aperture and edge scale by it); thickness_delta (mm), index_delta: added to the
    scaled thickness and to the index offset.
    """

    surfaces: dict
    changed: dict
    radius: float
    scale: float = 1.0
    thickness_delta: float = 0.0
    index_delta: float = 0.0

    def set_surface(self, side: str, cs: CanonicalSurface) -> None:
        self.surfaces[side] = cs
        self.changed[side] = True


@dataclass(frozen=True)
class ToleranceComponent:
    """One tolerance component, everything about it in one place.

    fields: its TOML table, in file order (:class:`ToleranceField`); main: (attr, unit)
    naming its size in the budget table (after ``Tolerances.resolved``); factor: the
    field multiplying its material-derived values; draw(rng, t) -> the standard random
    numbers one as-built lens takes from it (a fixed count whatever the values, for
    common random numbers); effect(state, t, draws): its change of the as-built lens
    (``AsBuiltState``; t resolved against the material); check(t): validation across
    its fields. draw_rank / effect_rank: its place in the draw order and in the order
    the effects apply (both fixed: changing them changes every seeded study).
    """

    name: str
    fields: tuple
    main: tuple
    draw: Callable = field(default=lambda rng, t: np.empty(0), compare=False)
    effect: Callable = field(default=lambda state, t, draws: None, compare=False)
    check: Callable = field(default=lambda t: None, compare=False)
    factor: str | None = None
    draw_rank: int = 99
    effect_rank: int = 99

    @property
    def table(self) -> dict:
        """{TOML key: Tolerances attribute}."""
        return {f.key: f.attr for f in self.fields}

    @property
    def scaled(self) -> tuple:
        """The attributes the budget's scale factor multiplies."""
        return tuple(f.attr for f in self.fields if f.scaled)


# --- the components' draws, effects and checks ---------------------------------------------


def _gamma(mean: float, sd: float, u: float) -> float:
    """Gamma-distributed value with the given mean and sd, from a uniform u (inverse CDF)."""
    if sd == 0.0:
        return mean
    k = (mean / sd) ** 2
    return float(sd * sd / mean * gammaincinv(k, u))


def _form_poly(modes, coeffs, radius: float) -> np.ndarray:
    """Monomial array of sum_j a_j Z_j(x/R, y/R) (mm)."""
    out = np.zeros((1, 1))
    for j, a in zip(modes, coeffs):
        if a == 0.0:
            continue
        m = np.asarray(zernike_monomials(j), float)
        pq = np.add.outer(np.arange(m.shape[0]), np.arange(m.shape[1]))
        out = add_monomials(out, a * m / radius ** pq)
    return out


def _form_effect(st: AsBuiltState, t, z) -> None:
    nm = len(t.form_modes)
    mode_sd = t.form_rms_mm / math.sqrt(nm) if nm else 0.0
    if mode_sd > 0:
        for k, side in enumerate(SIDES):
            cs = st.surfaces[side]
            poly = add_monomials(cs.poly, _form_poly(t.form_modes, mode_sd * z[k], st.radius))
            st.set_surface(side, CanonicalSurface(cs.c, cs.k, cs.alpha, poly, cs.ripple_amplitude, cs.ripple_period))


def _ripple_effect(st: AsBuiltState, t, _z) -> None:
    if t.ripple_amplitude_mm > 0:
        for side in SIDES:
            if side not in t.polished_surfaces:
                cs = st.surfaces[side]
                st.set_surface(side, CanonicalSurface(cs.c, cs.k, cs.alpha, cs.poly, t.ripple_amplitude_mm,
                                                      t.ripple_period_mm))


def _shrinkage_effect(st: AsBuiltState, t, z) -> None:
    s = 1.0 - (t.shrinkage_mean + t.shrinkage_sigma * z[0])
    if s <= 0:
        raise ConfigError("shrinkage: the draw shrinks the lens to nothing; check shrinkage.mean/sigma")
    st.scale = s
    if s != 1.0:
        for side in SIDES:
            st.set_surface(side, scale_canonical(st.surfaces[side], s))


def _polishing_effect(st: AsBuiltState, t, u) -> None:
    s, Ra = st.scale, st.radius
    for k, side in enumerate(SIDES):
        if side not in t.polished_surfaces:
            continue
        depth = _gamma(t.polish_depth_mm, t.polish_depth_sigma_mm, u[k, 0])
        roll = _gamma(t.polish_rolloff_mm, t.polish_rolloff_sigma_mm, u[k, 1])
        sign = 1.0 if side == "front" else -1.0  # removal moves the surface into the material
        if depth or roll:
            cs = st.surfaces[side]
            poly = cs.poly.copy()
            poly[0, 0] += sign * depth
            alpha = cs.alpha.copy()
            alpha[t.polish_rolloff_power // 2 - 1] += sign * roll / (s * Ra) ** t.polish_rolloff_power
            st.set_surface(side, CanonicalSurface(cs.c, cs.k, alpha, poly, cs.ripple_amplitude, cs.ripple_period))


def _thickness_effect(st: AsBuiltState, t, z) -> None:
    st.thickness_delta = t.thickness_mean_mm + t.thickness_sigma_mm * z[0]


def _index_effect(st: AsBuiltState, t, z) -> None:
    st.index_delta = t.index_mean + t.index_sigma * z[0] + t.index_batch_sigma * z[1]


def _check_polishing(t) -> None:
    for mean, sd in (("polish_depth_mm", "polish_depth_sigma_mm"), ("polish_rolloff_mm", "polish_rolloff_sigma_mm")):
        if getattr(t, sd) > 0 and getattr(t, mean) == 0:
            raise ConfigError(f"{_TOML_NAME[sd]}: a removal depth cannot scatter around a zero mean; "
                              f"set {_TOML_NAME[mean]} > 0 or the sigma to 0")


def _check_shrinkage(t) -> None:
    if t.shrinkage_mean is not None and not -0.5 < t.shrinkage_mean < 0.5:
        raise ConfigError(f"shrinkage.mean: linear fraction must lie in (-0.5, 0.5), got {t.shrinkage_mean}")


def _check_ripple(t) -> None:
    if t.ripple_period_mm <= 0:
        raise ConfigError(f"ripple.period_mm: must be > 0 mm, got {t.ripple_period_mm}")


F = ToleranceField
# Input ranges: plausible manufacturing sizes for a printed and polished lens (ASSUMPTION,
# generous): beyond these the file almost surely has a unit wrong (e.g. um written as
# mm). Zero is always allowed: a perfect lens.
_IDX = "(refractive index)"
_MULT = "(multiple of the material's value)"
_LIN = "(linear fraction)"

# THE REGISTRY, in the order of the TOML file. A new component is one entry here.
COMPONENT_SPECS = {c.name: c for c in (
    ToleranceComponent(
        "polishing",
        # SOURCED: the paper's printed lens was sanded and polished on both surfaces
        # (Optics Express 30(9) 14368, Sec. 4.3). ASSUMPTION: about one 25 um layer is
        # removed to clear the staircase (mean 25 um, sd 10 um), with 5 um (sd 3 um)
        # extra removal at the clear-aperture edge growing as r^4 (hand polishing rolls
        # the edge off).
        (F("polish_depth_mm", "depth_mm", 0.025, Num(0.0, 1.0, "mm"), non_negative=True, scaled=True, zero=0.0),
         F("polish_depth_sigma_mm", "depth_sigma_mm", 0.010, Num(0.0, 0.5, "mm"), non_negative=True, scaled=True,
           zero=0.0),
         F("polish_rolloff_mm", "rolloff_mm", 0.005, Num(0.0, 0.5, "mm"), non_negative=True, scaled=True, zero=0.0),
         F("polish_rolloff_sigma_mm", "rolloff_sigma_mm", 0.003, Num(0.0, 0.5, "mm"), non_negative=True, scaled=True,
           zero=0.0),
         F("polish_rolloff_power", "rolloff_power", 4, check=_even_power),
         F("polished_surfaces", "surfaces", SIDES, check=_surfaces, text=True)),
        main=("polish_depth_mm", "mm"),
        draw=lambda rng, t: rng.uniform(size=(2, 2)),  # (surface, depth/rolloff)
        effect=_polishing_effect, check=_check_polishing, draw_rank=1, effect_rank=3),
    ToleranceComponent(
        "form",
        # ASSUMPTION: 2 um RMS per surface over Noll modes 2..11 (tilt to primary
        # spherical), typical of hand-polished SLA optics.
        (F("form_rms_mm", "rms_mm", 0.002, Num(0.0, 0.1, "mm"), non_negative=True, scaled=True, zero=0.0),
         F("form_modes", "modes", tuple(range(2, 12)), check=_noll_modes)),
        main=("form_rms_mm", "mm RMS"),
        draw=lambda rng, t: rng.standard_normal((2, len(t.form_modes))),  # (surface, mode)
        effect=_form_effect, draw_rank=0, effect_rank=0),
    ToleranceComponent(
        "thickness",
        # ASSUMPTION: 50 um sd, about two Form 2 layers, no bias.
        (F("thickness_mean_mm", "mean_mm", 0.0, Num(-2.0, 2.0, "mm"), scaled=True, zero=0.0),
         F("thickness_sigma_mm", "sigma_mm", 0.05, Num(0.0, 1.0, "mm"), non_negative=True, scaled=True, zero=0.0)),
        main=("thickness_sigma_mm", "mm (1 sigma)"),
        draw=lambda rng, t: rng.standard_normal(1), effect=_thickness_effect, draw_rank=2, effect_rank=4),
    ToleranceComponent(
        "index",
        # SOURCED via the material file (materials/*.toml): None = the material's
        # index_sigma (absolute uncertainty) and batch_sigma (batch to batch), times factor.
        (F("index_mean", "mean", 0.0, Num(-0.1, 0.1, _IDX), scaled=True, zero=0.0),
         F("index_sigma", "sigma", None, Num(0.0, 0.05, _IDX), non_negative=True, material="index_sigma",
           scaled=True, zero=0.0),
         F("index_batch_sigma", "batch_sigma", None, Num(0.0, 0.05, _IDX), non_negative=True,
           material="batch_sigma", scaled=True, zero=0.0),
         F("index_factor", "factor", 1.0, Num(0.0, 100.0, _MULT), non_negative=True)),
        main=("index_sigma", "(1 sigma)"), factor="index_factor",
        draw=lambda rng, t: rng.standard_normal(2),  # (absolute, batch)
        effect=_index_effect, draw_rank=3, effect_rank=5),
    ToleranceComponent(
        "shrinkage",
        # From the material file (shrinkage, shrinkage_sigma; an ASSUMPTION there).
        (F("shrinkage_mean", "mean", None, Num(-0.2, 0.2, _LIN), material="shrinkage", scaled=True, zero=0.0),
         F("shrinkage_sigma", "sigma", None, Num(0.0, 0.05, _LIN), non_negative=True, material="shrinkage_sigma",
           scaled=True, zero=0.0),
         F("shrinkage_factor", "factor", 1.0, Num(0.0, 100.0, _MULT), non_negative=True)),
        main=("shrinkage_sigma", "(1 sigma, linear)"), factor="shrinkage_factor",
        draw=lambda rng, t: rng.standard_normal(1), effect=_shrinkage_effect, check=_check_shrinkage,
        draw_rank=4, effect_rank=2),
    ToleranceComponent(
        "ripple",
        # Layer ripple on unpolished surfaces. SOURCED: the paper printed 25 um layers.
        # ASSUMPTION: amplitude 25 um / pi, the fundamental of an unsmoothed 25 um sawtooth.
        (F("ripple_amplitude_mm", "amplitude_mm", 0.025 / math.pi, Num(0.0, 0.1, "mm"), non_negative=True,
           scaled=True, zero=0.0),
         F("ripple_period_mm", "period_mm", 0.025, Num(0.0, 1.0, "mm", lo_open=True))),
        main=("ripple_amplitude_mm", "mm"), effect=_ripple_effect, check=_check_ripple, effect_rank=1),
)}
del F
COMPONENTS = tuple(COMPONENT_SPECS)
_FIELDS = {f.attr: f for c in COMPONENT_SPECS.values() for f in c.fields}
_TOML_NAME = {f.attr: f"{c.name}.{f.key}" for c in COMPONENT_SPECS.values() for f in c.fields}
TOLERANCE_RANGES = {_TOML_NAME[a]: f.range for a, f in _FIELDS.items() if f.range is not None}


class _ToleranceMethods:
    """The behaviour of :class:`Tolerances` (its fields come from the registry)."""

    def __post_init__(self):
        for f in fields(self):
            object.__setattr__(self, f.name, _FIELDS[f.name].normalise(getattr(self, f.name), _TOML_NAME[f.name]))
        for c in COMPONENT_SPECS.values():
            c.check(self)

    # --- construction helpers -------------------------------------------------
    @classmethod
    def zero(cls) -> "Tolerances":
        """No deviation at all: sample_as_built returns the nominal lens."""
        return cls(**{a: f.zero for a, f in _FIELDS.items() if f.zero is not None})

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
        keep = {f.attr: getattr(self, f.attr) for f in COMPONENT_SPECS[name].fields}
        return replace(self.zero(), **keep)

    def scaled(self, name: str, factor: float) -> "Tolerances":
        """These tolerances with the magnitudes of component `name` multiplied by `factor` (>= 0).

        Means and standard deviations scale together; material-derived values
        (None) scale through the component's factor (index_factor, shrinkage_factor).
        """
        self._check_component(name)
        factor = float(factor)
        if not math.isfinite(factor) or factor < 0:
            raise ConfigError(f"scale factor for {name!r}: must be a finite number >= 0, got {factor}")
        comp = COMPONENT_SPECS[name]
        ch = {}
        for f in comp.scaled:
            v = getattr(self, f)
            if v is None:
                ch[comp.factor] = getattr(self, comp.factor) * factor
            else:
                ch[f] = v * factor
        return replace(self, **ch)

    def resolved(self, material: Material) -> "Tolerances":
        """A copy with every material-derived value (None) filled in from `material`."""
        ch = {}
        for c in COMPONENT_SPECS.values():
            filled = {f.attr: float(getattr(material, f.material)) * getattr(self, c.factor)
                      for f in c.fields if f.material is not None and getattr(self, f.attr) is None}
            if filled:
                ch.update(filled)
                ch[c.factor] = 1.0
        return replace(self, **ch)

    # --- I/O ------------------------------------------------------------------
    def to_dict(self) -> dict:
        """Nested dict in the TOML layout ("material" marks material-derived values)."""
        out = {"schema_version": SCHEMA_VERSION}
        for c in COMPONENT_SPECS.values():
            out[c.name] = {}
            for f in c.fields:
                v = getattr(self, f.attr)
                out[c.name][f.key] = MATERIAL if v is None else (list(v) if isinstance(v, tuple) else v)
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
            if table not in COMPONENT_SPECS:
                raise ConfigError(f"{where}: unknown tolerance component [{table}]; use one of {list(COMPONENTS)}")
            if not isinstance(body, dict):
                raise ConfigError(f"{where}.{table}: expected a table [{table}] of keys")
            keys = {f.key: f for f in COMPONENT_SPECS[table].fields}
            for k, v in body.items():
                if k not in keys:
                    raise ConfigError(f"{where}: unknown key {table}.{k}; allowed: {sorted(keys)}")
                f = keys[k]
                if isinstance(v, str):
                    if v == MATERIAL and f.material is not None:
                        v = None
                    elif not f.text:
                        raise ConfigError(f"{where}: {table}.{k} must be a number, got {v!r}")
                if isinstance(v, list):
                    v = tuple(v)
                kw[f.attr] = v
        sv = d.get("schema_version", SCHEMA_VERSION)
        if sv != SCHEMA_VERSION:
            raise ConfigError(f"{where}.schema_version: expected {SCHEMA_VERSION}, got {sv!r}")
        try:
            return cls(**kw)
        except ConfigError as e:
            raise ConfigError(f"{where}: {e}") from None

    def save(self, path: str | PathLike[str]) -> Path:
        """Write the tolerances as TOML (atomically)."""
        return save_tolerances(self, path)


def _default(attr: str):
    """The registry's default of field ``attr`` (the registry is the one place defaults live)."""
    return field(default=_FIELDS[attr].default)


@dataclass(frozen=True)
class Tolerances(_ToleranceMethods):
    """As-built tolerances (lengths mm; 1-sigma values): one attribute per field of the registry
    ``COMPONENT_SPECS``, in its order, with its default (its comments say where each default
    comes from; the module checks at import that these fields are the registry's).

    None in the index and shrinkage fields means "the lens material's value"
    (Material.index_sigma, batch_sigma, shrinkage, shrinkage_sigma), multiplied by
    index_factor / shrinkage_factor.

    Parameters
    ----------
    polish_depth_mm, polish_depth_sigma_mm : float
        Mean and sd of the uniform removal per polished surface, mm.
    polish_rolloff_mm, polish_rolloff_sigma_mm : float
        Mean and sd of the extra removal at the clear-aperture edge, mm.
    polish_rolloff_power : int
        Even power of the roll-off's radial profile (r / R_a)^power.
    polished_surfaces : tuple of str
        The polished sides, a subset of ("front", "back").
    form_rms_mm : float
        Total RMS form error per surface, mm.
    form_modes : tuple of int
        Noll modes (RMS-normalised over the clear aperture) carrying the form error.
    thickness_mean_mm, thickness_sigma_mm : float
        Mean and sd of the centre-thickness error, mm.
    index_mean : float
        Refractive-index offset (absolute).
    index_sigma, index_batch_sigma : float or None
        Index sd (absolute) and batch-to-batch sd; None: the material's.
    index_factor : float
        Multiplies the material-derived index sds.
    shrinkage_mean, shrinkage_sigma : float or None
        Linear cure shrinkage mean and sd (fraction); None: the material's.
    shrinkage_factor : float
        Multiplies the material-derived shrinkage values.
    ripple_amplitude_mm, ripple_period_mm : float
        Layer-ripple amplitude and period on unpolished surfaces, mm.
    """

    polish_depth_mm: float = _default("polish_depth_mm")
    polish_depth_sigma_mm: float = _default("polish_depth_sigma_mm")
    polish_rolloff_mm: float = _default("polish_rolloff_mm")
    polish_rolloff_sigma_mm: float = _default("polish_rolloff_sigma_mm")
    polish_rolloff_power: int = _default("polish_rolloff_power")
    polished_surfaces: tuple[str, ...] = _default("polished_surfaces")
    form_rms_mm: float = _default("form_rms_mm")
    form_modes: tuple[int, ...] = _default("form_modes")
    thickness_mean_mm: float = _default("thickness_mean_mm")
    thickness_sigma_mm: float = _default("thickness_sigma_mm")
    index_mean: float = _default("index_mean")
    index_sigma: float | None = _default("index_sigma")
    index_batch_sigma: float | None = _default("index_batch_sigma")
    index_factor: float = _default("index_factor")
    shrinkage_mean: float | None = _default("shrinkage_mean")
    shrinkage_sigma: float | None = _default("shrinkage_sigma")
    shrinkage_factor: float = _default("shrinkage_factor")
    ripple_amplitude_mm: float = _default("ripple_amplitude_mm")
    ripple_period_mm: float = _default("ripple_period_mm")


def _check_fields_match_registry() -> None:
    """Tolerances' typed fields are exactly the registry's, in its order (a component added
    to COMPONENT_SPECS adds its lines above; this names them)."""
    have = [f.name for f in fields(Tolerances)]
    if have != list(_FIELDS):
        missing = [a for a in _FIELDS if a not in have]
        raise RuntimeError("Tolerances' fields differ from COMPONENT_SPECS: declare, in the registry's order, "
                           + "; ".join(f'{a}: <type> = _default("{a}")' for a in missing)
                           + (f" and remove {sorted(set(have) - set(_FIELDS))}" if set(have) - set(_FIELDS) else ""))


_check_fields_match_registry()


def load_tolerances(path: str | PathLike[str]) -> Tolerances:
    """Tolerances from a TOML file (``kind = "lensforge.tolerances"``); missing keys keep the
    documented defaults.

    Parameters
    ----------
    path : str or os.PathLike
        The TOML file (layout of ``asbuilt/tolerances-default.toml``).

    Returns
    -------
    Tolerances
        The validated tolerances (lengths mm).

    Raises
    ------
    ConfigError
        An unknown table or key, a wrong type, or a value outside its range (the message
        names the file, field and unit).
    """
    p = Path(path)
    return Tolerances.from_dict(read_toml(p, "tolerances file"), where=f"tolerances file {p.name}")



def no_tolerance_model(spec) -> bool:
    """True for None or "none" (any case): the lens as designed, no as-built model."""
    return spec is None or (isinstance(spec, str) and spec.strip().lower() == "none")


def resolve_tolerances(spec) -> tuple[Tolerances | None, str]:
    """(Tolerances or None, label) of what a user or a caller may name a tolerance model:
    a Tolerances, "default" (the package's file), a TOML path, or None / "none" (the lens
    exactly as designed: None, label "none"). The label is what results record."""
    if no_tolerance_model(spec):
        return None, "none"
    if isinstance(spec, Tolerances):
        return spec, "given Tolerances"
    if isinstance(spec, str) and spec == "default":
        return load_tolerances(DEFAULT_TOLERANCES_FILE), str(DEFAULT_TOLERANCES_FILE)
    if isinstance(spec, (str, PathLike)):
        return load_tolerances(spec), str(Path(spec))
    raise ConfigError(f"tolerances: expected a Tolerances, 'default', 'none' or a TOML path, got {type(spec).__name__}")


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


def sample_as_built(lens: Lens, tolerances: Tolerances, rng: np.random.Generator, validate: bool = True) -> Lens:
    """One as-built lens drawn from the tolerance model (see the module notes).

    Parameters
    ----------
    lens : Lens
        The nominal lens.
    tolerances : Tolerances
        The tolerance model (material-derived values are filled from the lens's material).
    rng : numpy.random.Generator
        Source of the draws (a fixed number in a fixed order, whatever the values).
    validate : bool
        Run ``Lens.validate()`` on the draw (about 10 ms).

    Returns
    -------
    Lens
        The as-built lens: changed surfaces become Freeform surfaces holding the perturbed
        canonical form; with zero tolerances the nominal lens itself.

    Raises
    ------
    LensGeometryError
        With ``validate``, a draw that is not a physical lens.
    """
    if not isinstance(rng, np.random.Generator):
        raise ConfigError("rng: pass a numpy Generator, e.g. np.random.default_rng(seed)")
    t = tolerances.resolved(lens.material_data)
    # fixed draw order and count, whatever the values
    draws = {c.name: c.draw(rng, t) for c in sorted(COMPONENT_SPECS.values(), key=lambda c: c.draw_rank)}
    st = AsBuiltState(surfaces={side: getattr(lens, side).canonical() for side in SIDES},
                      changed=dict.fromkeys(SIDES, False), radius=0.5 * lens.aperture)
    for c in sorted(COMPONENT_SPECS.values(), key=lambda c: c.effect_rank):
        c.effect(st, t, draws[c.name])
    if not any(st.changed.values()) and st.thickness_delta == 0.0 and st.index_delta == 0.0:
        return lens
    s = st.scale
    surfaces = {side: Freeform.from_canonical(st.surfaces[side]) if st.changed[side] else getattr(lens, side)
                for side in SIDES}
    out = lens.replace(front=surfaces["front"], back=surfaces["back"],
                       thickness=lens.thickness * s + st.thickness_delta, aperture=lens.aperture * s,
                       edge_diameter=float(lens.edge_diameter * s), index_offset=lens.index_offset + st.index_delta)
    return out.validate() if validate else out
