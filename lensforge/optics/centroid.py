"""What a Shack-Hartmann lenslet measures: its spot centroid.

Centroid model (DESIGN.md, Zernike convention). A lenslet of pitch p and focal
length f images its square sub-aperture's field into a spot; the centroid of the
far-field spot of a field E = sqrt(I) exp(i k W) is, exactly (the first moment of
the angular spectrum), f times the irradiance-weighted mean slope of W over the
sub-aperture. lensforge therefore reports per lenslet

    s = sum_q w_q I(X_q) s(X_q) / sum_q w_q I(X_q)

with a Gauss-Legendre rule (``quadrature_rule``) of rays aimed at the points X_q
of the sub-aperture (exact for bicubic I*s; the error falls as p^4) and
I = I_beam / |det d(X,Y)/d(u,v)| (flux conservation).
  A camera centroid is taken over a window of pixels, which truncates the spot's
  sinc^2 side lobes; the part of the slope that comes from the irradiance weighting
  (s_w - s_u, with s_u the plain mean slope of the same quadrature) is then seen with
  a gain gamma < 1, so the model reports

    s = s_u + gamma_d (s_w - s_u - C) + gamma_c C      (``centroid_slopes``)

  where C is the cross part of the weighting term (d s_x/dy times the irradiance
  centroid offset along y, and alike for y). The gains come from ``window_gain``: a
  small Fraunhofer computation of one sub-aperture (linear irradiance ramp, weak
  curvature) imaged by the lenslet onto a ``sensor.centroid_window_px`` square of
  ``sensor.pixel_mm`` pixels centred on the spot, with ``sensor.centroid_threshold``
  x peak subtracted (0.871 direct, 0.949 cross on the default WFS40 bench; 1 for
  ``centroid_window_px = 0``, the complete-spot centroid). tests/test_physical_optics.py
  checks the whole model against simulated pixel centroids of real lenses: within
  0.06 sigma per mode on the paper's polynomial and extended-polynomial lenses, within
  0.7 sigma (Z4) on the strongly converging spherical and Zernike lenses (a residual
  the first-order gains do not capture; the lenslet-centre model was 15-30 sigma off).
  The mean slope s_u also holds the wavefront's third derivatives' share, (W_xxx + W_xyy)
  p^2 / 24 in s_x: a coma within the sub-aperture, whose flared side the window cuts, so
  the window sees it with gains ``cubic_gain`` (0.896 direct, 0.948 cross at the defaults),
  the third derivatives taken across neighbouring lenslets (``cubic_slopes``; the 'cells'
  model renders that coma in its kernel instead, ``_coma_factors``). On the
  co-designed default lens (slopes to 100 mrad) it is Z3 2.0-2.5 sigma; the paper's lenses,
  < 0.05 sigma (tests/test_physical_optics.py).
* threshold: a lenslet is used only when its mean irradiance sum_q w_q I_q is at
  least ``sensor.irradiance_threshold`` of the beam peak. Thorlabs' software cuts the
  noise floor per spot area ("Auto" noise cut, recommended; WFS Series manual,
  2007-2012, p. 72); ``centroid_threshold`` (default 0, ASSUMPTION) models a cut at a
  fraction of the spot peak.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from .aperture import square_aperture_moments
from .bench import CROSSTALK_MODELS, Sensor

__all__ = ["quadrature_rule", "window_gain", "centroid_slopes", "centroid_slope_derivatives", "CROSSTALK_MODELS",
           "crosstalk_shift", "reference_shift", "local_field", "crosstalk_slopes", "TRACKING_ITERATIONS",
           "crosstalk_slope_derivatives", "LOCAL_INPUTS", "cubic_gain", "cubic_slopes",
           "axis_derivative"]


@lru_cache(maxsize=8)
def quadrature_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(offsets (n*n, 2) in units of the pitch, weights (n*n,) summing to 1) over the
    square [-1/2, 1/2]^2: the tensor Gauss-Legendre rule (n = 1: the centre)."""
    x, w = np.polynomial.legendre.leggauss(int(n))
    X, Y = np.meshgrid(0.5 * x, 0.5 * x, indexing="xy")
    W = np.outer(0.5 * w, 0.5 * w)
    off = np.stack([X.ravel(), Y.ravel()], axis=1)
    wt = W.ravel()
    for a in (off, wt):
        a.setflags(write=False)
    return off, wt


def _one_lenslet_centroid(pitch, focal, pixel, window_px, threshold, wavelength_mm, inten_ap, W) -> float:
    """x centroid (mm) on a ``window_px`` square of ``pixel`` pixels, centred on the lenslet's axis, of the
    Fraunhofer spot of one square sub-aperture carrying irradiance inten_ap and wavefront W (mm), both (M, M)
    [y, x] at M midpoints across the pitch; ``threshold`` x the window's peak subtracted first."""
    M, sub = inten_ap.shape[0], 4
    t = pitch * ((np.arange(M) + 0.5) / M - 0.5)
    E = np.sqrt(inten_ap) * np.exp(2j * np.pi / wavelength_mm * W)
    cam = ((np.arange(window_px * sub) + 0.5) / sub - 0.5 * window_px) * pixel
    F = np.exp(-2j * np.pi * np.outer(cam, t) / (wavelength_mm * focal))
    A = F @ E @ F.T  # (y, x) on the camera samples
    inten = (np.abs(A) ** 2).reshape(window_px, sub, window_px, sub).sum(axis=(1, 3))
    if threshold > 0:
        inten = np.clip(inten - threshold * inten.max(), 0.0, None)
    c = (np.arange(window_px) - 0.5 * (window_px - 1)) * pixel
    return float(inten.sum(axis=0) @ c / inten.sum())


def _subaperture_grid(pitch: float, M: int = 128) -> tuple[np.ndarray, np.ndarray]:
    t = pitch * ((np.arange(M) + 0.5) / M - 0.5)  # gamma converges as 1/M^2: 0.8694 (M = 32), 0.8707 (64, 128)
    return np.meshgrid(t, t, indexing="xy")


@lru_cache(maxsize=32)
def _window_gain(pitch, focal, pixel, window_px, threshold, wavelength_mm, cross: bool, kappa: float = 1e-3) -> float:
    X, Y = _subaperture_grid(pitch)
    eps = 0.1  # irradiance ramp over the pitch; kappa: wavefront curvature 1/mm
    # direct: ramp along x, W = kappa x^2 / 2; cross: ramp along y, W = kappa x y (x-shift from the y-ramp)
    ramp = Y if cross else X
    inten_ap = 1.0 + eps * ramp / pitch
    W = kappa * X * Y if cross else 0.5 * kappa * X**2
    moment = focal * kappa * np.sum(inten_ap * ramp) / np.sum(inten_ap)  # complete-spot centroid shift, mm
    return _one_lenslet_centroid(pitch, focal, pixel, window_px, threshold, wavelength_mm, inten_ap, W) / moment


@lru_cache(maxsize=32)
def _cubic_gain(pitch, focal, pixel, window_px, threshold, wavelength_mm, cross: bool, c: float = 0.05) -> float:
    X, Y = _subaperture_grid(pitch)
    # W = c x^3 / 6 (direct) or c x y^2 / 2 (cross): either adds c p^2 / 24 to the mean x slope, as a coma whose
    # flared side the window cuts; the difference of +c and -c takes out the threshold's even part
    W = c * X * Y**2 / 2 if cross else c * X**3 / 6
    one = np.ones_like(X)
    d = [_one_lenslet_centroid(pitch, focal, pixel, window_px, threshold, wavelength_mm, one, sgn * W) for sgn in (1, -1)]
    return 0.5 * (d[0] - d[1]) / (focal * c * pitch**2 / 24)


def window_gain(sensor: Sensor, wavelength_nm: float) -> tuple[float, float]:
    """Gains (direct, cross) of the pixel-window centroid on the irradiance-weighting part of the slope.

    direct: on d s_x/dx times the irradiance centroid offset along x (and y alike); cross: on
    d s_x/dy times the offset along y. (1, 1) for the complete-spot centroid (window 0). First-order
    values (weak curvature): a curvature-dependent direct gain was tried and did not help.
    """
    if sensor.centroid_window_px == 0:
        return 1.0, 1.0
    args = _gain_args(sensor, wavelength_nm)
    return _window_gain(*args, False), _window_gain(*args, True)


def _gain_args(sensor: Sensor, wavelength_nm: float) -> tuple:
    return (sensor.pitch_mm, sensor.lenslet_focal_mm, sensor.pixel_mm, int(sensor.centroid_window_px),
            float(sensor.centroid_threshold), wavelength_nm * 1e-6)


def cubic_gain(sensor: Sensor, wavelength_nm: float) -> tuple[float, float]:
    """Gains (direct, cross) of the pixel-window centroid on the part of the mean slope that the wavefront's third
    derivatives add over the sub-aperture: W_xxx p^2 / 24 (direct) and W_xyy p^2 / 24 (cross) in s_x, and alike
    in s_y. Such a term is a coma within the lenslet, and the window cuts its flared side: (0.896, 0.948) on the
    default WFS40 bench, (1, 1) for the complete spot (window 0). First order: on a spot defocused by the
    sub-aperture's own curvature K (1/mm) the direct gain is 0.895, 0.890, 0.868, 0.801 at K = 0.01, 0.03, 0.06,
    0.1 (the default design's lenslets: |K| <= 0.033)."""
    if sensor.centroid_window_px == 0:
        return 1.0, 1.0
    args = _gain_args(sensor, wavelength_nm)
    return _cubic_gain(*args, False), _cubic_gain(*args, True)


def centroid_slopes(sq: np.ndarray, wi: np.ndarray, offsets: np.ndarray, weights: np.ndarray,
                    gains: tuple[float, float]) -> np.ndarray:
    """Pixel-window centroid slopes (..., 2) from quadrature slopes sq (..., q, 2), weighted irradiance
    wi = w_q I_q (..., q), rule offsets (q, 2) (any unit) and weights (q,).

    s = s_u + g_d (s_w - s_u - C) + g_c C, with s_u the plain and s_w the irradiance-weighted mean and
    C the cross part K_xy eta (K_yx xi for y) of the weighting term, K the least-squares slope
    gradient over the rule and (xi, eta) the irradiance centroid.
    """
    tot = wi.sum(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s_w = np.einsum("...q,...qk->...k", wi, sq) / tot[..., None]
        centroid = np.einsum("...q,qk->...k", wi, offsets) / tot[..., None]  # (xi, eta)
    s_u = np.einsum("q,...qk->...k", weights, sq)
    g_d, g_c = gains
    m2 = weights @ offsets**2  # (2,) second moments of the rule (0 for the centre sample)
    if g_d == g_c or np.any(m2 == 0):
        return s_u + g_d * (s_w - s_u)
    k_xy = np.einsum("q,...q->...", weights * offsets[:, 1], sq[..., 0]) / m2[1]  # d s_x / dy
    k_yx = np.einsum("q,...q->...", weights * offsets[:, 0], sq[..., 1]) / m2[0]  # d s_y / dx
    cross = np.stack([k_xy * centroid[..., 1], k_yx * centroid[..., 0]], axis=-1)
    return s_u + g_d * (s_w - s_u - cross) + g_c * cross


def centroid_slope_derivatives(sq: np.ndarray, wi: np.ndarray, dsq: np.ndarray, dwi: np.ndarray, offsets: np.ndarray,
                               weights: np.ndarray, gains: tuple[float, float]) -> np.ndarray:
    """Derivatives (..., 2, d) of ``centroid_slopes`` along d directions: dsq (..., q, 2, d) and
    dwi (..., q, d) the quadrature slopes' and weights' changes (forward mode, exact)."""
    tot = wi.sum(axis=-1)[..., None]
    dtot = dwi.sum(axis=-2)[..., None, :]  # (..., 1, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        s_w = (np.einsum("...q,...qk->...k", wi, sq) / tot)[..., None]  # (..., 2, 1)
        ds_w = (np.einsum("...qd,...qk->...kd", dwi, sq) + np.einsum("...q,...qkd->...kd", wi, dsq)
                - s_w * dtot) / tot[..., None]
    ds_u = np.einsum("q,...qkd->...kd", weights, dsq)
    g_d, g_c = gains
    m2 = weights @ offsets**2
    if g_d == g_c or np.any(m2 == 0):
        return ds_u + g_d * (ds_w - ds_u)
    with np.errstate(divide="ignore", invalid="ignore"):
        cen = (np.einsum("...q,qk->...k", wi, offsets) / tot)[..., None]  # (xi, eta)
        dcen = (np.einsum("...qd,qk->...kd", dwi, offsets) - cen * dtot) / tot[..., None]
    k_xy = np.einsum("q,...q->...", weights * offsets[:, 1], sq[..., 0]) / m2[1]
    k_yx = np.einsum("q,...q->...", weights * offsets[:, 0], sq[..., 1]) / m2[0]
    dk_xy = np.einsum("q,...qd->...d", weights * offsets[:, 1], dsq[..., 0, :]) / m2[1]
    dk_yx = np.einsum("q,...qd->...d", weights * offsets[:, 0], dsq[..., 1, :]) / m2[0]
    dcross = np.stack([dk_xy * cen[..., 1, :] + k_xy[..., None] * dcen[..., 1, :],
                       dk_yx * cen[..., 0, :] + k_yx[..., None] * dcen[..., 0, :]], axis=-2)
    return ds_u + g_d * (ds_w - ds_u - dcross) + g_c * dcross


# ----------------------------------------------------------------------------- neighbour cross-talk

# neighbours within this many pitches along x and y: the 7 x 7 block. Against the physical reference
# (4 samples per pixel; paper polynomial lens at nominal; sigma per mode) the 3 x 3 block leaves Z4 at
# 15 and other modes up to 4.9 sigma, 5 x 5 Z4 8.6 and up to 3.9, 7 x 7 Z4 6.8 and up to 1.8, 9 x 9 and
# 11 x 11 the same within 0.6 sigma: the sinc tails fall as 1 / distance, so the third ring still counts.
# (Those figures are of flat sub-apertures. The Z4 they left, 8e-4 of Z4, was mostly the sub-apertures'
# own curvature, now in ``crosstalk_shift``: 2.9 sigma there.) Truncations measured and dropped: only the
# own spot's interference with each neighbour and the neighbours' own intensities (no neighbour-neighbour
# terms) 10-40 sigma off the full block; one field sample per pixel instead of 2: 2-11 sigma.
_XT_RING = 3


def _neighbour_offsets(ring: int) -> np.ndarray:
    r = np.arange(-ring, ring + 1, dtype=float)
    X, Y = np.meshgrid(r, r, indexing="xy")
    return np.stack([X.ravel(), Y.ravel()], axis=1)  # (B, 2), the own lenslet included


# window re-centrings of the 'tracking' rule (ASSUMPTION, the device's algorithm is not published): the first window
# on the reference spot plus f times the slope, then on the centroid this many times. A spot within the window's
# truncation bias (~0.07 px at the defaults) of a half-pixel boundary has two stable windows, and the start picks one:
# 'cells' started on the lenslet centre plus f s and re-centred once, the reference on the reference spot plus f times
# the slope at the centre: 23 of the default design's 1709 lenslets at its plan pose took other windows in the two,
# ~70 urad each (Z2 1.5 sigma); with this rule in both and the lenslet's mean slope in the reference, 1 (Z2 0.8)
TRACKING_ITERATIONS = 3
_XT_CHUNK = 32  # lenslets per kernel pass: bounds its memory (a whole co-designed pose: 0.41 GB peak; >23 GB unchunked)
# K_xy's series exp(i a t_x t_y) = sum_r (i a t_x t_y)^r / r!: its terms kept down to this bound. On the co-designed
# design's lenslets (a up to 4.2: R = 8) the shifts are within 3e-4 nm of those at 1e-9 (R = 12), at 0.63x the cost
_XY_TOL = 1e-5
# the separable form (``_separable_centroid``): its cross-term series' bound and its most terms (beyond: the full block),
# lenslets per pass
_SEP_TOL = 1e-7
_SEP_MAX_RANK = 20
_SEP_CHUNK = 128


def _xy_ranks(a_abs: np.ndarray) -> np.ndarray:
    """Terms r = 0 .. R of K_xy's series per lenslet: (|a| / 4)^(R+1) / (R+1)! < ``_XY_TOL`` (|t_x t_y| <= 1/4)."""
    q = 0.25 * np.asarray(a_abs, dtype=float)
    R = np.zeros(q.shape, dtype=int)
    term = np.ones(q.shape)
    for r in range(1, 40):
        term = term * q / r
        R = np.where(term >= _XY_TOL, r, R)
    return R


def crosstalk_shift(spot: np.ndarray, centres: np.ndarray, K: np.ndarray, grad_log_i: np.ndarray, sensor: Sensor,
                    wavelength_nm: float, iterations: int = 1, sub: int = 2, windows: np.ndarray | None = None,
                    return_windows: bool = False, start: np.ndarray | None = None):
    """Centroid minus spot position (..., n, 2) mm of a pixel window that sees the own lenslet's and
    its neighbours' coherent Fraunhofer spots.

    spot: (..., n, 2) spot positions on the camera (mm, {S}); K: (..., n, 2, 2) slope gradients
    d s_i / d x_j (1/mm); grad_log_i: (..., n, 2) gradient of ln irradiance (1/mm); centres: (n, 2).
    Each sub-aperture of the (2 _XT_RING + 1)^2 block carries the lenslet's local quadratic wavefront:
    the lenslet's tilt plus K times its offset, amplitude exp(grad_log_i . offset / 2), the trapezoid
    piston between them, and its own curvature across it, K_xx, K_yy and K_xy (``aperture``: the square
    aperture's defocused Fresnel field along each axis, the sinc when flat; the cross term exp(i a t_x t_y),
    a = k p^2 (K_xy + K_yx) / 2, as its series in the aperture moments, r <= R with the terms' bound
    (|a| / 4)^r / r! down to ``_XY_TOL``). Against the physical reference (paper lenses at nominal and
    two plan poses) the K_xx, K_yy curvature took the Zernike lens's Z4 from 18-24 to 0.5-4.4 sigma and
    the worst mode over the three lenses from 24 to 6.7 sigma (an earlier second-order expansion had
    moved modes the wrong way); K_xy took the co-designed design's worst mode (nominal and three plan
    corners, ~100 mrad slopes) from 8.9-12.6 to 5.5-8.5 sigma, and left the paper lenses' at 1.6-6.7
    sigma (1.7-6.7 without), moving single modes by up to 4 sigma (the extended polynomial lens's Z4).
    Cost on the co-designed lenslets: 8.2 ms each (3.8 ms without K_xy). Lenslets whose cross term converges over
    the whole block within ``_SEP_MAX_RANK`` terms (``_block_ranks``: |a| < ~0.7; the paper's polynomial and
    Zernike lenses, a <= 0.016 at nominal, 0.17 at 5 deg tilts) take its separable form (``_separable_centroid``,
    the same field to ~1e-6 of the shift, 7x fewer aperture moments): the paper Zernike lens's pose 98 ms (264 ms
    before), polynomial 65 ms. The window
    (``centroid_window_px``) is placed on whole pixels on the spot (pixel edges at ``camera_offset_px``
    + k pixels), re-centred on its centroid ``iterations`` times (recomputed only for the lenslets whose
    window moved); ``centroid_threshold`` x the window's peak is cut. Runs ``_XT_CHUNK`` lenslets at a
    time. Written in real arithmetic (cos, sin, the aperture moments' jets) so that a complex step
    through it gives its exact derivative.

    windows: (..., n, 2) first pixels of frozen windows (none placed, none re-centred; e.g. those a fit
    linearised at: whole-pixel placement makes the shift jump where a spot crosses a half pixel, ~3 whitened
    units of a pose's Zernike residual, once per ~25 sigma of a pose's rotation on the paper polynomial lens);
    return_windows: also return the windows used (same shape); start: (..., n, 2) where the first windows go
    (default the spots; the tracking rule's, ``TRACKING_ITERATIONS``: the reference spot plus f times the slope).
    """
    lead = np.broadcast_shapes(spot.shape[:-1], K.shape[:-2], grad_log_i.shape[:-1])
    dt = np.result_type(spot, K, grad_log_i)
    sp = np.broadcast_to(spot, lead + (2,)).reshape(-1, 2)
    Kf = np.broadcast_to(K, lead + (2, 2)).reshape(-1, 2, 2)
    gf = np.broadcast_to(grad_log_i, lead + (2,)).reshape(-1, 2)
    out = np.empty(sp.shape, dtype=dt)
    st_all = np.empty(sp.shape)
    frozen = None if windows is None else np.broadcast_to(windows, lead + (2,)).reshape(-1, 2)
    first = None if start is None else np.broadcast_to(np.real(start), lead + (2,)).reshape(-1, 2)
    # the separable form where the block's cross term converges within _SEP_MAX_RANK terms (it needs only K and
    # grad ln I), the full block elsewhere
    ranks = _block_ranks(np.abs(np.real(_cross_term(Kf, sensor, wavelength_nm))))
    sep = np.nonzero(ranks <= _SEP_MAX_RANK)[0]
    sep = sep[np.argsort(ranks[sep], kind="stable")]  # passes of like ranks
    for rows, centroid, chunk in ((sep, _separable_centroid, _SEP_CHUNK),
                                  (np.nonzero(ranks > _SEP_MAX_RANK)[0], _window_centroid, _XT_CHUNK)):
        for i in range(0, len(rows), chunk):
            c = rows[i:i + chunk]
            block = ({"K": Kf[c], "g": gf[c]} if centroid is _separable_centroid
                     else _local_block(Kf[c], gf[c], sensor, wavelength_nm))
            out[c], st_all[c] = _tracked_window_shift(sp[c], block, sensor, wavelength_nm, iterations, sub, centroid,
                                                      None if frozen is None else frozen[c],
                                                      None if first is None else first[c])
    out = out.reshape(lead + (2,))
    return (out, st_all.reshape(lead + (2,))) if return_windows else out


def _tracked_window_shift(spot: np.ndarray, block: dict, sensor: Sensor, wavelength_nm: float, iterations: int,
                          sub: int, centroid, st: np.ndarray | None = None,
                          start: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(centroid minus spot (m, 2) mm, window first pixels (m, 2)) of m lenslets whose blocks are ``block``
    (``_local_block``): the whole-pixel window on start (default the spot), re-centred on its centroid
    ``iterations`` times (recomputed only for the lenslets whose window moved), or the frozen windows st;
    centroid: ``_window_centroid`` or ``_separable_centroid``."""
    if st is not None:
        return centroid(spot, block, st, sensor, wavelength_nm, sub) - spot, st
    pix, W = sensor.pixel_mm, int(sensor.centroid_window_px)
    edge0 = float(sensor.camera_offset_px) * pix
    st = _window_start(spot if start is None else start, edge0, pix, W)
    pos = centroid(spot, block, st, sensor, wavelength_nm, sub)
    for _ in range(iterations):
        st_new = _window_start(pos, edge0, pix, W)
        moved = np.nonzero(np.any(st_new != st, axis=-1))[0]
        if not moved.size:
            break
        pos[moved] = centroid(spot[moved], {key: v[moved] for key, v in block.items()}, st_new[moved], sensor,
                              wavelength_nm, sub)
        st = st_new
    return pos - spot, st


def _window_start(pos: np.ndarray, edge0: float, pix: float, W: int) -> np.ndarray:
    """First pixel (m, 2) of the whole-pixel window centred on pos (its real part)."""
    return np.floor((np.real(pos) - edge0) / pix - 0.5 * W + 0.5)


def _local_block(K: np.ndarray, grad_log_i: np.ndarray, sensor: Sensor, wavelength_nm: float) -> dict:
    """The (2 _XT_RING + 1)^2 block of m lenslets under their local quadratic wavefront (the block shares the
    lenslet's K): per lenslet and neighbour b, its spot relative to the own spot nb_pos (m, B, 2), its complex
    amplitude (cr, ci) (m, B) (relative amplitude, piston and the lenslets' focusing phase), and the curvature every
    sub-aperture of the block shares: alpha (m, 2) = k p^2 (K_xx, K_yy) / 2 and a_xy (m,) = k p^2 (K_xy + K_yx) / 2."""
    f, p = sensor.lenslet_focal_mm, sensor.pitch_mm
    k = 2 * np.pi / (wavelength_nm * 1e-6)
    pe = p * _neighbour_offsets(_XT_RING)  # (B, 2)
    delta = np.einsum("...ij,bj->...bi", K, pe)  # (m, B, 2): differential tilt of each neighbour
    amp = np.exp(0.5 * np.einsum("...i,bi->...b", grad_log_i, pe))
    phase = k * (0.5 * np.einsum("bi,...bi->...b", pe, delta) + (pe**2).sum(axis=1) / (2 * f))
    alpha = 0.5 * k * p * p * np.stack([K[..., 0, 0], K[..., 1, 1]], axis=-1)
    return {"nb_pos": pe + f * delta, "cr": amp * np.cos(phase), "ci": amp * np.sin(phase), "alpha": alpha,
            "a_xy": _cross_term(K, sensor, wavelength_nm)}


def _cross_term(K: np.ndarray, sensor: Sensor, wavelength_nm: float) -> np.ndarray:
    """a = k p^2 (K_xy + K_yx) / 2 (...): the wavefront's cross curvature exp(i a T_x T_y), T in pitches."""
    return 0.5 * (2 * np.pi / (wavelength_nm * 1e-6)) * sensor.pitch_mm ** 2 * (K[..., 0, 1] + K[..., 1, 0])


def _cmul(ar, ai, br, bi):
    """(Re, Im) of (ar + i ai)(br + i bi), in real arithmetic (the parts may carry a complex step)."""
    return ar * br - ai * bi, ar * bi + ai * br


def _rs_terms(block: dict, f: float, k: float):
    """The non-paraxial part of the propagation from each sub-aperture b to the window: the log of the
    Rayleigh-Sommerfeld kernel (f / r^2) exp(i k r) over the Fresnel one, r = sqrt(f^2 + |rho|^2), rho = camera point
    - aperture point, Lambda(rho) = ln(f^2 / r^2) + i k phi(rho), phi = r - f - |rho|^2 / 2 f = -|rho|^4 / 2 f (r + f)^2,
    less what the model already holds: its slopes are tan, so each sub-aperture's light is right along its own chief
    ray rho* = f s_b to first order (the tan mapping, and the pistons between lenslets): i k (phi(rho*) +
    grad phi(rho*) . (rho - rho*)). Expanded about rho_c = own spot - centre of b (``block`` 'rs_c', 'rs_star' = rho*;
    (m, B, 2)) in e = (camera point - own spot) - (aperture point - centre of b): the constant c0, the gradient g and
    the squares' phase e_x^2, e_y^2 exactly (an amplitude and phase per sub-aperture, a tilt and curvature of its
    aperture, a ramp and curvature over the window; the squares are a tilt's astigmatism, ~0.4 rad over the window
    at 0.1 rad), the squares' log-amplitude (|q e^2| <= ~1e-2 over a block; exact, it made the aperture moments'
    gamma vary per sample, ~3x the kernel's cost), the cross and higher terms to first order, as the monomials e_x^a e_y^b, 2 <= a + b <= 4 (``_rs_factors``; phi's
    Taylor coefficients at rho_c). Returns (c0 (re, im) (m, B), g (re, im) (m, B, 2), the squares' phase
    coefficients q (m, B, 2), the remainder's {(a, b): (re, im)}) in real arithmetic."""
    rc, rs = block["rs_c"], block["rs_star"]
    A, As = (rc**2).sum(-1), (rs**2).sum(-1)
    r, r_s = np.sqrt(f * f + A), np.sqrt(f * f + As)
    phi_c, phi_s = -0.5 * A * A / (f * (r + f) ** 2), -0.5 * As * As / (f * (r_s + f) ** 2)
    dphi_c = -rc * (A / (r * f * (r + f)))[..., None]  # grad phi = rho (1/r - 1/f)
    dphi_s = -rs * (As / (r_s * f * (r_s + f)))[..., None]
    c0 = (-np.log1p(A / (f * f)), k * (phi_c - phi_s - (dphi_s * (rc - rs)).sum(-1)))
    F = f * f + A
    g = (-2 * rc / F[..., None], k * (dphi_c - dphi_s))
    # half the Hessians of ln(f^2 / r^2) and of phi: -I / F + 2 rho rho^T / F^2 and ((1/r - 1/f) I - rho rho^T / r^3) / 2
    q_amp = -1 / F[..., None] + 2 * rc * rc / (F * F)[..., None]  # to first order, with the remainder
    q = 0.5 * k * (-(A / (r * f * (r + f)))[..., None] - rc * rc / (r**3)[..., None])
    u, v = rc[..., 0], rc[..., 1]
    r3, r5, r7 = r**3, r**5, r**7
    # phi's third and fourth derivatives over a! b!
    rem = {(1, 1): (4 * u * v / (F * F), -k * u * v / r3), (2, 0): (q_amp[..., 0], 0 * u), (0, 2): (q_amp[..., 1], 0 * v),
           (3, 0): (0 * u, k * (-u / (2 * r3) + u**3 / (2 * r5))), (0, 3): (0 * v, k * (-v / (2 * r3) + v**3 / (2 * r5))),
           (2, 1): (0 * v, 0.5 * k * (-v / r3 + 3 * u * u * v / r5)), (1, 2): (0 * u, 0.5 * k * (-u / r3 + 3 * u * v * v / r5)),
           (4, 0): (0 * u, k * (-1 / (8 * r3) + 3 * u * u / (4 * r5) - 5 * u**4 / (8 * r7))),
           (0, 4): (0 * v, k * (-1 / (8 * r3) + 3 * v * v / (4 * r5) - 5 * v**4 / (8 * r7))),
           (3, 1): (0 * u, k * (1.5 * u * v / r5 - 2.5 * u**3 * v / r7)),
           (1, 3): (0 * u, k * (1.5 * u * v / r5 - 2.5 * u * v**3 / r7)),
           (2, 2): (0 * u, 0.25 * k * (-1 / r3 + 3 * A / r5 - 15 * u * u * v * v / r7))}
    return c0, g, q, rem


def _rs_powers(ar: np.ndarray, ai: np.ndarray, xs: np.ndarray, p: float, R: int):
    """(Re, Im) (m, B, 5, 2, S, R+5) of E_a,r = int (x - p t)^a t^r (...) dt, a = 0 .. 4, r = 0 .. R (the larger r
    are scratch), from the moments M_0 .. M_(R+4) (m, B, S, 2, R+5) and the window's samples x (m, S, 2), by the
    recursion E_a,r = x E_(a-1),r - p E_(a-1),(r+1), E_0 = M. Each step runs over the flattened (2, S, r) axes (one
    long contiguous loop): a row's last r picks up the next row's first, which reaches only r > R + 4 - a."""
    m, B, S = ar.shape[:3]
    L = 2 * S * (R + 5)
    x = np.ascontiguousarray(np.broadcast_to(np.moveaxis(xs, -1, -2)[:, None, :, :, None], (m, 1, 2, S, R + 5)))
    x = x.reshape(m, 1, L)[..., :-1]
    dt = np.result_type(ar, ai, x)
    out = []
    for part in (ar, ai):
        e = np.empty((m, B, 5, L), dtype=dt)
        e[:, :, 0] = np.moveaxis(part, 3, 2).reshape(m, B, L)
        for a in range(1, 5):
            np.multiply(x, e[:, :, a - 1, :-1], out=e[:, :, a, :-1])
            e[:, :, a, :-1] -= p * e[:, :, a - 1, 1:]
            e[:, :, a, -1] = 0.0
        out.append(e.reshape(m, B, 5, 2, S, R + 5))
    return out[0], out[1]


def _rs_factors(er: np.ndarray, ei: np.ndarray, rem: dict, R: int):
    """The field's x and y factors (each (Re, Im) (m, B, 5, S, R+1)) with the remainder to first order:
    sum_b' Y_b'(y) X_b'(x), Y_b' = the y moments of e_y^b', X_b' = sum_a c_ab' (x moments of e_x^a), c_00 = 1;
    er, ei from ``_rs_powers``."""
    exr, exi = er[:, :, :, 0, :, :R + 1], ei[:, :, :, 0, :, :R + 1]  # (m, B, 5 (a), S, R+1): the scratch r left out
    xr, xi = np.empty_like(exr), np.empty_like(exi)
    xr[:, :, 0], xi[:, :, 0] = exr[:, :, 0], exi[:, :, 0]
    started = {0}
    for (a, b), (vr, vi) in rem.items():
        vr, vi = vr[:, :, None, None], vi[:, :, None, None]
        if b in started:
            xr[:, :, b] -= vi * exi[:, :, a]
            xi[:, :, b] += vi * exr[:, :, a]
        else:  # the first term of this y power
            np.multiply(-vi, exi[:, :, a], out=xr[:, :, b])
            np.multiply(vi, exr[:, :, a], out=xi[:, :, b])
            started.add(b)
        if np.any(vr != 0):
            xr[:, :, b] += vr * exr[:, :, a]
            xi[:, :, b] += vr * exi[:, :, a]
    assert started == set(range(5)), "every y power 0 .. 4 has a remainder term"
    return (xr, xi), (er[:, :, :, 1, :, :R + 1], ei[:, :, :, 1, :, :R + 1])


@lru_cache(maxsize=8)
def _disc_rows(diameter: float, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    u, wu = np.polynomial.legendre.leggauss(n)
    r, th = 0.5 * diameter, 0.5 * np.pi * u
    out = (r * np.sin(th), 0.5 * np.pi * wu * r * np.cos(th), 2.0 * r * np.cos(th))
    for v in out:
        v.setflags(write=False)
    return out


def disc_row_counts(sensor: Sensor, wavelength_nm: float, ring: int) -> np.ndarray:
    """Rows (B,) of each round sub-aperture of a block of ``ring`` rings (``_neighbour_offsets`` order) in its rule
    (``disc_rows``): neighbour b's light meets the window's corner at |beta| = 2 pi p |d| / (lambda f), |d| = |b| p +
    W pix / sqrt(2), and across the rows the rim's phase turns by up to r |beta| (r the disc's radius in pitches):
    r |beta| + 16, in eights (the own lenslet 40, the block's corner at 4 rings 168 on the default WFS40). Against
    a direct integral of random 4-ring blocks (tilts, curvatures, irradiance gradients) a uniform 104, 120, 128,
    144 rows read 0.58, 0.03, 2e-4, 2e-7 urad off, and 96 rows 136 urad (the far rows alias)."""
    p, f = sensor.pitch_mm, sensor.lenslet_focal_mm
    d = np.hypot(*_neighbour_offsets(ring).T) * p + float(sensor.centroid_window_px) * sensor.pixel_mm / np.sqrt(2.0)
    return _rows_needed(sensor, 2 * np.pi * p * d / (wavelength_nm * 1e-6 * f), 0.0)


def _rows_needed(sensor: Sensor, beta: np.ndarray, alpha) -> np.ndarray:
    """Rows r |beta| + r^2 |alpha| + 16, in eights, of sub-apertures whose light meets a window at |beta| at most,
    alpha their curvature (r the disc's radius in pitches)."""
    r = 0.5 * float(sensor.lenslet_diameter_mm) / float(sensor.pitch_mm)
    return (8 * np.ceil((r * beta + r * r * alpha + 16.0) / 8.0)).astype(int)


def _disc_row_counts_of(arg, alpha, sensor: Sensor) -> np.ndarray:
    """Rows (B,) of each round sub-aperture of a pass from the angles its light meets the windows at: r |beta| +
    r^2 |alpha| + 16 in eights (``disc_row_counts``' rule), |beta| the largest over the pass's windows of the
    kernel's own beta = 2 pi arg (m, B, S, 2), alpha (m, B, 1, 2) the sub-aperture's curvature: the spots' own
    offsets (a lens's slope differences across the block) take the light beyond the block geometry's angles
    (``disc_row_counts``, which sizes the passes)."""
    b = 2 * np.pi * np.abs(np.real(arg)).max(axis=(0, 2))  # (B, 2)
    return _rows_needed(sensor, np.hypot(b[:, 0], b[:, 1]), np.abs(np.real(alpha)).max(axis=(0, 2, 3)))


def disc_rows(sensor: Sensor, n: int):
    """A round lenslet (``sensor.lenslet_aperture``), the disc of ``lenslet_diameter_mm``, as n rows across y
    (``disc_row_counts``), in pitches: (y_j, weights w_j, chords h_j) (n,) each, with int_disc g dA =
    sum_j w_j int_chord_j g(t_x, y_j) dt_x. The rows sit at y = r sin(theta) on Gauss-Legendre nodes in theta (dy =
    r cos(theta) dtheta): the rim is smooth in theta, so the rule converges spectrally, and each chord is integrated
    exactly (``aperture.square_aperture_moments`` scaled to it). No staircase: a disc cut into strips diffracted its
    steps into the far neighbours' windows (32 strips: 3 urad off a direct integral, session 50)."""
    return _disc_rows(float(sensor.lenslet_diameter_mm) / float(sensor.pitch_mm), int(n))


def _disc_moments(beta, alpha, gam, dlt, a_xy, n_mom: int, rows):
    """(Re, Im) (m, B, N, S, 2, n_mom + 1) of each row's moments, the kernel's x and y factors of one round
    sub-aperture: along x the chord's moments int_{-h/2}^{h/2} t^r exp(gamma t + delta t^2 + i alpha t^2 - i beta' t)
    dt = h^(r+1) M_r(h beta', h^2 alpha, h gamma, h^2 delta), where the cross term exp(i a t_x y_j) is the chord's
    tilt, beta' = beta_x - a y_j (exact: no series); along y the row's point value w_j y_j^r exp(gamma y_j + delta
    y_j^2 + i (alpha y_j^2 - beta_y y_j)). beta (m, B, S, 2), alpha, gam, dlt (m, B, 1, 2) or 0, a_xy (m, B); the
    parts may carry a complex step."""
    y, w, h = rows

    def ax(v, i):  # one axis of a (m, B, 1 or S, 2) input, a row axis before the samples'
        return np.asarray(v)[:, :, None, :, i] if np.ndim(v) else v

    hb, yb, wb = h[:, None], y[:, None], w[:, None]
    bx = ax(beta, 0) - np.asarray(a_xy)[:, :, None, None] * yb
    xr, xi = square_aperture_moments(hb * bx, hb * hb * ax(alpha, 0), n_mom, hb * ax(gam, 0), hb * hb * ax(dlt, 0))
    hr = hb[..., None] ** np.arange(1, n_mom + 2)
    xr, xi = xr * hr, xi * hr
    amp = wb * np.exp(ax(gam, 1) * yb + ax(dlt, 1) * yb * yb)
    ph = ax(alpha, 1) * yb * yb - ax(beta, 1) * yb  # (m, B, N, S)
    yp = yb[..., None] ** np.arange(n_mom + 1)  # (N, 1, n_mom + 1)
    yr_, yi_ = (amp * np.cos(ph))[..., None] * yp, (amp * np.sin(ph))[..., None] * yp
    yr_, yi_ = (np.broadcast_to(v, xr.shape) for v in (yr_, yi_))
    return np.stack([xr, yr_], axis=-2), np.stack([xi, yi_], axis=-2)


def _window_centroid(spot: np.ndarray, block: dict, st: np.ndarray, sensor: Sensor, wavelength_nm: float,
                     sub: int) -> np.ndarray:
    """Centroid (m, 2) mm in the windows starting at pixels st (m, 2) of m lenslets whose blocks are ``block``
    (``_local_block``: one curvature per lenslet; ``_cell_block``: each sub-aperture its own curvature ``alpha``
    (m, B, 2), cross term ``a_xy`` (m, B) and irradiance gradient ``gam`` (m, B, 2), and its centre offset ``pe``)."""
    f, p, pix, W = sensor.lenslet_focal_mm, sensor.pitch_mm, sensor.pixel_mm, int(sensor.centroid_window_px)
    lam = wavelength_nm * 1e-6
    k = 2 * np.pi / lam
    nb_pos, cr, ci, a_xy = block["nb_pos"], block["cr"], block["ci"], block["a_xy"]
    pe = block["pe"] if "pe" in block else p * _neighbour_offsets(_XT_RING)  # (B, 2) or (m, B, 2)
    per_cell = block["alpha"].ndim == 3
    alpha = block["alpha"][:, :, None, :] if per_cell else block["alpha"][:, None, None, :]  # (m, B or 1, 1, 2)
    edge0 = float(sensor.camera_offset_px) * pix
    offs = (np.arange(W * sub) + 0.5) / sub
    # each sub-aperture's own curvature: the phase k (K_xx X^2 + (K_xy + K_yx) X Y + K_yy Y^2) / 2, X = p t_x;
    # K_xy's factor exp(i a t_x t_y) as sum_r (i a)^r / r! t_x^r t_y^r, terms zero beyond each sub-aperture's
    # own R: the result does not depend on which lenslets share a pass
    round_ = sensor.lenslet_aperture == "round"
    if round_:  # a round sub-aperture's rows carry the cross term exactly, as their chords' tilts: no series (its
        # one term's weight pw, one per row, comes with the rows)
        assert per_cell, "round lenslets: the 'cells' blocks only"
        R, ir_re, ir_im = 0, np.ones(1), np.zeros(1)
    else:
        R, pw, ir_re, ir_im = _series_weights(a_xy, _xy_ranks(np.abs(np.real(a_xy))))
        if not per_cell:
            pw = pw[:, None, :]
    xs = edge0 + (st[..., None, :] + offs[:, None]) * pix - spot[..., None, :]  # (m, S, 2) rel. own spot
    arg = p * (xs[..., None, :, :] - nb_pos[..., :, None, :]) / (lam * f)  # (m, B, S, 2)
    ramp = (-k * np.einsum("...bi,...si->...bsi", np.broadcast_to(pe, nb_pos.shape), xs) / f)[..., None]
    rs = "rs_c" in block
    if rs:  # the propagation's non-paraxial part, exact in its constant and linear terms (``_rs_terms``)
        c0, g, q, rem = _rs_terms(block, f, k)
        cr, ci = _cmul(cr, ci, np.exp(c0[0]) * np.cos(c0[1]), np.exp(c0[0]) * np.sin(c0[1]))
        # exp(g e + q e^2), e = x - p t per axis: over the window exp(g x + q x^2), over the aperture a tilt
        # exp(-(g + 2 q x) p t) and a curvature exp(q p^2 t^2)
        x4 = xs[:, None]  # (m, 1, S, 2)
        arg = arg + (p / (2 * np.pi)) * (g[1][:, :, None, :] + 2 * q[:, :, None, :] * x4)  # (m, B, S, 2)
        ramp = ramp + (g[1][:, :, None, :] * x4 + q[:, :, None, :] * x4 * x4)[..., None]
        alpha = alpha + p * p * q[:, :, None, :]
    coma = "coma" in block
    n_mom = R + (4 if rs else 3 if coma else 0)  # the remainder's and the coma's moments beyond the series' R
    gam = dlt = 0.0
    if "gam" in block:  # the irradiance gradient and curvature across each sub-aperture (its own weighting)
        gam, dlt = block["gam"][:, :, None, :], block["dlt"][:, :, None, :]
        if rs:  # one (gamma, delta) per sub-aperture and axis, not per sample: the aperture kernel's cache holds
            gam = gam - p * g[0][:, :, None, :]
    cos_r, sin_r = np.cos(ramp), np.sin(ramp)
    if rs:
        amp = np.exp(g[0][:, :, None, :] * x4)[..., None]
        cos_r, sin_r = amp * cos_r, amp * sin_r
    if not round_:  # (m, B, S, 2, n_mom+1): each sub-aperture's moments
        mr, mi = square_aperture_moments(2 * np.pi * arg, alpha, n_mom, gam, dlt)
        ar, ai = mr * cos_r - mi * sin_r, mr * sin_r + mi * cos_r
    else:  # each row of a round sub-aperture is a sub-aperture of its own from here on: (m, sum of rows, S, 2, .)
        counts = _disc_row_counts_of(arg, alpha, sensor)
        order = np.argsort(counts, kind="stable")  # sub-apertures grouped by their rows
        pw = np.ones((a_xy.shape[0], counts.sum(), 1))
        parts = []
        for n_rows in np.unique(counts):
            g_ = order[counts[order] == n_rows]

            def sub_(v):  # the group's sub-apertures of a (m, B, ...) input, or a scalar
                return v[:, g_] if np.ndim(v) else v

            mr, mi = _disc_moments(2 * np.pi * arg[:, g_], alpha[:, g_], sub_(gam), sub_(dlt), a_xy[:, g_], n_mom,
                                   disc_rows(sensor, n_rows))
            c_, s_ = cos_r[:, g_, None], sin_r[:, g_, None]
            parts.append([v.reshape((v.shape[0], -1) + v.shape[3:]) for v in (mr * c_ - mi * s_, mr * s_ + mi * c_)])
        ar, ai = (np.concatenate([pt[j] for pt in parts], axis=1) for j in (0, 1))

        def rep(v):  # a per-sub-aperture quantity (m, B, ...) to each of its rows, in the groups' order
            return np.repeat(v[:, order], counts[order], axis=1)

        cr, ci = rep(cr), rep(ci)
        if rs:
            rem = {key: (rep(vr), rep(vi)) for key, (vr, vi) in rem.items()}
        if coma:
            block = {**block, "coma": rep(block["coma"])}
    # the field is sum over b and slots j of Y_bj(y) X_bj(x), each a series in r: (Re, Im) (m, B, J, S, R+1)
    if rs:  # the remainder's monomials: x factors X_j against y factors e_y^j, j = 0 .. 4
        er, ei = _rs_powers(ar, ai, xs, p, R)  # the moments of e^a = (x - p t)^a, a = 0 .. 4
        x5, y5 = _rs_factors(er, ei, rem, R)  # (m, B, 5, S, R+1)
    else:
        x5 = (ar[:, :, None, :, 0, :R + 1], ai[:, :, None, :, 0, :R + 1])
        y5 = (ar[:, :, None, :, 1, :R + 1], ai[:, :, None, :, 1, :R + 1])
    slots = [(x5, y5)]
    if coma:
        (dx, dy), extra = _coma_factors(ar, ai, block["coma"], R)
        for (fr, fi), (dr, di) in zip((x5, y5), (dx, dy)):  # slot 0 in place: ar, ai are not read again
            fr[:, :, 0] += dr
            fi[:, :, 0] += di
        slots.append(extra)
    # y factor carries C_b (i a)^r / r!: its real and imaginary parts (real arithmetic for the complex step)
    wr = cr[..., None] * ir_re - ci[..., None] * ir_im  # C_b i^r, (m, B, R+1)
    wi = cr[..., None] * ir_im + ci[..., None] * ir_re
    wr, wi = (wr * pw)[:, :, None, None, :], (wi * pw)[:, :, None, None, :]
    ur = ui = 0.0
    for (xr5, xi5), (yr5, yi5) in slots:
        # stacks (m, S_y, B J (R+1)) @ (m, B J (R+1), S_x), contiguous: numpy's matmul takes its fast path only then
        m_, S = xr5.shape[0], xr5.shape[3]
        yrT = np.ascontiguousarray(np.moveaxis(wr * yr5 - wi * yi5, 3, 1).reshape(m_, S, -1))
        yiT = np.ascontiguousarray(np.moveaxis(wr * yi5 + wi * yr5, 3, 1).reshape(m_, S, -1))
        xr = np.ascontiguousarray(np.moveaxis(xr5, 3, -1).reshape(m_, -1, S))
        xi_ = np.ascontiguousarray(np.moveaxis(xi5, 3, -1).reshape(m_, -1, S))
        ur = ur + (yrT @ xr - yiT @ xi_)  # (m, S_y, S_x)
        ui = ui + (yrT @ xi_ + yiT @ xr)
    return _pixel_centroid(ur, ui, st, sensor, sub)


def _coma_factors(ar, ai, coma, R: int):
    """Each sub-aperture's coma in the field's factors (``_window_centroid``), to first order: its phase k W3,
    W3 = p^3 / 6 (W_xxx t_x^3 + 3 W_xxy t_x^2 t_y + 3 W_xyy t_x t_y^2 + W_yyy t_y^3) less its mean slope's tilt (the
    sub-aperture's tilt is the plain mean slope, which holds the cubic's share (W_xxx + W_xyy) p^2 / 24 in s_x), so
    exp(i k W3) ~ 1 + i k W3 (|k W3| <= ~0.01 rad on the co-designed lens), each monomial a shift of the series'
    moment index. coma (m, B, 4) = k p^3 / 6 (W_xxx, W_xxy, W_xyy, W_yyy); ar, ai (m, B, S, 2, >= R + 4) the raw
    moments M_r of x and y. Returns ((dx, dy): what the pure-x and pure-y terms add to slot 0's x and y factors
    (their product's second order, (k W3)^2, is dropped), each (Re, Im) (m, B, S, R+1); (x, y): two more slots for
    t_x^2 t_y and t_x t_y^2, each (Re, Im) (m, B, 2, S, R+1))."""
    c30, c21, c12, c03 = (coma[:, :, i, None, None] for i in range(4))  # (m, B, 1, 1)

    def mom(part, ax, j):  # M_(r+j), r = 0 .. R: (m, B, S, R+1)
        return part[:, :, :, ax, j:j + R + 1]

    def px(part):  # W_xxx (t_x^3 - t_x / 4) - 3 W_xyy t_x / 12: slot 0's x factor, times i
        return c30 * (mom(part, 0, 3) - 0.25 * mom(part, 0, 1)) - 0.25 * c12 * mom(part, 0, 1)

    def py(part):
        return c03 * (mom(part, 1, 3) - 0.25 * mom(part, 1, 1)) - 0.25 * c21 * mom(part, 1, 1)

    dx, dy = (-px(ai), px(ar)), (-py(ai), py(ar))  # (a + i b) i = -b + i a
    x = tuple(np.stack([mom(part, 0, 2), mom(part, 0, 1)], axis=2) for part in (ar, ai))  # 3 W_xxy t_x^2 t_y, ...
    y = (np.stack([-3 * c21 * mom(ai, 1, 1), -3 * c12 * mom(ai, 1, 2)], axis=2),  # ... 3 W_xyy t_x t_y^2
         np.stack([3 * c21 * mom(ar, 1, 1), 3 * c12 * mom(ar, 1, 2)], axis=2))
    return (dx, dy), (x, y)


def _pixel_centroid(ur: np.ndarray, ui: np.ndarray, st: np.ndarray, sensor: Sensor, sub: int) -> np.ndarray:
    """Centroid (m, 2) mm of the field (ur + i ui) (m, S_y, S_x) sampled sub x sub per pixel in the windows starting
    at pixels st (m, 2), ``centroid_threshold`` x the window's peak cut."""
    pix, W = sensor.pixel_mm, int(sensor.centroid_window_px)
    cut = float(sensor.centroid_threshold)
    edge0 = float(sensor.camera_offset_px) * pix
    m_ = ur.shape[0]
    inten = ur * ur + ui * ui
    inten = inten.reshape((m_, W, sub, W, sub)).sum(axis=(-3, -1))  # pixels (m, W_y, W_x)
    if cut > 0:  # the peak: the value at the real part's argmax (its derivative there)
        flat = inten.reshape((m_, W * W))
        idx = np.argmax(np.real(flat), axis=-1)
        peak = np.take_along_axis(flat, idx[..., None], axis=-1)[..., 0]
        inten = inten - cut * peak[..., None, None]
        inten = np.where(np.real(inten) > 0, inten, 0.0)
    pc = edge0 + (st[..., None, :] + np.arange(W)[:, None] + 0.5) * pix  # pixel centres (m, W, 2)
    tot = inten.sum(axis=(-2, -1))
    cx = np.einsum("...x,...x->...", inten.sum(axis=-2), pc[..., 0]) / tot
    cy = np.einsum("...y,...y->...", inten.sum(axis=-1), pc[..., 1]) / tot
    return np.stack([cx, cy], axis=-1)


def _series_weights(a: np.ndarray, ranks: np.ndarray):
    """(R, a^r / r! (m, 1, R+1), Re i^r, Im i^r (R+1,)) of the series exp(i a u) = sum_r (i a)^r / r! u^r, its
    terms zero beyond each lenslet's own rank: a lenslet's result does not depend on which lenslets share a pass."""
    R = int(ranks.max(initial=0))
    r = np.arange(R + 1)
    fact = np.cumprod(np.concatenate([[1.0], 1.0 / np.arange(1, R + 1)]))
    pw = a[..., None] ** r * fact * (r <= ranks[..., None])
    return R, pw, np.array([1.0, 0.0, -1.0, 0.0])[r % 4], np.array([0.0, 1.0, 0.0, -1.0])[r % 4]


def _block_ranks(a_abs: np.ndarray) -> np.ndarray:
    """Terms r = 0 .. R of the block's cross-term series exp(i a T_x T_y) = sum_r (i a T_x T_y)^r / r! per lenslet:
    (|a| T^2)^(R+1) / (R+1)! below ``_SEP_TOL`` with T^2 = (_XT_RING - 1/2)^2, the second ring's corner (the third
    ring's light in the window is ~1e-2 of the own spot's: against the full block, 32 lenslets at a = 0.06, 0.17,
    0.35, the shifts reach the full block's own 1e-7 of their size at R = 4-6, 8, 14; this bound gives 6, 9, 14);
    _SEP_MAX_RANK + 1 where that takes more terms (the lenslet goes to the full block)."""
    q = np.asarray(a_abs, dtype=float) * (_XT_RING - 0.5) ** 2
    R = np.zeros(q.shape, dtype=int)
    term = np.ones(q.shape)
    for r in range(1, _SEP_MAX_RANK + 2):
        term = term * q / r
        R = np.where(term >= _SEP_TOL, r, R)
    return R


@lru_cache(maxsize=4)
def _binomial_table(R: int) -> np.ndarray:
    """T (B1, R+1, R+1): (b + t)^r = sum_j T[b, r, j] t^j for the block's offsets b = -_XT_RING .. _XT_RING."""
    from math import comb

    b = np.arange(-_XT_RING, _XT_RING + 1, dtype=float)
    T = np.zeros((b.size, R + 1, R + 1))
    for r in range(R + 1):
        for j in range(r + 1):
            T[:, r, j] = comb(r, j) * b ** (r - j)
    T.setflags(write=False)
    return T


def _separable_centroid(spot: np.ndarray, block: dict, st: np.ndarray, sensor: Sensor, wavelength_nm: float,
                        sub: int) -> np.ndarray:
    """``_window_centroid`` of m lenslets by the block's separable form (the same field, to ``_SEP_TOL``).

    Over the block (T in pitches from the own lenslet's centre) the wavefront's curvature is the phase
    alpha_x T_x^2 + alpha_y T_y^2 + a T_x T_y; its cross term exp(i a T_x T_y) = sum_r (i a)^r / r! T_x^r T_y^r
    (``_block_ranks`` terms) makes the block's field a sum of R + 1 products X_r(x) Y_r(y), each a row of 2 _XT_RING + 1
    sub-apertures: X_r(x) = sum_b c_b exp(-i k p b x / f) int (b + t)^r exp(i alpha t^2 - i beta_b(x) t) dt, with
    (b + t)^r by the binomial on the aperture moments M_j, j <= r, c_b the neighbour's amplitude and phase along x,
    beta_b from its spot at p b (1 + f K_xx). 2 (2 _XT_RING + 1) moments per sample instead of (2 _XT_RING + 1)^2,
    and a rank R + 1 field. K's antisymmetric part (none in a gradient field) is left out."""
    f, p, pix, W = sensor.lenslet_focal_mm, sensor.pitch_mm, sensor.pixel_mm, int(sensor.centroid_window_px)
    lam = wavelength_nm * 1e-6
    k = 2 * np.pi / lam
    K, g = block["K"], block["g"]
    Kd = np.stack([K[:, 0, 0], K[:, 1, 1]], axis=-1)  # (m, 2)
    a = _cross_term(K, sensor, wavelength_nm)  # (m,)
    R, pw, ir_re, ir_im = _series_weights(a, _block_ranks(np.abs(np.real(a))))
    pb = p * np.arange(-_XT_RING, _XT_RING + 1, dtype=float)[None, :, None, None]  # (1, B1, 1, 1) offsets along an axis
    edge0 = float(sensor.camera_offset_px) * pix
    offs = (np.arange(W * sub) + 0.5) / sub
    xs = (edge0 + (st[..., None, :] + offs[:, None]) * pix - spot[..., None, :])[:, None]  # (m, 1, S, 2) rel. own spot
    nb = pb * (1.0 + f * Kd[:, None, None, :])  # (m, B1, 1, 2): the neighbours' spots along each axis
    mr, mi = square_aperture_moments(2 * np.pi * p * (xs - nb) / (lam * f), 0.5 * k * p * p * Kd[:, None, None, :], R)
    ph = k * (pb * pb * (0.5 * Kd[:, None, None, :] + 0.5 / f) - pb * xs / f)  # (m, B1, S, 2)
    amp = np.exp(0.5 * g[:, None, None, :] * pb)
    cr, ci = (amp * np.cos(ph))[..., None], (amp * np.sin(ph))[..., None]
    qr, qi = cr * mr - ci * mi, cr * mi + ci * mr  # (m, B1, S, 2, R+1): c_b M_j
    if R == 0:
        xr, xi_ = qr.sum(axis=1), qi.sum(axis=1)  # (m, S, 2, 1)
    else:  # sum over b and j of T[b, r, j] c_b M_j: one matmul over (b, j)
        B1 = qr.shape[1]
        T = _binomial_table(R).transpose(0, 2, 1).reshape(B1 * (R + 1), R + 1)
        xr, xi_ = (np.moveaxis(v, 1, 3).reshape(v.shape[0], v.shape[2], 2, -1) @ T for v in (qr, qi))
    pw = pw[:, None, :]
    yr = pw * (ir_re * xr[..., 1, :] - ir_im * xi_[..., 1, :])  # (m, S_y, R+1): (i a)^r / r! Y_r
    yi = pw * (ir_re * xi_[..., 1, :] + ir_im * xr[..., 1, :])
    xr, xi_ = np.swapaxes(xr[..., 0, :], 1, 2), np.swapaxes(xi_[..., 0, :], 1, 2)  # (m, R+1, S_x)
    return _pixel_centroid(yr @ xr - yi @ xi_, yr @ xi_ + yi @ xr, st, sensor, sub)


@lru_cache(maxsize=16)
def _reference_shift(sensor: Sensor, wavelength_nm: float, centres_key: bytes, n: int) -> np.ndarray:
    c = np.frombuffer(centres_key).reshape(n, 2)
    out = crosstalk_shift(c, c, np.zeros((n, 2, 2)), np.zeros((n, 2)), sensor, wavelength_nm)
    out.setflags(write=False)
    return out


def reference_shift(sensor: Sensor, wavelength_nm: float, centres: np.ndarray) -> np.ndarray:
    """crosstalk_shift (n, 2) mm of the factory reference: a uniform plane wave at normal incidence."""
    c = np.ascontiguousarray(centres, dtype=float)
    return _reference_shift(sensor, wavelength_nm, c.tobytes(), len(c))


def _slope_gradient(sq: np.ndarray, offsets: np.ndarray, weights: np.ndarray, pitch: float) -> np.ndarray:
    """K (..., 2, 2) = d s_i / d x_j (1/mm): the least-squares plane in the slopes sq (..., q, 2) over the rule."""
    m2 = weights @ offsets**2
    return np.einsum("q,qj,...qi->...ij", weights, offsets, sq) / (m2 * pitch)[None, :]


def local_field(sq: np.ndarray, wi: np.ndarray, offsets: np.ndarray, weights: np.ndarray,
                pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """(K (..., 2, 2) slope gradients d s_i / d x_j in 1/mm, gradient of ln I (..., 2) in 1/mm) of one
    lenslet's quadrature: least-squares over the rule (offsets in pitches); the irradiance centroid
    xi of I ~ exp(g . x) over the square is g p^2 / 12."""
    K = _slope_gradient(sq, offsets, weights, pitch)
    with np.errstate(divide="ignore", invalid="ignore"):
        centroid = np.einsum("...q,qk->...k", wi, offsets) / wi.sum(axis=-1)[..., None]
    return K, 12.0 * centroid / pitch


def crosstalk_slopes(s: np.ndarray, sq: np.ndarray, wi: np.ndarray, offsets: np.ndarray, weights: np.ndarray,
                     centres: np.ndarray, sensor: Sensor, wavelength_nm: float, windows: np.ndarray | None = None,
                     return_windows: bool = False):
    """Centroid slopes s (..., n, 2) with the neighbours' cross-talk, the whole-pixel window placement
    and the noise cut, against the factory reference: s (1 + p^2 / 6 f^2) + (shift - reference shift) / f.
    windows, return_windows: frozen windows, and the windows used (``crosstalk_shift``).

    The gain is the ideal thin lenslet's own mapping of a tilt onto the camera beyond its chief ray:
    the rays across a fully lit p x p aperture land, on average, at f tan(theta) (1 + 2 <u^2> / f^2),
    <u^2> = p^2 / 12 (1.4e-4 at the defaults; the physical reference gives 1.34e-4 for a 10 mrad
    plane wave). A real lenslet's distortion differs (ASSUMPTION: an ideal paraxial lenslet; it acts
    as a 1e-4 change of the effective focal length). This model keeps the Fresnel kernel and adds the gain
    by hand; 'cells' (``cell_crosstalk_slopes``) gets it from its Rayleigh-Sommerfeld kernel."""
    K, g = local_field(sq, wi, offsets, weights, sensor.pitch_mm)
    f, p = sensor.lenslet_focal_mm, sensor.pitch_mm
    spot = centres + f * s
    ref = reference_shift(sensor, wavelength_nm, centres)
    d, st = crosstalk_shift(spot, centres, K, g, sensor, wavelength_nm, iterations=TRACKING_ITERATIONS,
                            windows=windows, return_windows=True, start=spot + ref)
    out = s * (1.0 + p * p / (6.0 * f * f)) + (d - ref) / f
    return (out, st) if return_windows else out


# the cross-talk kernel's inputs per lenslet: spot (x, y), K (xx, xy, yx, yy), grad ln I (x, y)
LOCAL_INPUTS = 8


def crosstalk_slope_derivatives(sq: np.ndarray, wi: np.ndarray, dsq: np.ndarray, dwi: np.ndarray, offsets: np.ndarray,
                                weights: np.ndarray, gains: tuple[float, float], centres: np.ndarray, sensor: Sensor,
                                wavelength_nm: float, windows: np.ndarray | None = None) -> np.ndarray:
    """Derivatives (..., n, 2, d) of ``crosstalk_slopes`` (after ``centroid_slopes``) along d directions
    of the quadrature slopes dsq (..., n, q, 2, d) and weights dwi (..., n, q, d), exact (windows: frozen
    ones, ``crosstalk_shift``; the derivative is the same, the windows' placement is skipped).

    The kernel sees a lenslet only through ``LOCAL_INPUTS`` numbers (its spot, slope gradient K and
    gradient of ln I), so its derivatives are taken by a complex step along those 8 inputs, not along
    the d directions, and chained: a cost independent of d (the joint fit's 6 + 24 lens directions and
    a gain: 8 kernel evaluations instead of 31). The own centroid's part is in closed form."""
    f, p = sensor.lenslet_focal_mm, sensor.pitch_mm
    s = centroid_slopes(sq, wi, offsets, weights, gains)
    ds = centroid_slope_derivatives(sq, wi, dsq, dwi, offsets, weights, gains)  # (..., n, 2, d)
    K, g = local_field(sq, wi, offsets, weights, p)
    # K and g along the d directions: local_field is analytic in (sq, wi), a complex step per direction
    h = 1e-30
    Kc, gc = local_field(sq + 1j * h * np.moveaxis(dsq, -1, 0), wi + 1j * h * np.moveaxis(dwi, -1, 0),
                         offsets, weights, p)  # (d, ..., n, 2, 2), (d, ..., n, 2)
    dK, dg = np.moveaxis(Kc.imag / h, 0, -1), np.moveaxis(gc.imag / h, 0, -1)
    d_local = np.concatenate([f * ds, dK.reshape(dK.shape[:-3] + (4,) + dK.shape[-1:]), dg], axis=-2)
    spot = centres + f * s
    if windows is None:  # the windows the slopes' own tracking ends in (``crosstalk_slopes``)
        windows = crosstalk_slopes(s, sq, wi, offsets, weights, centres, sensor, wavelength_nm, return_windows=True)[1]
    jac = np.empty(s.shape + (LOCAL_INPUTS,))  # (..., n, 2, 8): d shift / d local input
    for j in range(LOCAL_INPUTS):
        e = np.zeros(LOCAL_INPUTS)
        e[j] = h
        jac[..., j] = crosstalk_shift(spot + 1j * e[:2], centres, K + 1j * e[2:6].reshape(2, 2), g + 1j * e[6:],
                                      sensor, wavelength_nm, windows=windows).imag / h
    return ds * (1.0 + p * p / (6.0 * f * f)) + np.einsum("...kl,...ld->...kd", jac, d_local) / f


# ----------------------------------------------------------------------------- cross-talk from each lenslet's own field

# rings of lit lenslets around each pupil lenslet that the 'cells' model sums, and field samples per pixel and axis.
# Plane waves (10 and 50 mrad) against the full-array physical reference at 8 samples per pixel, RMS per lenslet:
# rings 1-7: 0.9, 3.9, 4.0, 0.70, 0.66, 0.62, 0.60 urad (the 7 x 7 block is an unlucky truncation of the
# neighbours' ~1/distance sinc tails); at ring 5, 2 / 4 / 8 samples per pixel: 1.7-4.2 / 0.55-0.75 / 0.48-0.73 urad
CELL_RING = 4
CELL_SUB = 4


def _index_of(keys: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Index into the distinct integers ``keys`` (K,) of each of ``query`` (...), -1 where absent."""
    order = np.argsort(keys)
    at = np.minimum(np.searchsorted(keys, query, sorter=order), len(keys) - 1)
    return np.where(keys[order[at]] == query, order[at], -1)


def lit_lenslets(sensor: Sensor, pupil_centres: np.ndarray, ring: int = CELL_RING) -> tuple[np.ndarray, np.ndarray]:
    """(centres (L, 2) mm, neighbours (n, (2 ring + 1)^2) int) of the lenslets lit around the n pupil lenslets: every
    lenslet of the sensor within ``ring`` rings (Chebyshev distance in pitches) of a pupil lenslet, the pupil's
    first and in its order; neighbours[i] indexes the lit lenslets of pupil lenslet i's block, row-major from
    (-ring, -ring) (x fastest), -1 where the block leaves the sensor."""
    p = sensor.pitch_mm
    n_side = int(np.floor(sensor.aperture_mm / p + 1e-9))
    grid = np.rint(np.asarray(pupil_centres) / p + 0.5 * (n_side - 1)).astype(int)  # (n, 2) grid indices
    off = _neighbour_offsets(ring).astype(int)
    cand = (grid[:, None, :] + off[None]).reshape(-1, 2)
    cand = cand[np.all((cand >= 0) & (cand < n_side), axis=1)]
    keys = grid[:, 0] * n_side + grid[:, 1]
    extra = np.setdiff1d(np.unique(cand[:, 0] * n_side + cand[:, 1]), keys)
    allk = np.concatenate([keys, extra])
    ij = np.stack([allk // n_side, allk % n_side], axis=1)
    centres = p * (ij - 0.5 * (n_side - 1))
    nb = grid[:, None, :] + off[None]
    inside = np.all((nb >= 0) & (nb < n_side), axis=2)
    nbk = nb[..., 0] * n_side + nb[..., 1]
    neighbours = np.where(inside, _index_of(allk, nbk), -1)
    centres.setflags(write=False)
    neighbours.setflags(write=False)
    return centres, neighbours


def cell_fields(sq: np.ndarray, wi: np.ndarray, offsets: np.ndarray, weights: np.ndarray, pitch: float):
    """Each lenslet's local field from its quadrature rays: (tilt (..., L, 2) = the plain mean slope, K (..., L, 2, 2)
    = d s_i / d x_j (1/mm), g (..., L, 2) = gradient of ln I (1/mm), ln of the amplitude at the centre (..., L),
    lit (..., L)), a least-squares plane in the slopes and in ln I over the rule. A lenslet with a ray lost (weight
    0) is dark (lit False, its field zero)."""
    lit = np.all(np.real(wi) > 0, axis=-1)
    safe = np.where(lit[..., None], wi, weights)
    ln_i = np.log(safe / weights)
    m2 = weights @ offsets**2
    tilt = np.einsum("q,...qk->...k", weights, sq)
    K = _slope_gradient(sq, offsets, weights, pitch)
    g = np.einsum("q,qj,...q->...j", weights, offsets, ln_i) / (m2 * pitch)
    ln_a = 0.5 * np.einsum("q,...q->...", weights, ln_i)
    z = np.zeros((), dtype=tilt.dtype)
    return (np.where(lit[..., None], tilt, z), np.where(lit[..., None, None], K, z), np.where(lit[..., None], g, z),
            np.where(lit, ln_a, z), lit)


CELL_DELTA_MAX = 0.25  # the amplitude curvature kept across half a cell (a Gaussian beam's is ~0.01; aperture.py)


def axis_neighbours(lit_centres: np.ndarray, pitch: float) -> np.ndarray:
    """(L, 2, 2) index of each lit lenslet's lit neighbour at -1 and +1 pitch along x (axis 0) and y (axis 1); -1:
    none."""
    # in half pitches: an even lenslet count puts the centres on half-integer multiples of the pitch
    ij = np.rint(2.0 * np.asarray(lit_centres) / pitch).astype(np.int64)
    span = 2 * int(np.abs(ij).max(initial=0)) + 5  # keys of the grid points one pitch beyond stay distinct

    def key(a):
        return (a[..., 0] + span) * (2 * span) + (a[..., 1] + span)

    steps = 2 * np.array([[[-1, 0], [1, 0]], [[0, -1], [0, 1]]])  # (axis, side, xy)
    return _index_of(key(ij), key(ij[:, None, None, :] + steps[None]))


def hermite_step(pe, s0, sb, K0, Kb):
    """W_b - W_0 (...) between two lenslet centres pe (..., 2) apart from their slopes s (..., 2) and slope gradients
    K (..., 2, 2): the two-point Hermite rule along the segment (exact for a cubic W)."""
    Ks0, Ksb = 0.5 * (K0 + np.swapaxes(K0, -1, -2)), 0.5 * (Kb + np.swapaxes(Kb, -1, -2))
    return 0.5 * np.einsum("...i,...i->...", pe, s0 + sb) + np.einsum("...i,...ij,...j->...", pe, Ks0 - Ksb, pe) / 12.0


def cell_pistons(tilt: np.ndarray, K: np.ndarray, lit: np.ndarray, axis_nb: np.ndarray, pitch: float):
    """(W (..., L), component (..., L) int) the wavefront at every lit lenslet's centre, up to one constant per
    connected lit region (``component``, -1 for a dark lenslet), the least-squares integral of the one-pitch Hermite
    steps (``hermite_step``) between lit axis neighbours. One Hermite step across a whole block (up to 4 rings, 6
    pitches on the diagonal) misses a freeform's fifth-order terms by (6 p)^5 W^(5) / 720; chained one-pitch steps
    by ~p^5. Linear in the slopes, so a complex step passes through (real and imaginary parts solved alike). One
    sparse factorisation per distinct lit pattern (a pose's complex-step directions share theirs)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import splu

    lead, L = lit.shape[:-1], lit.shape[-1]
    P = int(np.prod(lead, dtype=int))
    t, KK, lt = tilt.reshape(P, L, 2), K.reshape(P, L, 2, 2), lit.reshape(P, L)
    W = np.zeros((P, L), dtype=np.result_type(tilt, K))
    comp = np.full((P, L), -1)
    edges = []  # (a, b, axis) with b the +1 pitch neighbour of a along the axis
    for ax in range(2):
        hi = axis_nb[:, ax, 1]
        a = np.nonzero(hi >= 0)[0]
        edges.append(np.stack([a, hi[a], np.full(len(a), ax)], axis=1))
    edges = np.concatenate(edges)
    patterns, which = np.unique(lt, axis=0, return_inverse=True)
    for u, pattern in enumerate(patterns):
        rows = np.nonzero(which.reshape(-1) == u)[0]
        e = edges[pattern[edges[:, 0]] & pattern[edges[:, 1]]]
        i, j, ax = e[:, 0], e[:, 1], e[:, 2]
        pe = np.zeros((len(e), 2))
        pe[np.arange(len(e)), ax] = pitch
        d = hermite_step(pe, t[rows][:, i], t[rows][:, j], KK[rows][:, i], KK[rows][:, j])  # (m, E): W_j - W_i
        _, c = connected_components(coo_matrix((np.ones(len(e)), (i, j)), shape=(L, L)), directed=False)
        c = np.where(pattern, c, -1)
        # normal equations: the graph Laplacian, one node of each region pinned (its constant is free)
        pin = np.nonzero(c >= 0)[0][np.unique(c[c >= 0], return_index=True)[1]]
        diag = (np.bincount(i, minlength=L) + np.bincount(j, minlength=L) + ~pattern).astype(float)
        diag[pin] += 1.0
        lap = coo_matrix((np.r_[diag, -np.ones(2 * len(e))], (np.r_[np.arange(L), i, j], np.r_[np.arange(L), j, i])),
                         shape=(L, L)).tocsc()
        inc = coo_matrix((np.r_[np.ones(len(e)), -np.ones(len(e))], (np.r_[j, i], np.tile(np.arange(len(e)), 2))),
                         shape=(L, len(e))).tocsr()  # the steps' divergence
        div = inc @ d.T  # (L, m)
        lu = splu(lap)
        sol = lu.solve(np.ascontiguousarray(np.real(div), dtype=float))
        if np.iscomplexobj(div):
            sol = sol + 1j * lu.solve(np.ascontiguousarray(np.imag(div), dtype=float))
        W[rows] = sol.T
        comp[rows] = c
    return W.reshape(lead + (L,)), comp.reshape(lead + (L,))


def axis_derivative(v: np.ndarray, lit: np.ndarray, axis_nb: np.ndarray, pitch: float, ax: int) -> np.ndarray:
    """d v / d x_ax (..., L) of a per-lenslet quantity v (..., L) from its lit axis neighbours (``axis_neighbours``):
    the central difference, one-sided at the lit region's edge, 0 for a lenslet with no lit neighbour along ax.
    Linear in v (a complex step passes through)."""
    lo, hi = axis_nb[:, ax, 0], axis_nb[:, ax, 1]
    has_lo = (lo >= 0) & np.take(lit, np.maximum(lo, 0), axis=-1) & lit
    has_hi = (hi >= 0) & np.take(lit, np.maximum(hi, 0), axis=-1) & lit
    z = np.zeros((), dtype=v.dtype)
    d_hi = np.where(has_hi, np.take(v, np.maximum(hi, 0), axis=-1) - v, z)
    d_lo = np.where(has_lo, v - np.take(v, np.maximum(lo, 0), axis=-1), z)
    n = has_hi.astype(float) + has_lo.astype(float)
    return (d_hi + d_lo) / (np.maximum(n, 1.0) * pitch)


def ln_i_curvature(g: np.ndarray, lit: np.ndarray, axis_nb: np.ndarray, pitch: float) -> np.ndarray:
    """h (..., L, 2) = d^2 ln I / dx^2, d^2 ln I / dy^2 (1/mm^2) of each lit lenslet from its lit neighbours'
    gradients g (..., L, 2) (the 2 x 2 rule sees no curvature in one cell): ``axis_derivative``; kept to
    |h| p^2 / 4 <= ``CELL_DELTA_MAX``."""
    h = np.stack([axis_derivative(g[..., ax], lit, axis_nb, pitch, ax) for ax in range(2)], axis=-1)
    lim = 4.0 * CELL_DELTA_MAX / pitch**2
    return np.where(np.abs(np.real(h)) > lim, np.sign(np.real(h)) * lim, h)


def third_derivatives(K: np.ndarray, lit: np.ndarray, axis_nb: np.ndarray, pitch: float) -> np.ndarray:
    """(..., L, 4) the wavefront's third derivatives (W_xxx, W_xxy, W_xyy, W_yyy) (1/mm^2) at the lit lenslets from
    their slope gradients K (..., L, 2, 2) (d s_i / d x_j): ``axis_derivative``s, W_xyy = d K_yy / dx = d K_xy / dy
    and W_xxy = d K_xx / dy = d K_xy / dx, each pair averaged. Linear in K."""
    v = np.stack([K[..., 0, 0], K[..., 1, 1], 0.5 * (K[..., 0, 1] + K[..., 1, 0])])  # (3, ..., L): xx, yy, xy
    dx, dy = (axis_derivative(v, lit, axis_nb, pitch, ax) for ax in (0, 1))
    return np.stack([dx[0], 0.5 * (dy[0] + dx[2]), 0.5 * (dx[1] + dy[2]), dy[1]], axis=-1)


def cubic_slopes(sq: np.ndarray, wi: np.ndarray, offsets: np.ndarray, weights: np.ndarray, axis_nb: np.ndarray,
                 pitch: float, gains: tuple[float, float]) -> np.ndarray:
    """Correction (..., L, 2) to the lenslets' plain mean slopes for the window's view of their wavefront's third
    derivatives: -(1 - g_d) W_xxx p^2 / 24 - (1 - g_c) W_xyy p^2 / 24 in s_x (W_yyy and W_xxy in s_y), gains from
    ``cubic_gain``; sq (..., L, q, 2) and wi (..., L, q) the quadratures of L lenslets, axis_nb (L, 2, 2) their
    ``axis_neighbours``. The 2 x 2 rule's mean slope holds the cubic's share exactly, but a model that renders it
    as a tilt (the own centroid, 'neighbours') sees it with gain 1, where a pixel window sees ~0.9 of it ('cells'
    renders the coma in its kernel instead, ``_coma_factors``). The third derivatives: ``third_derivatives``.
    Linear in sq: along a direction dsq (with the same wi) it is its own derivative."""
    g_d, g_c = gains
    if (g_d == 1.0 and g_c == 1.0) or np.any(weights @ offsets**2 == 0):  # the complete spot, or the centre rule
        return np.zeros(sq.shape[:-2] + (2,), dtype=sq.dtype)
    lit = np.all(np.real(wi) > 0, axis=-1)
    w_xxx, w_xxy, w_xyy, w_yyy = np.moveaxis(
        third_derivatives(_slope_gradient(sq, offsets, weights, pitch), lit, axis_nb, pitch), -1, 0)
    c = pitch * pitch / 24.0
    return -c * np.stack([(1 - g_d) * w_xxx + (1 - g_c) * w_xyy, (1 - g_d) * w_yyy + (1 - g_c) * w_xxy], axis=-1)


def _cell_block(rows: np.ndarray, cells: dict, neighbours: np.ndarray, lit_centres: np.ndarray, sensor: Sensor,
                wavelength_nm: float, exact: bool = True) -> dict:
    """The block of m window rows (``rows`` (m, 2): leading index, pupil lenslet) from every lit lenslet's own field
    (``cells``: tilt, K, g, h, ln_a, lit, each with a flattened leading axis): per neighbour b its spot relative to the
    own spot, complex amplitude (the amplitude ratio, the piston between the two centres from ``cells`` W, the
    integrated wavefront of ``cell_pistons``, else by the two-point Hermite rule on their slopes and curvatures, the
    lenslets' focusing phase), curvature alpha (m, B, 2), cross term a_xy (m, B),
    amplitude gradient gam (m, B, 2) and curvature dlt (m, B, 2) across the sub-aperture (from ln I's, ``cells`` g
    and h) and centre offset pe (m, B, 2)."""
    f, p = sensor.lenslet_focal_mm, sensor.pitch_mm
    k = 2 * np.pi / (wavelength_nm * 1e-6)
    lead, i = rows[:, 0], rows[:, 1]
    nb = neighbours[i]  # (m, B)
    have = nb >= 0
    nbc = np.where(have, nb, 0)
    L = lead[:, None]

    def own(key):
        return cells[key][lead, i]

    def other(key):
        return cells[key][L, nbc]

    pe = lit_centres[nbc] - lit_centres[i][:, None, :]  # (m, B, 2)
    s0, sb = own("tilt")[:, None, :], other("tilt")
    K0, Kb = own("K"), other("K")
    d_w = hermite_step(pe, s0, sb, K0[:, None], Kb)  # W_b - W_own at the centres
    if "W" in cells:  # the integrated wavefront where both lie in one lit region (``cell_pistons``)
        same = (other("comp") == own("comp")[:, None]) & (own("comp")[:, None] >= 0)
        d_w = np.where(same, other("W") - own("W")[:, None], d_w)
    phase = k * (d_w - np.einsum("mbi,mbi->mb", pe, np.broadcast_to(s0, pe.shape))
                 + 0.5 * (pe**2).sum(axis=-1) / f)
    amp = np.where(have & other("lit"), np.exp(other("ln_a") - own("ln_a")[:, None]), 0.0)
    alpha = 0.5 * k * p * p * np.stack([Kb[..., 0, 0], Kb[..., 1, 1]], axis=-1)
    block = {"nb_pos": pe + f * (sb - s0), "cr": amp * np.cos(phase), "ci": amp * np.sin(phase), "alpha": alpha,
             "a_xy": _cross_term(Kb, sensor, wavelength_nm), "gam": 0.5 * p * other("g"),
             "dlt": 0.25 * p * p * other("h"), "pe": pe}
    if exact:  # the propagation's non-paraxial part (``_rs_terms``)
        block.update(rs_c=f * s0 - pe, rs_star=f * sb)
    if "w3" in cells:  # each sub-aperture's coma: k p^3 / 6 (W_xxx, W_xxy, W_xyy, W_yyy) (``_coma_factors``)
        block["coma"] = (k * p**3 / 6.0) * other("w3")
    return block


def cell_shift(spot: np.ndarray, cells: dict, lit_centres: np.ndarray, neighbours: np.ndarray, sensor: Sensor,
               wavelength_nm: float, iterations: int = TRACKING_ITERATIONS, windows: np.ndarray | None = None,
               return_windows: bool = False, exact: bool = True, start: np.ndarray | None = None):
    """Centroid minus spot (..., n, 2) mm of each pupil lenslet's pixel window under the coherent sum of the fields of
    the lit lenslets of its block (``lit_lenslets``), each with its own tilt, curvature, irradiance gradient and
    amplitude (``cell_fields``; cells[...]: (..., L, ...)), the pistons between them from their slopes; spot
    (..., n, 2) the own spots. Windows placed on start (..., n, 2) (default the spots) and re-centred on the centroid
    ``iterations`` times (frozen ones: ``windows``).
    exact: the propagation to the camera as the Rayleigh-Sommerfeld integral (``_rs_terms``, what the angular
    spectrum's exact transfer function does), False: its Fresnel approximation (the field the kernel is built on).
    What exact changes, against the full-array reference (co-designed bench, spp 4): a diverging wave (R = -100 mm)
    through the 10.5 mm Gaussian beam centred 3 mm off, worst mode 6.3 sigma (Z5; Z3 -6.1) -> 1.1 (Z4; Z3 -0.55);
    the neighbours' light carries it (the Fresnel-against-exact reference's Z3 was -5.2 sigma with the whole
    array lit, -1.1 with every third lenslet). Plane waves, the tilt's p^2 / 6 f^2 gain now from the kernel:
    50 mrad 1.95 -> 0.65 sigma, (20, 30) mrad 1.34 -> 0.58, 100 mrad 5.6 (Z4) -> 3.7 (Z2, -0.77 urad)."""
    lead = spot.shape[:-2]
    n = spot.shape[-2]
    P = int(np.prod(lead, dtype=int))
    flat = {key: np.reshape(v, (P,) + v.shape[len(lead):]) for key, v in cells.items()}
    sp = spot.reshape(P * n, 2)
    # rows (leading index, pupil lenslet), lenslet-major: a complex step's directions of one lenslet share a pass,
    # where their real parts are computed once (``aperture._moments_of_rows``); each row's result is its own
    rows = np.stack(np.meshgrid(np.arange(P), np.arange(n), indexing="xy"), axis=-1).reshape(-1, 2)
    flat_row = rows[:, 0] * n + rows[:, 1]  # into sp
    out = np.empty(sp.shape, dtype=np.result_type(spot, *[v.dtype for v in flat.values()]))
    st_all = np.empty(sp.shape)
    frozen = None if windows is None else np.broadcast_to(windows, lead + (n, 2)).reshape(-1, 2)
    first = None if start is None else np.broadcast_to(start, spot.shape).reshape(-1, 2)
    # a round lenslet's rows multiply a pass's memory: fewer lenslets a pass
    chunk = _XT_CHUNK
    if sensor.lenslet_aperture == "round":
        counts = disc_row_counts(sensor, wavelength_nm, int(round((np.sqrt(neighbours.shape[1]) - 1) / 2)))
        chunk = max(1, int(2 * _XT_CHUNK * len(counts) // counts.sum()))
    for a in range(0, len(rows), chunk):
        c = flat_row[a:a + chunk]
        block = _cell_block(rows[a:a + chunk], flat, neighbours, lit_centres, sensor, wavelength_nm, exact)
        out[c], st_all[c] = _tracked_window_shift(sp[c], block, sensor, wavelength_nm, iterations, CELL_SUB,
                                                  _window_centroid, None if frozen is None else frozen[c],
                                                  None if first is None else first[c])
    out = out.reshape(lead + (n, 2))
    return (out, st_all.reshape(lead + (n, 2))) if return_windows else out


@lru_cache(maxsize=16)
def _cell_reference_shift(sensor: Sensor, wavelength_nm: float, key: bytes, L: int, nkey: bytes, n: int) -> np.ndarray:
    centres = np.frombuffer(key).reshape(L, 2)
    neighbours = np.frombuffer(nkey, dtype=np.int64).reshape(n, -1)
    cells = {"tilt": np.zeros((L, 2)), "K": np.zeros((L, 2, 2)), "g": np.zeros((L, 2)), "h": np.zeros((L, 2)),
             "ln_a": np.zeros(L), "lit": np.ones(L, bool)}
    out = cell_shift(centres[:n], cells, centres, neighbours, sensor, wavelength_nm)
    out.setflags(write=False)
    return out


def cell_reference_shift(sensor: Sensor, wavelength_nm: float, lit_centres: np.ndarray,
                         neighbours: np.ndarray) -> np.ndarray:
    """``cell_shift`` (n, 2) mm of the factory reference: a uniform plane wave at normal incidence over the lit lenslets."""
    c = np.ascontiguousarray(lit_centres, dtype=float)
    nb = np.ascontiguousarray(neighbours, dtype=np.int64)
    return _cell_reference_shift(sensor, wavelength_nm, c.tobytes(), len(c), nb.tobytes(), len(nb))


def cell_crosstalk_slopes(sq: np.ndarray, wi: np.ndarray, offsets: np.ndarray, weights: np.ndarray,
                          lit_centres: np.ndarray, neighbours: np.ndarray, sensor: Sensor, wavelength_nm: float,
                          windows: np.ndarray | None = None, return_windows: bool = False):
    """Centroid slopes (..., n, 2) of the n pupil lenslets from the quadratures sq (..., L, q, 2), wi (..., L, q) of all
    L lit lenslets (the pupil's first, ``lit_lenslets``), against the factory reference: each window sees its own and
    its neighbours' fields, each lenslet's from its own rays (``cell_shift``), so its irradiance weighting, window
    truncation, cross-talk and whole-pixel placement come from one coherent computation, propagated to the camera
    without the paraxial approximation (``cell_shift``): tilt + (shift - reference shift) / f (the non-paraxial
    gain that ``crosstalk_slopes`` adds by hand, p^2 / 6 f^2, is the kernel's own here)."""
    n = neighbours.shape[0]
    f, p = sensor.lenslet_focal_mm, sensor.pitch_mm
    tilt, K, g, ln_a, lit = cell_fields(sq, wi, offsets, weights, p)
    axis_nb = axis_neighbours(lit_centres, p)
    h = ln_i_curvature(g, lit, axis_nb, p)
    # ln_a is half the rule's mean of ln I, the cell's mean: the centre's is lower by its curvature's share
    ln_a = ln_a - 0.25 * p * p * np.einsum("k,...k->...", weights @ offsets**2, h)
    W, comp = cell_pistons(tilt, K, lit, axis_nb, p)
    cells = {"tilt": tilt, "K": K, "g": g, "h": h, "ln_a": ln_a, "lit": lit, "W": W, "comp": comp,
             "w3": third_derivatives(K, lit, axis_nb, p)}
    s = tilt[..., :n, :]
    spot = lit_centres[:n] + f * s
    ref = cell_reference_shift(sensor, wavelength_nm, lit_centres, neighbours)
    # the tracking rule's first window: on the reference spot plus f times the slope (``TRACKING_ITERATIONS``)
    d, st = cell_shift(spot, cells, lit_centres, neighbours, sensor, wavelength_nm, windows=windows,
                       return_windows=True, start=spot + ref)
    out = s + (d - ref) / f  # each window sees its lenslets' cubic in the kernel: no ``cubic_slopes`` on top
    return (out, st) if return_windows else out
