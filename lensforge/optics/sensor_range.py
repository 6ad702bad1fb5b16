"""Whether the sensor can still measure a lenslet: its spot must stay assignable.

* window: the spot's main lobe (half-width g = lambda f / p, first zero of the
  square aperture's sinc^2) must stay where the software can assign it
  (``sensor.spot_assignment``):
  - 'fixed': inside the lenslet's own p x p window, |f s_x|, |f s_y| <= p/2 - g;
  - 'tracking': neighbouring spots must not overlap, p + f (s_b - s_a) >= 2 g along
    each axis for adjacent lenslets a, b (local wavefront curvature limit), and every
    spot stays on the camera, |c + f s| <= aperture/2 - g;
  - 'none': no check.
  ``range_use`` expresses each rule as a fraction of its limit (<= 1: in range), so a
  design constraint can ask for a margin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .bench import Sensor

__all__ = ["spot_guard_mm", "range_use", "SensorRange", "summarize_range"]


def spot_guard_mm(sensor: Sensor, wavelength_nm: float) -> float:
    """Half-width of the spot's main lobe, lambda f / p (mm): the window guard."""
    return wavelength_nm * 1e-6 * sensor.lenslet_focal_mm / sensor.pitch_mm


def range_use(sensor: Sensor, wavelength_nm: float, centres: np.ndarray, neighbours: np.ndarray,
              slopes: np.ndarray) -> np.ndarray:
    """(P, n) fraction of the spot-assignment limit each lenslet uses (<= 1: assignable).

    centres: (n, 2) mm; neighbours: (k, 3) rows (a, b, axis) of adjacent pupil lenslets
    with b one pitch after a along axis; slopes: (P, n, 2) rad (centroid slopes).
    """
    f, p = sensor.lenslet_focal_mm, sensor.pitch_mm
    g = spot_guard_mm(sensor, wavelength_nm)
    shift = f * np.asarray(slopes)  # spot displacement on the camera, mm
    if sensor.spot_assignment == "none":
        return np.zeros(shift.shape[:-1])
    if sensor.spot_assignment == "fixed":
        return np.max(np.abs(shift), axis=-1) / (0.5 * p - g)
    # tracking: neighbouring main lobes must not overlap; spots stay on the camera
    use = np.max(np.abs(centres + shift), axis=-1) / (0.5 * sensor.aperture_mm - g)
    if len(neighbours):
        a, b, ax = neighbours[:, 0], neighbours[:, 1], neighbours[:, 2]
        closing = -(shift[:, b, ax] - shift[:, a, ax]) / (p - 2.0 * g)
        pair = np.zeros_like(use)
        for idx in (a, b):
            np.maximum.at(pair, (slice(None), idx), closing)
        use = np.maximum(use, pair)
    return use


@dataclass(frozen=True)
class SensorRange:
    """Sensor range at one pose: ok (every pupil lenslet assignable), max_slope_mrad
    (largest centroid slope component), lenslets_out (count), max_use (largest fraction
    of the assignment limit), model (sensor.spot_assignment), window_limit_mrad (the
    fixed-window slope limit (p/2 - g)/f, for reference)."""

    ok: bool
    max_slope_mrad: float
    lenslets_out: int
    max_use: float
    model: str
    window_limit_mrad: float

    def to_dict(self) -> dict:
        return {"ok": bool(self.ok), "max_slope_mrad": float(self.max_slope_mrad),
                "lenslets_out": int(self.lenslets_out), "max_use": float(self.max_use),
                "model": self.model, "window_limit_mrad": float(self.window_limit_mrad)}


def summarize_range(sensor: Sensor, wavelength_nm: float, slopes: np.ndarray, use: np.ndarray) -> SensorRange:
    """SensorRange of one pose from its (n, 2) slopes and (n,) range use."""
    g = spot_guard_mm(sensor, wavelength_nm)
    return SensorRange(
        ok=bool(np.all(use <= 1.0)), max_slope_mrad=float(np.max(np.abs(slopes)) * 1e3),
        lenslets_out=int(np.sum(use > 1.0)), max_use=float(np.max(use)), model=sensor.spot_assignment,
        window_limit_mrad=(0.5 * sensor.pitch_mm - g) / sensor.lenslet_focal_mm * 1e3,
    )
