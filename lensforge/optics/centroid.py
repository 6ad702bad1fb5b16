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
* threshold: a lenslet is used only when its mean irradiance sum_q w_q I_q is at
  least ``sensor.irradiance_threshold`` of the beam peak. Thorlabs' software cuts the
  noise floor per spot area ("Auto" noise cut, recommended; WFS Series manual,
  2007-2012, p. 72); ``centroid_threshold`` (default 0, ASSUMPTION) models a cut at a
  fraction of the spot peak.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .bench import Sensor

__all__ = ["quadrature_rule", "window_gain", "centroid_slopes"]


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


@lru_cache(maxsize=32)
def _window_gain(pitch, focal, pixel, window_px, threshold, wavelength_mm, cross: bool, kappa: float = 1e-3) -> float:
    M, sub = 128, 4  # gamma converges as 1/M^2: 0.8694 (M = 32), 0.8707 (64), 0.8707 (128)
    t = pitch * ((np.arange(M) + 0.5) / M - 0.5)
    X, Y = np.meshgrid(t, t, indexing="xy")
    eps = 0.1  # irradiance ramp over the pitch; kappa: wavefront curvature 1/mm
    # direct: ramp along x, W = kappa x^2 / 2; cross: ramp along y, W = kappa x y (x-shift from the y-ramp)
    ramp = Y if cross else X
    inten_ap = 1.0 + eps * ramp / pitch
    k = 2 * np.pi / wavelength_mm
    W = kappa * X * Y if cross else 0.5 * kappa * X**2
    E = np.sqrt(inten_ap) * np.exp(1j * k * W)
    moment = focal * kappa * np.sum(inten_ap * ramp) / np.sum(inten_ap)  # complete-spot centroid shift, mm
    cam = ((np.arange(window_px * sub) + 0.5) / sub - 0.5 * window_px) * pixel
    F = np.exp(-2j * np.pi * np.outer(cam, t) / (wavelength_mm * focal))
    A = F @ E @ F.T  # (y, x) on the camera samples
    inten = (np.abs(A) ** 2).reshape(window_px, sub, window_px, sub).sum(axis=(1, 3))
    if threshold > 0:
        inten = np.clip(inten - threshold * inten.max(), 0.0, None)
    c = (np.arange(window_px) - 0.5 * (window_px - 1)) * pixel
    centroid = inten.sum(axis=0) @ c / inten.sum()
    return float(centroid / moment)


def window_gain(sensor: Sensor, wavelength_nm: float) -> tuple[float, float]:
    """Gains (direct, cross) of the pixel-window centroid on the irradiance-weighting part of the slope.

    direct: on d s_x/dx times the irradiance centroid offset along x (and y alike); cross: on
    d s_x/dy times the offset along y. (1, 1) for the complete-spot centroid (window 0). First-order
    values (weak curvature): a curvature-dependent direct gain was tried and did not help.
    """
    if sensor.centroid_window_px == 0:
        return 1.0, 1.0
    args = (sensor.pitch_mm, sensor.lenslet_focal_mm, sensor.pixel_mm, int(sensor.centroid_window_px),
            float(sensor.centroid_threshold), wavelength_nm * 1e-6)
    return _window_gain(*args, False), _window_gain(*args, True)


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
