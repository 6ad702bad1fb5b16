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


def _potential_basis(xl, yl, deg: int = 6):
    """(values, d/dx, d/dy) of the monomials x^a y^b, 1 <= a + b <= deg, at the points (columns)."""
    terms = [(a, n - a) for n in range(1, deg + 1) for a in range(n + 1)]
    V = np.stack([xl**a * yl**b for a, b in terms], 1)
    Ax = np.stack([a * xl ** max(a - 1, 0) * yl**b for a, b in terms], 1)
    Ay = np.stack([b * xl**a * yl ** max(b - 1, 0) for a, b in terms], 1)
    return V, Ax, Ay


def simulate_centroids(model: ForwardModel, pose, n_grid: int = 160, M: int = 24, window_px: int = 27,
                       sub: int = 2, threshold: float = 0.0, follow: bool = True):
    """(slopes (n, 2) rad from simulated pixel-window spot centroids, spot displacements (n, 2) mm, lensforge result).

    follow=True centres each camera window on the spot (at f times the sub-aperture's mean ray slope);
    follow=False uses the lenslet's own fixed window (the spot may leave it).
    """
    bench = model.bench
    sen = bench.sensor
    p, f = sen.pitch_mm, sen.lenslet_focal_mm
    lam = bench.laser.wavelength_nm * 1e-6
    k = 2 * np.pi / lam
    interp, res = _ray_field(model, pose, n_grid)
    t = (np.arange(M) + 0.5) / M - 0.5  # midpoint samples over the sub-aperture (units of p)
    XL, YL = np.meshgrid(t, t, indexing="xy")
    c = model.pupil.centres
    v = interp(c[:, None, 0] + p * XL.ravel()[None, :], c[:, None, 1] + p * YL.ravel()[None, :])  # (n, M*M, 3)
    sx, sy, I = v[..., 0], v[..., 1], v[..., 2]
    # remove each sub-aperture's mean tilt t0 analytically (its spot sits at f t0); fit the rest as a potential
    t0 = np.stack([sx.mean(axis=1), sy.mean(axis=1)], 1)
    V, Ax, Ay = _potential_basis(XL.ravel(), YL.ravel())
    rhs = np.concatenate([(sx - t0[:, :1]) * p, (sy - t0[:, 1:]) * p], axis=1).T  # (2 M^2, n)
    coef, *_ = np.linalg.lstsq(np.vstack([Ax, Ay]), rhs, rcond=None)
    W = (V @ coef).T.reshape(-1, M, M)  # mm of OPD
    E = np.sqrt(np.clip(I, 0, None)).reshape(-1, M, M) * np.exp(1j * k * W)
    centre = f * t0 if follow else np.zeros_like(t0)  # camera window centre relative to the lenslet axis
    cam = ((np.arange(window_px * sub) + 0.5) / sub - 0.5 * window_px) * sen.pixel_mm
    xi = centre[:, :1] - f * t0[:, :1] + cam[None, :]  # (n, K) camera coords relative to the de-tilted spot
    eta = centre[:, 1:] - f * t0[:, 1:] + cam[None, :]
    Fx = np.exp(-2j * np.pi * xi[:, :, None] * (p * t)[None, None, :] / (lam * f))  # (n, K, M)
    Fy = np.exp(-2j * np.pi * eta[:, :, None] * (p * t)[None, None, :] / (lam * f))
    A = np.einsum("nim,nml,njl->nij", Fy, E, Fx)  # (n, eta, xi)
    inten = (np.abs(A) ** 2).reshape(-1, window_px, sub, window_px, sub).sum(axis=(2, 4))  # pixel integration
    if threshold > 0:
        inten = np.clip(inten - threshold * inten.max(axis=(1, 2), keepdims=True), 0, None)
    cpx = (np.arange(window_px) - 0.5 * (window_px - 1)) * sen.pixel_mm
    tot = inten.sum(axis=(1, 2))
    disp = np.stack([inten.sum(axis=1) @ cpx / tot, inten.sum(axis=2) @ cpx / tot], 1) + centre
    return disp / f, disp, res


def disc_nodes(diameter: float, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nodes (dx, dy) and weights (n, n) mm of a disc about its centre: rows dy = r sin(theta) on Gauss-Legendre
    nodes in theta (dy' = r cos(theta) dtheta), each row's chord by n Gauss-Legendre nodes. The rim is smooth in
    theta (no strips, no mask), so the rule converges spectrally; no aperture moments."""
    u, wu = np.polynomial.legendre.leggauss(n)
    r, th = 0.5 * diameter, 0.5 * np.pi * u
    half = r * np.cos(th)  # each row's half chord
    dx = half[:, None] * u[None, :]
    dy = np.broadcast_to((r * np.sin(th))[:, None], dx.shape)
    return dx, dy, (half * r * np.cos(th) * 0.5 * np.pi * wu)[:, None] * wu[None, :]


def block_fresnel_centroids(field, centres, windows, sensor, wavelength_nm: float, ring: int = 4, n_nodes: int = 160,
                            sub: int = 4, diameter: float | None = None, lit=None) -> np.ndarray:
    """Centroids (n, 2) mm in the pixel windows starting at pixels ``windows`` (n, 2) of the lenslets at ``centres``
    (n, 2) mm, each window lit by the (2 ring + 1)^2 block of square lenslets around its own (fully lit, no gaps):
    the Fresnel integral over each sub-aperture of field(X, Y) (complex amplitude on the lenslet plane) times the
    lenslet's focusing phase, by Gauss-Legendre nodes (``n_nodes`` per axis and cell: the far cells' linear phase
    makes ~(ring + 1/2) p^2 / (lambda f) oscillations across a cell), each pixel integrated over sub x sub points.
    Independent of lensforge's kernel (no moments, no series, no Hermite pistons): the field is evaluated where it
    is, the integral done by brute force, one sub-aperture a matrix product. diameter (mm): round lenslets instead,
    each disc integrated with its smooth rim, Y = r sin(theta) by Gauss-Legendre nodes in theta and X by nodes
    across each row's chord (no strips, no mask, no anti-aliasing); lit (L, 2) mm: every window lit by these
    lenslets' centres instead of its own block."""
    p, f, pix, W = sensor.pitch_mm, sensor.lenslet_focal_mm, sensor.pixel_mm, int(sensor.centroid_window_px)
    k = 2 * np.pi / (wavelength_nm * 1e-6)
    edge0 = float(sensor.camera_offset_px) * pix
    u, wu = np.polynomial.legendre.leggauss(n_nodes)
    t, wt = 0.5 * p * u, 0.5 * p * wu  # a square cell's nodes about its centre
    if diameter is not None:
        dxx, dyy, w_disc = disc_nodes(diameter, n_nodes)
        dy = dyy[:, 0]
    out = []
    for c, st in zip(np.asarray(centres, float), np.asarray(windows, float)):
        xs = edge0 + (st[:, None] + (np.arange(W * sub) + 0.5)[None, :] / sub) * pix  # (2, S) sample coordinates
        U = np.zeros((W * sub, W * sub), complex)
        block = (c + p * np.array([[a, b] for a in range(-ring, ring + 1) for b in range(-ring, ring + 1)])
                 if lit is None else np.asarray(lit, float))
        for cb in block:
            # exp(i k [(x - X)^2 - (X - c_b)^2] / 2 f) = exp(i k (x^2 - c_b^2) / 2 f) exp(-i k X (x - c_b) / f)
            if diameter is None:
                X, Y = cb[0] + t, cb[1] + t
                XX, YY = np.meshgrid(X, Y, indexing="xy")
                E = field(XX, YY) * np.outer(wt, wt)
                Fx, Fy = (np.exp(0.5j * k * (xs[j][:, None] ** 2 - cb[j] ** 2) / f)
                          * np.exp(-1j * k * np.outer(xs[j] - cb[j], (X, Y)[j]) / f) for j in (0, 1))
                U += Fy @ E @ Fx.T
                continue
            Y, XX = cb[1] + dy, cb[0] + dxx
            E = field(XX, np.broadcast_to(Y[:, None], XX.shape)) * w_disc
            Fy = np.exp(0.5j * k * (xs[1][:, None] ** 2 - cb[1] ** 2) / f) * np.exp(-1j * k * np.outer(xs[1] - cb[1], Y) / f)
            G = np.einsum("jn,sjn->sj", E, np.exp(-1j * k * (xs[0][:, None, None] - cb[0]) * XX[None] / f))  # (S, rows)
            U += (Fy @ G.T) * np.exp(0.5j * k * (xs[0] ** 2 - cb[0] ** 2) / f)[None, :]
        inten = (np.abs(U) ** 2).reshape(W, sub, W, sub).sum(axis=(1, 3))
        pc = edge0 + (st[:, None] + np.arange(W)[None, :] + 0.5) * pix
        out.append([inten.sum(0) @ pc[0] / inten.sum(), inten.sum(1) @ pc[1] / inten.sum()])
    return np.array(out)


def quadratic_beam_field(beam_offset_mm, waist_mm: float, hessian, wavelength_nm: float):
    """field(X, Y): a Gaussian beam (1/e amplitude radius waist_mm, centred at beam_offset_mm) carrying the path
    X^T H X / 2 (``hessian`` H (2, 2) 1/mm, symmetric), written out here, apart from lensforge's waves."""
    (x0, y0), H = beam_offset_mm, np.asarray(hessian, float)
    k = 2 * np.pi / (wavelength_nm * 1e-6)

    def field(X, Y):
        return np.exp(-((X - x0) ** 2 + (Y - y0) ** 2) / waist_mm**2
                      + 0.5j * k * (H[0, 0] * X * X + 2 * H[0, 1] * X * Y + H[1, 1] * Y * Y))

    return field
