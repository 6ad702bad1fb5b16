"""As-built lens parameters theta for the joint calibration, chosen from the data.

Two layers:

1. The *elementary* perturbations p (``LensSpace``): every deviation the tolerance
   model (``asbuilt.tolerances``) draws, as additive parameters of one lens
   builder: centre thickness (mm), index offset, cure shrinkage (linear fraction),
   per surface the polishing depth and edge roll-off (mm) and each form-error Noll
   mode (mm, RMS-normalised over the clear aperture; Z4 is the surface's power,
   Z2/Z3 its tilt (wedge), Z5/Z6 astigmatism, Z7/Z8 coma, Z11 spherical). The builder
   applies them in the tolerance sampler's order (form, then shrinkage, then polishing,
   thickness, index), so any draw of ``sample_as_built`` without layer ripple is
   exactly ``build(p)`` for some p. Ripple (the staircase of unpolished surfaces) is a
   25 um-period feature no low-order parameter describes; it is left to the chi^2
   mismatch test. Each p_j has the tolerance model's mean and 1-sigma (gamma
   depths approximated by their mean and sd).

2. theta (``LensParameterisation``): the leading right-singular directions of the
   whitened, prior-scaled Jacobian  J = L^-1 dh/dp . diag(sigma_p)  stacked over the
   calibration poses (the working range), p = mean_p + diag(sigma_p) V theta with V
   orthonormal. A direction is kept when a 1-sigma as-built deviation along it moves
   the whitened data by more than ``keep_threshold`` (default 0.1 noise sigma over
   all poses): the directions dropped are then invisible in the data and cannot bias
   the calibration by more than a fraction of its noise. The prior on theta is
   N(0, I) (the tolerance prior projected on the span of V).

Which directions the *calibration* can identify (with X, Z and the robot pose
errors free) is reported by ``calibration.joint`` from the joint Fisher information.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from ..errors import ConfigError
from .tolerances import scale_canonical
from ..optics.lens import Lens
from ..optics.shack_hartmann import ForwardModel
from ..optics.surfaces import CanonicalSurface, Freeform, add_monomials
from ..optics.trace import LensTangents, kernel_tangents, lens_kernel
from ..optics.zernike import zernike_monomials

__all__ = ["LensSpace", "LensParameterisation", "lens_space", "lens_tangents", "elementary_jacobian", "parameterise",
           "SIDES", "MODE_NAMES"]

SIDES = ("front", "back")
# Noll mode -> aberration name (for reports)
MODE_NAMES = {2: "tilt x (wedge)", 3: "tilt y (wedge)", 4: "power", 5: "astigmatism 45", 6: "astigmatism 0",
              7: "coma y", 8: "coma x", 9: "trefoil y", 10: "trefoil x", 11: "spherical"}


def _mode_poly(j: int, radius: float) -> np.ndarray:
    """Monomial array (mm units) of Z_j(x / radius, y / radius)."""
    m = np.asarray(zernike_monomials(j), float)
    pq = np.add.outer(np.arange(m.shape[0]), np.arange(m.shape[1]))
    return m / radius**pq


@dataclass(frozen=True, eq=False)
class LensSpace:
    """Elementary as-built perturbations p of one nominal lens (see the module doc).

    names: (d,) parameter names; mean, sigma: (d,) prior mean and 1-sigma from the
    tolerance model; form_modes: Noll modes per surface; rolloff_power: even power of
    the polishing roll-off.
    """

    lens: Lens
    names: tuple
    mean: np.ndarray
    sigma: np.ndarray
    form_modes: tuple
    rolloff_power: int

    @property
    def size(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        return self.names.index(name)

    @cached_property
    def _mode_polys(self) -> dict:
        Ra = 0.5 * self.lens.aperture
        return {j: _mode_poly(j, Ra) for j in self.form_modes}

    def build(self, p) -> Lens:
        """The as-built lens with elementary deviations p (d,) (absolute, not prior-scaled)."""
        p = np.asarray(p, dtype=float)
        if p.shape != (self.size,):
            raise ConfigError(f"lens parameters: expected {self.size} values, got shape {p.shape}")
        v = dict(zip(self.names, p))
        lens = self.lens
        s = 1.0 - v["shrinkage"]
        Ra = 0.5 * lens.aperture
        surfaces = {}
        for side in SIDES:
            cs = getattr(lens, side).canonical()
            poly = cs.poly
            for j in self.form_modes:
                a = v.get(f"{side}_Z{j}_mm", 0.0)
                if a:
                    poly = add_monomials(poly, a * self._mode_polys[j])
            cs = CanonicalSurface(cs.c, cs.k, cs.alpha.copy(), poly, cs.ripple_amplitude, cs.ripple_period)
            if s != 1.0:
                cs = scale_canonical(cs, s)
            sign = 1.0 if side == "front" else -1.0  # removal moves the surface into the material
            depth, roll = v[f"{side}_polish_depth_mm"], v[f"{side}_rolloff_mm"]
            if depth or roll:
                poly = add_monomials(cs.poly, np.zeros((1, 1)))
                poly[0, 0] += sign * depth
                alpha = cs.alpha.copy()
                alpha[self.rolloff_power // 2 - 1] += sign * roll / (s * Ra) ** self.rolloff_power
                cs = CanonicalSurface(cs.c, cs.k, alpha, poly, cs.ripple_amplitude, cs.ripple_period)
            surfaces[side] = Freeform.from_canonical(cs)
        return lens.replace(front=surfaces["front"], back=surfaces["back"],
                            thickness=lens.thickness * s + v["thickness_mm"], aperture=lens.aperture * s,
                            edge_diameter=float(lens.edge_diameter * s), index_offset=lens.index_offset + v["index"])


def lens_space(lens: Lens, tolerances) -> LensSpace:
    """The elementary perturbations of ``lens`` with their prior from ``tolerances``
    (a manufacturing Tolerances; material-derived values resolved from the lens)."""
    t = tolerances.resolved(lens.material_data)
    names, mean, sigma = [], [], []

    def add(name, m, s):
        names.append(name)
        mean.append(float(m))
        sigma.append(float(s))

    add("thickness_mm", t.thickness_mean_mm, t.thickness_sigma_mm)
    add("index", t.index_mean, math.hypot(t.index_sigma, t.index_batch_sigma))
    add("shrinkage", t.shrinkage_mean, t.shrinkage_sigma)
    nm = len(t.form_modes)
    mode_sd = t.form_rms_mm / math.sqrt(nm) if nm else 0.0
    for side in SIDES:
        polished = side in t.polished_surfaces
        add(f"{side}_polish_depth_mm", t.polish_depth_mm if polished else 0.0,
            t.polish_depth_sigma_mm if polished else 0.0)
        add(f"{side}_rolloff_mm", t.polish_rolloff_mm if polished else 0.0,
            t.polish_rolloff_sigma_mm if polished else 0.0)
        for j in t.form_modes:
            add(f"{side}_Z{j}_mm", 0.0, mode_sd)
    return LensSpace(lens=lens, names=tuple(names), mean=np.array(mean), sigma=np.array(sigma),
                     form_modes=tuple(t.form_modes), rolloff_power=int(t.polish_rolloff_power))


@dataclass(frozen=True, eq=False)
class LensParameterisation:
    """theta -> as-built lens: p = space.mean + diag(space.sigma) V theta.

    V: (d, k) orthonormal directions in prior-scaled elementary space; singular_values:
    (all d) of the whitened prior-scaled Jacobian over the working range (how many
    noise sigmas a 1-sigma deviation along each direction moves the data); kept: k;
    poses: (P, 6) the working range it was chosen on (or None); theta_jacobian: (P, m,
    k) whitened dh/dtheta of the mean lens (theta = 0) at those poses (or None), a free
    start for the joint calibration's iteration Jacobian at poses near them.
    """

    space: LensSpace
    V: np.ndarray
    singular_values: np.ndarray
    keep_threshold: float
    poses: np.ndarray | None = None
    theta_jacobian: np.ndarray | None = None

    @property
    def k(self) -> int:
        return self.V.shape[1]

    @property
    def names(self) -> tuple:
        return tuple(f"theta{i + 1}" for i in range(self.k))

    def elementary(self, theta) -> np.ndarray:
        """Elementary deviations p (d,) of theta (k,)."""
        return self.space.mean + self.space.sigma * (self.V @ np.asarray(theta, dtype=float))

    def build(self, theta) -> Lens:
        """The as-built lens of theta (theta = 0: the tolerance model's mean lens)."""
        return self.space.build(self.elementary(theta))

    def tangents(self, theta, wavelength_nm: float) -> LensTangents:
        """The packed lens's change per unit of each theta component at theta (k tangents,
        ``lens_tangents``)."""
        return lens_tangents(self.build, np.asarray(theta, dtype=float), np.eye(self.k), wavelength_nm)

    def describe(self, i: int, n_terms: int = 3) -> str:
        """The largest elementary components of direction i, e.g. '0.71 front_Z4_mm - 0.70 back_Z4_mm'."""
        v = self.V[:, i]
        order = np.argsort(-np.abs(v))[:n_terms]
        return " ".join(f"{v[j]:+.2f} {self.space.names[j]}" for j in order)


def lens_tangents(build, x0, directions, wavelength_nm: float, step: float = 1e-4) -> LensTangents:
    """Tangents of the packed lens build(x) at x0 along each row of directions: forward
    differences of the packing over step (no ray is traced). The packing is linear in the
    elementary deviations except through cure shrinkage's scale (1 - s), so the truncation
    is ~step s sigma_s ~ 1e-10 relative; rounding ~1e-16 / step."""
    base = lens_kernel(build(x0), wavelength_nm)
    plus = [lens_kernel(build(x0 + step * d), wavelength_nm) for d in directions]
    return kernel_tangents(plus, [base] * len(plus), step)


def elementary_jacobian(bench, space: LensSpace, poses) -> np.ndarray:
    """Whitened, prior-scaled dh/dp (P, m, d) at the mean lens over poses (P, 6): the
    forward model's exact derivative along each elementary deviation (one sigma_p each; a
    deviation the tolerances hold at zero has a zero column, and none is traced)."""
    poses = np.atleast_2d(np.asarray(poses, dtype=float))
    model = ForwardModel(bench, space.build(space.mean), validate=False)
    free = np.flatnonzero(space.sigma)
    out = np.zeros((len(poses), model.whitener.shape[0], space.size))
    if free.size:
        lt = lens_tangents(space.build, space.mean, np.diag(space.sigma)[free], bench.laser.wavelength_nm)
        _, J, _ = model.jacobians(poses, lens_tangents=lt)
        out[..., free] = np.einsum("ij,pjd->pid", model.whitener, J)
    return out


def parameterise(bench, lens: Lens, tolerances, poses, keep_threshold: float = 0.1,
                 max_directions: int | None = None, as_designed: bool = False) -> LensParameterisation:
    """theta for ``lens`` under ``tolerances`` over the working range ``poses`` (P, 6):
    the right-singular directions of the whitened prior-scaled Jacobian whose singular
    value exceeds keep_threshold (at most max_directions). as_designed: the lens known as
    designed: no directions, and theta's (empty) origin is the design itself, not the
    tolerance model's mean as-built lens (which a model with systematic deviations, e.g.
    the print's shrinkage, moves off the design); no Jacobian is traced (singular_values
    empty, theta_jacobian None)."""
    space = lens_space(lens, tolerances)
    poses = np.atleast_2d(np.asarray(poses, dtype=float)).copy()
    if as_designed:
        space = replace(space, mean=np.zeros_like(space.mean))
        return LensParameterisation(space=space, V=np.zeros((space.size, 0)), singular_values=np.zeros(0),
                                    keep_threshold=keep_threshold, poses=poses, theta_jacobian=None)
    J = elementary_jacobian(bench, space, poses)
    _, s, Vt = np.linalg.svd(J.reshape(-1, space.size), full_matrices=False)
    k = int(np.sum(s > keep_threshold))
    if max_directions is not None:
        k = min(k, int(max_directions))
    V = Vt[:k].T.copy()
    return LensParameterisation(space=space, V=V, singular_values=s, keep_threshold=keep_threshold, poses=poses,
                                theta_jacobian=J @ V)
