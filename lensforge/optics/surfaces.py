"""Sag surfaces, named as in the optical-design tools engineers already use.

Every surface is a dataclass with its native parameters and lowers itself to one
*canonical form* (:class:`CanonicalSurface`)::

    s(x, y) = c r^2 / (1 + sqrt(1 - (1 + k) c^2 r^2)) + sum_i alpha_i r^(2 i)
              + sum_{p, q} P[p, q] x^p y^q              (all lengths in mm)
    z(x, y) = s + a sin(2 pi s / h)                      (optional layer ripple)

The ripple term models the residual staircase of SLA layers of height h (the
layers are planes of constant sag along the print axis) as a sinusoid of
amplitude a; it is zero for designed surfaces.

The conic part carries the rotationally symmetric base, the monomial array P
carries every freeform term (polynomial, extended polynomial and Zernike terms
are all exact polynomials in x and y). The ray tracer, the mesh and STEP
exporters and the tolerance models all evaluate this one form, so they agree by
construction.

Sag is along +z of the surface's vertex frame; lengths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import ClassVar

import numpy as np
from numpy.polynomial import polynomial as P

from ..errors import ConfigError
from ..input_checks import MAX_SAG_COEFFICIENTS
from .zernike import zernike_monomials

__all__ = [
    "CanonicalSurface",
    "Surface",
    "Conic",
    "Polynomial",
    "ExtendedPolynomial",
    "ZernikeSag",
    "Freeform",
    "surface_from_dict",
    "extended_monomial_exponents",
    "add_monomials",
    "N_ASPHERIC",
]

N_ASPHERIC = 8  # even aspheric terms alpha_1 .. alpha_8 (r^2 .. r^16)


def add_monomials(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Sum of two square monomial arrays (x^p y^q coefficients) of possibly different degree."""
    n = max(a.shape[0], b.shape[0])
    out = np.zeros((n, n))
    out[: a.shape[0], : a.shape[1]] += a
    out[: b.shape[0], : b.shape[1]] += b
    return out


@dataclass(frozen=True)
class CanonicalSurface:
    """Conic + even asphere + bivariate monomials; the form every consumer evaluates.

    c: vertex curvature (1/mm); k: conic constant; alpha: (8,) coefficients of
    r^2 .. r^16 (mm^(1-2i)); poly: (D+1, D+1) coefficients of x^p y^q (mm^(1-p-q)).
    """

    c: float
    k: float
    alpha: np.ndarray
    poly: np.ndarray
    ripple_amplitude: float = 0.0
    ripple_period: float = 1.0

    def sag(self, x, y):
        """Sag z(x, y) in mm; NaN where the conic is undefined (beyond its edge)."""
        return self.sag_and_gradient(x, y)[0]

    def gradient(self, x, y):
        """(dz/dx, dz/dy), dimensionless."""
        _, gx, gy = self.sag_and_gradient(x, y)
        return gx, gy

    def sag_and_gradient(self, x, y):
        """(z, dz/dx, dz/dy) vectorised over broadcastable arrays x, y (mm)."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        r2 = x * x + y * y
        c, k = self.c, self.k
        arg = 1.0 - (1.0 + k) * c * c * r2
        with np.errstate(invalid="ignore"):
            root = np.sqrt(arg)
            z = c * r2 / (1.0 + root)
            dz_dr2_2 = np.where(arg > 0, c / np.where(arg > 0, root, 1.0), np.nan)  # dz/dx = x * this
        # even asphere: sum alpha_i r^(2i); derivative 2 i alpha_i r^(2i-2) * x
        a = self.alpha
        if np.any(a):
            za = np.zeros_like(r2)
            da = np.zeros_like(r2)
            for i in range(len(a), 0, -1):
                za = (za + a[i - 1]) * r2
                da = da * r2 + 2.0 * i * a[i - 1] if i > 1 else da * r2 + 2.0 * a[0]
            # da above is Horner of sum 2 i a_i r2^(i-1)
            z = z + za
            dz_dr2_2 = dz_dr2_2 + da
        gx = x * dz_dr2_2
        gy = y * dz_dr2_2
        p = self.poly
        if p.size and np.any(p):
            z = z + P.polyval2d(x, y, p)
            if p.shape[0] > 1:
                gx = gx + P.polyval2d(x, y, P.polyder(p, axis=0))
            if p.shape[1] > 1:
                gy = gy + P.polyval2d(x, y, P.polyder(p, axis=1))
        if self.ripple_amplitude:
            w = 2.0 * np.pi / self.ripple_period
            f = 1.0 + self.ripple_amplitude * w * np.cos(w * z)
            z = z + self.ripple_amplitude * np.sin(w * z)
            gx = gx * f
            gy = gy * f
        return z, gx, gy


def _as_coeffs(name: str, value, length: int | None = None) -> np.ndarray:
    length = MAX_SAG_COEFFICIENTS if length is None else length
    if isinstance(value, (list, tuple)) and len(value) > length:  # before converting a million entries
        raise ConfigError(f"{name}: at most {length} coefficients allowed, got {len(value)}")
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    if arr.ndim != 1:
        raise ConfigError(f"{name}: expected a list of numbers, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"{name}: all coefficients must be finite numbers (no NaN/inf)")
    if length is not None and len(arr) > length:
        raise ConfigError(f"{name}: at most {length} coefficients allowed, got {len(arr)}")
    return arr


def _check_finite(name: str, value: float) -> float:
    value = float(value)
    if not np.isfinite(value):
        raise ConfigError(f"{name}: must be a finite number, got {value}")
    return value


def _check_radius(name: str, value: float) -> float:
    value = _check_finite(name, value)
    if value <= 0:
        raise ConfigError(f"{name}: normalisation radius must be > 0 mm, got {value}")
    return value


@dataclass(frozen=True)
class Surface:
    """Base of all surface models: conic base + even aspheric terms.

    curvature: 1/R in 1/mm (0 = plane); conic: conic constant k;
    aspheric: alpha_1 .. alpha_8 for r^2 .. r^16.
    """

    kind: ClassVar[str] = "surface"
    curvature: float = 0.0
    conic: float = 0.0
    aspheric: tuple = ()

    def __post_init__(self):
        object.__setattr__(self, "curvature", _check_finite(f"{self.kind}.curvature", self.curvature))
        object.__setattr__(self, "conic", _check_finite(f"{self.kind}.conic", self.conic))
        a = _as_coeffs(f"{self.kind}.aspheric", self.aspheric, N_ASPHERIC)
        object.__setattr__(self, "aspheric", tuple(float(v) for v in a))

    def _alpha(self) -> np.ndarray:
        a = np.zeros(N_ASPHERIC)
        a[: len(self.aspheric)] = self.aspheric
        return a

    def _poly(self) -> np.ndarray:
        return np.zeros((1, 1))

    def canonical(self) -> CanonicalSurface:
        """The surface in canonical form (conic + asphere + monomials, mm)."""
        return CanonicalSurface(self.curvature, self.conic, self._alpha(), self._poly())

    def sag(self, x, y):
        """Sag (mm) at (x, y) in mm."""
        return self.canonical().sag(x, y)

    def gradient(self, x, y):
        """(dz/dx, dz/dy) at (x, y) in mm."""
        return self.canonical().gradient(x, y)

    def is_rotationally_symmetric(self) -> bool:
        return not np.any(self._poly())

    def to_dict(self) -> dict:
        out = {"kind": self.kind}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = list(v) if isinstance(v, tuple) else v
        return out

    def replace(self, **changes) -> "Surface":
        d = self.to_dict()
        d.pop("kind")
        d.update(changes)
        return type(self)(**d)


@dataclass(frozen=True)
class Conic(Surface):
    """Sphere or conic with optional even aspheric terms (Zemax 'Standard' / 'Even Asphere'):
    z = c r^2 / (1 + sqrt(1 - (1 + k) c^2 r^2)) + sum_i alpha_i r^(2i), mm.

    Parameters
    ----------
    curvature : float
        Base curvature c = 1/R, 1/mm (0: plane).
    conic : float
        Conic constant k (0 sphere, -1 paraboloid).
    aspheric : tuple of float
        Even aspheric coefficients alpha_i of r^(2i), i = 1..8, in mm^(1-2i).
    """

    kind: ClassVar[str] = "conic"


@dataclass(frozen=True)
class Polynomial(Surface):
    """z = base + sum_i (zeta_i x^i + gamma_i y^i), unnormalised, mm units (the paper uses
    i in {2, 4}).

    Parameters
    ----------
    curvature : float
        Base curvature c = 1/R, 1/mm (0: plane).
    conic : float
        Conic constant k (0 sphere, -1 paraboloid).
    aspheric : tuple of float
        Even aspheric coefficients alpha_i of r^(2i), i = 1..8, in mm^(1-2i).
    zeta, gamma : tuple of float
        Coefficients of x^1, x^2, ... and y^1, y^2, ... (zeta[0] multiplies x^1), in mm^(1-i).
    """

    kind: ClassVar[str] = "polynomial"
    zeta: tuple = ()
    gamma: tuple = ()

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "zeta", tuple(_as_coeffs("polynomial.zeta", self.zeta)))
        object.__setattr__(self, "gamma", tuple(_as_coeffs("polynomial.gamma", self.gamma)))

    def _poly(self) -> np.ndarray:
        d = max(len(self.zeta), len(self.gamma), 0)
        p = np.zeros((d + 1, d + 1))
        for i, v in enumerate(self.zeta, start=1):
            p[i, 0] += v
        for i, v in enumerate(self.gamma, start=1):
            p[0, i] += v
        return p


def extended_monomial_exponents(n_terms: int) -> list[tuple[int, int]]:
    """Exponents (p, q) of x^p y^q in extended-polynomial order: x, y, x^2, xy, y^2, x^3, ..."""
    out = []
    deg = 1
    while len(out) < n_terms:
        for q in range(deg + 1):
            out.append((deg - q, q))
            if len(out) == n_terms:
                break
        deg += 1
    return out


@dataclass(frozen=True)
class ExtendedPolynomial(Surface):
    """Zemax-style 'Extended Polynomial': base + sum_i A_i E_i(x/R_n, y/R_n).

    Parameters
    ----------
    curvature : float
        Base curvature c = 1/R, 1/mm (0: plane).
    conic : float
        Conic constant k (0 sphere, -1 paraboloid).
    aspheric : tuple of float
        Even aspheric coefficients alpha_i of r^(2i), i = 1..8, in mm^(1-2i).
    coefficients : tuple of float
        A_i in mm, monomials ordered x, y, x^2, xy, y^2, x^3, ...
    norm_radius : float
        Normalisation radius R_n, mm.
    """

    kind: ClassVar[str] = "extended_polynomial"
    coefficients: tuple = ()
    norm_radius: float = 1.0

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "coefficients", tuple(_as_coeffs("extended_polynomial.coefficients", self.coefficients)))
        object.__setattr__(self, "norm_radius", _check_radius("extended_polynomial.norm_radius", self.norm_radius))

    def _poly(self) -> np.ndarray:
        exps = extended_monomial_exponents(len(self.coefficients))
        d = max((p + q for p, q in exps), default=0)
        out = np.zeros((d + 1, d + 1))
        for (p, q), a in zip(exps, self.coefficients):
            out[p, q] += a / self.norm_radius ** (p + q)
        return out


@dataclass(frozen=True)
class ZernikeSag(Surface):
    """Zemax-style 'Zernike Standard Sag': base + sum_j A_j Z_j(x/R_n, y/R_n).

    Parameters
    ----------
    curvature : float
        Base curvature c = 1/R, 1/mm (0: plane).
    conic : float
        Conic constant k (0 sphere, -1 paraboloid).
    aspheric : tuple of float
        Even aspheric coefficients alpha_i of r^(2i), i = 1..8, in mm^(1-2i).
    coefficients : tuple of float
        A_j in mm for Noll j = 1, 2, ... (Noll order, RMS-normalised).
    norm_radius : float
        Normalisation radius R_n, mm.
    """

    kind: ClassVar[str] = "zernike_sag"
    coefficients: tuple = ()
    norm_radius: float = 1.0

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "coefficients", tuple(_as_coeffs("zernike_sag.coefficients", self.coefficients)))
        object.__setattr__(self, "norm_radius", _check_radius("zernike_sag.norm_radius", self.norm_radius))

    def _poly(self) -> np.ndarray:
        if not self.coefficients:
            return np.zeros((1, 1))
        mons = [zernike_monomials(j) for j in range(1, len(self.coefficients) + 1)]
        d = max(m.shape[0] for m in mons) - 1
        out = np.zeros((d + 1, d + 1))
        scale = np.array([[self.norm_radius ** -(p + q) for q in range(d + 1)] for p in range(d + 1)])
        for a, m in zip(self.coefficients, mons):
            out[: m.shape[0], : m.shape[1]] += a * m
        return out * scale


@dataclass(frozen=True)
class Freeform(Surface):
    """Canonical form written out: base + sum P[p][q] x^p y^q (mm) + layer ripple. Used for
    as-built lenses and by tools that perturb a design.

    Parameters
    ----------
    curvature : float
        Base curvature c = 1/R, 1/mm (0: plane).
    conic : float
        Conic constant k (0 sphere, -1 paraboloid).
    aspheric : tuple of float
        Even aspheric coefficients alpha_i of r^(2i), i = 1..8, in mm^(1-2i).
    poly : tuple of tuple of float, shape (D+1, D+1)
        Monomial coefficients P[p][q] of x^p y^q, in mm^(1-p-q).
    ripple_amplitude : float
        Amplitude of the residual layer staircase, mm (z = sag + a sin(2 pi sag / h)).
    ripple_period : float
        Its period h (the layer height), mm.
    """

    kind: ClassVar[str] = "freeform"
    poly: tuple = ((0.0,),)
    ripple_amplitude: float = 0.0
    ripple_period: float = 0.025

    def __post_init__(self):
        super().__post_init__()
        arr = np.asarray(self.poly, dtype=float)
        if arr.ndim != 2 or arr.shape[0] != arr.shape[1] or not np.all(np.isfinite(arr)):
            raise ConfigError("freeform.poly: expected a finite square nested list of monomial coefficients")
        object.__setattr__(self, "poly", tuple(tuple(float(v) for v in row) for row in arr))
        a = _check_finite("freeform.ripple_amplitude", self.ripple_amplitude)
        h = _check_finite("freeform.ripple_period", self.ripple_period)
        if a < 0 or h <= 0:
            raise ConfigError("freeform.ripple_amplitude must be >= 0 and ripple_period > 0 (mm)")
        object.__setattr__(self, "ripple_amplitude", a)
        object.__setattr__(self, "ripple_period", h)

    def _poly(self) -> np.ndarray:
        return np.array(self.poly, dtype=float)

    def canonical(self) -> CanonicalSurface:
        return CanonicalSurface(self.curvature, self.conic, self._alpha(), self._poly(),
                                self.ripple_amplitude, self.ripple_period)

    def is_rotationally_symmetric(self) -> bool:
        return not np.any(self._poly()) and self.ripple_amplitude == 0.0

    def to_dict(self) -> dict:
        d = super().to_dict()
        d["poly"] = [list(r) for r in self.poly]
        return d

    @classmethod
    def from_canonical(cls, cs: CanonicalSurface) -> "Freeform":
        """Freeform surface holding exactly the given canonical form."""
        return cls(curvature=cs.c, conic=cs.k, aspheric=tuple(cs.alpha), poly=np.asarray(cs.poly),
                   ripple_amplitude=cs.ripple_amplitude, ripple_period=cs.ripple_period)


_KINDS = {cls.kind: cls for cls in (Conic, Polynomial, ExtendedPolynomial, ZernikeSag, Freeform)}
_KINDS["sphere"] = Conic


def surface_from_dict(d: dict, where: str = "surface") -> Surface:
    """Build a surface from its dict form (as written by ``to_dict``)."""
    if not isinstance(d, dict):
        raise ConfigError(f"{where}: expected a table/dict, got {type(d).__name__}")
    d = dict(d)
    kind = d.pop("kind", None)
    if kind not in _KINDS:
        raise ConfigError(f"{where}.kind: unknown surface kind {kind!r}; use one of {sorted(_KINDS)}")
    cls = _KINDS[kind]
    allowed = {f.name for f in fields(cls)}
    unknown = set(d) - allowed
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)} for kind {kind!r}; allowed: {sorted(allowed)}")
    try:
        return cls(**d)
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    except (TypeError, ValueError, OverflowError) as e:
        raise ConfigError(f"{where}: {e}") from None
