"""Zernike polynomials: Noll order, RMS (Noll) normalisation over the unit disc.

One convention inside lensforge (DESIGN.md): Noll index j >= 1. Conversions to
OSA/ANSI (j from 0) and to the Thorlabs WFS ordering (OSA j + 1) are offered for
input and output only.

Every Zernike polynomial is a polynomial in x and y; :func:`zernike_monomials`
returns its exact monomial coefficient array ``C`` with
``Z_j(x, y) = sum_{p,q} C[p, q] x**p y**q`` on the unit disc. Sag surfaces and the
slope fit both evaluate Zernikes through that array, so value and gradient come
from one definition.
"""

from __future__ import annotations

from numpy.typing import ArrayLike

from functools import lru_cache
from math import comb, factorial, sqrt

import numpy as np
from numpy.polynomial import polynomial as P

__all__ = [
    "noll_to_nm",
    "nm_to_noll",
    "noll_to_osa",
    "osa_to_noll",
    "noll_to_thorlabs",
    "thorlabs_to_noll",
    "modes_up_to_order",
    "zernike_monomials",
    "zernike",
    "zernike_gradient",
    "to_osa_vector",
    "from_osa_vector",
    "to_thorlabs_vector",
    "from_thorlabs_vector",
]


def noll_to_nm(j: int) -> tuple[int, int]:
    """Radial order and signed azimuthal frequency of a Noll index.

    Sign convention: m > 0 is a cosine term, m < 0 a sine term (even j -> cosine).

    Parameters
    ----------
    j : int
        Noll index, j >= 1 (1 = piston).

    Returns
    -------
    tuple of int
        (n, m): radial order n >= 0 and azimuthal frequency m, |m| <= n, n - |m| even.
    """
    j = int(j)
    if j < 1:
        raise ValueError(f"Noll index must be >= 1, got {j}")
    n = 0
    while (n + 1) * (n + 2) // 2 < j:
        n += 1
    k = j - n * (n + 1) // 2  # 1-based position within order n
    # |m| values in order n, each non-zero one twice, sorted ascending
    ms = [m for m in range(n % 2, n + 1, 2) for _ in ((0,) if m == 0 else (0, 1))]
    am = ms[k - 1]
    if am == 0:
        return n, 0
    return n, am if j % 2 == 0 else -am


def nm_to_noll(n: int, m: int) -> int:
    """Noll index of a radial order and signed azimuthal frequency.

    Parameters
    ----------
    n : int
        Radial order, n >= 0.
    m : int
        Azimuthal frequency, |m| <= n and n - |m| even; m > 0 cosine, m < 0 sine.

    Returns
    -------
    int
        Noll index j >= 1.
    """
    if n < 0 or abs(m) > n or (n - abs(m)) % 2:
        raise ValueError(f"invalid Zernike (n, m) = ({n}, {m})")
    for j in range(n * (n + 1) // 2 + 1, (n + 1) * (n + 2) // 2 + 1):
        if noll_to_nm(j) == (n, m):
            return j
    raise AssertionError("unreachable")


def noll_to_osa(j: int) -> int:
    """OSA/ANSI index of a Noll index (edge conversion only; lensforge uses Noll inside).

    Parameters
    ----------
    j : int
        Noll index, j >= 1.

    Returns
    -------
    int
        OSA/ANSI index, counted from 0 (0 = piston).
    """
    n, m = noll_to_nm(j)
    return (n * (n + 2) + m) // 2


def osa_to_noll(i: int) -> int:
    """Noll index of an OSA/ANSI index.

    Parameters
    ----------
    i : int
        OSA/ANSI index, counted from 0.

    Returns
    -------
    int
        Noll index j >= 1.
    """
    i = int(i)
    if i < 0:
        raise ValueError(f"OSA index must be >= 0, got {i}")
    n = 0
    while (n + 1) * (n + 2) // 2 <= i:
        n += 1
    m = 2 * i - n * (n + 2)
    return nm_to_noll(n, m)


def noll_to_thorlabs(j: int) -> int:
    """Thorlabs WFS mode number of a Noll index (Thorlabs k = OSA index + 1).

    Parameters
    ----------
    j : int
        Noll index, j >= 1.

    Returns
    -------
    int
        Thorlabs mode number k >= 1.
    """
    return noll_to_osa(j) + 1


def thorlabs_to_noll(k: int) -> int:
    """Noll index of a Thorlabs WFS mode number.

    Parameters
    ----------
    k : int
        Thorlabs mode number (OSA index + 1), k >= 1.

    Returns
    -------
    int
        Noll index j >= 1.
    """
    return osa_to_noll(int(k) - 1)


def modes_up_to_order(order: int, piston: bool = False) -> np.ndarray:
    """Noll indices of all modes of radial order <= ``order`` (piston excluded by default)."""
    last = (order + 1) * (order + 2) // 2
    return np.arange(1 if piston else 2, last + 1)


@lru_cache(maxsize=None)
def _monomials(j: int) -> np.ndarray:
    n, m = noll_to_nm(j)
    am = abs(m)
    norm = sqrt(n + 1) if m == 0 else sqrt(2 * (n + 1))
    # angular part rho^|m| cos/sin(|m| phi) = Re/Im (x + i y)^|m|
    ang = np.zeros((am + 1, am + 1))
    for q in range(am + 1):  # term C(am, q) x^(am-q) (i y)^q
        coeff = comb(am, q)
        phase = q % 4  # i^q: 0 -> 1, 1 -> i, 2 -> -1, 3 -> -i
        real = {0: 1.0, 1: 0.0, 2: -1.0, 3: 0.0}[phase]
        imag = {0: 0.0, 1: 1.0, 2: 0.0, 3: -1.0}[phase]
        ang[am - q, q] = coeff * (real if m >= 0 else imag)
    out = np.zeros((n + 1, n + 1))
    for s in range((n - am) // 2 + 1):
        r = (-1) ** s * factorial(n - s) / (
            factorial(s) * factorial((n + am) // 2 - s) * factorial((n - am) // 2 - s)
        )
        e = (n - am) // 2 - s  # (x^2 + y^2)^e
        rad = np.zeros((2 * e + 1, 2 * e + 1))
        for t in range(e + 1):
            rad[2 * t, 2 * (e - t)] = comb(e, t)
        term = _polymul2d(rad, ang) * r
        out[: term.shape[0], : term.shape[1]] += term
    out *= norm
    out.setflags(write=False)
    return out


def _polymul2d(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.zeros((a.shape[0] + b.shape[0] - 1, a.shape[1] + b.shape[1] - 1))
    for (p, q), v in np.ndenumerate(a):
        if v:
            out[p : p + b.shape[0], q : q + b.shape[1]] += v * b
    return out


def zernike_monomials(j: int) -> np.ndarray:
    """Monomial coefficients C[p, q] of Noll Z_j on the unit disc (read-only array)."""
    return _monomials(int(j))


def zernike(j: int, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Value of Noll Z_j at normalised Cartesian coordinates (x, y) (unit disc)."""
    return P.polyval2d(x, y, zernike_monomials(j))


def zernike_gradient(j: int, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(dZ_j/dx, dZ_j/dy) at normalised coordinates (x, y)."""
    c = zernike_monomials(j)
    gx = P.polyval2d(x, y, P.polyder(c, axis=0)) if c.shape[0] > 1 else np.zeros_like(x)
    gy = P.polyval2d(x, y, P.polyder(c, axis=1)) if c.shape[1] > 1 else np.zeros_like(x)
    return gx, gy


def to_osa_vector(noll_indices: ArrayLike, coefficients: ArrayLike) -> np.ndarray:
    """Reorder coefficients given at Noll indices into an OSA-indexed vector.

    Parameters
    ----------
    noll_indices : array_like of int, shape (n,)
        Noll index of each coefficient (j >= 1, distinct).
    coefficients : array_like, shape (n,)
        Zernike coefficients at those indices (any unit; um of wavefront in lensforge).

    Returns
    -------
    numpy.ndarray, shape (max OSA index + 1,)
        Entry i holds the coefficient of OSA/ANSI index i (from 0); modes not given are 0.
    """
    noll_indices = np.asarray(noll_indices, dtype=int)
    coefficients = np.asarray(coefficients, dtype=float)
    osa = np.array([noll_to_osa(j) for j in noll_indices])
    out = np.zeros(osa.max() + 1)
    out[osa] = coefficients
    return out


def from_osa_vector(osa_coefficients: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Noll indices and coefficients of an OSA-indexed vector.

    Parameters
    ----------
    osa_coefficients : array_like, shape (n,)
        Entry i is the coefficient of OSA/ANSI index i (from 0).

    Returns
    -------
    noll : numpy.ndarray of int, shape (n,)
        Noll indices, ascending.
    coefficients : numpy.ndarray, shape (n,)
        The coefficients in that order (unit unchanged).
    """
    c = np.asarray(osa_coefficients, dtype=float)
    noll = np.array([osa_to_noll(i) for i in range(len(c))])
    order = np.argsort(noll)
    return noll[order], c[order]


def to_thorlabs_vector(noll_indices: ArrayLike, coefficients: ArrayLike) -> np.ndarray:
    """Coefficients reordered as the Thorlabs WFS reports them.

    Parameters
    ----------
    noll_indices : array_like of int, shape (n,)
        Noll index of each coefficient (j >= 1, distinct).
    coefficients : array_like, shape (n,)
        Zernike coefficients, um of wavefront, RMS-normalised.

    Returns
    -------
    numpy.ndarray, shape (max mode number,)
        Entry k - 1 holds Thorlabs mode k = OSA index + 1 (um); modes not given are 0.
    """
    return to_osa_vector(noll_indices, coefficients)


def from_thorlabs_vector(thorlabs_coefficients: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Noll indices and coefficients of a Thorlabs-ordered vector.

    Parameters
    ----------
    thorlabs_coefficients : array_like, shape (n,)
        Entry k - 1 is Thorlabs mode k (= OSA index + 1), um.

    Returns
    -------
    noll : numpy.ndarray of int, shape (n,)
        Noll indices, ascending.
    coefficients : numpy.ndarray, shape (n,)
        The coefficients in that order, um.
    """
    return from_osa_vector(thorlabs_coefficients)
