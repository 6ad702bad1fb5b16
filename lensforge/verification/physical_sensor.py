"""Full-array physical reference model of the Shack-Hartmann sensor (issue 21).

What a real sensor does to the field the posed lens delivers, with none of the fast
model's simplifications (``optics/shack_hartmann.py``): it shares only the exact ray
trace and lensforge's Zernike fit matrix.

1. Field at the lenslet array. A regular grid of beam rays is traced through the lens
   at the pose to the lenslet plane z = 0 of {S}. The eikonal S(X, Y) (optical path,
   mm) is the least-squares potential of the rays' direction cosines (dS/dX = L,
   dS/dY = M: Malus-Dupin), a tensor-product B-spline of degree ``potential_degree`` on knots
   ``potential_knot_mm`` apart over the lit lenslets (and a one-pitch collar): local, so a
   fast-varying region (a lens's caustic near the lit margin) does not spoil the fit elsewhere,
   as a global polynomial's did (see ``PhysicalSensor``); the irradiance
   I = I_beam / |det d(X, Y)/d(u, v)| (exact derivatives of the trace) is fitted alike in
   log I. The fit residual is reported (``PhysicalMeasurement.potential_residual_urad``). E = sqrt(I) exp(i k S).
2. The whole lit lenslet array at once, coherently: every lenslet of the sensor within
   ``margin_lenslets`` rings of a pupil lenslet (each pupil lenslet's (2 margin + 1)^2 block) multiplies
   E by its thin-lens phase exp(-i k r^2 / 2 f) (ASSUMPTION: ideal paraxial lenslets)
   inside its aperture: 'square' (fully filled pitch x pitch cells) or 'round'
   (``lenslet_diameter_mm``, dark gaps). Sample cells that straddle an aperture edge
   take the area fraction inside.
3. Angular-spectrum propagation (exact transfer function, no Fresnel or Fraunhofer
   approximation, zero padding ``pad_mm`` against wrap-around) over the lenslet focal
   length f to the camera; intensity integrated over 5.5 um pixels
   (``samples_per_pixel`` field samples per pixel and axis; pixel edges at
   ``sensor.camera_offset_px`` + multiples of the pixel from the sensor axis).
   Neighbours' light falls into every window and interferes there.
4. Centroids: per pupil lenslet a ``sensor.centroid_window_px`` square window placed on
   whole pixels on the expected spot ('tracking', ASSUMPTION of the algorithm: start at
   the reference spot plus f times the lenslet's mean ray slope, then re-centre on the
   centroid, ``tracking_iterations`` times); ``sensor.centroid_threshold`` x the
   window's peak is subtracted (the per-spot noise cut) before the first moment.
5. Reference spot field: 'factory' (a uniform plane wave at normal incidence through
   the same model), 'beam' (a user reference recorded with the bench's laser and no
   lens, ``WFS_SetSpotsToUserReference``), or given centroids. Slopes are
   (centroid - reference) / f, fitted with lensforge's fit matrix.
Cost: ~1-3 s per pose on one core for the FFTs (two of ~1700^2 at the defaults), plus ~5-10 s for the ray
field's spline fit (an SVD of ~27,000 x 2,500). Memory: the (N, N) grids are built
and reduced a chunk of rows at a time: at most the lens's and the reference's fields (complex128) and the
transmitted field, its spectrum or the camera field (complex64) live at once, ~45 N^2 bytes (the co-designed
bench's 3.5 mm pupil at 12 samples per pixel, N = 21,000: 19.7 GB peak; before, 10 did not fit in 24 GB).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
import scipy.fft as sfft
from scipy.spatial import cKDTree

from ..errors import ConfigError
from ..input_checks import BENCH_RANGES, number
from ..optics.centroid import TRACKING_ITERATIONS, quadrature_rule
from ..optics.bench import Bench, Sensor
from ..optics.shack_hartmann import ForwardModel
from ..optics.trace import OK, aim_rays, trace_rays

__all__ = ["PhysicalSensor", "PhysicalMeasurement", "MlaField", "physical_measure", "physical_session_slopes", "field_slopes",
           "ray_field", "plane_field", "spot_centroids", "reference_centroids", "lit_box", "samples_needed",
           "field_max_slope"]

APERTURES = ("square", "round")


@dataclass(frozen=True)
class PhysicalSensor:
    """Settings of the reference model that the bench does not hold.

    aperture: 'square' (fully filled cells) or 'round'; lenslet_diameter_mm: the round
    aperture (None, the default: the bench's ``sensor.lenslet_aperture`` and ``lenslet_diameter_mm``, 140 um by
    the MLA150-5C spec sheet as cited in issue 21); samples_per_pixel:
    field samples per camera pixel and axis (4: 1.375 um; the modes move by <= 0.4 sigma
    from 4 to 5 and by up to 3 sigma from 2 to 4 on the paper's polynomial lens: the lenslet
    edges' diffraction needs fine samples; a field whose phase it would alias is refused,
    ``samples_needed``; the session simulator raises it to its slopes' need, ``sampled_for``);
    margin_lenslets: lit lenslet rings beyond each pupil lenslet (the square apertures' cross-talk decays slowly:
    the 'cells' model's plane-wave slopes, truncated at 1 ... 7 rings, were 0.9, 3.9, 4.0, 0.70, 0.66, 0.62, 0.60
    urad RMS off this reference at 7; 5 by default, the model lights 4; a wider lit box needs finer samples where
    edge rays are steep); oversample: sub-sample
    shifts per axis of the camera field for the pixel integral (``_camera_intensity``); pad_mm: zero padding of the propagation grid; potential_degree,
    potential_knot_mm, ray_grid: the ray-field fit (B-spline degree, knot spacing, rays per axis; a fit whose slope
    residual over the fitted rays exceeds ``POTENTIAL_TOL_URAD`` RMS is refused: the field would not be the lens's.
    A global Legendre polynomial of degree 14, used before, missed the default design's plan pose
    (-0.5, -0.5, -0.5 mm, -5, 5, 5 deg) by 39 urad RMS inside the pupil (degree 48: 0.38), where the lit margin
    nears the lens's caustic, and made the reference read 23 sigma off 'cells' there; degree 7 on 0.2 mm knots:
    0.004 urad in the pupil, 0.16 over all fitted rays; on 0.3 mm knots 0.06); reference: 'factory' or 'beam' (see the module);

    tracking_iterations: window re-centrings; lit_stride: 1 lights the whole array at once;
    s > 1 lights only every s-th lenslet along x and y at a time (s^2 runs), which takes the
    neighbours' cross-talk out (a diagnostic, not a sensor); window_px / threshold: None = the bench's
    centroid_window_px / centroid_threshold; focal_mm: the lenslets' true focal length (None = the
    bench's ``sensor.lenslet_focal_mm``). The light is propagated over it, while slopes are
    converted with the bench's value, as a device converts with its stored MLA data: a
    different true focal length is a common gain f_true / f_bench on every slope.
    propagation: 'exact' (the angular spectrum's transfer function) or 'fresnel' (its paraxial
    approximation, the fast kernel's: a diagnostic of what the non-paraxial terms move, not a sensor).
    """

    aperture: str | None = None
    lenslet_diameter_mm: float | None = None
    samples_per_pixel: int = 4
    margin_lenslets: int = 5
    pad_mm: float = 0.5
    potential_degree: int = 7
    potential_knot_mm: float = 0.2
    ray_grid: int = 160
    reference: str = "factory"
    tracking_iterations: int = TRACKING_ITERATIONS
    oversample: int = 1
    lit_stride: int = 1
    window_px: int | None = None
    threshold: float | None = None
    focal_mm: float | None = None
    propagation: str = "exact"

    def __post_init__(self):
        if self.propagation not in ("exact", "fresnel"):
            raise ConfigError(f"physical sensor propagation: must be 'exact' or 'fresnel', got {self.propagation!r}")
        if self.aperture is not None and self.aperture not in APERTURES:
            raise ConfigError(f"physical sensor aperture: must be one of {list(APERTURES)}, got {self.aperture!r}")
        if self.reference not in ("factory", "beam"):
            raise ConfigError(f"physical sensor reference: must be 'factory' or 'beam', got {self.reference!r}")
        if self.focal_mm is not None:  # the lenslets' true focal length: the bench's range and unit
            number(self.focal_mm, "physical sensor focal_mm", BENCH_RANGES["sensor.lenslet_focal_mm"])
        if self.samples_per_pixel < 1 or self.margin_lenslets < 1 or self.potential_degree < 3:
            raise ConfigError("physical sensor: samples_per_pixel >= 1, margin_lenslets >= 1, potential_degree >= 3")
        if not (np.isfinite(self.potential_knot_mm) and 0.01 <= self.potential_knot_mm <= 2.0):
            raise ConfigError(f"physical sensor potential_knot_mm: must be 0.01-2 mm, got {self.potential_knot_mm!r}")

    def sampled_for(self, bench: Bench, max_slope: float) -> "PhysicalSensor":
        """These settings with samples_per_pixel raised, if need be, to resolve rays sloping up to
        max_slope (``samples_needed``)."""
        return replace(self, samples_per_pixel=max(self.samples_per_pixel, samples_needed(bench, self, max_slope)))

    def focal(self, sensor: Sensor) -> float:
        return float(self.focal_mm if self.focal_mm is not None else sensor.lenslet_focal_mm)

    def window(self, sensor: Sensor) -> int:
        w = int(self.window_px if self.window_px is not None else sensor.centroid_window_px)
        if w < 3:
            raise ConfigError("physical sensor: the pixel centroid needs a window of >= 3 px "
                              "(sensor.centroid_window_px = 0, the complete spot, has no camera analogue)")
        return w

    def shape(self, sensor: Sensor) -> tuple[str, float]:
        """(aperture, diameter mm) of the lenslets: these settings', else the bench's."""
        return (self.aperture if self.aperture is not None else sensor.lenslet_aperture,
                float(self.lenslet_diameter_mm if self.lenslet_diameter_mm is not None else sensor.lenslet_diameter_mm))

    def cut(self, sensor: Sensor) -> float:
        return float(self.threshold if self.threshold is not None else sensor.centroid_threshold)


@dataclass(frozen=True, eq=False)
class MlaField:
    """A field sampled on the lenslet plane: x (N,) sample centres (mm, both axes), the
    complex field E (N, N) [y, x] (zero outside the lit box), expected slopes (n, 2) of
    the pupil lenslets (the window's start), and the fit's slope residual (rad, RMS and max)."""

    x: np.ndarray
    E: np.ndarray
    expected_slopes: np.ndarray
    residual_rms: float = 0.0
    residual_max: float = 0.0


@dataclass(frozen=True, eq=False)
class PhysicalMeasurement:
    """z (m,) um (Noll modes of the model); slopes (n, 2) rad; centroids_mm / reference_mm
    (n, 2) spot centroids on the camera; potential_residual_urad: (RMS, max) slope misfit of
    the ray-field potential; valid: the fast model's verdict (traced, lit, in range)."""

    z: np.ndarray
    slopes: np.ndarray
    centroids_mm: np.ndarray
    reference_mm: np.ndarray
    potential_residual_urad: tuple
    valid: bool


# ----------------------------------------------------------------------------- geometry

_CHUNK_ROWS = 480  # rows of an (N, N) grid built or reduced at a time: the temporaries stay ~N x 480, not N x N
# (at the co-designed bench's 3.5 mm pupil and 8 samples per pixel, N = 14,000: a complex128 temporary is 3.1 GB)


def _row_chunks(n: int, step: int = _CHUNK_ROWS):
    """Slices covering 0 .. n in steps of ``step`` rows (the last one shorter)."""
    return [slice(i, min(i + step, n)) for i in range(0, n, step)]


def _lenslet_coords(sensor: Sensor) -> np.ndarray:
    n_side = int(np.floor(sensor.aperture_mm / sensor.pitch_mm + 1e-9))
    return sensor.pitch_mm * (np.arange(n_side) - 0.5 * (n_side - 1))


def lit_box(sensor: Sensor, cfg: PhysicalSensor, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cx, cy): lenslet centre coordinates (mm) of the lit lenslets along x and y: the pupil
    lenslets' box widened by ``cfg.margin_lenslets`` on every side (within the sensor)."""
    c = _lenslet_coords(sensor)
    m = cfg.margin_lenslets * sensor.pitch_mm + 1e-9
    out = []
    for k in range(2):
        lo, hi = centres[:, k].min() - m, centres[:, k].max() + m
        out.append(c[(c >= lo) & (c <= hi)])
    return out[0], out[1]


def _grid(sensor: Sensor, cfg: PhysicalSensor, cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
    """Sample centres (N,) (mm), symmetric about 0, N a multiple of 2 spp so pixel edges fall on k * pixel."""
    spp = cfg.samples_per_pixel
    dx = sensor.pixel_mm / spp
    half = max(abs(cx).max(), abs(cy).max()) + 0.5 * sensor.pitch_mm + cfg.pad_mm
    n = int(np.ceil(2 * half / dx))
    step = 2 * spp
    n = int(np.ceil(n / step) * step)
    while sfft.next_fast_len(n) != n:
        n += step
    return (np.arange(n) - 0.5 * n + 0.5) * dx + sensor.camera_offset_px * sensor.pixel_mm


def _cell_fractions(x: np.ndarray, dx: float, centres: np.ndarray, width: float) -> np.ndarray:
    """(N, n) fraction of each sample interval [x - dx/2, x + dx/2] inside each cell [c - w/2, c + w/2]."""
    lo = np.maximum(x[:, None] - 0.5 * dx, centres[None, :] - 0.5 * width)
    hi = np.minimum(x[:, None] + 0.5 * dx, centres[None, :] + 0.5 * width)
    return np.clip(hi - lo, 0.0, None) / dx


def lenslet_transmission_rows(x: np.ndarray, sensor: Sensor, cfg: PhysicalSensor, cx: np.ndarray, cy: np.ndarray,
                              wavelength_mm: float) -> Callable[[slice], np.ndarray]:
    """rows -> those rows [y, x] of the lit lenslets' complex transmission on the sample grid x (mm): the x
    factors are computed once, each call builds only its rows (the grid is too large to hold twice)."""
    f, p = cfg.focal(sensor), sensor.pitch_mm
    k = 2 * np.pi / wavelength_mm
    dx = x[1] - x[0]
    aperture, diameter = cfg.shape(sensor)
    if aperture == "square":  # separable: sum_i frac_i(x) exp(-i k (x - c_i)^2 / 2f), one sample in <= 2 cells
        def factor(v, c):
            return (_cell_fractions(v, dx, c, p) * np.exp(-0.5j * k * (v[:, None] - c[None, :]) ** 2 / f)).sum(axis=1)

        ax = factor(x, cx)
        return lambda rows: factor(x[rows], cy)[:, None] * ax[None, :]
    # round: each sample belongs to its nearest lenslet; area fraction inside radius R (edge linearised)
    R = 0.5 * diameter
    ux = x - cx[np.clip(np.rint((x - cx[0]) / p).astype(int), 0, len(cx) - 1)]

    def rows_of(rows):
        y = x[rows]
        uy = y - cy[np.clip(np.rint((y - cy[0]) / p).astype(int), 0, len(cy) - 1)]
        r = np.sqrt(ux[None, :] ** 2 + uy[:, None] ** 2)
        mask = np.clip((R - r) / dx + 0.5, 0.0, 1.0)
        return mask * np.exp(-0.5j * k * r**2 / f)

    return rows_of


def lenslet_transmission(x: np.ndarray, sensor: Sensor, cfg: PhysicalSensor, cx: np.ndarray, cy: np.ndarray,
                         wavelength_mm: float) -> np.ndarray:
    """Complex transmission (N, N) [y, x] of the lit lenslets on the sample grid x (mm)."""
    return lenslet_transmission_rows(x, sensor, cfg, cx, cy, wavelength_mm)(slice(None))


def _camera_intensity(E: np.ndarray, x: np.ndarray, f: float, wavelength_mm: float, spp: int,
                      oversample: int = 1, fresnel: bool = False) -> np.ndarray:
    """Pixel intensities (Np, Np) [y, x] at distance f: angular spectrum, then the intensity summed over
    spp x spp field samples per pixel, each of them seen at oversample x oversample sub-sample shifts (the
    band-limited field evaluated exactly there by a phase ramp on its spectrum: the intensity has twice the
    field's bandwidth, so its midpoint sum needs the finer samples)."""
    n = len(x)
    dx = x[1] - x[0]
    fr = sfft.fftfreq(n, dx)
    # single precision: relative rounding ~1e-6 of the intensities, ~1e-4 um of a centroid (1/400 of its noise)
    spec = sfft.fft2(np.asarray(E, dtype=np.complex64), workers=1)
    del E  # the caller's complex64 field, when it passed a temporary
    for c in _row_chunks(n):  # the transfer function, a chunk of rows at a time
        arg = 1.0 / wavelength_mm**2 - fr[None, :] ** 2 - fr[c, None] ** 2
        if fresnel:  # paraxial: kz - k = -pi lambda (fx^2 + fy^2)
            kz = -np.pi * wavelength_mm * (fr[None, :] ** 2 + fr[c, None] ** 2)
        else:
            kz = 2 * np.pi * (np.sqrt(np.clip(arg, 0.0, None)) - 1.0 / wavelength_mm)  # the plane-wave phase k f dropped
        spec[c] *= np.where(arg > 0, np.exp(1j * f * kz), 0.0).astype(np.complex64)
    m = n // spp
    inten = np.zeros((m, m))
    shifts = (np.arange(oversample) + 0.5) / oversample - 0.5  # in samples
    for sy in shifts:
        ry = np.exp(2j * np.pi * fr * sy * dx).astype(np.complex64)
        for sx in shifts:
            rx = np.exp(2j * np.pi * fr * sx * dx).astype(np.complex64)
            U = sfft.ifft2(spec if sx == sy == 0.0 else spec * ry[:, None] * rx[None, :], workers=1)
            for c in _row_chunks(n, _CHUNK_ROWS // spp * spp):  # whole pixel rows: summed into pixels per chunk
                u = U[c]
                inten[c.start // spp:c.stop // spp] += (u.real.astype(float) ** 2 + u.imag.astype(float) ** 2).reshape(
                    -1, spp, m, spp).sum(axis=(1, 3))
            del U
    return inten


def spot_centroids(inten: np.ndarray, x: np.ndarray, pixel: float, spp: int, start_mm: np.ndarray, window: int,
                   cut: float, iterations: int) -> np.ndarray:
    """Centroids (n, 2) mm of pixel windows of ``window`` px placed on whole pixels at start_mm (n, 2),
    re-centred on their centroid ``iterations`` times; ``cut`` x the window's peak subtracted first."""
    m = inten.shape[0]
    edge0 = x[0] - 0.5 * (x[1] - x[0])  # left edge of pixel 0 (a multiple of the pixel)
    pos = np.array(start_mm, dtype=float)
    offs = np.arange(window)
    for _ in range(iterations + 1):
        s = np.floor((pos - edge0) / pixel - 0.5 * window + 0.5).astype(int)  # first pixel of each window
        if s.min() < 0 or s.max() + window > m:
            raise ConfigError("physical sensor: a centroid window leaves the computed camera area; "
                              "raise pad_mm or margin_lenslets")
        iy = s[:, 1, None, None] + offs[None, :, None]
        ix = s[:, 0, None, None] + offs[None, None, :]
        w = inten[iy, ix]  # (n, window, window) [y, x]
        if cut > 0:
            w = np.clip(w - cut * w.max(axis=(1, 2), keepdims=True), 0.0, None)
        tot = w.sum(axis=(1, 2))
        cxp = edge0 + (s[:, 0, None] + offs[None, :] + 0.5) * pixel
        cyp = edge0 + (s[:, 1, None] + offs[None, :] + 0.5) * pixel
        new = np.stack([np.einsum("nx,nx->n", w.sum(axis=1), cxp), np.einsum("ny,ny->n", w.sum(axis=2), cyp)],
                       axis=1) / tot[:, None]
        pos = new
    return pos


# ----------------------------------------------------------------------------- fields

POTENTIAL_TOL_URAD = 1.0  # the ray-field fit's slope residual (RMS over the fitted rays) beyond which it is refused


@dataclass(frozen=True)
class _Knots:
    """A clamped B-spline knot vector of degree k over [lo, hi], ~step apart (``PhysicalSensor.potential_knot_mm``)."""

    lo: float
    hi: float
    step: float
    k: int

    @property
    def t(self) -> np.ndarray:
        n = max(1, int(np.ceil((self.hi - self.lo) / self.step)))
        return np.r_[[self.lo] * self.k, np.linspace(self.lo, self.hi, n + 1), [self.hi] * self.k]

    @property
    def size(self) -> int:
        return len(self.t) - self.k - 1

    def dense(self, x: np.ndarray, nu: int = 0) -> np.ndarray:
        """(n, size) basis values (or their nu-th derivatives) at x, clipped into [lo, hi] (scipy's BSpline with the
        identity as coefficients: every basis function at once)."""
        from scipy.interpolate import BSpline

        x = np.clip(np.asarray(x, float), self.lo, self.hi)
        return BSpline(self.t, np.eye(self.size), self.k)(x, nu)

    def local(self, x: np.ndarray, nu: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(first basis index (n,), values (n, k + 1)) of the k + 1 basis functions nonzero at x (their local
        support) or of their nu-th derivatives."""
        x = np.clip(np.asarray(x, float), self.lo, self.hi)
        first = np.clip(np.searchsorted(self.t, x, side="right") - 1, self.k, self.size - 1) - self.k
        return first, np.take_along_axis(self.dense(x, nu), first[:, None] + np.arange(self.k + 1), axis=1)


def _spline_eval(kx: _Knots, ky: _Knots, C: np.ndarray, X: np.ndarray, nx: int = 0, ny: int = 0) -> np.ndarray:
    """d^(nx + ny) s / dx^nx dy^ny (n,) of the tensor-product spline C (``_spline_fit``) at the points X (n, 2)."""
    return np.einsum("nb,ba,na->n", ky.dense(X[:, 1], ny), C, kx.dense(X[:, 0], nx))


def _spline_fit(kx: _Knots, ky: _Knots, X: np.ndarray, rows: list[tuple[np.ndarray, int, int]]) -> tuple:
    """Coefficients C (ky.size, kx.size) of the tensor-product spline s(x, y) = sum C[j, i] B_j(y) B_i(x) that fits,
    in least squares, the values v of its derivatives d^(nx + ny) s / dx^nx dy^ny at the points X (n, 2), rows =
    [(v (n,), nx, ny), ...], and the residuals. By SVD (relative cutoff 1e-10) over the coefficients some point
    touches (the others 0): the partly covered edge makes the system ill-conditioned, and its normal equations
    (cond^2) or a pivoted QR left 5-10x the SVD's slope residual on the default design's plan pose."""
    from scipy import linalg

    nk = kx.k + 1
    blocks = []
    for v, nx, ny in rows:
        fx, vx = kx.local(X[:, 0], nx)
        fy, vy = ky.local(X[:, 1], ny)
        cols = ((fy[:, None] + np.arange(nk))[:, :, None] * kx.size + (fx[:, None] + np.arange(nk))[:, None, :])
        blocks.append((cols.reshape(len(v), -1), (vy[:, :, None] * vx[:, None, :]).reshape(len(v), -1)))
    used = np.unique(np.concatenate([c.ravel() for c, _ in blocks]))
    A = np.zeros((sum(len(v) for v, _, _ in rows), used.size))
    r0 = 0
    for cols, vals in blocks:
        n = len(cols)
        A[np.arange(r0, r0 + n)[:, None], np.searchsorted(used, cols)] = vals  # a point's columns are distinct
        r0 += n
    b = np.concatenate([v for v, _, _ in rows])
    coef = linalg.lstsq(A, b, cond=1e-10, lapack_driver="gelsd", check_finite=False)[0]
    C = np.zeros(kx.size * ky.size)
    C[used] = coef
    return C.reshape(ky.size, kx.size), A @ coef - b


def _box_slices(x, sensor, cx, cy) -> tuple[slice, slice]:
    """(x, y) slices of the sample grid x (ascending) over the lit box's cells."""
    p = sensor.pitch_mm

    def span(c):
        inside = np.nonzero((x >= c[0] - 0.5 * p - 1e-12) & (x <= c[-1] + 0.5 * p + 1e-12))[0]
        return slice(int(inside[0]), int(inside[-1]) + 1)

    return span(cx), span(cy)


def _field_rays(model: ForwardModel, pose, cfg: PhysicalSensor) -> dict:
    """The traced ray grid behind the lit lenslets (``ray_field``): landing points X, unit directions d,
    |det d(X, Y)/d(u, v)|, beam irradiance, the rays to fit (``fit``: the lit lenslets and a one-pitch
    collar) and those on the lit lenslets (``lit``), the box (centre, half-size h, lenslet coordinates)."""
    bench, sensor = model.bench, model.bench.sensor
    pose = np.asarray(pose, dtype=float).reshape(1, 6)
    cx, cy = lit_box(sensor, cfg, model.pupil.centres)
    p = sensor.pitch_mm
    lo = np.array([cx[0], cy[0]]) - 0.5 * p
    hi = np.array([cx[-1], cy[-1]]) + 0.5 * p
    # the beam preimage of the lit box: rays aimed at a 9 x 9 grid over it
    g = np.linspace(0.0, 1.0, 9)
    T = np.stack(np.meshgrid(lo[0] + g * (hi[0] - lo[0]), lo[1] + g * (hi[1] - lo[1]), indexing="xy"), -1).reshape(-1, 2)
    uv, _, _, st, _ = aim_rays(bench, model.lens, pose, T, kernel=model.kernel)
    good = st[0] == OK
    if good.sum() < 4:
        raise ConfigError("physical sensor: the beam does not reach the lit lenslet box at this pose")
    u_lo, u_hi = uv[0, good].min(axis=0), uv[0, good].max(axis=0)
    span = u_hi - u_lo
    u_lo, u_hi = u_lo - 0.08 * span, u_hi + 0.08 * span
    n = cfg.ray_grid
    U, V = np.meshgrid(np.linspace(u_lo[0], u_hi[0], n), np.linspace(u_lo[1], u_hi[1], n), indexing="xy")
    uvg = np.stack([U.ravel(), V.ravel()], 1)
    tr = trace_rays(bench, model.lens, pose, uvg, kernel=model.kernel)
    X = tr.xy[0]
    d = tr.direction[0] / np.linalg.norm(tr.direction[0], axis=1, keepdims=True)
    J = tr.derivatives[0, :, :2, :]  # d(X, Y)/d(u, v)
    det = np.abs(J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0])
    w = 0.5 * bench.laser.beam_diameter_mm
    I_beam = np.exp(-2.0 * (uvg[:, 0] ** 2 + uvg[:, 1] ** 2) / (w * w))  # uv: relative to the beam centre
    centre, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    # fitted over the lit lenslets and a one-pitch collar only: the box's corners beyond, where the
    # lens's edge bends the rays steeply, spoil a global fit (on the co-designed bench 0.2 mrad RMS
    # inside the pupil and 26 mrad at the corners at degree 14; 2.5e-9 rad at degree 20 without them)
    inside = np.all(np.abs(X - centre) <= h * 1.05, axis=1)
    dist = _pupil_distance(X, model.pupil.centres)
    fit = (tr.status[0] == OK) & inside & (dist <= (cfg.margin_lenslets + 1.0) * p) & (det > 0)
    return {"X": X, "d": d, "det": det, "I_beam": I_beam, "fit": fit,
            "lit": fit & (dist <= (cfg.margin_lenslets + 0.5) * p), "centre": centre, "h": h, "cx": cx, "cy": cy}


def _lit_max_slope(r: dict) -> float:
    d = r["d"][r["lit"]]
    return float(np.max(np.abs(d[:, :2] / d[:, 2:3]), initial=0.0))


def field_max_slope(model: ForwardModel, pose, cfg: PhysicalSensor) -> float:
    """Largest ray slope (tan, either axis) on the lit lenslets at ``pose``: what the field's sampling
    must resolve (``samples_needed``). Traces the ray grid only."""
    return _lit_max_slope(_field_rays(model, pose, cfg))


def ray_field(model: ForwardModel, pose, cfg: PhysicalSensor) -> MlaField:
    """The field the posed lens delivers on the lit lenslet box, from the exact ray trace (module step 1)."""
    bench, sensor = model.bench, model.bench.sensor
    lam = bench.laser.wavelength_nm * 1e-6
    r = _field_rays(model, pose, cfg)
    X, d, det, I_beam, ok = r["X"], r["d"], r["det"], r["I_beam"], r["fit"]
    centre, h, cx, cy = r["centre"], r["h"], r["cx"], r["cy"]
    # the sampled field must resolve its phase (``samples_needed``)
    s_max = _lit_max_slope(r)
    need = samples_needed(bench, cfg, s_max)
    if cfg.samples_per_pixel < need:
        raise ConfigError(f"physical sensor: samples_per_pixel {cfg.samples_per_pixel} under-samples the field's "
                          f"phase (largest ray slope {1e3 * s_max:.0f} mrad): use samples_per_pixel >= {need}")
    if ok.sum() < 1000:
        raise ConfigError("physical sensor: too few rays over the lit lenslet box (the lens clips the beam?)")
    # the splines span the fitted rays (the box and 5 % beyond)
    kx, ky = (_Knots(centre[a] - 1.06 * h[a], centre[a] + 1.06 * h[a], cfg.potential_knot_mm, cfg.potential_degree)
              for a in (0, 1))
    Xf = X[ok]
    Cs, res = _spline_fit(kx, ky, Xf, [(d[ok, 0], 1, 0), (d[ok, 1], 0, 1)])  # dS/dX = L, dS/dY = M
    res_n = np.hypot(*res.reshape(2, -1))
    rms, mx = float(np.sqrt(np.mean(res_n**2))), float(res_n.max())
    if rms * 1e6 > POTENTIAL_TOL_URAD:
        raise ConfigError(f"physical sensor: the ray field's potential misses the traced slopes by {rms * 1e6:.2f} urad "
                          f"RMS (> {POTENTIAL_TOL_URAD}): use a smaller potential_knot_mm or a larger ray_grid")
    log_i = np.log(I_beam[ok] / det[ok])
    CI, _ = _spline_fit(kx, ky, Xf, [(log_i, 0, 0)])
    x = _grid(sensor, cfg, cx, cy)
    bx, by = _box_slices(x, sensor, cx, cy)
    Bx, By = kx.dense(x[bx]), ky.dense(x[by])
    k = 2 * np.pi / lam
    log_max = float(log_i.max())  # a scale: the brightest fitted ray at 1
    E = np.zeros((len(x), len(x)), complex)
    box = E[by, bx]  # a view, filled a chunk of rows at a time
    for c in _row_chunks(len(x[by])):
        S = By[c] @ Cs @ Bx.T
        # capped: the box's dark corners hold no rays, and the spline is free to grow there (the lit cells stay
        # within the fit's error of <= 0)
        logI = np.minimum(By[c] @ CI @ Bx.T - log_max, 2.0)
        box[c] = np.exp(0.5 * logI + 1j * k * S) * _lit_cells(x[bx], x[by][c], cx, cy, model, cfg)
    # expected spot start: each pupil lenslet's mean ray slope (tan), 4 x 4 Gauss-Legendre over its cell (the
    # slope at the centre differs by the slope's curvature, and where a spot sits within the window's truncation
    # bias of a half-pixel boundary the start picks its window: ``centroid.TRACKING_ITERATIONS``)
    off, wq = quadrature_rule(4)
    q = (model.pupil.centres[:, None, :] + sensor.pitch_mm * off[None]).reshape(-1, 2)
    Lq, Mq = _spline_eval(kx, ky, Cs, q, nx=1), _spline_eval(kx, ky, Cs, q, ny=1)
    Nq = np.sqrt(np.clip(1 - Lq**2 - Mq**2, 1e-12, None))
    tan = np.stack([Lq / Nq, Mq / Nq], 1).reshape(-1, len(wq), 2)
    return MlaField(x, E, np.einsum("q,nqk->nk", wq, tan), rms, mx)


def samples_needed(bench: Bench, cfg: PhysicalSensor, max_slope: float) -> int:
    """Fewest samples per pixel that resolve the phase of a field whose rays slope up to max_slope
    (tan) over the lit lenslets: with the lenslet's own phase to its edge, at most pi / 1.5 per
    sample (spp 2 aliased the co-designed bench's 100 mrad, Z4 off by 2600 sigma, where spp 4, 6
    and 8 agree within 1 sigma; on the paper Zernike lens's 56 mrad spp 2 was 15 sigma off spp 4,
    spp 3 within 1.5)."""
    sensor = bench.sensor
    s = abs(float(max_slope)) + 0.5 * sensor.pitch_mm / cfg.focal(sensor)
    return int(np.ceil(3.0 * s * sensor.pixel_mm / (bench.laser.wavelength_nm * 1e-6)))


def _pupil_distance(X: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(N,) distance (the larger of |dx|, |dy|: lenslet rings) from each point X (N, 2) to the
    nearest pupil lenslet centre."""
    return cKDTree(centres).query(X, p=np.inf)[0]


def _lit_cells(xs: np.ndarray, ys: np.ndarray, cx: np.ndarray, cy: np.ndarray, model: ForwardModel,
               cfg: PhysicalSensor) -> np.ndarray:
    """(len(ys), len(xs)) 1 on the cells of the lit lenslets, 0 elsewhere in the box: a lenslet is lit
    when it lies within ``margin_lenslets`` rings of a pupil lenslet (every pupil lenslet's
    (2 margin + 1)^2 block; the box's corners beyond stay dark)."""
    p = model.bench.sensor.pitch_mm
    CX, CY = np.meshgrid(cx, cy, indexing="xy")
    lit = (_pupil_distance(np.stack([CX.ravel(), CY.ravel()], 1), model.pupil.centres)
           <= cfg.margin_lenslets * p + 1e-9).reshape(len(cy), len(cx))
    ix = np.clip(np.rint((xs - cx[0]) / p).astype(int), 0, len(cx) - 1)
    iy = np.clip(np.rint((ys - cy[0]) / p).astype(int), 0, len(cy) - 1)
    return lit[np.ix_(iy, ix)].astype(float)


def _analytic_wave(X: np.ndarray, Y: np.ndarray, slope, curvature_mm: float | None, hessian) -> tuple:
    """(optical path S (...) mm, direction cosines (..., 2)) on the lenslet plane of a plane wave of tan slope
    ``slope``, plus a sphere converging to ``curvature_mm`` after the plane (< 0: diverging), plus the quadratic
    X^T H X / 2 (``hessian`` H (2, 2) 1/mm, symmetric: a saddle H_xy isolates the cross curvature)."""
    tx, ty = slope
    nrm = np.sqrt(1 + tx * tx + ty * ty)
    S = (tx * X + ty * Y) / nrm
    gx, gy = np.full(X.shape, tx / nrm), np.full(X.shape, ty / nrm)
    if curvature_mm is not None:
        R = float(curvature_mm)
        rr = np.sqrt(X**2 + Y**2 + R * R)
        S = S - np.sign(R) * (rr - abs(R))
        gx, gy = gx - np.sign(R) * X / rr, gy - np.sign(R) * Y / rr
    if hessian is not None:
        H = np.asarray(hessian, float)
        S = S + 0.5 * (H[0, 0] * X * X + (H[0, 1] + H[1, 0]) * X * Y + H[1, 1] * Y * Y)
        gx = gx + H[0, 0] * X + 0.5 * (H[0, 1] + H[1, 0]) * Y
        gy = gy + H[1, 1] * Y + 0.5 * (H[0, 1] + H[1, 0]) * X
    return S, np.stack([gx, gy], axis=-1)


def _tan(cosines: np.ndarray) -> np.ndarray:
    """tan slopes (..., 2) of rays with direction cosines (..., 2)."""
    return cosines / np.sqrt(1.0 - (cosines**2).sum(-1, keepdims=True))


def plane_field(bench: Bench, cfg: PhysicalSensor, centres: np.ndarray, slope=(0.0, 0.0), gaussian: bool = False,
                curvature_mm: float | None = None, beam_offset_mm=(0.0, 0.0), hessian=None) -> MlaField:
    """An analytic field on the lit box of the pupil lenslets ``centres``: a plane wave of slope (tan) ``slope``
    (uniform, or the bench's Gaussian beam when ``gaussian``, centred at ``beam_offset_mm`` (x, y) on the
    lenslet plane), or with ``curvature_mm`` = R a spherical wave converging to a point R (mm) after the lenslet
    plane (R < 0: diverging from a point -R before it), and with ``hessian`` H (2, 2) (1/mm) the quadratic
    X^T H X / 2 added to its path (``_analytic_wave``)."""
    sensor = bench.sensor
    lam = bench.laser.wavelength_nm * 1e-6
    cx, cy = lit_box(sensor, cfg, centres)
    x = _grid(sensor, cfg, cx, cy)
    bx, by = _box_slices(x, sensor, cx, cy)
    E = np.zeros((len(x), len(x)), complex)
    box = E[by, bx]  # a view, filled a chunk of rows at a time
    for c in _row_chunks(len(x[by])):
        X, Y = np.meshgrid(x[bx], x[by][c], indexing="xy")
        S = _analytic_wave(X, Y, slope, curvature_mm, hessian)[0]
        amp = np.ones_like(X)
        if gaussian:
            w = 0.5 * bench.laser.beam_diameter_mm
            amp = np.exp(-((X - beam_offset_mm[0]) ** 2 + (Y - beam_offset_mm[1]) ** 2) / (w * w))
        box[c] = amp * np.exp(2j * np.pi / lam * S)
    c = np.asarray(centres, float)
    return MlaField(x, E, _tan(_analytic_wave(c[:, 0], c[:, 1], slope, curvature_mm, hessian)[1]))


def analytic_wave_quadratures(bench: Bench, X: np.ndarray, curvature_mm: float | None = None,
                              gaussian: bool = False, beam_offset_mm=(0.0, 0.0), slope=(0.0, 0.0),
                              hessian=None) -> tuple[np.ndarray, np.ndarray]:
    """The fast models' inputs for ``plane_field``'s wave: slopes (tan, from the path's exact direction cosines)
    (..., 2) and relative irradiance (...) at the points X (..., 2) mm (a sphere's tan slopes are exactly -X / R;
    the Gaussian beam of ``plane_field`` centred at beam_offset_mm, or uniform)."""
    X = np.asarray(X, float)
    sq = _tan(_analytic_wave(X[..., 0], X[..., 1], slope, curvature_mm, hessian)[1])
    if not gaussian:
        return sq, np.ones(X.shape[:-1])
    w = 0.5 * bench.laser.beam_diameter_mm
    return sq, np.exp(-2 * ((X - np.asarray(beam_offset_mm, float)) ** 2).sum(-1) / w**2)


def _centroids_of(field: MlaField, bench: Bench, cfg: PhysicalSensor, centres: np.ndarray,
                  start_mm: np.ndarray | None = None) -> np.ndarray:
    sensor = bench.sensor
    lam = bench.laser.wavelength_nm * 1e-6
    f = cfg.focal(sensor)
    cx, cy = lit_box(sensor, cfg, centres)
    start = centres + f * field.expected_slopes if start_mm is None else start_mm
    args = (field.x, sensor.pixel_mm, cfg.samples_per_pixel)

    transmission = lenslet_transmission_rows(field.x, sensor, cfg, cx, cy, lam)
    fresnel = cfg.propagation == "fresnel"

    def transmitted(lit_x=None, lit_y=None) -> np.ndarray:
        """E x the lenslets' transmission (x the lit lattice class), complex64 as the camera's FFT takes it,
        built a chunk of rows at a time."""
        out = np.empty(field.E.shape, np.complex64)
        for c in _row_chunks(len(field.x)):
            v = field.E[c] * transmission(c)
            if lit_x is not None:
                v = v * (lit_y[c, None] & lit_x[None, :])
            out[c] = v
        return out

    k = cfg.lit_stride
    if k == 1:
        inten = _camera_intensity(transmitted(), field.x, f, lam, cfg.samples_per_pixel, cfg.oversample, fresnel)
        return spot_centroids(inten, *args, start, cfg.window(sensor), cfg.cut(sensor), cfg.tracking_iterations)
    p = sensor.pitch_mm
    ix = np.rint(field.x / p).astype(int) % k  # lattice class of the lenslet each sample belongs to
    jx = np.rint(centres / p).astype(int) % k
    out = np.empty_like(start)
    for a in range(k):
        for b in range(k):
            mine = (jx[:, 0] == a) & (jx[:, 1] == b)
            if not mine.any():
                continue
            inten = _camera_intensity(transmitted(ix == a, ix == b), field.x, f, lam, cfg.samples_per_pixel,
                                      cfg.oversample, fresnel)
            out[mine] = spot_centroids(inten, *args, start[mine], cfg.window(sensor), cfg.cut(sensor),
                                       cfg.tracking_iterations)
    return out


@lru_cache(maxsize=16)
def _reference_cached(bench: Bench, cfg: PhysicalSensor, centres_key: bytes, n: int) -> np.ndarray:
    centres = np.frombuffer(centres_key).reshape(n, 2)
    field = plane_field(bench, cfg, centres, gaussian=(cfg.reference == "beam"))
    out = _centroids_of(field, bench, cfg, centres)
    out.setflags(write=False)
    return out


def reference_centroids(bench: Bench, cfg: PhysicalSensor, centres: np.ndarray) -> np.ndarray:
    """Reference spot centroids (n, 2) mm of the pupil lenslets ``centres``: 'factory' (uniform plane wave,
    normal incidence) or 'beam' (the bench's Gaussian laser, no lens), through the same model."""
    c = np.ascontiguousarray(centres, dtype=float)
    return _reference_cached(bench, cfg, c.tobytes(), len(c))


def field_slopes(field: MlaField, bench: Bench, cfg: PhysicalSensor, centres: np.ndarray,
                 reference: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(slopes (n, 2) rad, centroids (n, 2) mm, reference (n, 2) mm) of a field on the lenslet plane."""
    ref = reference_centroids(bench, cfg, centres) if reference is None else np.asarray(reference, float)
    cen = _centroids_of(field, bench, cfg, centres, start_mm=ref + cfg.focal(bench.sensor) * field.expected_slopes)
    # the device divides by its stored (calibrated) focal length, the bench's: a true one that differs
    # (cfg.focal_mm) scales every reported slope by f_true / f_bench, the gain calibrate can estimate
    return (cen - ref) / bench.sensor.lenslet_focal_mm, cen, ref


def physical_measure(model: ForwardModel, pose, cfg: PhysicalSensor | None = None,
                     reference: np.ndarray | None = None) -> PhysicalMeasurement:
    """What the physical sensor reports for the model's lens at ``pose`` (6,) (mm, rad): noise-free.

    reference: user reference centroids (n, 2) mm (default: ``cfg.reference``'s field)."""
    cfg = cfg or PhysicalSensor()
    field = ray_field(model, pose, cfg)
    slopes, cen, ref = field_slopes(field, model.bench, cfg, model.pupil.centres, reference)
    valid = bool(model.evaluate(np.asarray(pose, float)[None], check_range=False).valid[0])
    return PhysicalMeasurement(model.pupil.fit(slopes), slopes, cen, ref,
                               (field.residual_rms * 1e6, field.residual_max * 1e6), valid)


def physical_session_slopes(model: ForwardModel, poses, cfg: PhysicalSensor | None = None,
                            tick: Callable[[], None] | None = None) -> np.ndarray:
    """Noise-free physical slopes (P, n, 2) at poses (P, 6); ``tick()`` after each pose (progress)."""
    out = []
    for x in np.atleast_2d(np.asarray(poses, float)):
        out.append(physical_measure(model, x, cfg).slopes)
        if tick is not None:
            tick()
    return np.array(out)


