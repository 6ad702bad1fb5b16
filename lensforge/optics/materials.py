"""Refractive-index models n(lambda) and the material data files in ``materials/``.

Dispersion models: Sellmeier (n^2 - 1 = sum B_i l^2 / (l^2 - C_i)) and Cauchy
(n = A + sum B_i / l^(2 i)), wavelength l in micrometres. Each data file names its
source; uncertainties (1-sigma) travel with the material for tolerance studies.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..fileio import read_toml

__all__ = ["Material", "load_material", "materials_dir", "list_materials"]


def materials_dir() -> Path:
    """Folder of material data files: $LENSFORGE_MATERIALS or the project's ``materials/``."""
    env = os.environ.get("LENSFORGE_MATERIALS")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "materials"


@dataclass(frozen=True)
class Material:
    """A refractive material.

    model: "sellmeier", "cauchy" or "constant"; B, C: model coefficients (um^2 units);
    A: Cauchy constant term (or the constant index); index_sigma: 1-sigma uncertainty
    of the absolute index; batch_sigma: batch-to-batch 1-sigma variation.
    """

    name: str
    model: str
    A: float = 0.0
    B: tuple = ()
    C: tuple = ()
    valid_um: tuple = (0.3, 2.5)
    index_sigma: float = 0.0
    batch_sigma: float = 0.0
    shrinkage: float = 0.0
    shrinkage_sigma: float = 0.0
    source: str = ""

    def __post_init__(self):
        if self.model not in ("sellmeier", "cauchy", "constant"):
            raise ConfigError(f"material {self.name}: model must be sellmeier, cauchy or constant, got {self.model!r}")
        if self.model == "sellmeier" and len(self.B) != len(self.C):
            raise ConfigError(f"material {self.name}: Sellmeier needs as many B as C coefficients")

    def index(self, wavelength_nm: float) -> float:
        """Refractive index (relative to air) at the wavelength in nm."""
        lam = np.asarray(wavelength_nm, dtype=float) / 1000.0
        if np.any(lam <= 0) or not np.all(np.isfinite(lam)):
            raise ConfigError(f"wavelength_nm: must be a positive number, got {wavelength_nm}")
        l2 = lam * lam
        if self.model == "sellmeier":
            n2 = 1.0 + sum(b * l2 / (l2 - c) for b, c in zip(self.B, self.C))
            n = np.sqrt(n2)
        elif self.model == "cauchy":
            n = self.A + sum(b / l2 ** (i + 1) for i, b in enumerate(self.B))
        else:
            n = self.A + 0.0 * lam
        return float(n) if np.ndim(n) == 0 else n

    @classmethod
    def constant(cls, n: float, name: str = "constant") -> "Material":
        return cls(name=name, model="constant", A=float(n))

    def to_dict(self) -> dict:
        return {"name": self.name}


@lru_cache(maxsize=None)
def _load(path: str) -> Material:
    d = read_toml(path, "material file")
    allowed = {f for f in Material.__dataclass_fields__}
    unknown = set(d) - allowed
    if unknown:
        raise ConfigError(f"material file {path}: unknown key(s) {sorted(unknown)}")
    for key in ("B", "C", "valid_um"):
        if key in d:
            d[key] = tuple(float(v) for v in d[key])
    return Material(**d)


def list_materials() -> list[str]:
    """Names of the material data files available."""
    return sorted(p.stem for p in materials_dir().glob("*.toml"))


def load_material(name: str) -> Material:
    """A refractive material by name or file.

    Parameters
    ----------
    name : str or Material
        A file stem in ``materials/`` (case-insensitive), a path to a material TOML file, or
        a Material (returned as is).

    Returns
    -------
    Material
        Dispersion model (index at a wavelength via ``Material.index(wavelength_nm)``),
        index uncertainties and cure shrinkage, with their sources.

    Raises
    ------
    ConfigError
        An unknown material (the message lists the available ones).
    """
    if isinstance(name, Material):
        return name
    p = Path(name)
    if p.suffix == ".toml" and p.exists():
        return _load(str(p))
    for f in materials_dir().glob("*.toml"):
        if f.stem.lower() == str(name).lower():
            return _load(str(f))
    raise ConfigError(f"material: unknown material {name!r}; available: {list_materials()} (or give a .toml path)")
