"""Where the beam meets the lens: the working range's poses, the beam footprint on the
front surface, its outline, and a surface's departure from its best-fit sphere (geometry
the plots draw; no drawing here). Lengths in mm, in the lens frame {O}."""

from __future__ import annotations

import numpy as np

from .trace import pose_frames

__all__ = ["working_range_poses", "beam_footprint", "outline", "lit_outlines", "sag_departure"]


def sag_departure(surface, x, y, n_phi: int = 64):
    """(sag, departure from rotational symmetry) at (x, y) in mm: the departure is the
    sag minus its azimuthal mean on the circle of the same radius."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    z = surface.sag(x, y)
    r = np.hypot(x, y)
    phi = np.linspace(0.0, 2 * np.pi, n_phi, endpoint=False)
    ring = surface.sag(r[..., None] * np.cos(phi), r[..., None] * np.sin(phi))
    return z, z - ring.mean(axis=-1)


def working_range_poses(range_mm: float, range_rad: float, n_random: int = 40, seed: int = 0) -> np.ndarray:
    """Poses (P, 6) spanning the working range: nominal, +-range on each DOF alone, all
    translation corners, and ``n_random`` uniform draws in the box (mm, rad)."""
    scale = np.array([range_mm] * 3 + [range_rad] * 3, dtype=float)
    poses = [np.zeros(6)]
    for j in range(6):
        for sgn in (-1.0, 1.0):
            e = np.zeros(6)
            e[j] = sgn * scale[j]
            poses.append(e)
    for corner in np.array(np.meshgrid(*[[-1.0, 1.0]] * 3)).reshape(3, -1).T:
        poses.append(np.concatenate([corner * range_mm, np.zeros(3)]))
    rng = np.random.default_rng(seed)
    poses.extend(rng.uniform(-1.0, 1.0, (n_random, 6)) * scale)
    return np.array(poses)


def beam_footprint(bench, lens, poses, n_edge: int = 72, max_iter: int = 30) -> np.ndarray:
    """Where the beam's 1/e^2 edge rays hit the front surface, in the lens frame {O}.

    Rays start on the beam circle (diameter ``bench.laser.beam_diameter_mm``, centred on
    the beam offset, direction from the beam slope) in {S}; each pose (P, 6) places the
    lens (DESIGN.md), and Newton's method on the ray parameter finds the front-surface
    hit. Returns (P, n_edge, 2) hit points (x, y) in {O} (mm); NaN where a ray misses.
    """
    poses = np.atleast_2d(np.asarray(poses, dtype=float))
    R, t = pose_frames(bench, poses)
    a = 0.5 * bench.laser.beam_diameter_mm
    phi = np.linspace(0.0, 2 * np.pi, n_edge, endpoint=False)
    ox, oy = bench.laser.offset_mm
    sx, sy = bench.laser.slope
    d_s = np.array([sx, sy, 1.0]) / np.sqrt(1.0 + sx * sx + sy * sy)
    z_start = -bench.placement.distance_mm - 3.0 * lens.thickness - 10.0  # well before the lens
    p_s = np.stack([ox + a * np.cos(phi), oy + a * np.sin(phi), np.full(n_edge, z_start)], axis=-1)
    # into {O}: p_O = R^T (p_S - t)
    p = np.einsum("pji,pnj->pni", R, p_s[None] - t[:, None, :])
    d = np.einsum("pji,j->pi", R, d_s)[:, None, :]
    cs = lens.front.canonical()
    z0 = -0.5 * lens.thickness
    s = (z0 - p[..., 2]) / d[..., 2]  # start at the vertex plane
    for _ in range(max_iter):
        x, y = p[..., 0] + s * d[..., 0], p[..., 1] + s * d[..., 1]
        z, gx, gy = cs.sag_and_gradient(x, y)
        g = p[..., 2] + s * d[..., 2] - (z0 + z)
        dg = d[..., 2] - gx * d[..., 0] - gy * d[..., 1]
        step = g / dg
        s = s - step
        if np.all(np.abs(step[np.isfinite(step)]) < 1e-12):
            break
    hit = np.stack([p[..., 0] + s * d[..., 0], p[..., 1] + s * d[..., 1]], axis=-1)
    return np.where(np.isfinite(hit), hit, np.nan)


def outline(points: np.ndarray) -> np.ndarray:
    """Closed convex-hull outline (K, 2) of 2-D points (NaNs dropped)."""
    from scipy.spatial import ConvexHull

    pts = points[np.all(np.isfinite(points), axis=1)]
    hull = ConvexHull(pts)
    v = pts[hull.vertices]
    return np.vstack([v, v[:1]])


def lit_outlines(bench, lens, range_mm: float, range_rad: float) -> dict:
    """{"nominal": outline, "range": outline} of the beam footprint on the front surface (mm, {O})."""
    fp = beam_footprint(bench, lens, working_range_poses(range_mm, range_rad))
    nominal = np.vstack([fp[0], fp[0][:1]])
    return {"nominal": nominal, "range": outline(fp.reshape(-1, 2)), "footprints": fp}
