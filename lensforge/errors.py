"""The lensforge exception hierarchy.

Every error a user can cause is a :class:`LensforgeError`; its message names the
field at fault and the fix, so that the CLI can print it on one line.
"""

from __future__ import annotations


class LensforgeError(Exception):
    """Base class of all errors a user can cause."""


class ConfigError(LensforgeError, ValueError):
    """A bench, tolerance, design or pose file holds a bad key, type or value."""


class LensGeometryError(LensforgeError, ValueError):
    """The lens is not physical (thickness, surfaces crossing, bad aperture)."""


class TraceError(LensforgeError, RuntimeError):
    """Rays cannot pass the lens: total internal reflection, missed surface, clipping."""


class PupilError(LensforgeError, RuntimeError):
    """The Shack-Hartmann pupil is not fully lit, or the beam misses the sensor."""


class SensorRangeError(PupilError):
    """A pupil lenslet's spot leaves the sensor's spot-assignment range (handled like a lost pupil)."""


class PoseRangeError(LensforgeError, ValueError):
    """A lens pose lies outside the bench's valid range."""


class RankError(LensforgeError, RuntimeError):
    """The sensitivity matrix has lost rank: some pose direction is unobservable."""


class DesignError(LensforgeError, RuntimeError):
    """A design problem is infeasible or an optimiser got bad settings."""


class CalibrationError(LensforgeError, RuntimeError):
    """Hand-eye data is malformed or the motion is degenerate."""


class ModelCheckError(CalibrationError):
    """A fit ran but fails its chi2 model check: the data do not fit the model (exit status 3).

    Raised by the CLI after the diagnostics are written (``valid: false`` and the reason, no
    file a robot cell would load); the message names the likely mistake where one is found."""

    exit_code = 3
