"""Exact real-ray trace of a posed lens, vectorised over rays and poses (numba).

Rays start on a plane before the lens, in the sensor frame {S}, travel along the
beam direction, refract at the front and back sag surfaces (Newton intersection on
the canonical surface form, vector Snell's law) and are propagated to the lenslet
plane z = 0 of {S}. Each ray carries a status code:

    OK, MISSED (no intersection / conic undefined / Newton failed), TIR,
    CLIPPED (outside the clear aperture), BACKWARD (does not reach the sensor),
    NOT_AIMED (ray aiming did not converge)

Every ray also carries its exact first derivatives along the beam coordinates (u, v):
forward differentiation of the intersection (implicit in the sag equation, with the
sag's Hessian for the normal) and of Snell's law at each surface. Ray aiming takes its
Newton steps with them (one trace per step, where finite differences took three) and
the irradiance weights use the exact |det d(X, Y)/d(u, v)| they give.

The lens frame {O} is posed by T_SO = T_SO(nominal) [R(r), t]; nominal places {O}
at z = -d in {S} with parallel axes (DESIGN.md).
"""

from __future__ import annotations

from numpy.typing import ArrayLike

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from .bench import Bench
from .jit import compile_notice, kernel_threads
from .lens import Lens
from .pose import right_jacobian_so3, rotations, skew

__all__ = [
    "OK", "MISSED", "TIR", "CLIPPED", "BACKWARD", "NOT_AIMED", "STATUS_NAMES",
    "AIM_TOL", "LensKernel", "lens_kernel", "LensTangents", "kernel_tangents", "pose_frames", "pose_frame_derivatives",
    "trace_rays", "aim_rays", "aimed_tangents", "TraceResult",
]

OK, MISSED, TIR, CLIPPED, BACKWARD, NOT_AIMED = 0, 1, 2, 3, 4, 5
STATUS_NAMES = {OK: "ok", MISSED: "missed surface", TIR: "total internal reflection",
                CLIPPED: "clipped by clear aperture", BACKWARD: "does not reach sensor",
                NOT_AIMED: "ray aiming failed"}

_NEWTON_MAXIT = 40
AIM_TOL = 1e-10  # mm: an aimed ray lands this close to its target (per axis); see _aim
# Newton on the ray parameter converges quadratically: after a step of size d the error
# is ~ (f''/2f') d^2 < 1e-16 mm for d < 1e-8 mm, so stopping there loses nothing.
_NEWTON_TOL = 1e-8  # mm
_FM = {"contract", "arcp", "nsz", "reassoc", "afn"}  # fast math without no-NaN/no-inf assumptions

# Compile cost (first run after install, empty numba cache). Profiled with NUMBA_DEBUG_CACHE and
# benchmarks/bench_first_run.py: numba-level ``inline="always"`` copied _sag/_trace_lens/_trace_one
# into every caller (_aim calls _trace_one three times), so typing and parfor passes ran over ~10x
# the IR: 21 s of CPU for _aim alone. Plain calls let LLVM inline instead: ~3 s, same results to
# 1e-15. Every array reaches a kernel as a writeable C-contiguous float64/int64 array (``_arr``):
# a read-only input (e.g. np.broadcast_to) is a different numba type and cost a second full compile.


def _arr(a, dtype=np.float64) -> np.ndarray:
    """a as the one array type the kernels are compiled for (writeable, C order)."""
    return np.require(a, dtype, ("C", "W"))


@dataclass(frozen=True)
class LensKernel:
    """A lens packed into arrays for the numba kernels (both surfaces share one degree)."""

    c: np.ndarray        # (2,) curvature 1/mm
    k: np.ndarray        # (2,) conic
    alpha: np.ndarray    # (2, 8)
    n_alpha: np.ndarray  # (2,) number of aspheric terms in use
    poly: np.ndarray     # (2, D+1, D+1), D = highest total degree in use (p + q <= D)
    ripple: np.ndarray   # (2, 2) layer ripple (amplitude, period) mm
    zv: np.ndarray       # (2,) vertex z in {O}: -l/2, +l/2
    ap_r: float          # clear-aperture radius, mm
    n: float             # glass index at the bench wavelength


def lens_kernel(lens: Lens, wavelength_nm: float) -> LensKernel:
    """Pack a lens for the kernels at the given wavelength."""
    cf, cb = lens.front.canonical(), lens.back.canonical()
    deg = 0
    for cs in (cf, cb):
        nz = np.argwhere(cs.poly != 0)
        if nz.size:
            deg = max(deg, int(nz.sum(axis=1).max()))
    poly = np.zeros((2, deg + 1, deg + 1))
    for i, cs in enumerate((cf, cb)):
        m = min(deg + 1, cs.poly.shape[0])
        poly[i, :m, :m] = cs.poly[:m, :m]
    n_alpha = np.array([int(np.max(np.nonzero(cs.alpha)[0], initial=-1)) + 1 for cs in (cf, cb)], dtype=np.int64)
    return LensKernel(
        c=np.array([cf.c, cb.c]), k=np.array([cf.k, cb.k]),
        alpha=np.stack([cf.alpha, cb.alpha]), n_alpha=n_alpha, poly=poly,
        ripple=np.array([[cf.ripple_amplitude, cf.ripple_period], [cb.ripple_amplitude, cb.ripple_period]]),
        zv=np.array([-0.5 * lens.thickness, 0.5 * lens.thickness]),
        ap_r=0.5 * lens.aperture, n=lens.index(wavelength_nm),
    )


def pose_frames(bench: Bench, poses) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of T_SO for pose vectors (P, 6): p_S = R p_O + t."""
    poses = np.atleast_2d(np.asarray(poses, dtype=float))
    R = _arr(rotations(poses[:, 3:]))
    t = _arr(poses[:, :3].copy())
    t[:, 2] -= bench.placement.distance_mm
    return R, t


# ----------------------------------------------------------------------------- kernels

@nb.njit(cache=True, fastmath=_FM)
def _poly(coef, x, y, hess):
    """sum coef[p, q] x^p y^q (nested Horner) with its first and, when ``hess``, second
    derivatives: (z, z_x, z_y, z_xx, z_xy, z_yy)."""
    d1 = coef.shape[0]
    pz = 0.0
    px = 0.0
    py = 0.0
    pxx = 0.0
    pxy = 0.0
    pyy = 0.0
    for p in range(d1 - 1, -1, -1):
        r = 0.0
        ry = 0.0
        ryy = 0.0
        for q in range(d1 - 1 - p, -1, -1):
            if hess:
                ryy = ryy * y + 2.0 * ry
            ry = ry * y + r
            r = r * y + coef[p, q]
        if hess:
            pxx = pxx * x + 2.0 * px
            pxy = pxy * x + py
            pyy = pyy * x + ryy
        px = px * x + pz
        pz = pz * x + r
        py = py * x + ry
    return pz, px, py, pxx, pxy, pyy


@nb.njit(cache=True, fastmath=_FM)
def _sag(c, k, alpha, n_alpha, poly, ripple, s, x, y, hess):
    """(z, dz/dx, dz/dy, d2z/dx2, d2z/dxdy, d2z/dy2, rf, re, zb, ok) of surface s at (x, y);
    the second derivatives only when ``hess`` (else 0). zb is the base sag under the layer
    ripple, rf = 1 + a w cos(w zb) and re = a w^2 sin(w zb) its factors (1, 0 without
    ripple): z = zb + a sin(w zb), grad z = rf grad zb."""
    r2 = x * x + y * y
    cs = c[s]
    z = 0.0
    dr = 0.0  # radial part: dz/dx = x * dr(r2), d2z/dx2 = dr + 2 x^2 ddr
    ddr = 0.0  # d(dr)/d(r2)
    if cs != 0.0:
        arg = 1.0 - (1.0 + k[s]) * cs * cs * r2
        if arg <= 0.0:
            return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, False
        root = math.sqrt(arg)
        z = cs * r2 / (1.0 + root)
        dr = cs / root
        if hess:
            ddr = 0.5 * (1.0 + k[s]) * cs * cs * cs / (root * arg)
    za = 0.0
    da = 0.0
    dda = 0.0
    for i in range(n_alpha[s], 0, -1):
        a = alpha[s, i - 1]
        if hess and i >= 2:
            dda = dda * r2 + 2.0 * i * (i - 1) * a
        da = da * r2 + 2.0 * i * a
        za = (za + a) * r2
    z += za
    dr += da
    ddr += dda
    gx = x * dr
    gy = y * dr
    hxx = 0.0
    hxy = 0.0
    hyy = 0.0
    if hess:
        hxx = dr + 2.0 * x * x * ddr
        hxy = 2.0 * x * y * ddr
        hyy = dr + 2.0 * y * y * ddr
    pz, px, py, pxx, pxy, pyy = _poly(poly[s], x, y, hess)
    z += pz
    gx += px
    gy += py
    hxx += pxx
    hxy += pxy
    hyy += pyy
    a = ripple[s, 0]
    f = 1.0
    e = 0.0
    zb = z
    if a != 0.0:
        w = 2.0 * math.pi / ripple[s, 1]
        sn = math.sin(w * z)
        f = 1.0 + a * w * math.cos(w * z)
        e = a * w * w * sn
        if hess:
            hxx = hxx * f - e * gx * gx
            hxy = hxy * f - e * gx * gy
            hyy = hyy * f - e * gy * gy
        z += a * sn
        gx *= f
        gy *= f
    return z, gx, gy, hxx, hxy, hyy, f, e, zb, True


@nb.njit(cache=True, fastmath=_FM)
def _conic_sensitivity(c, k, s, r2):
    """(dz/dc, dz/dk, dD/dc, dD/dk) of the conic base at r^2 (D: its radial gradient
    factor, grad = (x, y) D): the same for every lens tangent at a point."""
    cs = c[s]
    arg = 1.0 - (1.0 + k[s]) * cs * cs * r2
    root = math.sqrt(arg)
    q = 1.0 + root
    rc = -(1.0 + k[s]) * cs * r2 / root  # d root / dc
    rk = -0.5 * cs * cs * r2 / root  # d root / dk
    return (r2 / q - cs * r2 * rc / (q * q), -cs * r2 * rk / (q * q), 1.0 / root - cs * rc / arg, -cs * rk / arg)


@nb.njit(cache=True, fastmath=_FM)
def _sag_tangents(ripple, s, x, y, gx, gy, rf, re, zb, lt, conic, n_glass, phi, w):
    """Each lens tangent's change at the fixed point (x, y) of surface s: rows 4 s .. 4 s + 3
    of w (8, l) receive the change of the surface height (vertex and sag), of its gradient
    (x, y) and of the index ratio. lt: the tangents in kernel layout (``LensTangents.arrays``:
    per surface and tangent the coefficients of the sag's terms, so height and gradient are
    three dot products with the terms' values phi (n, 3) here); gx, gy, rf, re, zb: the
    surface's gradient, ripple factors and base sag there (``_sag``); conic:
    ``_conic_sensitivity`` there."""
    C, Lr, Lzv, Ln, dims = lt
    n_l = w.shape[1]
    n_a = dims[0]
    d1 = dims[1]
    r2 = x * x + y * y
    # the terms: curvature, conic (value, radial gradient factor times (x, y)), alpha_i r^(2 i),
    # then the polynomial x^p y^q (p + q <= D) in C's order
    phi[0, 0], phi[0, 1], phi[0, 2] = conic[0], x * conic[2], y * conic[2]
    phi[1, 0], phi[1, 1], phi[1, 2] = conic[1], x * conic[3], y * conic[3]
    rp = 1.0  # r2^(i - 1)
    for i in range(1, n_a + 1):
        phi[1 + i, 0] = rp * r2
        phi[1 + i, 1] = 2.0 * i * rp * x
        phi[1 + i, 2] = 2.0 * i * rp * y
        rp *= r2
    t = 2 + n_a
    xp = 1.0  # x^p
    xpm = 0.0  # p x^(p - 1)
    for p in range(d1):
        yq = 1.0
        yqm = 0.0  # q y^(q - 1)
        for q in range(d1 - p):
            phi[t, 0] = xp * yq
            phi[t, 1] = xpm * yq
            phi[t, 2] = xp * yqm
            t += 1
            yqm = (q + 1) * yq
            yq *= y
        xpm = (p + 1) * xp
        xp *= x
    rip = re != 0.0 or rf != 1.0
    a = ripple[s, 0]
    om = 1.0
    sn = cs_ = 0.0
    if a != 0.0:
        om = 2.0 * math.pi / ripple[s, 1]
        sn = math.sin(om * zb)
        cs_ = math.cos(om * zb)
    for j in range(n_l):
        dz = 0.0
        dgx = 0.0
        dgy = 0.0
        for e in range(t):
            cj = C[s, j, e]
            dz += cj * phi[e, 0]
            dgx += cj * phi[e, 1]
            dgy += cj * phi[e, 2]
        if rip:  # ripple on the base sag z_b: z = z_b + a sin(w z_b), grad = rf grad z_b
            dz, dgx, dgy = rf * dz, rf * dgx - re * gx / rf * dz, rf * dgy - re * gy / rf * dz
        if a != 0.0:  # the ripple itself changes: amplitude a, period h (w = 2 pi / h)
            da = Lr[s, j, 0]
            dw = -om * Lr[s, j, 1] / ripple[s, 1]
            f = 1.0 + a * om * cs_
            dz += sn * da + a * cs_ * zb * dw
            df = om * cs_ * da + (a * cs_ - a * om * sn * zb) * dw  # change of rf at fixed zb
            dgx += gx / f * df
            dgy += gy / f * df
        w[4 * s, j] = dz + Lzv[s, j]
        w[4 * s + 1, j] = dgx
        w[4 * s + 2, j] = dgy
        # mu = 1 / n entering the glass, n leaving it
        w[4 * s + 3, j] = -Ln[j] / (n_glass * n_glass) if s == 0 else Ln[j]


@nb.njit(cache=True, fastmath=_FM)
def _surface_tangent(t, dx, dy, dz, fp, gx, gy, hxx, hxy, hyy, inv, nx, ny, nz, mu, ci, sk, g,
                     dox, doy, doz, ddx, ddy, ddz, lens):
    """Tangent (d origin, d direction) of the ray leaving a surface, from the tangent of
    the incoming ray (origin o, direction d; first-order forward differentiation of the
    intersection o + t d on the sag and of the vector Snell's law at the found point).
    lens: None for a direction that moves only the ray, else (dsurf, dgxp, dgyp, dmu): the
    change of the surface height (vertex and sag) and of its gradient at the fixed point,
    and of the index ratio (None compiles without those terms)."""
    dsurf = dgxp = dgyp = dmu = 0.0
    if lens is not None:
        dsurf, dgxp, dgyp, dmu = lens
    ax = dox + t * ddx
    ay = doy + t * ddy
    az = doz + t * ddz
    dt = -(az - dsurf - gx * ax - gy * ay) / fp  # the intersection stays on the (moved) surface
    px = ax + dt * dx
    py = ay + dt * dy
    pz = az + dt * dz
    dgx = hxx * px + hxy * py
    dgy = hxy * px + hyy * py
    if lens is not None:
        dgx += dgxp
        dgy += dgyp
    dinv = -inv * inv * inv * (gx * dgx + gy * dgy)
    dnx = -dgx * inv - gx * dinv
    dny = -dgy * inv - gy * dinv
    dnz = dinv
    dci = dnx * dx + dny * dy + dnz * dz + nx * ddx + ny * ddy + nz * ddz
    # g = sqrt(1 - mu^2 (1 - ci^2)) - mu ci
    if lens is None:
        dg = mu * mu * ci * dci / sk - mu * dci
        return (px, py, pz, mu * ddx + dg * nx + g * dnx, mu * ddy + dg * ny + g * dny, mu * ddz + dg * nz + g * dnz)
    dg = (mu * mu * ci * dci - mu * dmu * (1.0 - ci * ci)) / sk - dmu * ci - mu * dci
    return (px, py, pz, dmu * dx + mu * ddx + dg * nx + g * dnx, dmu * dy + mu * ddy + dg * ny + g * dny,
            dmu * dz + mu * ddz + dg * nz + g * dnz)


@nb.njit(cache=True, fastmath=_FM)
def _trace_lens(ox, oy, oz, dx, dy, dz, c, k, alpha, n_alpha, poly, ripple, zv, ap_r, n_glass, tan, m0, lt, w, phi):
    """Trace one ray (lens frame) through both surfaces. Returns the exit ray and status.

    tan (m, 6): tangents (d origin, d direction) of the entering ray along m directions,
    replaced in place by those of the exit ray (meaningful when the status is OK).
    lt: l lens tangents in kernel layout (``LensTangents.arrays``: per surface and tangent
    the change of each sag term's coefficient, of the ripple, the vertex z and the index);
    lt = None (no lens tangents) compiles without that code. A lens tangent reaches the
    ray only through what it changes where the ray meets each surface s: the surface's
    height, its gradient and the index ratio (4 numbers, ``_sag_tangents``), and the ray's
    tangent is linear in those. So rows m0 .. m0 + 7 carry the 8 unit changes (4 per
    surface; rows of surface 1 are zero until the ray reaches it) and w (8, l) receives
    each lens tangent's 8 changes: tangent j of the exit ray = sum_b w[b, j] tan[m0 + b]
    (``_trace_one`` combines them at the sensor). 8 propagated directions instead of l.
    """
    n_in = 1.0
    for s in range(2):
        n_out = n_glass if s == 0 else 1.0
        if dz <= 0.0:
            return ox, oy, oz, dx, dy, dz, 4
        t = (zv[s] - oz) / dz
        ok = False
        for _ in range(40):  # _NEWTON_MAXIT
            x = ox + t * dx
            y = oy + t * dy
            z, gx, gy, _, _, _, _, _, _, good = _sag(c, k, alpha, n_alpha, poly, ripple, s, x, y, False)
            if not good:
                break
            f = oz + t * dz - zv[s] - z
            fp = dz - gx * dx - gy * dy
            if fp == 0.0:
                break
            step = f / fp
            t -= step
            if abs(step) < 1e-8:
                ok = True
                break
        if not ok:
            return ox, oy, oz, dx, dy, dz, 1
        x = ox + t * dx
        y = oy + t * dy
        z, gx, gy, hxx, hxy, hyy, rf, re, zb, good = _sag(c, k, alpha, n_alpha, poly, ripple, s, x, y, True)
        if not good:
            return ox, oy, oz, dx, dy, dz, 1
        if x * x + y * y > ap_r * ap_r:
            return ox, oy, oz, dx, dy, dz, 3
        fp = dz - gx * dx - gy * dy
        # unit normal along +z side
        inv = 1.0 / math.sqrt(gx * gx + gy * gy + 1.0)
        nx = -gx * inv
        ny = -gy * inv
        nz = inv
        mu = n_in / n_out
        ci = nx * dx + ny * dy + nz * dz
        kk = 1.0 - mu * mu * (1.0 - ci * ci)
        if kk < 0.0:
            return ox, oy, oz, dx, dy, dz, 2
        sk = math.sqrt(kk)
        g = sk - mu * ci
        if lt is not None:  # each lens tangent's change of height, gradient and index ratio here
            _sag_tangents(ripple, s, x, y, gx, gy, rf, re, zb, lt, _conic_sensitivity(c, k, s, x * x + y * y),
                          n_glass, phi, w)
        for j in range(tan.shape[0]):
            b = j - m0 - 4 * s  # the unit change b of this surface (rows of the other surface: b < 0 or > 3)
            if lt is not None and 0 <= b < 4:
                (tan[j, 0], tan[j, 1], tan[j, 2], tan[j, 3], tan[j, 4], tan[j, 5]) = _surface_tangent(
                    t, dx, dy, dz, fp, gx, gy, hxx, hxy, hyy, inv, nx, ny, nz, mu, ci, sk, g,
                    0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                    (1.0 if b == 0 else 0.0, 1.0 if b == 1 else 0.0, 1.0 if b == 2 else 0.0, 1.0 if b == 3 else 0.0))
            elif lt is not None and j >= m0 + 4 * (s + 1):
                continue  # surface 1's unit changes: no tangent before the ray reaches it
            else:
                (tan[j, 0], tan[j, 1], tan[j, 2], tan[j, 3], tan[j, 4], tan[j, 5]) = _surface_tangent(
                    t, dx, dy, dz, fp, gx, gy, hxx, hxy, hyy, inv, nx, ny, nz, mu, ci, sk, g,
                    tan[j, 0], tan[j, 1], tan[j, 2], tan[j, 3], tan[j, 4], tan[j, 5], None)
        ox = x
        oy = y
        oz = zv[s] + z
        dx = mu * dx + g * nx
        dy = mu * dy + g * ny
        dz = mu * dz + g * nz
        n_in = n_out
    return ox, oy, oz, dx, dy, dz, 0


@nb.njit(cache=True, fastmath=_FM)
def _rotate(R, x, y, z):
    """R (x, y, z)."""
    return (R[0, 0] * x + R[0, 1] * y + R[0, 2] * z, R[1, 0] * x + R[1, 1] * y + R[1, 2] * z,
            R[2, 0] * x + R[2, 1] * y + R[2, 2] * z)


@nb.njit(cache=True, fastmath=_FM)
def _rotate_t(R, x, y, z):
    """R^T (x, y, z)."""
    return (R[0, 0] * x + R[1, 0] * y + R[2, 0] * z, R[0, 1] * x + R[1, 1] * y + R[2, 1] * z,
            R[0, 2] * x + R[1, 2] * y + R[2, 2] * z)


@nb.njit(cache=True, fastmath=_FM)
def _plane_tangent(pz, L, M, N, s, dpx, dpy, dpz, dL, dM, dN):
    """Tangent of the landing point X = p + s d (s = -p_z / N) and of the slopes (L/N, M/N)."""
    ds = -dpz / N + pz * dN / (N * N)
    return (dpx + ds * L + s * dL, dpy + ds * M + s * dM, (dL * N - L * dN) / (N * N), (dM * N - M * dN) / (N * N))


@nb.njit(cache=True, fastmath=_FM)
def _trace_one(u, v, R, t, dT, lt, z0, bx, by, bsx, bsy, c, k, alpha, n_alpha, poly, ripple, zv, ap_r, n_glass,
               tan, dout, w, g8, phi):
    """Trace the beam ray with transverse coordinates (u, v) for one pose (R, t).

    Returns sensor-plane x, y, direction L, M, N (in {S}) and status. dT (m, 3, 4): the
    derivatives of [R | t] along m pose directions; lt: the l lens tangents of
    ``_trace_lens``; tan (2 + m + 8, 6) (2 + m without lens tangents), w (8, l), g8 (8, 4),
    phi (n, 3) (``_sag_tangents``): scratch; dout
    (2 + m + l, 4) receives d(x, y, L/N, M/N) along u, v, each pose direction and each
    lens tangent (the beam ray fixed in {S}).
    """
    m0 = 2 + dT.shape[0]
    # ray in {S}
    inv = 1.0 / math.sqrt(1.0 + bsx * bsx + bsy * bsy)
    dSx = bsx * inv
    dSy = bsy * inv
    dSz = inv
    # to {O}: p_O = R^T (p_S - t), d_O = R^T d_S
    qx = bx + u - t[0]
    qy = by + v - t[1]
    qz = z0 - t[2]
    ox, oy, oz = _rotate_t(R, qx, qy, qz)
    dx, dy, dz = _rotate_t(R, dSx, dSy, dSz)
    # tangents at the start: a step in u (v) moves the start along x_S (y_S); a pose direction
    # (dR, dt) moves it by dR^T (p_S - t) - R^T dt and turns the direction by dR^T d_S
    for j in range(tan.shape[0]):
        if j < 2:
            tan[j, 0], tan[j, 1], tan[j, 2] = R[j, 0], R[j, 1], R[j, 2]
            tan[j, 3] = 0.0
            tan[j, 4] = 0.0
            tan[j, 5] = 0.0
        elif j >= m0:  # a lens tangent leaves the entering ray unchanged
            for e in range(6):
                tan[j, e] = 0.0
        else:
            D = dT[j - 2]
            a0, a1, a2 = _rotate_t(D, qx, qy, qz)
            b0, b1, b2 = _rotate_t(R, D[0, 3], D[1, 3], D[2, 3])
            tan[j, 0] = a0 - b0
            tan[j, 1] = a1 - b1
            tan[j, 2] = a2 - b2
            tan[j, 3], tan[j, 4], tan[j, 5] = _rotate_t(D, dSx, dSy, dSz)
    ox, oy, oz, dx, dy, dz, st = _trace_lens(ox, oy, oz, dx, dy, dz, c, k, alpha, n_alpha, poly, ripple, zv, ap_r,
                                             n_glass, tan, m0, lt, w, phi)
    if st != 0:
        return 0.0, 0.0, 0.0, 0.0, 1.0, st
    # back to {S}
    px, py, pz = _rotate(R, ox, oy, oz)
    px += t[0]
    py += t[1]
    pz += t[2]
    L, M, N = _rotate(R, dx, dy, dz)
    if N <= 0.0 or pz > 0.0:
        return 0.0, 0.0, 0.0, 0.0, 1.0, 4
    s = -pz / N
    for j in range(tan.shape[0]):
        dpx, dpy, dpz = _rotate(R, tan[j, 0], tan[j, 1], tan[j, 2])
        dL, dM, dN = _rotate(R, tan[j, 3], tan[j, 4], tan[j, 5])
        if 2 <= j < m0:  # the pose moves the exit ray too: dR o + dt, dR d
            D = dT[j - 2]
            a0, a1, a2 = _rotate(D, ox, oy, oz)
            dpx += a0 + D[0, 3]
            dpy += a1 + D[1, 3]
            dpz += a2 + D[2, 3]
            a0, a1, a2 = _rotate(D, dx, dy, dz)
            dL += a0
            dM += a1
            dN += a2
        if j < m0:
            dout[j, 0], dout[j, 1], dout[j, 2], dout[j, 3] = _plane_tangent(pz, L, M, N, s, dpx, dpy, dpz, dL, dM, dN)
        else:  # a unit change at a surface
            g8[j - m0, 0], g8[j - m0, 1], g8[j - m0, 2], g8[j - m0, 3] = _plane_tangent(pz, L, M, N, s, dpx, dpy, dpz,
                                                                                      dL, dM, dN)
    if lt is not None:  # each lens tangent: its changes at the two surfaces times the unit changes' effects
        for L_ in range(w.shape[1]):
            for r in range(4):
                acc = 0.0
                for b in range(8):
                    acc += w[b, L_] * g8[b, r]
                dout[m0 + L_, r] = acc
    return px + s * L, py + s * M, L, M, N, 0


_CHUNK = 64  # rays per parallel work item (one scratch allocation each)


@nb.njit(cache=True, parallel=True, fastmath=_FM)
def _trace_grid(uv, Rs, ts, dTs, lt, z0, bx, by, bsx, bsy, c, k, alpha, n_alpha, poly, ripple, zv, ap_r, n_glass,
                out, deriv, status):
    """Trace rays uv (P, N, 2) at P poses; deriv (P, N, 2 + m + l, 4) receives d(x, y, L/N, M/N)
    along u, v, the m pose directions dTs (P, m, 3, 4) and the l lens tangents lt."""
    n_p = Rs.shape[0]
    n_r = uv.shape[1]
    n_l = 0 if lt is None else lt[3].shape[0]
    n_phi = 0 if lt is None else lt[0].shape[2]
    m = 2 + dTs.shape[1] + (0 if lt is None else 8)  # lens tangents: 8 unit changes (``_trace_lens``)
    total = n_p * n_r
    for chunk in nb.prange((total + _CHUNK - 1) // _CHUNK):
        tan = np.empty((m, 6))
        w = np.empty((8, n_l))
        g8 = np.empty((8, 4))
        phi = np.empty((n_phi, 3))
        for idx in range(chunk * _CHUNK, min(total, (chunk + 1) * _CHUNK)):
            p = idx // n_r
            i = idx - p * n_r
            x, y, L, M, N, st = _trace_one(uv[p, i, 0], uv[p, i, 1], Rs[p], ts[p], dTs[p], lt, z0, bx, by, bsx, bsy,
                                           c, k, alpha, n_alpha, poly, ripple, zv, ap_r, n_glass, tan, deriv[p, i],
                                           w, g8, phi)
            out[p, i, 0] = x
            out[p, i, 1] = y
            out[p, i, 2] = L
            out[p, i, 3] = M
            out[p, i, 4] = N
            if st != 0:
                deriv[p, i, :, :] = 0.0
            status[p, i] = st


@nb.njit(cache=True, fastmath=_FM)
def _aim_one(p, i, targets, u0, Rs, ts, no_pose, no_lens, z0, bx, by, bsx, bsy, c, k, alpha, n_alpha, poly, ripple,
             zv, ap_r, n_glass, tol, maxit, out, status, counts, tan, d, w, g8, phi):
    """Aim the ray of target i at pose p (``_aim``); tan, d, w, g8, phi: scratch."""
    u = u0[p, i, 0]
    v = u0[p, i, 1]
    X = targets[i, 0]
    Y = targets[i, 1]
    st = 5
    traced = 0
    sx = 0.0
    sy = 0.0
    det = 0.0
    for it in range(maxit):
        x, y, L, M, N, s0 = _trace_one(u, v, Rs[p], ts[p], no_pose, no_lens, z0, bx, by, bsx, bsy, c, k, alpha,
                                       n_alpha, poly, ripple, zv, ap_r, n_glass, tan, d, w, g8, phi)
        traced += 1
        if s0 != 0:
            st = s0
            break
        xu, yu, xv, yv = d[0, 0], d[0, 1], d[1, 0], d[1, 1]
        det = xu * yv - xv * yu
        rx = x - X
        ry = y - Y
        sx = L / N
        sy = M / N
        if det == 0.0:
            st = 5
            break
        du = -(yv * rx - xv * ry) / det
        dv = -(-yu * rx + xu * ry) / det
        u += du
        v += dv
        if abs(rx) < tol and abs(ry) < tol:
            sx += d[0, 2] * du + d[1, 2] * dv
            sy += d[0, 3] * du + d[1, 3] * dv
            st = 0
            break
    out[p, i, 0] = u
    out[p, i, 1] = v
    out[p, i, 2] = sx
    out[p, i, 3] = sy
    out[p, i, 4] = abs(det)
    status[p, i] = st
    counts[p, i] = traced


@nb.njit(cache=True, parallel=True, fastmath=_FM)
def _aim(targets, u0, Rs, ts, z0, bx, by, bsx, bsy, c, k, alpha, n_alpha, poly, ripple, zv, ap_r, n_glass,
         tol, maxit, out, status, counts):
    """Newton ray aiming: find beam coordinates (u, v) whose ray lands on each target.

    Each iteration traces one ray with its exact derivatives along u and v (``_trace_one``).
    Once the ray lands within ``tol`` (per axis) the last Newton step D is taken without
    tracing again: the slopes move by their derivatives times D (exact to second order,
    ~|D|^2), the landing error falls to ~|D|^2, and |det| keeps its value at the traced
    ray (off by ~|D| relative). With tol = 1e-10 mm both are far below rounding of the
    Zernike fit (z from two warm starts agree to ~1e-8 sigma); a looser tol would let
    |det| jump with the warm start.
    out[p, i] = (u, v, L/N, M/N, |det d(X,Y)/d(u,v)|); counts[p, i] = rays traced.
    """
    n_p = Rs.shape[0]
    n_t = targets.shape[0]
    no_pose = np.zeros((0, 3, 4))
    total = n_p * n_t
    for chunk in nb.prange((total + _CHUNK - 1) // _CHUNK):
        tan = np.empty((2, 6))
        d = np.empty((2, 4))
        w = np.empty((8, 0))
        g8 = np.empty((8, 4))
        phi = np.empty((0, 3))
        for idx in range(chunk * _CHUNK, min(total, (chunk + 1) * _CHUNK)):
            _aim_one(idx // n_t, idx % n_t, targets, u0, Rs, ts, no_pose, None, z0, bx, by, bsx, bsy, c, k, alpha,
                     n_alpha, poly, ripple, zv, ap_r, n_glass, tol, maxit, out, status, counts, tan, d, w, g8, phi)


# ----------------------------------------------------------------------------- Python API

@dataclass(frozen=True)
class TraceResult:
    """Rays at the sensor plane for P poses and N rays.

    xy: (P, N, 2) positions in {S} (mm); direction: (P, N, 3) unit vectors (L, M, N);
    status: (P, N) codes (0 = OK); derivatives: (P, N, 4, 2) the exact Jacobian
    d(x, y, L/N, M/N) / d(u, v) of the beam-to-sensor map (rows x, y in mm/mm, slopes
    in rad/mm); pose_derivatives: (P, N, 4, 6) d(x, y, L/N, M/N) / d(pose) with the
    beam ray fixed (per mm of tx, ty, tz and per rad of rx, ry, rz; DESIGN's pose
    vector), when asked for, else None; lens_derivatives: (P, N, 4, l) along the l lens
    tangents asked for, else None. Derivatives are zero where status is not OK.
    """

    xy: np.ndarray
    direction: np.ndarray
    status: np.ndarray
    derivatives: np.ndarray
    pose_derivatives: np.ndarray | None = None
    lens_derivatives: np.ndarray | None = None
    all_derivatives: np.ndarray | None = None  # (P, N, 4, 2 + 6 + l): the three above side by side

    @property
    def slopes(self) -> np.ndarray:
        """(P, N, 2) ray slopes (L/N, M/N), dimensionless."""
        return self.direction[..., :2] / self.direction[..., 2:3]

    @property
    def ok(self) -> np.ndarray:
        return self.status == OK


def pose_frame_derivatives(poses) -> np.ndarray:
    """(P, 6, 3, 4): derivatives of [R | t] of T_SO along the six pose-vector components
    (translation: dt = e_j; rotation: dR = R [J_r(r) e_j]x, J_r the right Jacobian of SO(3))."""
    poses = np.atleast_2d(np.asarray(poses, dtype=float))
    r = poses[:, 3:]
    Jr = right_jacobian_so3(r)
    dT = np.zeros((len(poses), 6, 3, 4))
    dT[:, :3, :, 3] = np.eye(3)
    dT[:, 3:, :, :3] = rotations(r)[:, None] @ skew(np.swapaxes(Jr, 1, 2))
    return dT


def _beam_args(bench: Bench, lens: Lens):
    las = bench.laser
    # start plane: safely before the lens at any valid pose
    z0 = -bench.placement.distance_mm - lens.thickness - lens.edge_diameter - bench.pose_limits.translation_mm - 10.0
    return float(z0), float(las.offset_mm[0]), float(las.offset_mm[1]), float(las.slope[0]), float(las.slope[1])


def _kernel_args(kern: LensKernel):
    return (_arr(kern.c), _arr(kern.k), _arr(kern.alpha), _arr(kern.n_alpha, np.int64), _arr(kern.poly),
            _arr(kern.ripple), _arr(kern.zv), float(kern.ap_r), float(kern.n))


@dataclass(frozen=True)
class LensTangents:
    """l directions of change of a packed lens (``LensKernel``), one row each: curvature
    dc (l, 2), conic dk (l, 2), aspheric dalpha (l, 2, <= 8), polynomial dpoly (l, 2, D+1, D+1),
    layer ripple dripple (l, 2, 2) (amplitude, period), vertex z dzv (l, 2) and index dn
    (l,). The clear aperture is held (it only clips)."""

    dc: np.ndarray
    dk: np.ndarray
    dalpha: np.ndarray
    dpoly: np.ndarray
    dripple: np.ndarray
    dzv: np.ndarray
    dn: np.ndarray

    @property
    def size(self) -> int:
        return self.dn.shape[0]

    def arrays(self) -> tuple:
        """The kernel layout (``_sag_tangents``): (C (2, l, n), ripple (2, l, 2), vertex z (2, l),
        index (l,), (n_alpha, D + 1)) with C[s, j] the coefficients of surface s's sag terms
        along tangent j: curvature, conic, alpha_1.., then poly[p, q] for p + q <= D."""
        d1 = self.dpoly.shape[2]
        p, q = np.divmod(np.arange(d1 * d1), d1)
        tri = p + q < d1  # row-major (p, then q): the order _sag_tangents fills its terms in
        C = np.concatenate([self.dc[..., None], self.dk[..., None], self.dalpha,
                            self.dpoly.reshape(self.size, 2, d1 * d1)[..., tri]], axis=2)
        return (_arr(np.swapaxes(C, 0, 1)), _arr(np.swapaxes(self.dripple, 0, 1)), _arr(self.dzv.T), _arr(self.dn),
                _arr(np.array([self.dalpha.shape[2], d1]), np.int64))


_NO_TANGENTS = LensTangents(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2, 8)), np.zeros((0, 2, 1, 1)),
                            np.zeros((0, 2, 2)), np.zeros((0, 2)), np.zeros(0))


def kernel_tangents(plus: list, minus: list, spacing) -> LensTangents:
    """Differences (K+ - K-) / spacing of packed lenses (``LensKernel``), one direction per
    pair (spacing: the parameter distance between the two, one for all or one per pair;
    2 h for central differences, h for forward ones with K- the base): the lens tangents of
    a parameterised lens (exact for the parts linear in the parameters; the packing is
    cheap, no ray is traced). A ripple-free lens has no ripple tangent (its period is
    then meaningless)."""
    deg = max((k.poly.shape[1] for k in [*plus, *minus]), default=1)
    pad = lambda kk: np.pad(kk.poly, ((0, 0), (0, deg - kk.poly.shape[1]), (0, deg - kk.poly.shape[2])))
    rows = []
    spacings = np.broadcast_to(np.asarray(spacing, dtype=float), (len(plus),))
    for kp, km, h in zip(plus, minus, spacings):
        d = lambda a, b: (np.asarray(a, float) - np.asarray(b, float)) / h
        rip = np.where((kp.ripple[:, :1] != 0) | (km.ripple[:, :1] != 0), d(kp.ripple, km.ripple), 0.0)
        rows.append((d(kp.c, km.c), d(kp.k, km.k), d(kp.alpha, km.alpha), d(pad(kp), pad(km)), rip,
                     d(kp.zv, km.zv), d(kp.n, km.n)))
    if not rows:
        return _NO_TANGENTS
    t = [np.stack([r[i] for r in rows]) for i in range(7)]
    used = np.flatnonzero(np.any(t[2] != 0, axis=(0, 1)))  # aspheric orders any tangent moves
    t[2] = np.ascontiguousarray(t[2][..., :used.max() + 1 if used.size else 0])
    return LensTangents(*t)


def trace_rays(bench: Bench, lens: Lens, poses: ArrayLike, uv: ArrayLike, kernel: LensKernel | None = None,
               pose_derivatives: bool = False, lens_tangents: LensTangents | None = None) -> TraceResult:
    """Trace beam rays through the lens at each pose to the sensor plane, with exact
    derivatives of where they land and of their slopes.

    Parameters
    ----------
    bench : Bench
        The bench (beam, placement).
    lens : Lens
        The lens.
    poses : array_like, shape (P, 6) or (6,)
        Poses (mm, rad) about nominal.
    uv : array_like, shape (N, 2) or (P, N, 2)
        Beam coordinates (mm, relative to the beam centre): the same for every pose, or per pose.
    kernel : LensKernel, optional
        The lens packed for the kernels (default: packed here).
    pose_derivatives : bool
        Also return d(x, y, L/N, M/N)/d(pose).
    lens_tangents : LensTangents, optional
        Also return the derivatives along these lens-parameter directions.

    Returns
    -------
    TraceResult
        ``xy`` (P, N, 2) mm in {S}, ``direction`` (P, N, 3), ``status`` (P, N) (0 = OK),
        ``derivatives`` (P, N, 4, 2) along (u, v), ``pose_derivatives`` (P, N, 4, 6) per mm
        and per rad or None, ``lens_derivatives`` (P, N, 4, l) or None; zero where status
        is not OK.
    """
    kern = kernel or lens_kernel(lens, bench.laser.wavelength_nm)
    Rs, ts = pose_frames(bench, poses)
    n_p = Rs.shape[0]
    uv = np.asarray(uv, dtype=float)
    uv = _arr(np.broadcast_to(uv if uv.ndim == 3 else np.atleast_2d(uv), (n_p,) + np.atleast_2d(uv).shape[-2:]))
    dT = _arr(pose_frame_derivatives(poses) if pose_derivatives else np.zeros((n_p, 0, 3, 4)))
    lt = lens_tangents
    m = 2 + dT.shape[1] + (lt.size if lt is not None else 0)
    out = np.empty((n_p, uv.shape[1], 5))
    deriv = np.empty((n_p, uv.shape[1], m, 4))
    status = np.empty((n_p, uv.shape[1]), dtype=np.int8)
    with compile_notice(), kernel_threads():
        _trace_grid(uv, Rs, ts, dT, lt.arrays() if lt is not None else None, *_beam_args(bench, lens), *_kernel_args(kern), out, deriv, status)
    d = np.swapaxes(deriv, -1, -2)  # (P, N, 4, m)
    m0 = 2 + dT.shape[1]
    return TraceResult(out[..., :2], out[..., 2:5], status, d[..., :2], d[..., 2:m0] if pose_derivatives else None,
                       d[..., m0:] if lens_tangents is not None else None, d)


def aim_rays(bench: Bench, lens: Lens, poses, targets, u0=None, kernel: LensKernel | None = None,
             tol: float = AIM_TOL, maxit: int = 30):
    """Aim one beam ray onto each target point (lenslet centre) of the sensor plane.

    Returns (uv, slopes, jac_det, status, n_traced): beam coordinates (P, T, 2) of
    the aimed rays, their slopes (L/N, M/N) at the targets (P, T, 2), the local
    |det d(X, Y)/d(u, v)| of the beam-to-sensor map (P, T) (irradiance at the
    sensor = input irradiance / det), status (P, T) and the number of rays traced
    (each with its derivatives along u and v). ``u0`` (P, T, 2) warm-starts the Newton
    iteration (default: the targets); tol: landing tolerance (mm) per axis.
    """
    kern = kernel or lens_kernel(lens, bench.laser.wavelength_nm)
    Rs, ts = pose_frames(bench, poses)
    targets = _arr(targets)
    n_p, n_t = Rs.shape[0], targets.shape[0]
    if u0 is None:
        u0 = np.broadcast_to(targets - np.asarray(bench.laser.offset_mm), (n_p, n_t, 2))
    u0 = _arr(np.broadcast_to(u0, (n_p, n_t, 2)))
    out = np.empty((n_p, n_t, 5))
    status = np.empty((n_p, n_t), dtype=np.int8)
    counts = np.empty((n_p, n_t), dtype=np.int64)
    with compile_notice(), kernel_threads():
        _aim(targets, u0, Rs, ts, *_beam_args(bench, lens), *_kernel_args(kern), float(tol), int(maxit),
             out, status, counts)
    return out[..., :2], out[..., 2:4], out[..., 4], status, int(counts.sum())


@nb.njit(cache=True, parallel=True, fastmath=_FM)
def _aimed_tangents(D, ok, uv, irr, w_beam, h, dsq, dwi):
    """The aimed rays' tangents (``aimed_tangents``): D (3, P, N, m, 4) the traced derivatives
    of the aimed rays and of copies displaced by h in u and in v, ok (P, N), uv (P, N, 2),
    irr (P, N) (0 where a ray failed); dsq (P, N, 2, m - 2) and dwi (P, N, m - 2) receive the
    slope and irradiance derivatives along each direction q (0 where not ok). D (1, P, N, m, 4),
    the aimed rays alone: no change of det J (``aimed_tangents``)."""
    second = D.shape[0] == 3
    n_p = D.shape[1]
    n_r = D.shape[2]
    nq = D.shape[3] - 2
    c4 = -4.0 / (w_beam * w_beam)
    for p in nb.prange(n_p):
        for i in range(n_r):
            A = D[0, p, i]
            if not ok[p, i]:
                for q in range(nq):
                    dsq[p, i, 0, q] = 0.0
                    dsq[p, i, 1, q] = 0.0
                    dwi[p, i, q] = 0.0
                continue
            U = D[1, p, i] if second else A
            V = D[2, p, i] if second else A
            j00, j01, j10, j11 = A[0, 0], A[1, 0], A[0, 1], A[1, 1]  # J = d(X, Y)/d(u, v)
            det = j00 * j11 - j01 * j10
            if det == 0.0:
                det = 1.0
            # second derivatives of X, Y along u (H?0) and v (H?1) of the u, v columns (0 without copies)
            hx00 = (U[0, 0] - A[0, 0]) / h
            hx01 = (U[1, 0] - A[1, 0]) / h
            hx10 = (V[0, 0] - A[0, 0]) / h
            hx11 = (V[1, 0] - A[1, 0]) / h
            hy00 = (U[0, 1] - A[0, 1]) / h
            hy01 = (U[1, 1] - A[1, 1]) / h
            hy10 = (V[0, 1] - A[0, 1]) / h
            hy11 = (V[1, 1] - A[1, 1]) / h
            u0 = uv[p, i, 0]
            v0 = uv[p, i, 1]
            I = irr[p, i]
            for q in range(nq):
                c = q + 2
                Xq = A[c, 0]
                Yq = A[c, 1]
                du = (-j11 * Xq + j01 * Yq) / det  # du/dq = -J^-1 dX/dq
                dv = (j10 * Xq - j00 * Yq) / det
                dsq[p, i, 0, q] = A[c, 2] + A[0, 2] * du + A[1, 2] * dv
                dsq[p, i, 1, q] = A[c, 3] + A[0, 3] * du + A[1, 3] * dv
                # d/dq of each J entry on the aimed path: d/dq (dX/dc) = d/dc (dX/dq)
                tx0 = (U[c, 0] - Xq) / h + hx00 * du + hx10 * dv
                tx1 = (V[c, 0] - Xq) / h + hx01 * du + hx11 * dv
                ty0 = (U[c, 1] - Yq) / h + hy00 * du + hy10 * dv
                ty1 = (V[c, 1] - Yq) / h + hy01 * du + hy11 * dv
                ddet = tx0 * j11 + j00 * ty1 - tx1 * j10 - j01 * ty0
                # I = I_beam(u) / |det|: dI / I = -4 u.du / w^2 - d det / det
                dwi[p, i, q] = I * (c4 * (u0 * du + v0 * dv) - ddet / det)


def aimed_tangents(t: TraceResult, n_aimed: int, uv: np.ndarray, irr: np.ndarray, beam_diameter_mm: float,
                   h: float) -> tuple[np.ndarray, np.ndarray]:
    """Slope and irradiance derivatives of aimed rays, each held on its target, along every
    direction q of a trace (poses, lens tangents).

    t: the trace of 3 n_aimed poses (``trace_rays``): the aimed rays uv (P, N, 2), then the
    same displaced by h in u, then in v (or of the aimed rays alone: d(det J)/dq is then left
    out, the weights move with the beam profile only, an approximation for iterations). With
    J = d(X, Y)/d(u, v) the aimed (u, v) move by du/dq = -J^-1 dX/dq (implicit function
    theorem) and the slope by ds/dq + ds/d(u, v) du/dq; the irradiance I = I_beam(u) / |det J|
    (irr (P, N), 0 where a ray failed) by dI/I = -4 u.du / w^2 - d(det J)/det J, whose second
    derivatives come from the displaced copies' first ones, with d/dq (dX/du) = d/du (dX/dq).
    Returns (dsq (P, N, 2, nq), dI (P, N, nq)), zero where any traced copy of the ray failed."""
    P = n_aimed
    N = uv.shape[1]
    D = np.swapaxes(t.all_derivatives, -1, -2)  # the kernel's own (3 P, N, m, 4) layout
    copies = t.status.shape[0] // P if P else 1
    D = _arr(D.reshape(copies, P, N, D.shape[-2], 4))
    ok = _arr(np.all((t.status == OK).reshape(copies, P, N), axis=0), np.bool_)
    nq = D.shape[3] - 2
    dsq = np.empty((P, N, 2, nq))
    dwi = np.empty((P, N, nq))
    with kernel_threads():
        _aimed_tangents(D, ok, _arr(uv), _arr(irr), float(0.5 * beam_diameter_mm), float(h), dsq, dwi)
    return dsq, dwi
