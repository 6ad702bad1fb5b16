"""The lensforge exception hierarchy.

Every error a user can cause is a :class:`LensforgeError`; its message names the
field at fault and the fix, so that the CLI can print it on one line.
"""

from __future__ import annotations


class LensforgeError(Exception):
    """Base class of all errors a user can cause; the CLI prints it as one line ``error: ...``
    and exits 2.

    Parameters
    ----------
    message : str
        One line naming the file or field at fault and the fix.
    """


class ConfigError(LensforgeError, ValueError):
    """A bench, tolerance, design or pose file (or an argument) holds a bad key, type or value.

    Parameters
    ----------
    message : str
        One line naming the file and field at fault and the fix.
    """


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


class MissingDependencyError(LensforgeError, ImportError):
    """An optional part of lensforge is used without the extra that installs its libraries
    (``pip install 'lensforge[export]'`` brings the mesh and CAD stack)."""


class ExceptionWrapper:
    """Stands in for an optional module that failed to import, and raises only when used.

    The pattern is trimesh's (``trimesh.exceptions.ExceptionWrapper``): a module imports its
    optional dependency once at the top; when it is missing, the name is bound to this
    object instead, so the rest of the module (and everything that imports it) loads, and
    the first attribute access or call raises ``error`` with the import failure chained.

    Parameters
    ----------
    error : MissingDependencyError
        The error to raise on use (its message names the missing extra).
    cause : ImportError
        The original import failure (kept as ``__cause__``).
    """

    def __init__(self, error: MissingDependencyError, cause: ImportError) -> None:
        error.__cause__ = cause
        object.__setattr__(self, "_error", error)

    def __getattribute__(self, name: str):
        if name == "__class__":  # isinstance() and repr() keep working
            return ExceptionWrapper
        raise object.__getattribute__(self, "_error")

    def __call__(self, *args, **kwargs):
        raise object.__getattribute__(self, "_error")


class ModelCheckError(CalibrationError):
    """A fit ran but fails its chi2 model check: the data do not fit the model (exit status 3).

    Raised by the CLI after the diagnostics are written (``valid: false`` and the reason, no
    file a robot cell would load); the message names the likely mistake where one is found."""

    exit_code = 3
