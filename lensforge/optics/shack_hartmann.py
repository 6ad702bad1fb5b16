"""Shack-Hartmann sensor model: lenslet centroid slopes in a fixed pupil -> Zernike coefficients.

The sensor samples the wavefront at each lenslet of a fixed circular pupil in {S}
(centre and radius from the bench). Each lenslet reports its spot centroid: the
irradiance-weighted mean slope over its square sub-aperture (``centroid.py``
documents the centroid model). lensforge aims one beam ray at each point of a
Gauss-Legendre rule over every sub-aperture (Newton iteration on the beam
coordinates, ``trace.aim_rays``), so the model varies smoothly with the pose and
finite differences of it are clean. The local Jacobian of the beam-to-sensor map
gives the irradiance at each point (flux conservation):
I = I_beam(u, v) / |det d(X, Y)/d(u, v)|; a lenslet is lit when its mean irradiance
is at least ``sensor.irradiance_threshold`` times the input peak, and assignable
while its spot stays within the sensor's spot-assignment range
(``sensor.spot_assignment``). A pose is valid when every pupil lenslet is traced,
lit and assignable.

Zernike fit (DESIGN.md): W in um of OPD, dW/dx = L/N, dW/dy = M/N, Noll modes
2..N of the sensor's radial order over the pupil (piston is not measurable), by
least squares z = F s with the fit matrix F = pinv(G) computed once per pupil
(G holds the modes' gradients at the lenslet centres).
Sensor noise: independent Gaussian slope noise sigma per lenslet and axis, so
cov(z) = sigma^2 F F^T.
"""

from __future__ import annotations

from numpy.typing import ArrayLike

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

from ..errors import PoseRangeError, PupilError, SensorRangeError, TraceError
from .bench import Bench, Sensor
from .lens import Lens
from .centroid import (LOCAL_INPUTS, axis_neighbours, cell_crosstalk_slopes, centroid_slope_derivatives,
                       centroid_slopes, crosstalk_slope_derivatives, crosstalk_slopes, cubic_gain, cubic_slopes,
                       lit_lenslets, quadrature_rule, window_gain)
from .sensor_range import SensorRange, range_use, summarize_range
from .trace import (AIM_TOL, CLIPPED, MISSED, OK, STATUS_NAMES, TIR, LensTangents, aim_rays, aimed_tangents,
                    lens_kernel, trace_rays)
from .zernike import modes_up_to_order, zernike_gradient

# step (mm) of the forward differences in the beam coordinates that give the ray map's second
# derivatives (for d|det|/dq, ~1 % of dz/dq): truncation ~ step times the third over the second
# derivative (1e-6 relative; 3e-4 for a 25 um layer ripple), rounding ~1e-16 / step (1e-10)
_UV_STEP = 1e-6

__all__ = ["LensletPupil", "lenslet_pupil", "ForwardModel", "ZernikeResult", "measure", "check_pose_range"]


@dataclass(frozen=True, eq=False)
class LensletPupil:
    """The fixed lenslet set of the Zernike pupil and its fit matrices.

    centres: (n, 2) lenslet centres in {S} (mm); modes: Noll indices fitted;
    G: (2n, m) slopes [sx..., sy...] (rad) per um of each coefficient;
    F: (m, 2n) least-squares fit matrix (um per rad); radius_mm, center_mm: pupil;
    neighbours: (k, 3) rows (a, b, axis): pupil lenslet b is one pitch after a along axis.
    """

    centres: np.ndarray
    modes: np.ndarray
    G: np.ndarray
    F: np.ndarray
    radius_mm: float
    center_mm: tuple
    neighbours: np.ndarray

    @property
    def n_lenslets(self) -> int:
        return self.centres.shape[0]

    def fit(self, slopes: np.ndarray) -> np.ndarray:
        """Zernike coefficients (..., m) in um from slopes (..., n, 2) in rad."""
        s = np.concatenate([slopes[..., 0], slopes[..., 1]], axis=-1)
        return s @ self.F.T

    def noise_covariance(self, slope_sigma_rad: float) -> np.ndarray:
        """Covariance (m, m) of the fitted coefficients (um^2) for i.i.d. slope noise."""
        return slope_sigma_rad**2 * (self.F @ self.F.T)


@lru_cache(maxsize=64)
def lenslet_pupil(sensor: Sensor) -> LensletPupil:
    """Lenslets whose centres lie inside the pupil, and the Zernike fit matrix."""
    n_side = int(np.floor(sensor.aperture_mm / sensor.pitch_mm + 1e-9))
    coords = sensor.pitch_mm * (np.arange(n_side) - 0.5 * (n_side - 1))
    X, Y = np.meshgrid(coords, coords, indexing="xy")
    cx, cy = (float(v) for v in sensor.pupil_center_mm)
    a = sensor.pupil_radius_mm
    inside = (X - cx) ** 2 + (Y - cy) ** 2 <= a * a
    centres = np.stack([X[inside], Y[inside]], axis=1)
    modes = modes_up_to_order(sensor.zernike_order)
    rx, ry = (centres[:, 0] - cx) / a, (centres[:, 1] - cy) / a
    gx = np.empty((len(centres), len(modes)))
    gy = np.empty_like(gx)
    for col, j in enumerate(modes):
        gx[:, col], gy[:, col] = zernike_gradient(j, rx, ry)
    # W (um) over x (mm): slope = 1e-3 * dW/dx_mm = 1e-3 / a * dZ/drho
    G = 1e-3 / a * np.vstack([gx, gy])
    if np.linalg.matrix_rank(G) < len(modes):
        raise PupilError(
            f"sensor.pupil_radius_mm: {len(centres)} lenslets cannot resolve {len(modes)} Zernike modes; "
            "enlarge the pupil or lower sensor.zernike_order"
        )
    F = np.linalg.pinv(G)
    index = -np.ones(X.shape, dtype=np.int64)
    index[inside] = np.arange(len(centres))
    pairs = []
    for axis, (ia, ib) in enumerate([(index[:, :-1], index[:, 1:]), (index[:-1, :], index[1:, :])]):
        both = (ia >= 0) & (ib >= 0)
        pairs.append(np.stack([ia[both], ib[both], np.full(both.sum(), axis)], axis=1))
    neighbours = np.concatenate(pairs)
    for arr in (centres, G, F, neighbours):
        arr.setflags(write=False)
    return LensletPupil(centres, modes, G, F, a, (cx, cy), neighbours)


def check_pose_range(bench: Bench, poses) -> None:
    """Raise PoseRangeError if any pose lies outside the bench's valid range."""
    poses = np.atleast_2d(poses)
    lim = bench.pose_limits
    bad_t = np.abs(poses[:, :3]) > lim.translation_mm
    bad_r = np.linalg.norm(poses[:, 3:], axis=1) > lim.rotation_rad
    if np.any(~np.isfinite(poses)):
        raise PoseRangeError("pose: contains NaN or inf")
    if bad_t.any():
        p = poses[np.argwhere(bad_t)[0, 0]]
        raise PoseRangeError(
            f"pose: translation {np.round(p[:3], 4).tolist()} mm exceeds bench.pose_limits.translation_mm = "
            f"{lim.translation_mm}; move the lens closer to nominal or widen the limit"
        )
    if bad_r.any():
        p = poses[np.argmax(bad_r)]
        raise PoseRangeError(
            f"pose: rotation {np.degrees(np.linalg.norm(p[3:])):.3g} deg exceeds bench.pose_limits.rotation_rad = "
            f"{lim.rotation_rad:.4g} rad; bring the lens closer to nominal or widen the limit"
        )


@dataclass(frozen=True)
class ZernikeResult:
    """Forward-model output for P poses.

    z: (P, m) Zernike coefficients (um, Noll modes ``modes``); slopes: (P, n, 2) rad
    centroid slopes (centroid.py); irradiance: (P, n) sub-aperture mean relative
    to the input beam peak; status: (P, n) ray codes (worst over the sub-aperture);
    valid: (P,) all lenslets traced, lit and assignable; uv: (P, n*q, 2) aimed beam
    coordinates of the q quadrature points per lenslet (warm start for nearby poses);
    rays_traced: total rays traced; range_use: (P, n) fraction of the spot-assignment
    limit used (<= 1: in the sensor's range); spot_model: sensor.spot_assignment; windows:
    (P, n, 2) first pixels of the centroid windows on a cross-talk bench (None otherwise), to
    freeze them (``ForwardModel.evaluate``).
    """

    z: np.ndarray
    slopes: np.ndarray
    irradiance: np.ndarray
    status: np.ndarray
    valid: np.ndarray
    uv: np.ndarray
    rays_traced: int
    threshold: float
    range_use: np.ndarray | None = None
    spot_model: str = "none"
    windows: np.ndarray | None = None

    @property
    def in_range(self) -> np.ndarray:
        """(P, n) True where the lenslet's spot can be assigned."""
        return np.ones(self.irradiance.shape, bool) if self.range_use is None else self.range_use <= 1.0

    def reason(self, p: int = 0) -> str:
        """Why pose p is invalid ('' if valid)."""
        if self.valid[p]:
            return ""
        st = self.status[p]
        bad = st != OK
        if bad.any():
            codes, counts = np.unique(st[bad], return_counts=True)
            worst = codes[np.argmax(counts)]
            return f"{counts.sum()} of {st.size} pupil lenslets not reached: {STATUS_NAMES[int(worst)]}"
        low = self.irradiance[p] < self.threshold
        if low.any():
            return (
                f"pupil under-filled: {low.sum()} of {low.size} lenslets below the irradiance threshold "
                f"(min {self.irradiance[p].min():.3g} of beam peak, threshold {self.threshold:.3g})"
            )
        out = ~self.in_range[p]
        return (
            f"out of sensor range: the spots of {out.sum()} of {out.size} pupil lenslets cannot be assigned "
            f"('{self.spot_model}' spot assignment, up to {self.range_use[p].max():.3g} x its limit; "
            f"max slope {np.abs(self.slopes[p]).max() * 1e3:.3g} mrad)"
        )

    def raise_if_invalid(self) -> None:
        """Raise TraceError/PupilError for the first invalid pose."""
        for p in np.flatnonzero(~self.valid):
            st = self.status[p]
            msg = self.reason(p)
            if np.any(st == TIR):
                raise TraceError(f"{msg} at pose {p}; reduce surface slopes or the lens tilt")
            if np.any((st == CLIPPED) | (st == MISSED)):
                raise TraceError(f"{msg} at pose {p}; enlarge the lens aperture or re-centre the beam")
            if np.any(self.irradiance[p] < self.threshold):
                raise PupilError(
                    f"{msg} at pose {p}: the beam misses or under-fills the sensor pupil; "
                    "change sensor.pupil_radius_mm/pupil_center_mm or placement.distance_mm"
                )
            raise SensorRangeError(
                f"{msg} at pose {p}; move the lens closer to the sensor (placement.distance_mm), shrink "
                "sensor.pupil_radius_mm, or use a lens with weaker wavefront slopes"
            )


_CELL_DIRECTIONS = 4  # directions per complex-step pass of the 'cells' model (bounds its memory)


class ForwardModel:
    """z = h(x, p) for one bench and lens: the posed lens -> SH Zernike coefficients.

    Holds the packed lens and the fixed pupil; stateless otherwise, so it can be
    shared between threads and pickled to workers. ``evaluate(poses)`` gives a
    ZernikeResult, ``zernike(poses, rng)`` the (noisy) vector, ``jacobians(poses)`` the
    exact dz/dx.

    Parameters
    ----------
    bench : Bench
        Laser, placement, sensor, noise and pose limits.
    lens : Lens
        The lens (mm).
    validate : bool
        Check the lens first (LensGeometryError when it is not physical).
    quadrature : (offsets (q, 2) in pitches, weights (q,) summing to 1), optional
        The centroid's rule over each lenslet (default ``quadrature_rule`` of
        ``sensor.subaperture_quadrature`` over the square; a diagnostic may give another aperture's).
    """

    def __init__(self, bench: Bench, lens: Lens, validate: bool = True, quadrature=None):
        self.bench = bench
        self.lens = lens.validate() if validate else lens
        self.kernel = lens_kernel(lens, bench.laser.wavelength_nm)
        self.pupil = lenslet_pupil(bench.sensor)
        off, w = quadrature_rule(bench.sensor.subaperture_quadrature) if quadrature is None else quadrature
        self.quad_offsets, self.quad_weights = off, w
        self.window_gain = window_gain(bench.sensor, bench.laser.wavelength_nm)
        # the added coma term's gains (``_cubic``); (1, 1), no term, with 'cells', whose kernel renders every
        # lenslet's coma in its window (``centroid._coma_factors``)
        self.cubic_gain = (1.0, 1.0) if self._cells else cubic_gain(bench.sensor, bench.laser.wavelength_nm)
        # the traced lenslets: the pupil's, and with the 'cells' cross-talk model every lenslet lit within its
        # rings of the pupil (their fields reach the pupil's windows), the pupil's first (``lit_lenslets``)
        if self._cells:
            self.lit_centres, self.lit_neighbours = lit_lenslets(bench.sensor, self.pupil.centres)
        else:
            self.lit_centres, self.lit_neighbours = self.pupil.centres, None
        self.n_traced = len(self.lit_centres)
        self.axis_neighbours = axis_neighbours(self.lit_centres, bench.sensor.pitch_mm)
        # aim targets: the quadrature points of every traced lenslet, lenslet-major (L * q, 2)
        self.targets = np.ascontiguousarray(
            (self.lit_centres[:, None, :] + bench.sensor.pitch_mm * off[None, :, :]).reshape(-1, 2))

    @property
    def modes(self) -> np.ndarray:
        return self.pupil.modes

    @cached_property
    def own_centroid_model(self) -> "ForwardModel":
        """The same bench and lens with each lenslet's own centroid only (``sensor.crosstalk`` 'none'): this model
        itself when it has no cross-talk. Hundreds of times cheaper than 'cells'; a cross-talk fit iterates on it
        with the cross-talk's correction frozen (``pose_estimation.estimate_poses_batch``)."""
        if self._own_centroid:
            return self
        return ForwardModel(self.bench.own_centroid(), self.lens, validate=False)

    @cached_property
    def noise_cov(self) -> np.ndarray:
        """Zernike noise covariance R (m, m) in um^2."""
        return self.pupil.noise_covariance(self.bench.noise.slope_sigma_urad * 1e-6)

    @cached_property
    def whitener(self) -> np.ndarray:
        """L^-1 with R = L L^T (1/um): whitened residuals w = L^-1 (z - h(x)) have unit covariance."""
        return np.linalg.inv(np.linalg.cholesky(self.noise_cov))

    def evaluate(self, poses: ArrayLike, uv0: ArrayLike | None = None, check_range: bool = True,
                 windows: np.ndarray | None = None) -> ZernikeResult:
        """Noise-free Zernike coefficients for poses (P, 6); never raises on bad rays. windows: the
        cross-talk model's centroid windows (P, n, 2) frozen (a previous result's ``windows``):
        its whole-pixel placement then does not jump within a fit's linearisation."""
        return self._zernike(self._aim(poses, uv0, check_range), windows)

    def _aim(self, poses, uv0, check_range: bool) -> dict:
        """The aimed quadrature rays at poses: uv (P, n*q, 2), slopes sq (P, n, q, 2),
        status st (P, n, q), irradiance irr (P, n*q) of the beam over |det|, rays traced."""
        poses = np.atleast_2d(np.asarray(poses, dtype=float))
        if check_range:
            check_pose_range(self.bench, poses)
        uv, sq, det, st, n = aim_rays(self.bench, self.lens, poses, self.targets, u0=uv0, kernel=self.kernel)
        P, q = uv.shape[0], self.quad_weights.size
        with np.errstate(divide="ignore", invalid="ignore"):
            irr = self._beam(uv) / det
        n_l = self.n_traced  # explicit: P may be 0
        return {"poses": poses, "uv": uv, "sq": sq.reshape(P, n_l, q, 2), "st": st.reshape(P, n_l, q), "irr": irr,
                "n": n}

    def _beam(self, uv: np.ndarray) -> np.ndarray:
        """Input irradiance (relative to its peak) of the Gaussian beam at beam coordinates uv (..., 2)."""
        w = 0.5 * self.bench.laser.beam_diameter_mm
        return np.exp(-2.0 * (uv[..., 0] ** 2 + uv[..., 1] ** 2) / (w * w))

    def _weights(self, a: dict) -> np.ndarray:
        """w_q I_q (P, n, q): the centroid weights of the traced quadrature rays (0 where a ray failed)."""
        P, n_l, q = a["st"].shape
        return np.where(a["st"] == OK, a["irr"].reshape(P, n_l, q), 0.0) * self.quad_weights

    @property
    def crosstalk(self) -> bool:
        """The centroids see the neighbours' cross-talk (``sensor.crosstalk``, a pixel window): an
        exact Jacobian then costs ~9 cross-talk kernel passes, an iteration one (``jacobians``,
        exact=False) none."""
        return not self._own_centroid

    @property
    def _own_centroid(self) -> bool:
        """Each lenslet's centroid depends on its own light only (no cross-talk model; window 0:
        the complete spot)."""
        sensor = self.bench.sensor
        return sensor.crosstalk == "none" or sensor.centroid_window_px == 0

    @property
    def _cells(self) -> bool:
        """The 'cells' cross-talk model: every window sees the fields of the lit lenslets around it, each from its
        own rays (``centroid.cell_crosstalk_slopes``)."""
        return self.bench.sensor.crosstalk == "cells" and not self._own_centroid

    def _centroids(self, sq, wi, windows=None, return_windows: bool = False):
        """Centroid slopes (..., n, 2) of the pupil lenslets from the traced lenslets' quadratures sq (..., L, q, 2)
        and weights wi (..., L, q): the window's centroid (``_window_centroids``) and its view of each lenslet's
        wavefront third derivatives (``_cubic``), which every sensor model shares."""
        s, st = self._window_centroids(sq, wi, windows)
        s = s + self._cubic(sq, wi)[..., :self.pupil.n_lenslets, :]
        return (s, st) if return_windows else s

    def _window_centroids(self, sq, wi, windows=None):
        """(slopes (..., n, 2), windows or None) of the bench's sensor model (``sensor.crosstalk``), without the
        cubic term."""
        sensor, wl = self.bench.sensor, self.bench.laser.wavelength_nm
        if self._cells:
            return cell_crosstalk_slopes(sq, wi, self.quad_offsets, self.quad_weights, self.lit_centres,
                                         self.lit_neighbours, sensor, wl, windows=windows, return_windows=True)
        s = centroid_slopes(sq, wi, self.quad_offsets, self.quad_weights, self.window_gain)
        if self._own_centroid:
            return s, None
        return crosstalk_slopes(s, sq, wi, self.quad_offsets, self.quad_weights, self.pupil.centres, sensor, wl,
                                windows=windows, return_windows=True)

    def _cubic(self, sq, wi) -> np.ndarray:
        """(..., L, 2) the window's view of each traced lenslet's wavefront third derivatives (``centroid.cubic_slopes``).
        Linear in sq: along directions dsq (..., d, L, q, 2) with wi (..., 1, L, q) it gives their derivatives.
        Zero with 'cells' (its ``cubic_gain`` is (1, 1))."""
        return cubic_slopes(sq, wi, self.quad_offsets, self.quad_weights, self.axis_neighbours,
                            self.bench.sensor.pitch_mm, self.cubic_gain)

    def _centroid_derivatives(self, sq, wi, dsq, dwi, exact: bool = True, windows=None) -> np.ndarray:
        """(P, d, n, 2): the centroids' derivatives along d directions of the quadrature slopes
        dsq (P, n, q, 2, d) and weights dwi (P, n, q, d): in closed form for the lenslet's own
        centroid; with the neighbours' cross-talk by a complex step through ``_window_centroids``
        (analytic in (sq, wi), so Im f(x + i e dx) / e = f'(x) dx exactly), or, for more than
        ``LOCAL_INPUTS`` directions, along the kernel's 8 inputs per lenslet, chained
        (``crosstalk_slope_derivatives``). exact=False: the own centroid's, cross-talk or not
        (an iteration Jacobian's: the cross-talk's part of the derivative, a few percent of the
        information, costs 8 kernel passes). The cubic term, linear in the slopes, is added once."""
        n = self.pupil.n_lenslets
        cubic = self._cubic(np.moveaxis(dsq, -1, 1), wi[:, None])[:, :, :n]
        return self._window_derivatives(sq, wi, dsq, dwi, exact, windows) + cubic

    def _window_derivatives(self, sq, wi, dsq, dwi, exact: bool, windows) -> np.ndarray:
        """(P, d, n, 2): ``_centroid_derivatives`` without the cubic term."""
        if self._own_centroid or not exact:
            n = self.pupil.n_lenslets
            ds = centroid_slope_derivatives(sq[:, :n], wi[:, :n], dsq[:, :n], dwi[:, :n], self.quad_offsets,
                                            self.quad_weights, self.window_gain)
            return np.moveaxis(ds, -1, 1)
        if self._cells:  # a window sees its neighbours' inputs too: a complex step along each direction
            eps, d = 1e-30, dsq.shape[-1]
            out = []
            for j in range(0, d, _CELL_DIRECTIONS):
                k = slice(j, j + _CELL_DIRECTIONS)
                sq_c = sq[:, None] + 1j * eps * np.moveaxis(dsq[..., k], -1, 1)  # (P, d', L, q, 2)
                wi_c = wi[:, None] + 1j * eps * np.moveaxis(dwi[..., k], -1, 1)
                w_ = None if windows is None else np.broadcast_to(windows[:, None], (sq.shape[0], sq_c.shape[1])
                                                                  + windows.shape[1:])
                out.append(self._window_centroids(sq_c, wi_c, w_)[0].imag / eps)
            return np.concatenate(out, axis=1)
        if dsq.shape[-1] > LOCAL_INPUTS:  # more directions than the kernel has inputs: chain through them
            ds = crosstalk_slope_derivatives(sq, wi, dsq, dwi, self.quad_offsets, self.quad_weights, self.window_gain,
                                             self.pupil.centres, self.bench.sensor, self.bench.laser.wavelength_nm,
                                             windows=windows)
            return np.moveaxis(ds, -1, 1)
        eps = 1e-30
        sq_c = sq[:, None] + 1j * eps * np.moveaxis(dsq, -1, 1)  # (P, d, n, q, 2)
        wi_c = wi[:, None] + 1j * eps * np.moveaxis(dwi, -1, 1)  # (P, d, n, q)
        return self._window_centroids(sq_c, wi_c, None if windows is None else windows[:, None])[0].imag / eps

    def _zernike(self, a: dict, windows=None) -> ZernikeResult:
        sensor = self.bench.sensor
        n = self.pupil.n_lenslets
        wi = self._weights(a)
        irr_mean = wi[:, :n].sum(axis=2)
        slopes, windows = self._centroids(a["sq"], wi, windows, return_windows=True)
        status = a["st"][:, :n].max(axis=2)  # OK (0) only if every quadrature ray is OK
        slopes = np.where((status == OK)[..., None] & (irr_mean > 0)[..., None], slopes, 0.0)
        thr = sensor.irradiance_threshold
        use = range_use(sensor, self.bench.laser.wavelength_nm, self.pupil.centres, self.pupil.neighbours, slopes)
        valid = np.all(status == OK, axis=1) & np.all(irr_mean >= thr, axis=1) & np.all(use <= 1.0, axis=1)
        z = self.pupil.fit(slopes)
        return ZernikeResult(z, slopes, irr_mean, status, valid, a["uv"], a["n"], thr, use, sensor.spot_assignment,
                             windows)

    def jacobians(self, poses: ArrayLike, uv0: ArrayLike | None = None, check_range: bool = False,
                  lens_tangents: LensTangents | None = None, exact: bool = True,
                  windows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None, ZernikeResult]:
        """Exact dz/dx (P, m, 6) at poses (P, 6) (um per mm, um per rad), dz along each of the
        l lens tangents (P, m, l) (None without them) and the model at the poses.

        Each aimed ray stays on its target: with the ray map's derivatives J = d(X, Y)/d(u, v)
        and d(X, Y)/dq along a direction q (``trace_rays``) the aimed beam coordinates move by
        du/dq = -J^-1 dX/dq (implicit function theorem), and its slope by
        ds/dq + ds/d(u, v) du/dq. The irradiance weights I = I_beam(u) / |det J| move with
        u and with det J, whose derivative needs second derivatives of the ray map: those
        come from differences in u and v (step ``_UV_STEP``) of the exact first derivatives,
        with d/dq (dX/du) = d/du (dX/dq) (symmetry of second derivatives), so two traced
        copies of each aimed ray give every direction (``aimed_tangents``). The centroid's
        derivative is exact (``_centroid_derivatives``); the Zernike fit is linear. uv0: the
        rays aimed at x by a previous evaluation (used as they are when every one still lands
        within ``AIM_TOL``, else the start of a new aim); windows: frozen centroid windows
        (``evaluate``). exact=False
        leaves out the change of det J (the irradiance weights then move with the beam profile
        only), traces the aimed rays alone, ~2.5x cheaper, and on a cross-talk bench takes the
        own centroid's derivatives (``_centroid_derivatives``; ~9x cheaper there): an iteration
        Jacobian (a few 1e-3 off, ``aimed_tangents``; a few 1e-2 with cross-talk), never a
        covariance's.
        """
        x = np.atleast_2d(np.asarray(poses, dtype=float))
        if check_range:
            check_pose_range(self.bench, x)
        P, N = x.shape[0], self.targets.shape[0]
        # the aimed rays and, for the second derivatives, each displaced by _UV_STEP in u and in v:
        # one trace of 3 P poses, d(X, Y, sx, sy) along u, v, the six pose directions and the lens tangents
        shifts = (np.array([[0, 0], [1, 0], [0, 1]]) * _UV_STEP)[:3 if exact else 1]

        def derivatives(uv):
            return trace_rays(self.bench, self.lens, np.tile(x, (len(shifts), 1)),
                              (uv[None] + shifts[:, None, None]).reshape(-1, N, 2), kernel=self.kernel,
                              pose_derivatives=True, lens_tangents=lens_tangents)

        t = None
        if uv0 is not None:  # a previous evaluation's rays at x: the first trace checks they still land
            uv = np.array(np.broadcast_to(uv0, (P, N, 2)), dtype=float)
            t = derivatives(uv)
            landed = (t.status[:P] == OK) & np.all(np.abs(t.xy[:P] - self.targets) < AIM_TOL, axis=-1)
            if landed.all():  # the aim's record, from the first trace (irradiance once det J is known)
                n_l, q = self.n_traced, self.quad_weights.size
                a = {"poses": x, "uv": uv, "sq": t.slopes[:P].reshape(P, n_l, q, 2),
                     "st": t.status[:P].reshape(P, n_l, q), "irr": None, "n": P * N}
            else:
                t = None
        if t is None:
            a = self._aim(x, uv0, False)
            uv = a["uv"]
            t = derivatives(uv)
        P3 = t.all_derivatives.reshape(len(shifts), P, N, 4, t.all_derivatives.shape[-1])
        # J = d(X, Y)/d(u, v)
        j00, j01, j10, j11 = P3[0, ..., 0, 0], P3[0, ..., 0, 1], P3[0, ..., 1, 0], P3[0, ..., 1, 1]
        if a["irr"] is None:
            with np.errstate(divide="ignore", invalid="ignore"):
                a["irr"] = self._beam(uv) / np.abs(j00 * j11 - j01 * j10)
        res = self._zernike(a, windows)
        irr = np.where(np.isfinite(a["irr"]), a["irr"], 0.0)  # a failed ray has no weight (nor derivative)
        dsq, dirr = aimed_tangents(t, P, uv, irr, self.bench.laser.beam_diameter_mm, _UV_STEP)
        nq = dirr.shape[-1]  # directions q: pose, then lens
        _, n_l, q = a["st"].shape
        good = a["st"] == OK  # rays whose trace failed have zero tangents already (``aimed_tangents``)
        wi = self._weights(a)
        dwi = np.where(good[..., None], dirr.reshape(P, n_l, q, nq), 0.0) * self.quad_weights[:, None]
        dsq = np.where(good[..., None, None], dsq.reshape(P, n_l, q, 2, nq), 0.0)
        ds = self._centroid_derivatives(a["sq"], wi, dsq, dwi, exact, res.windows)  # (P, nq, n, 2): the value's windows
        lit = (res.status == OK) & (res.irradiance > 0)
        ds = np.where(lit[:, None, :, None], ds, 0.0)
        Jall = np.swapaxes(self.pupil.fit(ds), 1, 2)  # (P, m, nq)
        return Jall[..., :6], (Jall[..., 6:] if lens_tangents is not None else None), res

    def sensor_range(self, pose: ArrayLike | None = None) -> SensorRange:
        """Spot-assignment summary at ``pose`` (default nominal): ok, max slope, lenslets out."""
        res = self.evaluate(np.zeros(6) if pose is None else pose, check_range=False)
        return summarize_range(self.bench.sensor, self.bench.laser.wavelength_nm, res.slopes[0], res.range_use[0])

    def zernike(self, poses: ArrayLike, rng: np.random.Generator | None = None) -> np.ndarray:
        """Zernike coefficients (P, m) or (m,) in um; raises if any pose is not measurable.

        With an rng, slope noise of the bench's noise model is added before the fit.
        """
        poses = np.asarray(poses, dtype=float)
        res = self.evaluate(poses)
        res.raise_if_invalid()
        z = res.z if rng is None else self.add_noise(res, rng)
        return z[0] if poses.ndim == 1 else z

    def noisy_slopes(self, res: ZernikeResult, rng: np.random.Generator) -> np.ndarray:
        """The lenslet slopes (P, n, 2) in rad the sensor measures for a noise-free result: its
        slopes plus the bench's slope noise (``noise.slope_sigma_urad``, drawn for every lenslet
        of every pose, lit or not, so that a pose's draw does not depend on the others'). The one
        noisy measurement of every simulation."""
        sigma = self.bench.noise.slope_sigma_urad * 1e-6
        return res.slopes + rng.normal(0.0, sigma, res.slopes.shape)

    def add_noise(self, res: ZernikeResult, rng: np.random.Generator) -> np.ndarray:
        """The Zernike vectors (P, m) in um the sensor reports: ``noisy_slopes`` fitted over the pupil."""
        return self.pupil.fit(self.noisy_slopes(res, rng))

    def measure_noisy(self, poses: ArrayLike, rng: np.random.Generator
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(z (P, m) um, lit (P,) bool, slopes (P, n, 2) rad): noisy Zernike vectors at poses
        (P, 6), which poses the sensor can measure (pupil lit, in range) and the noisy lenslet
        slopes they were fitted from (``noisy_slopes``); never raises on a dark pose."""
        res = self.evaluate(poses, check_range=False)
        slopes = self.noisy_slopes(res, rng)
        return self.pupil.fit(slopes), np.asarray(res.valid, bool), slopes


def measure(bench: Bench, lens: Lens, pose: ArrayLike | None = None, rng: np.random.Generator | None = None) -> np.ndarray:
    """The Zernike vector the SH sensor reports for the lens at a pose.

    Parameters
    ----------
    bench : Bench
        The bench.
    lens : Lens
        The lens.
    pose : array_like, shape (6,) or (P, 6), optional
        Pose vector(s) (tx, ty, tz in mm; rx, ry, rz rotation vector in rad) relative to the
        nominal placement (default: nominal).
    rng : numpy.random.Generator, optional
        When given, slope noise of ``bench.noise`` is added before the Zernike fit.

    Returns
    -------
    numpy.ndarray, shape (m,) or (P, m)
        Coefficients in um of wavefront, Noll modes 2.. (piston is never part of z),
        RMS-normalised.

    Raises
    ------
    PupilError, SensorRangeError, TraceError, PoseRangeError
        A pose at which the lens cannot be measured (unlit pupil, spot out of range,
        rays lost, pose out of the bench's limits).
    """
    pose = np.zeros(6) if pose is None else pose
    return ForwardModel(bench, lens).zernike(pose, rng=rng)
