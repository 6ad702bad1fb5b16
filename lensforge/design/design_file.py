"""The design file: one optimised (or evaluated) lens with everything that produced it.

JSON, ``schema_version`` 1. Keys: ``model``, ``free`` (free-parameter names),
``parameters`` {name: value}, ``bounds`` {name: [lo, hi]}, ``labels`` {name: text},
``lens`` (``Lens.to_dict()``; the manufacturing and verification modules read the lens
from here), ``bench`` (``Bench.to_dict()``), ``criterion``, ``weights``,
``constraints``, ``feasibility``, ``metrics`` (rank, kappa, sigma_min, J, D, A, CRLB
std per DOF in um / urad, ...), ``method``, ``seed``, ``settings``, ``start``,
``history`` (best cost per iteration, thinned to at most 200 rows), ``n_evals``,
``wall_time_s``, ``lensforge_version``, ``conventions`` (written for other tools and
ignored on reading: Zernike order and normalisation, coefficient units, the design
wavelength and the glass index there; see ``lensforge.optics.lens.lens_conventions``); optional ``robust`` (present only for a
tolerance-robust design: ``tolerances`` in the TOML layout, ``n_samples``, ``seed``,
``statistic``, ``criterion``, and the returned lens's robust ``cost``, ``mean``,
``nominal``, ``n_failed`` and per-draw ``values``). Files without it are nominal
designs (schema_version stays 1). ``load_design(save_design(d))`` gives back a
design whose ``to_dict()`` equals the original's.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from os import PathLike

import copy
import math
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..fileio import read_json, write_atomic
from ..optics.bench import Bench
from ..optics.lens import Lens, lens_conventions
from ..input_checks import DESIGN_KIND, Num, check_header, number, number_array

if TYPE_CHECKING:
    from ..optics.sensitivity import Metrics
    from .robust import RobustSpec

__all__ = ["SCHEMA_VERSION", "Design", "save_design", "load_design", "metrics_dict"]

SCHEMA_VERSION = 1
_MAX_HISTORY = 200


def _plain(o):
    """Numpy scalars/arrays and tuples -> JSON types (recursively)."""
    if isinstance(o, dict):
        return {str(k): _plain(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_plain(v) for v in o]
    if isinstance(o, np.ndarray):
        return _plain(o.tolist())
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        o = o.item()
    if isinstance(o, float) and not np.isfinite(o):
        return None
    return o


def metrics_dict(m, weights=(1.0, 1.0)) -> dict:
    """JSON-ready metrics of a ``Metrics`` object plus the D and A criteria and the CRLB."""
    from .criteria import criteria_values

    d = m.to_dict()
    crit = criteria_values(m, weights)
    d["D"] = crit["D"]
    d["A"] = crit["A"]
    d["crlb_mm_rad"] = _plain(np.where(np.isfinite(m.crlb), m.crlb, np.nan))
    return _plain(d)


def thin_history(history, n_max: int = _MAX_HISTORY) -> list:
    """At most n_max rows, first and last kept, evenly spaced."""
    history = list(history)
    if len(history) <= n_max:
        return history
    idx = np.unique(np.linspace(0, len(history) - 1, n_max).round().astype(int))
    return [history[i] for i in idx]


@dataclass(frozen=True)
class Design:
    """A lens design and its provenance (the module docstring describes the JSON keys).

    Parameters
    ----------
    lens : Lens
        The designed lens (mm).
    bench : Bench
        The bench it was designed on.
    model : str
        Surface model: 'polynomial', 'extended_polynomial', 'zernike' or 'conic'.
    free : tuple of str
        Names of the free parameters.
    parameters : dict
        {name: value} of the free parameters (mm, 1/mm, dimensionless as named).
    bounds : dict
        {name: (lo, hi)} search box of each free parameter.
    criterion : str
        'J' (paper), 'D' or 'A'.
    weights : tuple of float
        (w1, w2) of J.
    constraints, feasibility, metrics : dict
        The constraints applied, their verdicts, and the metrics of the lens (rank, kappa,
        sigma_min, J, D, A, CRLB std per DOF in um / urad, ...).
    method : str
        Optimiser name.
    seed : int or None
        Its seed (same seed, same design).
    settings, start : dict
        Optimiser settings and the start point.
    history : tuple
        Best cost per iteration (thinned to at most 200 rows).
    n_evals : int
        Cost evaluations.
    wall_time_s : float
        Wall time, s.
    labels : dict
        {name: text} of the parameters.
    lensforge_version : str
        Version that wrote the design.
    robust : dict or None
        For a tolerance-robust design: the spec and the returned lens's robust cost.
    """

    lens: Lens
    bench: Bench
    model: str
    free: tuple
    parameters: dict
    bounds: dict
    criterion: str = "J"
    weights: tuple = (1.0, 1.0)
    constraints: dict = field(default_factory=dict)
    feasibility: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    method: str = ""
    seed: int | None = None
    settings: dict = field(default_factory=dict)
    start: dict = field(default_factory=dict)
    history: tuple = ()
    n_evals: int = 0
    wall_time_s: float = 0.0
    labels: dict = field(default_factory=dict)
    lensforge_version: str = ""
    robust: dict | None = None

    def __post_init__(self):
        object.__setattr__(self, "free", tuple(self.free))
        object.__setattr__(self, "weights", tuple(float(w) for w in self.weights))
        object.__setattr__(self, "history", tuple(thin_history(_plain(list(self.history)))))
        for f in ("parameters", "bounds", "constraints", "feasibility", "metrics", "settings", "start", "labels"):
            object.__setattr__(self, f, _plain(dict(getattr(self, f))))
        if self.robust is not None:
            if not isinstance(self.robust, dict):
                raise ConfigError("design.robust: expected an object (the robust-design record) or null")
            object.__setattr__(self, "robust", _plain(copy.deepcopy(dict(self.robust))))
        if not self.lensforge_version:
            from .. import __version__

            object.__setattr__(self, "lensforge_version", __version__)

    # convenience -------------------------------------------------------------
    @property
    def J(self):
        return self.metrics.get("J")

    @property
    def rank(self):
        return self.metrics.get("rank")

    def compute_metrics(self, bench: Bench | None = None) -> "Metrics":
        """Fresh ``Metrics`` of the lens on ``bench`` (default: the design's own bench)."""
        from ..optics.sensitivity import metrics

        return metrics(bench or self.bench, self.lens, weights=self.weights)

    def robust_spec(self) -> "RobustSpec | None":
        """The :class:`~lensforge.design.robust.RobustSpec` this design was optimised with (None if nominal)."""
        if self.robust is None:
            return None
        from .robust import RobustSpec

        return RobustSpec.from_dict(self.robust, "design.robust")

    def parameter_vector(self) -> np.ndarray:
        return np.array([self.parameters[n] for n in self.free], dtype=float)

    # I/O ----------------------------------------------------------------------
    def to_dict(self) -> dict:
        d = {
            "schema_version": SCHEMA_VERSION,
            "kind": DESIGN_KIND,
            "model": self.model,
            "free": list(self.free),
            "parameters": copy.deepcopy(self.parameters),
            "bounds": copy.deepcopy(self.bounds),
            "labels": copy.deepcopy(self.labels),
            "lens": self.lens.to_dict(),
            "bench": self.bench.to_dict(),
            "criterion": self.criterion,
            "weights": list(self.weights),
            "constraints": copy.deepcopy(self.constraints),
            "feasibility": copy.deepcopy(self.feasibility),
            "metrics": copy.deepcopy(self.metrics),
            "method": self.method,
            "seed": self.seed,
            "settings": copy.deepcopy(self.settings),
            "start": copy.deepcopy(self.start),
            "history": copy.deepcopy(list(self.history)),
            "n_evals": int(self.n_evals),
            "wall_time_s": float(self.wall_time_s),
            "lensforge_version": self.lensforge_version,
            # optional, written for other tools, ignored on reading (recomputed from lens and bench)
            "conventions": lens_conventions(self.lens, self.bench.laser.wavelength_nm),
        }
        if self.robust is not None:
            d["robust"] = copy.deepcopy(self.robust)
        return d

    @classmethod
    def from_dict(cls, d: dict, where: str = "design") -> "Design":
        if not isinstance(d, dict):
            raise ConfigError(f"{where}: expected a JSON object")
        check_header(d, where, kind=DESIGN_KIND, required=True, versions=(SCHEMA_VERSION,))
        for req in ("lens", "bench", "model", "free", "parameters"):
            if req not in d:
                raise ConfigError(f"{where}.{req}: missing")
        for key, typ, what in (("free", list, "a list of parameter names"), ("parameters", dict, "an object"),
                               ("bounds", dict, "an object"), ("labels", dict, "an object"),
                               ("constraints", dict, "an object"), ("feasibility", dict, "an object"),
                               ("metrics", dict, "an object"), ("settings", dict, "an object"),
                               ("start", dict, "an object"), ("history", list, "a list")):
            if key in d and not isinstance(d[key], typ):
                raise ConfigError(f"{where}: {key} must be {what}, got {type(d[key]).__name__}")
        if "weights" in d:
            number_array(d["weights"], f"{where}: weights", (2,))
        if d.get("seed") is not None:
            number(d["seed"], f"{where}: seed", Num(0, 2**63 - 1, integer=True))
        for key in ("n_evals", "wall_time_s"):
            if key in d:
                number(d[key], f"{where}: {key}", Num(0, math.inf))
        seed = d.get("seed")
        try:
            return cls(
                lens=Lens.from_dict(d["lens"], f"{where}.lens"),
                bench=Bench.from_dict(d["bench"], f"{where}.bench"),
                model=str(d["model"]),
                free=tuple(d["free"]),
                parameters=d["parameters"],
                bounds=d.get("bounds", {}),
                criterion=str(d.get("criterion", "J")),
                weights=tuple(d.get("weights", (1.0, 1.0))),
                constraints=d.get("constraints", {}),
                feasibility=d.get("feasibility", {}),
                metrics=d.get("metrics", {}),
                method=str(d.get("method", "")),
                seed=None if seed is None else int(seed),
                settings=d.get("settings", {}),
                start=d.get("start", {}),
                history=tuple(d.get("history", ())),
                n_evals=int(d.get("n_evals", 0)),
                wall_time_s=float(d.get("wall_time_s", 0.0)),
                labels=d.get("labels", {}),
                lensforge_version=str(d.get("lensforge_version", "")),
                robust=d.get("robust"),
            )
        except (TypeError, ValueError, OverflowError) as e:  # metadata of an unexpected shape
            raise ConfigError(f"{where}: malformed design file ({e}); write it with `lensforge design`") from None


def save_design(design: Design, path: str | PathLike[str]) -> Path:
    """Write the design as JSON (atomically: the file is complete or absent).

    Parameters
    ----------
    design : Design
        The design.
    path : str or os.PathLike
        Destination file.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    text = json.dumps(design.to_dict(), indent=2, allow_nan=False)
    return write_atomic(path, text + "\n")


def load_design(path: str | PathLike[str]) -> Design:
    """Read a design JSON file written by :func:`save_design`.

    Parameters
    ----------
    path : str or os.PathLike
        The JSON file (``schema_version`` 1).

    Returns
    -------
    Design
        The design; ``load_design(save_design(d))`` has the same ``to_dict()`` as d.

    Raises
    ------
    ConfigError
        A missing file, bad JSON, schema version or field (the message names it).
    """
    p = Path(path)
    return Design.from_dict(read_json(p, "design file"), where=f"{p.name}")
