"""Independent physical-optics model of the Shack-Hartmann measurement (test helper).

Shares only the exact ray tracer with lensforge (itself checked against optiland):
no ray aiming, no sub-aperture quadrature, no flux-Jacobian of the aim.

1. A dense regular grid of beam rays (u, v) is traced to the lenslet plane. The
   irradiance there is I = I_beam / |det dX/du| with the Jacobian by central
   differences on the ray grid; the slopes and I are interpolated to each lenslet's
   fine sample grid (M x M points over the p x p sub-aperture) by Clough-Tocher C1
   cubics.
2. Per lenslet the wavefront W is the least-squares polynomial potential of the
   sampled slopes (degree 6 in the local coordinates), the field E = sqrt(I) exp(i k W).
3. The lenslet (focal length f, hard square aperture) forms its spot: the Fraunhofer
   integral of E (matrix Fourier transform, no periodic wrap-around) on a camera window
   of ``window_px`` pixels of ``pixel`` mm centred where the spot is expected, each
   pixel integrated over ``sub`` x ``sub`` points. The spot centroid / f is the slope
   the sensor reports (optionally with a noise cut ``threshold`` x peak subtracted, as
   the Thorlabs software does per spot).
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CloughTocher2DInterpolator

from lensforge.optics.shack_hartmann import ForwardModel
from lensforge.optics.trace import OK, trace_rays


def _ray_field(model: ForwardModel, pose, n_grid: int):
    """Scattered (X, slopes, I) at the lenslet plane from a regular beam-ray grid covering the pupil's preimage."""
    bench, lens = model.bench, model.lens
    coarse = model.evaluate(pose, check_range=False)
    uv = coarse.uv[0]
    p = bench.sensor.pitch_mm
    lo, hi = uv.min(axis=0) - 3 * p, uv.max(axis=0) + 3 * p
    gu = np.linspace(lo[0], hi[0], n_grid)
    gv = np.linspace(lo[1], hi[1], n_grid)
    U, V = np.meshgrid(gu, gv, indexing="xy")
    tr = trace_rays(bench, lens, np.atleast_2d(pose), np.stack([U.ravel(), V.ravel()], 1), kernel=model.kernel)
    X = tr.xy[0, :, 0].reshape(U.shape)
    Y = tr.xy[0, :, 1].reshape(U.shape)
    S = tr.slopes[0].reshape(U.shape + (2,))
    ok = (tr.status[0] == OK).reshape(U.shape)
    Xu, Xv = np.gradient(X, gu, gv, axis=(1, 0))
    Yu, Yv = np.gradient(Y, gu, gv, axis=(1, 0))
    det = np.abs(Xu * Yv - Xv * Yu)
    w = 0.5 * bench.laser.beam_diameter_mm
    I = np.exp(-2.0 * (U**2 + V**2) / (w * w)) / det
    good = ok.copy()
    good[1:-1, 1:-1] &= ok[:-2, 1:-1] & ok[2:, 1:-1] & ok[1:-1, :-2] & ok[1:-1, 2:]
    pts = np.stack([X[good], Y[good]], 1)
    vals = np.stack([S[..., 0][good], S[..., 1][good], I[good]], 1)
    return CloughTocher2DInterpolator(pts, vals), coarse


def spot_moment_slopes(model: ForwardModel, pose, n_grid: int = 240, M: int = 24):
    """(slopes (n, 2) rad, lensforge result): the first moment of each lenslet's complete Fraunhofer spot / f.

    By Parseval the spot's first moment equals the irradiance-weighted mean phase gradient over the
    sub-aperture, here evaluated on the M x M midpoint grid of the independent ray field (no windowing).
    """
    interp, res = _ray_field(model, pose, n_grid)
    p = model.bench.sensor.pitch_mm
    t = p * ((np.arange(M) + 0.5) / M - 0.5)
    XL, YL = np.meshgrid(t, t, indexing="xy")
    c = model.pupil.centres
    v = interp(c[:, None, 0] + XL.ravel()[None, :], c[:, None, 1] + YL.ravel()[None, :])  # (n, M*M, 3)
    I = v[..., 2]
    return np.einsum("nq,nqk->nk", I, v[..., :2]) / I.sum(axis=1)[:, None], res


def _potential(xl, yl, sx, sy, deg: int = 6):
    """Coefficients of W = sum c_ab x^a y^b (a + b in 1..deg) fitting grad W = (sx, sy) (least squares)."""
    terms = [(a, b) for n in range(1, deg + 1) for a in range(n + 1) for b in [n - a]]
    Ax = np.stack([a * xl ** max(a - 1, 0) * yl**b if a else 0 * xl for a, b in terms], 1)
    Ay = np.stack([b * xl**a * yl ** max(b - 1, 0) if b else 0 * xl for a, b in terms], 1)
    c, *_ = np.linalg.lstsq(np.vstack([Ax, Ay]), np.concatenate([sx, sy]), rcond=None)
    W = sum(ci * xl**a * yl**b for ci, (a, b) in zip(c, terms))
    return W


def simulate_centroids(model: ForwardModel, pose, n_grid: int = 240, M: int = 24, window_px: int = 27,
                       sub: int = 3, threshold: float = 0.0, follow: bool = True):
    """(slopes (n, 2) rad from simulated spot centroids, spot displacements (n, 2) mm, lensforge result).

    follow=True centres each camera window on the spot (its position from the ray field's mean tilt);
    follow=False uses the lenslet's own fixed window (the spot may leave it).
    """
    bench = model.bench
    sen = bench.sensor
    p, f = sen.pitch_mm, sen.lenslet_focal_mm
    lam = bench.laser.wavelength_nm * 1e-6
    k = 2 * np.pi / lam
    interp, res = _ray_field(model, pose, n_grid)
    t = (np.arange(M) + 0.5) / M - 0.5  # midpoint samples over the sub-aperture (units of p)
    XL, YL = np.meshgrid(p * t, p * t, indexing="xy")
    dx = p / M
    px = sen.pixel_mm
    cam = (np.arange(window_px * sub) + 0.5) / sub - 0.5 * window_px  # camera sample coords (pixels)
    out = np.zeros((len(model.pupil.centres), 2))
    disp = np.zeros_like(out)
    for i, (cx, cy) in enumerate(model.pupil.centres):
        v = interp(cx + XL, cy + YL)
        sx, sy, I = v[..., 0], v[..., 1], v[..., 2]
        # remove the sub-aperture's mean tilt t0 analytically: the spot of E exp(-i k t0.x) sits t0 f closer
        t0 = np.array([np.mean(sx), np.mean(sy)])
        W = _potential(XL.ravel() / p, YL.ravel() / p, (sx - t0[0]).ravel() * p, (sy - t0[1]).ravel() * p)
        E = np.sqrt(np.clip(I, 0, None)) * np.exp(1j * k * W.reshape(M, M))
        centre = f * t0 if follow else np.zeros(2)  # camera window centre relative to the lenslet axis
        xi = centre[0] - f * t0[0] + cam * px  # camera coords relative to the de-tilted spot
        eta = centre[1] - f * t0[1] + cam * px
        Fx = np.exp(-2j * np.pi * np.outer(xi, p * t) / (lam * f)) * dx
        Fy = np.exp(-2j * np.pi * np.outer(eta, p * t) / (lam * f)) * dx
        A = Fy @ E @ Fx.T  # (eta, xi)
        inten = np.abs(A) ** 2
        inten = inten.reshape(window_px, sub, window_px, sub).sum(axis=(1, 3))  # pixel integration
        if threshold > 0:
            inten = np.clip(inten - threshold * inten.max(), 0, None)
        cpx = (np.arange(window_px) - 0.5 * (window_px - 1)) * px
        tot = inten.sum()
        mx = (inten.sum(axis=0) @ cpx) / tot + centre[0]
        my = (inten.sum(axis=1) @ cpx) / tot + centre[1]
        disp[i] = (mx, my)
        out[i] = (mx / f, my / f)
    return out, disp, res
