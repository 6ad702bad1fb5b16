"""The Fraunhofer field of one square sub-aperture carrying a quadratic phase (its own curvature).

Per axis a lenslet's sub-aperture is t in [-1/2, 1/2] (in pitches) with the phase alpha t^2; seen at the
camera angle beta its far field is

    A(beta, alpha) = int_{-1/2}^{1/2} exp(i alpha t^2 - i beta t) dt          (the sinc when alpha = 0)

with the moments M_r = int t^r exp(...) dt (M_0 = A; the cross-talk kernel's K_xy series needs M_r up to
~12) and their derivatives dM_r/dbeta = -i M_(r+1), dM_r/dalpha = i M_(r+2). ``square_aperture_moments``
evaluates them; under a complex step (beta + i h db, alpha + i h da, h ~ 1e-30) it returns M + i h (dM/dbeta
db + dM/dalpha da), the exact first-order jet, so the cross-talk kernel's complex-step Jacobian stays exact.

Evaluation (``_moment_jets``, compiled): |alpha| < ``ALPHA_FRESNEL``: M_r = sum_n (i alpha)^n / n! F_(2n+r) with the
moments F_m = int t^m exp(-i beta t) dt (G_m cos, H_m sin parts), for |beta| >= ``BETA_SPLIT`` by
integration by parts (G_m = 2^(1-m) sin(beta/2) / beta - (m / beta) H_(m-1), H_m = -2^(1-m)
cos(beta/2) / beta + (m / beta) G_(m-1); its rounding grows by m / beta a step, on the high moments
that carry the small weights alpha^n / n!), below from the top moment's power series (terms <= e^(BETA_SPLIT / 2))
by the same relations downwards (4x cheaper than a series per moment); larger
|alpha|: A from the Fresnel integrals by completing the square (``_fresnel_field``; A(beta, -alpha) =
conj A(-beta, alpha)), and the moments by integration by parts, upwards:

    2 alpha M_(r+1) = beta M_r + i r M_(r-1) - i [t^r exp(i alpha t^2 - i beta t)]_{-1/2}^{1/2},

which multiplies rounding by |beta| / 2|alpha| a step: where that would grow past ``_RECURSION_GROWTH``
over the moments asked for, the alpha series is taken instead (its m-recursion is stable there, |beta| large).
Checked against a 400-node Gauss-Legendre rule to 2e-11 for r <= 12 (tests/test_crosstalk_kernel.py).

An amplitude exp(gamma t + delta t^2) across the aperture (the 'cells' model's irradiance gradient and curvature)
is the series sum_n c_n M_(r+n) of the plain moments, c_n the Taylor coefficients of the exponential. Its high
moments carry the upward recursion's rounding where |beta| > ``BETA_SPLIT``: 1e-12 for |gamma| <= 1 and |delta|
<= 0.05, 1e-9 at |delta| = 0.2, 2e-7 at |gamma| = 3 (r <= 12; a Gaussian beam's delta is ~0.01).
"""

from __future__ import annotations

import numba as nb
import numpy as np
from scipy import special

from .jit import compile_notice

__all__ = ["square_aperture_moments", "ALPHA_FRESNEL", "BETA_SPLIT"]

ALPHA_FRESNEL = 2.0  # |alpha| from which the Fresnel integrals are taken
BETA_SPLIT = 10.0  # |beta| from which the moments come from integration by parts
_SERIES_TOL = 1e-15  # the alpha series' last term: (|alpha| / 4)^N / N! below this
_MAX_TERMS = 40  # alpha-series terms at most: (|alpha| / 4)^40 / 40! < 1e-15 for |alpha| <= 26 (1e-8 at 40)
_RECURSION_GROWTH = 1e3  # the Fresnel branch's upward moment recursion: rounding growth allowed
_BETA_TERMS = 26  # power-series terms of the top moment below BETA_SPLIT: (5)^52 / 52! ~ 1e-31
_GRAD_TOL = 1e-12  # the irradiance gradient's series exp(gamma t) = sum_n (gamma t)^n / n!: terms down to this
_GRAD_MAX_TERMS = 24  # ... at most: (|gamma| / 2)^24 / 24! < 1e-12 for |gamma| <= 8


def _fresnel_field(beta, alpha):
    """(Re, Im) of A(beta, alpha) for alpha > 0: exp(-i beta^2 / 4 alpha) sqrt(pi / 2 alpha) (dC + i dS),
    C and S the Fresnel integrals between the aperture's edges (scipy)."""
    sc = np.sqrt(2.0 * alpha / np.pi)
    t0 = beta / (2.0 * alpha)
    s_b, c_b = special.fresnel((0.5 - t0) * sc)
    s_a, c_a = special.fresnel((-0.5 - t0) * sc)
    dc, ds = c_b - c_a, s_b - s_a
    phi = beta * beta / (4.0 * alpha)
    amp = np.sqrt(np.pi / (2.0 * alpha))
    cp, sp = np.cos(phi), np.sin(phi)
    return amp * (cp * dc + sp * ds), amp * (cp * ds - sp * dc)


@nb.njit(cache=True)
def _moment_jets(beta, alpha, gamma, delta, big_re, big_im, r_max, out):
    """out[i, r] = (Re M_r, Im M_r, Re dM_r/dbeta, Im .., Re dM_r/dalpha, Im .., Re dM_r/dgamma, Im ..),
    r = 0 .. r_max, at (beta[i], alpha[i], gamma[i], delta[i]); dM_r/dbeta = -i M_(r+1), dM_r/dalpha = i M_(r+2),
    dM_r/dgamma = M_(r+1) (and dM_r/ddelta = M_(r+2) = -i dM_r/dalpha). big_re, big_im: A at gamma = delta = 0 where
    |alpha| >= ALPHA_FRESNEL (from the Fresnel integrals), unused elsewhere. gamma or delta != 0: the moments of the
    plain aperture up to r_max + 2 + N, combined as sum_n c_n M_(r+n), c_n the Taylor coefficients of
    exp(gamma t + delta t^2) (``_GRAD_TOL`` on their bound with |t| = 1/2)."""
    n_g_max = _GRAD_MAX_TERMS
    G = np.empty(2 * _MAX_TERMS + r_max + n_g_max + 4)  # moments of exp(-i beta t) alone: cos part (even m) ...
    H = np.empty(2 * _MAX_TERMS + r_max + n_g_max + 4)  # ... sin part (odd m)
    Mr0 = np.empty(r_max + n_g_max + 3)
    Mi0 = np.empty(r_max + n_g_max + 3)
    Mr = np.empty(r_max + 3)
    Mi = np.empty(r_max + 3)
    cg = np.empty(n_g_max + 1)  # gamma^n / n!
    cd = np.empty(n_g_max // 2 + 1)  # delta^j / j!
    bn = np.empty(n_g_max + 1)  # their bound: the same sums of |gamma / 2|^(n - 2j) / (n - 2j)! |delta / 4|^j / j!
    # the coefficients c_n and their term count of the last two (gamma, delta): a sub-aperture's pair repeats over
    # its samples, alternating between the x and y axes (2.0x the plain moments' cost without this)
    cn_c = np.empty((2, n_g_max + 1))
    ng_c = np.zeros(2, dtype=np.int64)
    key_c = np.full((2, 2), np.nan)
    slot_next = 0
    for i in range(beta.size):
        b = beta[i]
        a = alpha[i]
        gm = gamma[i]
        dl = delta[i]
        n_g = 0
        if gm != 0.0 or dl != 0.0:
            slot = -1
            for s in range(2):
                if key_c[s, 0] == gm and key_c[s, 1] == dl:
                    slot = s
            if slot < 0:  # a new pair: its coefficients replace the older slot's
                slot = slot_next
                slot_next = 1 - slot
                cg[0], cd[0] = 1.0, 1.0
                for n in range(1, n_g_max + 1):
                    cg[n] = cg[n - 1] * gm / n
                for j in range(1, n_g_max // 2 + 1):
                    cd[j] = cd[j - 1] * dl / j
                for n in range(n_g_max + 1):
                    cs, bs = 0.0, 0.0
                    for j in range(n // 2 + 1):
                        cs += cg[n - 2 * j] * cd[j]
                        bs += abs(cg[n - 2 * j] * cd[j]) * 0.5 ** (n - 2 * j) * 0.25 ** j
                    cn_c[slot, n], bn[n] = cs, bs
                # terms down to _GRAD_TOL: the last n whose bound (or the next one's) is above it
                ng_c[slot] = 0
                for n in range(1, n_g_max + 1):
                    if bn[n] >= _GRAD_TOL or (n < n_g_max and bn[n + 1] >= _GRAD_TOL):
                        ng_c[slot] = n
                key_c[slot, 0], key_c[slot, 1] = gm, dl
            n_g = ng_c[slot]
            cn = cn_c[slot]
        r_top = r_max + n_g  # plain moments wanted: 0 .. r_top + 2
        fresnel = abs(a) >= ALPHA_FRESNEL
        if fresnel:  # the upward recursion multiplies rounding by |b| / 2|a| a step: only where that stays small
            ratio = abs(b) / (2.0 * abs(a))
            fresnel = ratio <= 1.0 or ratio ** (r_top + 1) < _RECURSION_GROWTH
        if fresnel:
            Mr0[0], Mi0[0] = big_re[i], big_im[i]
            ep, em = 0.25 * a - 0.5 * b, 0.25 * a + 0.5 * b  # phi at t = +1/2, -1/2
            epr, epi, emr, emi = np.cos(ep), np.sin(ep), np.cos(em), np.sin(em)
            hp, hm = 1.0, 1.0  # (1/2)^r, (-1/2)^r
            inv2a = 0.5 / a
            for r in range(r_top + 2):  # 2 a M_(r+1) = b M_r + i r M_(r-1) - i [t^r exp(i phi)]
                br, bi = hp * epr - hm * emr, hp * epi - hm * emi
                rr, ri = b * Mr0[r] + bi, b * Mi0[r] - br
                if r > 0:
                    rr -= r * Mi0[r - 1]
                    ri += r * Mr0[r - 1]
                Mr0[r + 1], Mi0[r + 1] = rr * inv2a, ri * inv2a
                hp *= 0.5
                hm *= -0.5
        else:
            q = 0.25 * abs(a)
            n_terms, term = 0, 1.0
            while term >= _SERIES_TOL and n_terms < _MAX_TERMS:
                n_terms += 1
                term *= q / n_terms
            mmax = 2 * n_terms + r_top + 2
            if abs(b) >= BETA_SPLIT:
                inv = 1.0 / b
                s2, c2 = 2.0 * np.sin(0.5 * b) * inv, 2.0 * np.cos(0.5 * b) * inv
                G[0] = s2
                half = 1.0
                for m in range(1, mmax + 1, 2):
                    half *= 0.5
                    H[m] = -half * c2 + (m * inv) * G[m - 1]
                    half *= 0.5
                    G[m + 1] = half * s2 - ((m + 1) * inv) * H[m]
            else:  # the top H_(2N+1) = 4^-N / 2 sum_j (-1)^j x^(2j+1) / ((2j+1)! (2N + 2j + 3)), x = b / 2, then
                # downwards: H_(m-1) = (2^(1-m) sin(b/2) - b G_m) / m, G_(m-1) = (b H_m + 2^(1-m) cos(b/2)) / m (stable
                # where m > |b|; below, rounding grows by at most prod_(m<10) 10/m ~ 3e3 on moments ~2^-m / m)
                x = 0.5 * b
                n_top = mmax // 2
                ho, t = 0.0, x  # t = (-1)^j x^(2j+1) / (2j+1)!
                for j in range(_BETA_TERMS):
                    ho += t / (2 * n_top + 2 * j + 3)
                    t *= -x * x / ((2 * j + 2) * (2 * j + 3))
                H[2 * n_top + 1] = 0.5 * 0.25 ** n_top * ho
                sb, cb = np.sin(x), np.cos(x)
                p2 = 2.0 ** (-2 * n_top)  # 2^(1-m) at m = 2 n_top + 1
                for m in range(2 * n_top + 1, 0, -1):
                    if m % 2 == 1:
                        G[m - 1] = (b * H[m] + p2 * cb) / m
                    else:
                        H[m - 1] = (p2 * sb - b * G[m]) / m
                    p2 *= 2.0
            # M_r = sum_n (i a)^n / n! F_(2n+r), F_m = G_m (even m), -i H_m (odd m)
            for r in range(r_top + 3):
                Mr0[r] = 0.0
                Mi0[r] = 0.0
            coef = 1.0
            for n in range(n_terms + 1):
                if n > 0:
                    coef *= a / n
                k = n % 4  # i^n = cr + i ci: 1, i, -1, -i
                cr = coef if k == 0 else (-coef if k == 2 else 0.0)
                ci = coef if k == 1 else (-coef if k == 3 else 0.0)
                for r in range(0, r_top + 3, 2):
                    g = G[2 * n + r]
                    Mr0[r] += cr * g
                    Mi0[r] += ci * g
                for r in range(1, r_top + 3, 2):  # (cr + i ci) (-i H) = ci H - i cr H
                    h = H[2 * n + r]
                    Mr0[r] += ci * h
                    Mi0[r] -= cr * h
        if n_g == 0:
            for r in range(r_max + 3):
                Mr[r] = Mr0[r]
                Mi[r] = Mi0[r]
        else:
            for r in range(r_max + 3):
                sr, si = 0.0, 0.0
                for n in range(n_g + 1):
                    sr += cn[n] * Mr0[r + n]
                    si += cn[n] * Mi0[r + n]
                Mr[r] = sr
                Mi[r] = si
        for r in range(r_max + 1):
            out[i, r, 0] = Mr[r]
            out[i, r, 1] = Mi[r]
            out[i, r, 2] = Mi[r + 1]  # -i M_(r+1)
            out[i, r, 3] = -Mr[r + 1]
            out[i, r, 4] = -Mi[r + 2]  # i M_(r+2)
            out[i, r, 5] = Mr[r + 2]
            out[i, r, 6] = Mr[r + 1]  # M_(r+1)
            out[i, r, 7] = Mi[r + 1]


def _moments(beta: np.ndarray, alpha: np.ndarray, gamma: np.ndarray, delta: np.ndarray, r_max: int) -> np.ndarray:
    """(..., r_max + 1, 8) jets of M_0 .. M_r_max at real beta, alpha, gamma, delta of one shape (``_moment_jets``)."""
    b = np.ascontiguousarray(beta, dtype=float).ravel()
    a = np.ascontiguousarray(alpha, dtype=float).ravel()
    g = np.ascontiguousarray(gamma, dtype=float).ravel()
    d = np.ascontiguousarray(delta, dtype=float).ravel()
    if np.any(np.abs(g) > 8.0):
        raise ValueError("square_aperture_moments: |gamma| > 8 (an irradiance ratio of e^16 across a sub-aperture)")
    if np.any(np.abs(d) > 1.0):
        raise ValueError("square_aperture_moments: |delta| > 1 (an amplitude ratio of e^(1/4) between a sub-aperture's "
                         "centre and edge)")
    big_re, big_im = np.zeros_like(b), np.zeros_like(b)
    big = np.nonzero(np.abs(a) >= ALPHA_FRESNEL)[0]
    if big.size:
        ab, bb = a[big], b[big]
        neg = ab < 0
        fr, fi = _fresnel_field(np.where(neg, -bb, bb), np.abs(ab))
        big_re[big], big_im[big] = fr, np.where(neg, -fi, fi)
    out = np.empty((b.size, int(r_max) + 1, 8))
    with compile_notice("cross-talk aperture kernel"):
        _moment_jets(b, a, g, d, big_re, big_im, int(r_max), out)
    return out.reshape(np.shape(beta) + (int(r_max) + 1, 8))


def _moments_of_rows(beta: np.ndarray, alpha: np.ndarray, gamma: np.ndarray, delta: np.ndarray, r_max: int) -> np.ndarray:
    """``_moments`` of inputs of one shape, computed once per run of equal rows (leading index): a complex step along
    d directions repeats each lenslet's real inputs in d consecutive rows (``centroid.cell_shift``)."""
    n = beta.shape[0] if beta.ndim else 0
    if n < 2:
        return _moments(beta, alpha, gamma, delta, r_max)
    repeat = np.ones(n - 1, bool)
    for v in (beta, alpha, gamma, delta):
        repeat &= np.all(np.reshape(v[1:] == v[:-1], (n - 1, -1)), axis=1)
    if not repeat.any():
        return _moments(beta, alpha, gamma, delta, r_max)
    new = np.r_[True, ~repeat]
    first = np.flatnonzero(new)
    return _moments(beta[first], alpha[first], gamma[first], delta[first], r_max)[np.cumsum(new) - 1]


def square_aperture_moments(beta, alpha, r_max: int = 0, gamma=0.0, delta=0.0) -> tuple[np.ndarray, np.ndarray]:
    """(Re, Im) (..., r_max + 1) of the moments M_r = int_{-1/2}^{1/2} t^r exp(gamma t + delta t^2 + i alpha t^2
    - i beta t) dt, r = 0 .. r_max (M_0 = A; gamma, delta: the amplitude's gradient and curvature across the
    aperture, amplitude exp(gamma t + delta t^2)); beta (...) and alpha, gamma, delta broadcastable to it. Complex
    inputs are a complex step: the result carries the moments' exact first-order change (Re and Im each complex),
    so Im(out) / h is the derivative along the step."""
    beta = np.asarray(beta)
    shape = np.broadcast_shapes(beta.shape, np.shape(alpha), np.shape(gamma), np.shape(delta))
    beta, alpha, gamma, delta = (np.broadcast_to(np.asarray(v), shape) for v in (beta, alpha, gamma, delta))
    if not any(np.iscomplexobj(v) for v in (beta, alpha, gamma, delta)):
        j = _moments(beta, alpha, gamma, delta, r_max)
        return j[..., 0], j[..., 1]
    j = _moments_of_rows(np.real(beta), np.real(alpha), np.real(gamma), np.real(delta), r_max)
    db, da, dg, dd = (np.imag(v)[..., None] for v in (beta, alpha, gamma, delta))
    # dM/ddelta = M_(r+2) = -i dM/dalpha: (Re, Im) = (j5, -j4)
    re = j[..., 0] + 1j * (j[..., 2] * db + j[..., 4] * da + j[..., 6] * dg + j[..., 5] * dd)
    im = j[..., 1] + 1j * (j[..., 3] * db + j[..., 5] * da + j[..., 7] * dg - j[..., 4] * dd)
    return re, im
