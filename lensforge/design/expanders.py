"""A small catalogue of real Galilean beam expanders a bench can put between laser and lens.

The registry ``EXPANDERS`` maps a name to an :class:`Expander`; adding one is one entry.
Sources: Thorlabs' achromatic Galilean beam expanders (GBE series, AR coated 400-650 nm,
which covers the CPS532-C2's 532 nm), whose part numbers give the magnification:
GBE02-A 2x, GBE03-A 3x, GBE05-A 5x (Thorlabs catalogue, "Achromatic Galilean Beam
Expanders"). Their largest input beams were not checked here (ASSUMPTION: the laser's
3.5 mm beam fits every entry). "none" is the bare laser.

A design may only choose an expander whose output beam (laser beam x magnification) fits
the WFS aperture (``fits``): a larger beam over-fills the sensor and wastes power without
adding lenslets.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import ConfigError

__all__ = ["Expander", "EXPANDERS", "expander", "fitting_expanders"]


@dataclass(frozen=True)
class Expander:
    """name, magnification (output / input beam diameter), source (where the value comes from)."""

    name: str
    magnification: float
    source: str


EXPANDERS = {e.name: e for e in (
    Expander("none", 1.0, "no expander: the laser's own beam"),
    Expander("GBE02-A", 2.0, "Thorlabs GBE02-A, 2x achromatic Galilean beam expander (part number)"),
    Expander("GBE03-A", 3.0, "Thorlabs GBE03-A, 3x achromatic Galilean beam expander (part number)"),
    Expander("GBE05-A", 5.0, "Thorlabs GBE05-A, 5x achromatic Galilean beam expander (part number)"),
)}


def expander(name: str) -> Expander:
    """The catalogue entry ``name`` ("" means "none"); ConfigError naming the choices otherwise."""
    key = name or "none"
    if key not in EXPANDERS:
        raise ConfigError(f"expander: unknown {name!r}; use one of {', '.join(EXPANDERS)} (design/expanders.py)")
    return EXPANDERS[key]


def fitting_expanders(laser_beam_mm: float, aperture_mm: float, names=None) -> tuple:
    """Names (of ``names``, default the whole catalogue) whose output beam fits the aperture."""
    names = tuple(EXPANDERS) if names is None else tuple(names)
    return tuple(n for n in names if expander(n).magnification * laser_beam_mm <= aperture_mm)
