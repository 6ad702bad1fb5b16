"""Design parameters p of a lens: which surface coefficients are free, and their bounds.

A parameter is named by its place in the lens: ``thickness`` (centre thickness l,
mm) or ``<side>.<field>`` / ``<side>.<field>[i]`` with side ``front``/``back`` and
field a surface field (``curvature``, ``conic``, ``aspheric``, ``zeta``, ``gamma``,
``coefficients``); ``[i]`` indexes the field's tuple from 0 exactly as in the lens
JSON (so ``front.zeta[1]`` multiplies x^2, ``front.coefficients[0]`` of a Zernike
sag is Noll j = 1). Parameters that are not free keep the template lens's values.

Models and their paper parameter sets (Optics Express 30(9) 14368, 2022, Eqs. 9-17):

* ``polynomial``: l, zeta_2, zeta_4, gamma_2, gamma_4 per surface (9 parameters).
* ``extended_polynomial``: l, the first five terms x, y, x^2, xy, y^2 per surface (11).
* ``zernike``: l, Noll terms 1..3 per surface (7) on the base sphere of the template.
  The ``base`` preset also frees both base curvatures (the paper does not give them;
  with the assumed f = 50 mm base sphere fixed, no lens of the paper set keeps the
  pupil lit over +-1 mm). lensforge's default for this model is ``full``: the base
  curvatures and Noll 1..8 per surface (astigmatism and coma break the rotational
  symmetry; with CMA-ES and the A-optimal criterion this gives all six DOF observable).
* ``conic`` (lensforge): l and the two base curvatures; rotationally symmetric, so
  always rank 5 -- a reference and a test of the rank penalty.

Each model also has a ``full`` preset (more freeform terms; see FREE_PRESETS).

Default bounds (lensforge choices, not from the paper): thickness 3..10 mm;
curvature +-0.05 1/mm (|R| >= 20 mm); conic +-3; every other coefficient is bounded
so that its term alone departs at most a *sag budget* from the vertex plane at the
rim of the clear aperture: 1 mm for piston terms, a slope of 0.2 rad for linear
(tilt/wedge) terms, 8 mm for quadratic terms (the back surface of the paper's polynomial
lens reaches 6.7 mm) and 0.5 mm for cubic and higher terms. The paper's vectors lie inside.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..optics.lens import Lens, paper_lens
from ..optics.surfaces import ExtendedPolynomial, ZernikeSag, extended_monomial_exponents
from ..optics.zernike import noll_to_nm

__all__ = ["MODELS", "FREE_PRESETS", "BoxBounds", "Parameterisation", "parameterisation", "default_bound",
           "parse_bounds", "describe_parameter"]

MODELS = ("polynomial", "extended_polynomial", "zernike", "conic")
DEFAULT_PRESET = {"polynomial": "paper", "extended_polynomial": "paper", "zernike": "full", "conic": "paper"}
_TEMPLATE = {"polynomial": "polynomial", "extended_polynomial": "extended_polynomial",
             "zernike": "zernike", "conic": "spherical"}


def _both(fields: list[str]) -> tuple[str, ...]:
    return tuple(["thickness"] + [f"front.{f}" for f in fields] + [f"back.{f}" for f in fields])


FREE_PRESETS = {
    "polynomial": {
        "paper": _both(["zeta[1]", "zeta[3]", "gamma[1]", "gamma[3]"]),
        "full": _both([f"zeta[{i}]" for i in range(4)] + [f"gamma[{i}]" for i in range(4)]),
    },
    "extended_polynomial": {
        "paper": _both([f"coefficients[{i}]" for i in range(5)]),
        "full": _both([f"coefficients[{i}]" for i in range(9)]),
    },
    "zernike": {
        "paper": _both([f"coefficients[{i}]" for i in range(3)]),
        # the paper set plus both base curvatures: the base sphere of the paper's Zernike
        # lens is an assumption (lens.py), and with it fixed no lens of the paper set keeps
        # the default +-1 mm working range lit on the default bench, so lensforge frees it
        "base": ("thickness", "front.curvature", "back.curvature")
        + _both([f"coefficients[{i}]" for i in range(3)])[1:],
        # + curvatures, defocus, both astigmatisms and both comas (Noll 4..8): the astigmatism the
        # paper names as the way to break the rotational symmetry
        "full": ("thickness", "front.curvature", "back.curvature")
        + _both([f"coefficients[{i}]" for i in range(8)])[1:],
    },
    "conic": {
        "paper": ("thickness", "front.curvature", "back.curvature"),
        "full": ("thickness", "front.curvature", "front.conic", "back.curvature", "back.conic"),
    },
}

# sag budgets at the rim of the clear aperture (mm), by total degree of the term
_SLOPE_BUDGET = 0.2       # rad, linear terms
_SAG_BUDGET = {0: 1.0, 2: 8.0}
_SAG_BUDGET_HIGH = 0.5    # degree >= 3

_NAME_RE = re.compile(r"^(front|back)\.([a-z_]+)(?:\[(\d+)\])?$")


def _parse_name(name: str):
    if name == "thickness":
        return None, "thickness", None
    m = _NAME_RE.match(name)
    if not m:
        raise ConfigError(
            f"design parameter {name!r}: expected 'thickness' or '<front|back>.<field>[i]', e.g. 'front.zeta[1]'"
        )
    side, field, idx = m.group(1), m.group(2), m.group(3)
    return side, field, None if idx is None else int(idx)


def _term_degree(surface, field: str, idx: int) -> int:
    """Total polynomial degree of a coefficient's term."""
    if field in ("zeta", "gamma"):
        return idx + 1
    if field == "aspheric":
        return 2 * (idx + 1)
    if field == "coefficients" and isinstance(surface, ExtendedPolynomial):
        p, q = extended_monomial_exponents(idx + 1)[-1]
        return p + q
    if field == "coefficients" and isinstance(surface, ZernikeSag):
        return noll_to_nm(idx + 1)[0]
    raise ConfigError(f"design parameter: field {field!r} has no default bound")


def _rim_value(surface, field: str, idx: int, r_a: float) -> float:
    """Largest |term| at the rim per unit coefficient (mm per coefficient unit)."""
    if field in ("zeta", "gamma"):
        return r_a ** (idx + 1)
    if field == "aspheric":
        return r_a ** (2 * (idx + 1))
    if isinstance(surface, ExtendedPolynomial):
        p, q = extended_monomial_exponents(idx + 1)[-1]
        rho = r_a / surface.norm_radius
        return rho ** (p + q)  # max of |x^p y^q| on a circle is below rho^(p+q); a safe scale
    if isinstance(surface, ZernikeSag):
        n, m = noll_to_nm(idx + 1)
        rho = min(r_a / surface.norm_radius, 1.0) if n else 1.0
        return math.sqrt(n + 1) * (math.sqrt(2.0) if m else 1.0) * rho ** n
    raise ConfigError(f"design parameter: field {field!r} has no default bound")


def default_bound(lens: Lens, name: str) -> tuple[float, float]:
    """Documented default (lower, upper) bound of a parameter for a template lens."""
    side, field, idx = _parse_name(name)
    if field == "thickness":
        return (3.0, 10.0)
    surf = getattr(lens, side)
    if field == "curvature":
        return (-0.05, 0.05)
    if field == "conic":
        return (-3.0, 3.0)
    if idx is None:
        raise ConfigError(f"design parameter {name!r}: field {field!r} needs an index, e.g. {name}[0]")
    r_a = 0.5 * lens.aperture
    deg = _term_degree(surf, field, idx)
    rim = _rim_value(surf, field, idx, r_a)
    if deg == 1:
        budget = _SLOPE_BUDGET * r_a
    else:
        budget = _SAG_BUDGET.get(deg, _SAG_BUDGET_HIGH)
    b = budget / rim
    return (-b, b)


def describe_parameter(lens: Lens, name: str) -> str:
    """Human label of a parameter, e.g. 'front x^2 (mm^-1)' or 'back Noll 5 (mm)'."""
    side, field, idx = _parse_name(name)
    if field == "thickness":
        return "centre thickness l (mm)"
    surf = getattr(lens, side)
    if field == "curvature":
        return f"{side} curvature (1/mm)"
    if field == "conic":
        return f"{side} conic constant"
    if field == "aspheric":
        return f"{side} r^{2 * (idx + 1)} aspheric"
    if field in ("zeta", "gamma"):
        v = "x" if field == "zeta" else "y"
        return f"{side} {v}^{idx + 1} (mm^{-idx})"
    if isinstance(surf, ExtendedPolynomial):
        p, q = extended_monomial_exponents(idx + 1)[-1]
        mono = "*".join([f"x^{p}"] * (p > 0) + [f"y^{q}"] * (q > 0)).replace("^1", "")
        return f"{side} {mono}/R_n^{p + q} (mm)"
    if isinstance(surf, ZernikeSag):
        return f"{side} Zernike Noll {idx + 1} (mm)"
    return name


def _get(lens: Lens, name: str) -> float:
    side, field, idx = _parse_name(name)
    if side is None:
        return float(lens.thickness)
    surf = getattr(lens, side)
    if not hasattr(surf, field):
        raise ConfigError(
            f"design parameter {name!r}: a {surf.kind} surface has no field {field!r}"
        )
    v = getattr(surf, field)
    if isinstance(v, tuple):
        if idx is None:
            raise ConfigError(f"design parameter {name!r}: field {field!r} needs an index, e.g. {name}[0]")
        return float(v[idx]) if idx < len(v) else 0.0
    if idx is not None:
        raise ConfigError(f"design parameter {name!r}: field {field!r} is a single number; drop the [{idx}]")
    return float(v)


class BoxBounds:
    """The box of a parameter vector p (physical units) and the optimisers' unit cube:
    for a class with ``names``, ``lower`` and ``upper`` (tuples)."""

    @property
    def n(self) -> int:
        return len(self.names)

    @property
    def lo(self) -> np.ndarray:
        return np.asarray(self.lower, dtype=float)

    @property
    def hi(self) -> np.ndarray:
        return np.asarray(self.upper, dtype=float)

    def to_unit(self, p) -> np.ndarray:
        """p -> u in [0, 1]^n (the optimisers' space)."""
        return (np.asarray(p, dtype=float) - self.lo) / (self.hi - self.lo)

    def from_unit(self, u) -> np.ndarray:
        """u in [0, 1]^n -> p (clipped to the bounds)."""
        u = np.clip(np.asarray(u, dtype=float), 0.0, 1.0)
        return self.lo + u * (self.hi - self.lo)

    def in_bounds(self, p, rtol: float = 1e-12) -> bool:
        """p inside the box (to rtol of its widths)."""
        p = np.asarray(p, dtype=float)
        slack = rtol * (self.hi - self.lo)
        return bool(np.all(p >= self.lo - slack) and np.all(p <= self.hi + slack))

    def bounds_dict(self) -> dict:
        """{name: [lower, upper]}."""
        return {n: [lo, hi] for n, lo, hi in zip(self.names, self.lower, self.upper)}


@dataclass(frozen=True)
class Parameterisation(BoxBounds):
    """Maps a parameter vector p (physical units) to a lens.

    model: model name; template: lens whose non-free values are kept; names: free
    parameter names; lower/upper: bounds (same units as p).
    """

    model: str
    template: Lens
    names: tuple
    lower: tuple
    upper: tuple

    def to_lens(self, p) -> Lens:
        """The lens of parameter vector p (raises ConfigError on non-finite values)."""
        p = np.asarray(p, dtype=float)
        d = self.template.to_dict()
        for name, v in zip(self.names, p):
            side, field, idx = _parse_name(name)
            if side is None:
                d["thickness"] = float(v)
            elif idx is None:
                d[side][field] = float(v)
            else:
                arr = list(d[side][field])
                if len(arr) <= idx:
                    arr += [0.0] * (idx + 1 - len(arr))
                arr[idx] = float(v)
                d[side][field] = arr
        return Lens.from_dict(d, where="design lens")

    def from_lens(self, lens: Lens) -> np.ndarray:
        """Parameter vector of a lens of the same surface kinds."""
        return np.array([_get(lens, n) for n in self.names])

    def labels(self) -> dict:
        return {n: describe_parameter(self.template, n) for n in self.names}


def parse_bounds(spec) -> dict:
    """Bounds overrides from a dict {name: (lo, hi)} or a string
    'name=lo:hi,name=lo:hi' (e.g. 'thickness=4:8,front.zeta[1]=-0.03:0.03')."""
    if spec is None or spec == "":
        return {}
    if isinstance(spec, dict):
        items = list(spec.items())
    else:
        items = []
        for part in str(spec).split(","):
            part = part.strip()
            if not part:
                continue
            if "=" not in part or ":" not in part.split("=", 1)[1]:
                raise ConfigError(f"bounds: {part!r} is not 'name=lo:hi' (e.g. thickness=4:8)")
            name, rng = part.split("=", 1)
            lo, hi = rng.split(":", 1)
            try:
                items.append((name.strip(), (float(lo), float(hi))))
            except ValueError:
                raise ConfigError(f"bounds: {part!r}: lo and hi must be numbers") from None
    out = {}
    for name, b in items:
        try:
            lo, hi = (float(v) for v in b)
        except (TypeError, ValueError):
            raise ConfigError(f"bounds[{name!r}]: expected two numbers (lo, hi), got {b!r}") from None
        out[str(name)] = (lo, hi)
    return out


def parameterisation(model: str, free=None, bounds=None, template: Lens | None = None) -> Parameterisation:
    """Parameterisation of a model.

    free: preset name ('paper', 'full', for zernike also 'base'; default DEFAULT_PRESET)
    or a list of parameter names;
    bounds: overrides {name: (lo, hi)} or 'name=lo:hi,...' on top of the defaults;
    template: lens holding the non-free values (default: the paper's lens of the model).
    """
    key = str(model).lower().replace("-", "_")
    if key not in MODELS:
        raise ConfigError(f"model: unknown design model {model!r}; use one of {', '.join(MODELS)}")
    tmpl = template if template is not None else paper_lens(_TEMPLATE[key])
    if free is None or isinstance(free, str):
        preset = DEFAULT_PRESET[key] if free in (None, "") else free
        if isinstance(preset, str) and "," in preset:
            names = tuple(s.strip() for s in preset.split(",") if s.strip())
        elif preset not in FREE_PRESETS[key]:
            raise ConfigError(
                f"free: unknown preset {preset!r} for model {key}; use {sorted(FREE_PRESETS[key])} or a list of names"
            )
        else:
            names = FREE_PRESETS[key][preset]
    else:
        names = tuple(str(n) for n in free)
    if not names:
        raise ConfigError("free: at least one free parameter is needed")
    if len(set(names)) != len(names):
        raise ConfigError(f"free: duplicate parameter names in {list(names)}")
    for n in names:
        _get(tmpl, n)  # validates the name against the template's surfaces
    over = parse_bounds(bounds)
    unknown = set(over) - set(names)
    if unknown:
        raise ConfigError(f"bounds: {sorted(unknown)} not among the free parameters {list(names)}")
    lower, upper = [], []
    for n in names:
        lo, hi = over.get(n, default_bound(tmpl, n))
        if not (np.isfinite(lo) and np.isfinite(hi)) or not lo < hi:
            raise ConfigError(f"bounds[{n!r}]: need finite lo < hi, got ({lo}, {hi})")
        if n == "thickness" and lo <= 0:
            raise ConfigError(f"bounds['thickness']: lower bound must be > 0 mm, got {lo}")
        lower.append(float(lo))
        upper.append(float(hi))
    return Parameterisation(key, tmpl, tuple(names), tuple(lower), tuple(upper))
