"""How numbers are shown to a person: one spelling for an unobservable value, units in labels.

JSON keeps numbers (``null`` for an infinite bound); console tables go through these
helpers so every command shows an unobservable pose direction the same way.
"""

from __future__ import annotations

import math

__all__ = ["UNOBSERVABLE", "UNOBSERVABLE_NOTE", "fmt_bound", "crlb_columns", "crlb_cells"]

UNOBSERVABLE = "unobs."
UNOBSERVABLE_NOTE = ("unobs. = unobservable: the predicted 1-sigma is infinite (rank lost) or above the "
                     "bench's pose scale (default 1 mm, 1 deg), so the sensor cannot measure that DOF")

_DOF = ("tx", "ty", "tz", "rx", "ry", "rz")
_KEYS = tuple(f"{d}_um" for d in _DOF[:3]) + tuple(f"{d}_urad" for d in _DOF[3:])


def fmt_bound(value, unobservable: bool = False, spec: str = ".3g") -> str:
    """A bound or error for a table: ``unobs.`` when unobservable or infinite (None), else the number."""
    if unobservable or value is None or (isinstance(value, float) and not math.isfinite(value)):
        return UNOBSERVABLE
    return format(value, spec)


def crlb_columns(prefix: str = "CRLB ") -> list[str]:
    """Column labels of the per-DOF Cramer-Rao bound (1-sigma), with units."""
    return [f"{prefix}{d} ({'um' if i < 3 else 'urad'})" for i, d in enumerate(_DOF)]


def crlb_cells(crlb_std: dict | None, pose_scales=None, unobservable=()) -> list[str]:
    """Table cells of a metrics ``crlb_std`` dict (um, urad keys).

    A DOF is shown as unobservable when its bound is infinite, named in ``unobservable``, or
    above ``pose_scales`` (mm, rad; DESIGN.md's statistical rule)."""
    if not crlb_std:
        return ["-"] * 6
    out = []
    for i, (d, k) in enumerate(zip(_DOF, _KEYS)):
        v = crlb_std.get(k)
        over = False
        if pose_scales is not None and v is not None:
            over = v > pose_scales[i] * (1e3 if i < 3 else 1e6)
        out.append(fmt_bound(v, over or d in unobservable))
    return out
