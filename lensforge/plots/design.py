"""Plots of a design: singular values, sag maps with the lit area, Zernike response, beam
footprint over the working range, lenslet slope field, dimensioned cross-section and the
design's convergence history; ``design_plots`` writes the set for a design file.

Units are in every label: sag in mm, Zernike response in um of wavefront per 1 mm
(translations) or per 1 deg (rotations).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from os import PathLike
from pathlib import Path

import numpy as np

from ..optics.footprint import lit_outlines, sag_departure
from .figure import new_figure, save_figure

if TYPE_CHECKING:
    from ..design.design_file import Design
    from ..optics.lens import Lens

__all__ = ["plot_singular_values", "plot_sag_maps", "plot_zernike_response", "plot_beam_footprint",
           "plot_lenslet_field", "plot_cross_section", "plot_convergence", "design_plots"]


def plot_singular_values(ax, spectra: dict, title: str = "Singular values of the scaled, whitened S"):
    """Bar/line plot of singular-value spectra {label: sv (descending)} on a log axis."""
    for label, sv in spectra.items():
        sv = np.asarray(sv, dtype=float)
        sv = np.where(sv > 0, sv, np.nan)
        ax.semilogy(np.arange(1, sv.size + 1), sv, "o-", label=label)
    ax.set_xlabel("index i")
    ax.set_ylabel("sigma_i of S~ (dimensionless)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return ax


def plot_sag_maps(lens, n: int = 121, lit=None):
    """Figure: sag of front and back surface and their departure from rotational symmetry (mm).

    lit: optional dict {"nominal": (K, 2) outline, "range": (K, 2) outline} of the beam
    footprint on the front surface in {O} (mm), drawn on every map (see :func:`beam_footprint`).
    """
    fig = new_figure(figsize=(10, 8.5), layout="constrained")
    a = 0.5 * lens.aperture
    g = np.linspace(-a, a, n)
    X, Y = np.meshgrid(g, g)
    outside = X**2 + Y**2 > a * a
    for row, side in enumerate(("front", "back")):
        z, dep = sag_departure(getattr(lens, side), X, Y)
        for col, (data, what) in enumerate(((z, "sag"), (dep, "departure from rotational symmetry"))):
            ax = fig.add_subplot(2, 2, 2 * row + col + 1)
            data = np.where(outside, np.nan, data)
            im = ax.imshow(data, extent=(-a, a, -a, a), origin="lower", cmap="viridis" if col == 0 else "RdBu_r")
            ax.set_title(f"{side} {what} (mm)", fontsize=9)
            ax.set_xlabel("x (mm)")
            ax.set_ylabel("y (mm)")
            fig.colorbar(im, ax=ax, shrink=0.8, label="mm")
            if lit is not None:
                for key, style, label in (("range", ":", "beam over the working range"),
                                          ("nominal", "-", "beam 1/e^2, nominal pose")):
                    if lit.get(key) is not None:
                        ax.plot(*np.asarray(lit[key]).T, "k" + style, lw=1.2, label=label)
                if row == 0 and col == 0:
                    ax.legend(fontsize=7, loc="lower left", title="lit area (front surface)", title_fontsize=7)
    fig.suptitle(lens.name or "lens")
    return fig


def plot_zernike_response(S, modes, pose_scales, title: str = "Zernike response per pose DOF"):
    """Figure: column j of S times the pose scale (um of wavefront per 1 mm / per 1 deg)."""
    from ..optics.pose import DOF_NAMES

    S = np.asarray(S, dtype=float)
    fig = new_figure(figsize=(12, 6.5), layout="constrained")
    scales = np.asarray(pose_scales, dtype=float)
    for j in range(6):
        ax = fig.add_subplot(2, 3, j + 1)
        ax.bar(np.arange(S.shape[0]), S[:, j] * scales[j], color="tab:blue")
        unit = f"{scales[j]:g} mm" if j < 3 else f"{np.degrees(scales[j]):g} deg"
        ax.set_title(f"pose DOF {DOF_NAMES[j]}", fontsize=10)
        ax.set_xticks(np.arange(S.shape[0]))
        ax.set_xticklabels([str(m) for m in modes], fontsize=9)
        ax.tick_params(axis="y", labelsize=9)
        ax.set_xlabel("Zernike mode (Noll j)", fontsize=9)
        ax.set_ylabel(f"um of wavefront per {unit}", fontsize=9)
        ax.axhline(0.0, color="k", lw=0.6)
        ax.grid(True, axis="y", alpha=0.3)
    fig.suptitle(title)
    return fig


def plot_beam_footprint(lens, lit: dict, range_mm: float, range_rad: float):
    """Figure: the beam footprint on the front surface for every pose of the working range,
    with the clear aperture and the mechanical edge (mm, lens frame {O}); left the whole
    lens, right a close-up of the lit area."""
    fig = new_figure(figsize=(12, 5.8), layout="constrained")
    th = np.linspace(0, 2 * np.pi, 361)
    Re = 0.5 * max(lens.edge_diameter, lens.aperture)
    for k, span in enumerate((1.08 * Re, max(np.nanmax(np.abs(lit["range"])) * 1.25, 0.1))):
        ax = fig.add_subplot(1, 2, k + 1)
        ax.plot(0.5 * lens.aperture * np.cos(th), 0.5 * lens.aperture * np.sin(th), "k-", lw=1,
                label=f"clear aperture {lens.aperture:g} mm")
        if lens.edge_diameter > lens.aperture:
            ax.plot(Re * np.cos(th), Re * np.sin(th), "k--", lw=1, label=f"edge {lens.edge_diameter:g} mm")
        for i, f in enumerate(lit["footprints"][1:]):
            ax.plot(*np.vstack([f, f[:1]]).T, color="tab:blue", lw=0.5, alpha=0.5,
                    label="beam 1/e^2 at one pose of the range" if i == 0 else None)
        ax.fill(*lit["range"].T, color="tab:blue", alpha=0.15, label="lit over the working range")
        ax.plot(*lit["nominal"].T, color="tab:red", lw=1.8, label="beam 1/e^2, nominal pose")
        ax.set_xlim(-span, span)
        ax.set_ylim(-span, span)
        ax.set_aspect("equal")
        ax.set_xlabel("x in lens frame {O} (mm)")
        ax.set_ylabel("y in lens frame {O} (mm)")
        ax.set_title("whole lens" if k == 0 else "close-up of the lit area", fontsize=9)
        ax.grid(True, alpha=0.3)
        if k == 1:
            ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{lens.name or 'lens'}: beam footprint on the front surface over the working range "
                 f"+-{range_mm:g} mm, +-{np.degrees(range_rad):g} deg")
    return fig


# --------------------------------------------------------------------------- sensor

def plot_lenslet_field(bench, lens, pose=None, step=None):
    """Figure: the Shack-Hartmann slope field on the lenslets of the Zernike pupil.

    Left: slopes at ``pose`` (default nominal) as arrows (mrad; the mean slope, a pure tilt,
    is removed so the shape shows), colour = irradiance relative to the input peak.
    Right: the change of the slopes for a pose step (default +1 pose scale in rz, the
    hardest DOF to observe), in urad. Lenslet grid around the pupil in grey.
    """
    from ..optics.pose import DOF_NAMES
    from ..optics.shack_hartmann import ForwardModel

    fm = ForwardModel(bench, lens)
    pupil = fm.pupil
    x0 = np.zeros(6) if pose is None else np.asarray(pose, dtype=float)
    if step is None:
        step = np.zeros(6)
        step[5] = bench.pose_scales[5]
    step = np.asarray(step, dtype=float)
    res = fm.evaluate(np.stack([x0, x0 + step]), check_range=False)
    c = pupil.centres
    fig = new_figure(figsize=(12, 5.6), layout="constrained")
    pitch = bench.sensor.pitch_mm
    r = pupil.radius_mm
    cx, cy = pupil.center_mm
    g = np.arange(-np.ceil(1.4 * r / pitch), np.ceil(1.4 * r / pitch) + 1) * pitch
    gx, gy = np.meshgrid(g + cx, g + cy)
    th = np.linspace(0, 2 * np.pi, 361)
    sl = res.slopes[0] - np.nanmean(res.slopes[0], axis=0)
    dsl = res.slopes[1] - res.slopes[0]
    jn = int(np.argmax(np.abs(step)))
    unit = "mm" if jn < 3 else "deg"
    mag = step[jn] if jn < 3 else np.degrees(step[jn])
    panels = ((sl * 1e3, "mrad", "slope minus mean tilt at the " + ("nominal pose" if pose is None else "pose")),
              (dsl * 1e6, "urad", f"slope change for {DOF_NAMES[jn]} {mag:+.3g} {unit}"))
    for k, (v, u, title) in enumerate(panels):
        ax = fig.add_subplot(1, 2, k + 1)
        ax.plot(gx.ravel(), gy.ravel(), ".", color="0.8", ms=2, label=f"lenslet grid, pitch {1000 * pitch:g} um")
        ax.plot(cx + r * np.cos(th), cy + r * np.sin(th), "k-", lw=1, label=f"Zernike pupil r = {r:g} mm")
        q = ax.quiver(c[:, 0], c[:, 1], v[:, 0], v[:, 1], res.irradiance[0] if k == 0 else np.hypot(*v.T),
                      cmap="viridis", angles="xy", pivot="middle")
        mx = float(np.nanmax(np.hypot(*v.T))) if np.isfinite(v).any() else 0.0
        if mx > 0:
            ax.quiverkey(q, 0.72, 0.95, mx, f"{mx:.3g} {u}", labelpos="E", coordinates="axes",
                         fontproperties={"size": 8})
        fig.colorbar(q, ax=ax, shrink=0.8,
                     label="irradiance / input peak" if k == 0 else f"|slope change| ({u})")
        ax.set_aspect("equal")
        ax.set_xlabel("x on the lenslet plane {S} (mm)")
        ax.set_ylabel("y on the lenslet plane {S} (mm)")
        ax.set_title(title, fontsize=9)
        ax.legend(fontsize=7, loc="lower left")
    fig.suptitle(f"{lens.name or 'lens'}: Shack-Hartmann slopes on {pupil.n_lenslets} pupil lenslets")
    return fig


# --------------------------------------------------------------------------- drawing

def _dim(ax, p0, p1, text, offset=(0.0, 0.0), color="k", fontsize=8):
    """A dimension line with arrows from p0 to p1 (data units) and its label."""
    p0, p1 = np.asarray(p0, float) + offset, np.asarray(p1, float) + offset
    ax.annotate("", xy=p1, xytext=p0, arrowprops=dict(arrowstyle="<|-|>", lw=0.8, color=color, shrinkA=0, shrinkB=0))
    mid = 0.5 * (p0 + p1)
    vertical = abs(p1[1] - p0[1]) > abs(p1[0] - p0[0])
    ax.text(*mid, text, fontsize=fontsize, color=color, ha="center", va="center", rotation=90 if vertical else 0,
            bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.9))


def plot_cross_section(lens):
    """Figure: dimensioned cross-sections of the lens in the x-z and y-z planes of {O} (mm):
    centre thickness, edge thickness, clear aperture, edge diameter, sag at the clear aperture."""
    fig = new_figure(figsize=(11, 6), layout="constrained")
    R, Ra, half = 0.5 * lens.edge_diameter, 0.5 * lens.aperture, 0.5 * lens.thickness
    s = np.linspace(-R, R, 801)
    for k, (axis, label) in enumerate(((0, "x"), (1, "y"))):
        ax = fig.add_subplot(1, 2, k + 1)
        x, y = (s, 0 * s) if axis == 0 else (0 * s, s)
        zf = -half + lens.front.sag(x, y)
        zb = half + lens.back.sag(x, y)
        ax.fill(np.concatenate([zf, zb[::-1]]), np.concatenate([s, s[::-1]]), color="lightsteelblue", ec="k", lw=1)
        ax.axhline(0.0, color="k", lw=0.6, ls="-.")  # optical axis
        for yy in (-Ra, Ra):
            ax.axhline(yy, color="tab:green", lw=0.6, ls="--")
        zmin, zmax = float(np.min(zf)), float(np.max(zb))
        w = zmax - zmin
        # centre thickness along the axis
        zf0, zb0 = float(lens.front.sag(0.0, 0.0)) - half, float(lens.back.sag(0.0, 0.0)) + half
        _dim(ax, (zf0, 0.06 * R), (zb0, 0.06 * R), f"centre {zb0 - zf0:.3f}")
        # edge thickness at both ends of the section, with extension lines
        for e in (-R, R):
            xe, ye = (e, 0.0) if axis == 0 else (0.0, e)
            a, b = -half + float(lens.front.sag(xe, ye)), half + float(lens.back.sag(xe, ye))
            yd = e + 0.1 * R * np.sign(e)
            for zz in (a, b):
                ax.plot([zz, zz], [e, yd + 0.02 * R * np.sign(e)], "k-", lw=0.5)
            _dim(ax, (a, yd), (b, yd), f"edge {b - a:.3f}")
        # apertures
        _dim(ax, (zmin - 0.3 * R, -Ra), (zmin - 0.3 * R, Ra), f"clear aperture {2 * Ra:.2f}", color="tab:green")
        if R > Ra:
            _dim(ax, (zmax + 0.3 * R, -R), (zmax + 0.3 * R, R), f"edge diameter {2 * R:.2f}")
        # sag of each surface at the clear aperture rim (+ side), relative to its vertex
        xa, ya = (Ra, 0.0) if axis == 0 else (0.0, Ra)
        sags = [float(getattr(lens, side).sag(xa, ya)) - float(getattr(lens, side).sag(0.0, 0.0))
                for side in ("front", "back")]
        ax.text(0.02, 0.02, f"sag at {label} = +{Ra:.2f} (clear-aperture rim):\nfront {sags[0]:+.4f}, "
                f"back {sags[1]:+.4f}", transform=ax.transAxes, fontsize=7, va="bottom",
                bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="0.7"))
        zc = 0.5 * (zmin + zmax)
        ax.set_xlim(zc - 0.5 * w - 0.6 * R, zc + 0.5 * w + 0.6 * R)
        ax.set_ylim(-1.35 * R, 1.25 * R)
        ax.set_aspect("equal")
        ax.set_xlabel("z in lens frame {O} (mm), beam travels +z")
        ax.set_ylabel(f"{label} in lens frame {{O}} (mm)")
        ax.set_title(f"section {label}-z (all dimensions in mm)", fontsize=9)
        ax.grid(True, alpha=0.2)
    fig.suptitle(f"{lens.name or 'lens'}: cross-sections, material {lens.material}")
    return fig


def plot_bench_layout(bench, lens, range_mm: float = 1.0, range_rad: float = np.radians(1.0)):
    """Figure: the bench around the lens. Left, side view (y-z of {S}): laser and beam expander
    (schematic, not to scale along z), the expanded beam, the lens section at its nominal
    distance, traced beam rays to the sensor, the WFS aperture and the Zernike pupil. Right,
    the sensor face (x-y of {S}): aperture, Zernike pupil, and the beam's 1/e^2 footprint at
    the nominal pose and over the working range (axis poses at +-range)."""
    from matplotlib.patches import Rectangle

    from ..optics.trace import OK, trace_rays

    fig = new_figure(figsize=(13, 5.5), layout="constrained")
    ax = fig.add_subplot(1, 2, 1)
    d = bench.placement.distance_mm
    w = 0.5 * bench.laser.beam_diameter_mm
    mag = bench.laser.expander_magnification
    w0 = w / mag
    half_ap = 0.5 * bench.sensor.aperture_mm
    cy, r = bench.sensor.pupil_center_mm[1], bench.sensor.pupil_radius_mm
    R = 0.5 * lens.edge_diameter
    z_lens = -d
    z_exp = z_lens - max(0.6 * d, 12.0)
    z_laser = z_exp - max(0.5 * d, 10.0)
    # laser and expander (schematic)
    ax.add_patch(Rectangle((z_laser - 8, -1.5 * w0), 8, 3 * w0, fc="0.3", ec="k"))
    ax.text(z_laser - 4, 1.7 * w0, f"laser\n{2 * w0:.3g} mm beam\n{bench.laser.wavelength_nm:g} nm", ha="center",
            va="bottom", fontsize=7)
    name = bench.laser.expander or "no expander"
    if mag != 1.0:
        for zz, hh in ((z_exp - 3, 1.3 * w0), (z_exp + 3, 1.15 * w)):
            ax.plot([zz, zz], [-hh, hh], color="tab:blue", lw=2)
        ax.text(z_exp, 1.25 * w, f"{name}\n{mag:g}x Galilean", ha="center", va="bottom", fontsize=7, color="tab:blue")
        zb = [z_laser, z_exp - 3, z_exp + 3, z_lens - 0.5 * lens.thickness]
        wb = [w0, w0, w, w]
    else:
        ax.text(z_exp, 1.25 * w, name, ha="center", va="bottom", fontsize=7, color="tab:blue")
        zb, wb = [z_laser, z_lens - 0.5 * lens.thickness], [w0, w0]
    ax.fill_between(zb, [-v for v in wb], wb, color="tab:green", alpha=0.25, lw=0, label="beam (1/e^2)")
    # lens section (y-z) at its nominal placement
    s = np.linspace(-R, R, 401)
    zf = z_lens - 0.5 * lens.thickness + lens.front.sag(0 * s, s)
    zk = z_lens + 0.5 * lens.thickness + lens.back.sag(0 * s, s)
    ax.fill(np.concatenate([zf, zk[::-1]]), np.concatenate([s, s[::-1]]), color="lightsteelblue", ec="k", lw=0.8,
            label=f"lens (d = {d:.3g} mm)")
    # rays from the lens to the sensor: a fan across the beam in y
    v = np.linspace(-0.98 * w, 0.98 * w, 15)
    uv = np.stack([0 * v, v], axis=1)
    tr = trace_rays(bench, lens, np.zeros((1, 6)), uv)
    for k in range(len(v)):
        if tr.status[0, k] != OK:
            continue
        y1 = tr.xy[0, k, 1]
        # drawn straight from the beam height at the back vertex (a sketch: the trace gives only the landing)
        ax.plot([z_lens + 0.5 * lens.thickness, 0.0], [v[k], y1], color="tab:green", lw=0.5, alpha=0.8)
    # sensor and pupil
    ax.plot([0, 0], [-half_ap, half_ap], color="k", lw=3, label=f"WFS aperture {2 * half_ap:.3g} mm")
    ax.plot([0.4, 0.4], [cy - r, cy + r], color="tab:red", lw=3, label=f"Zernike pupil r = {r:.3g} mm")
    ax.set_xlabel("z in {S} (mm); laser and expander schematic, not to scale")
    ax.set_ylabel("y in {S} (mm)")
    ax.set_ylim(-max(R, half_ap) * 1.3, max(R, half_ap) * 1.45)
    ax.set_title("side view: laser, expander, lens, sensor", fontsize=9)
    ax.legend(fontsize=7, loc="lower left")
    ax.grid(True, alpha=0.2)
    # sensor face
    ax = fig.add_subplot(1, 2, 2)
    sq = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]]) * half_ap
    ax.plot(sq[:, 0], sq[:, 1], "k-", lw=1.5, label="WFS aperture")
    phi = np.linspace(0, 2 * np.pi, 181)
    cx = bench.sensor.pupil_center_mm[0]
    ax.plot(cx + r * np.cos(phi), cy + r * np.sin(phi), color="tab:red", lw=2, label="Zernike pupil")
    ring = np.stack([w * np.cos(phi[:-1]), w * np.sin(phi[:-1])], axis=1)
    poses = [np.zeros(6)]
    for i, sc in enumerate((range_mm, range_mm, range_mm, range_rad, range_rad, range_rad)):
        for sg in (1.0, -1.0):
            e = np.zeros(6)
            e[i] = sg * sc
            poses.append(e)
    tr = trace_rays(bench, lens, np.array(poses), ring)
    for k in range(len(poses)):
        ok = tr.status[k] == OK
        if not ok.any():
            continue
        xy = tr.xy[k][ok]
        kw = dict(color="tab:green", lw=1.8, label="beam 1/e^2 at nominal") if k == 0 else \
            dict(color="tab:green", lw=0.6, alpha=0.5, label="over the working range" if k == 1 else None)
        ax.plot(np.append(xy[:, 0], xy[0, 0]), np.append(xy[:, 1], xy[0, 1]), **kw)
    ax.set_aspect("equal")
    ax.set_xlim(-1.1 * half_ap, 1.1 * half_ap)
    ax.set_ylim(-1.1 * half_ap, 1.25 * half_ap)
    ax.set_xlabel("x in {S} (mm)")
    ax.set_ylabel("y in {S} (mm)")
    ax.set_title(f"sensor face: beam footprint (+-{range_mm:g} mm, +-{np.degrees(range_rad):.3g} deg) and pupil",
                 fontsize=9)
    ax.legend(fontsize=7, loc="upper right")
    ax.grid(True, alpha=0.2)
    fig.suptitle(f"bench layout: {name}, {2 * w:.3g} mm beam, pupil r {r:.3g} mm, lens at {d:.3g} mm "
                 f"({bench.sensor.spot_assignment} spot assignment)")
    return fig


# --------------------------------------------------------------------------- design and calibration

def plot_convergence(history, title: str = "Design convergence"):
    """Figure: best cost against cost evaluations from a design's stored history
    (rows with "n_evals", "best", "feasible"); infeasible stretches shaded."""
    rows = [r for r in history if isinstance(r, dict)]
    fig = new_figure(figsize=(7, 4.2), layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    if not rows:
        ax.text(0.5, 0.5, "no history stored in the design file", ha="center", va="center", transform=ax.transAxes)
        return fig
    n = np.array([r.get("n_evals", i) for i, r in enumerate(rows)], dtype=float)
    best = np.array([np.nan if r.get("best") is None else r["best"] for r in rows], dtype=float)
    feas = np.array([bool(r.get("feasible", True)) for r in rows])
    ok = feas & np.isfinite(best)
    ax.step(n[ok], best[ok], where="post", color="tab:blue", label="best feasible cost")
    if np.all(best[ok] > 0):
        ax.set_yscale("log")
    if (~feas).any():
        ax.axvspan(n[0], n[~feas].max(), color="tab:red", alpha=0.1, label="no feasible point yet")
    ax.set_xlabel("cost evaluations")
    ax.set_ylabel("best cost (criterion value, dimensionless)")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def design_plots(design: "Design | Lens", out_dir: str | PathLike[str], stem: str | None = None) -> list[Path]:
    """Write the PNGs of a design (or lens) into out_dir: singular values, sag maps with the lit
    area, Zernike response, beam footprint over the working range, lenslet slope field,
    dimensioned cross-section and (for a design file) the convergence history.

    Parameters
    ----------
    design : Design or Lens
        The design (a Lens is plotted on the default bench).
    out_dir : str or os.PathLike
        Output folder.
    stem : str, optional
        File-name stem (default: the design's model, or "lens").

    Returns
    -------
    list of pathlib.Path
        The written PNGs.
    """
    from ..optics.bench import Bench
    from ..optics.lens import Lens
    from ..optics.sensitivity import metrics
    from ..optics.shack_hartmann import lenslet_pupil

    out = Path(out_dir)
    if isinstance(design, Lens):
        lens, bench, history, cons = design, Bench.default(), None, {}
    else:
        lens, bench, history, cons = design.lens, design.bench, design.history, design.constraints
    range_mm = float(cons.get("range_mm") or 1.0)
    range_rad = float(cons.get("range_rad") or np.radians(1.0))
    m = metrics(bench, lens)
    stem = stem or (getattr(design, "model", None) or "lens")
    paths = []
    fig = new_figure(figsize=(6, 4))
    plot_singular_values(fig.add_subplot(1, 1, 1), {f"{stem} (rank {m.rank}, kappa {m.kappa:.3g})": m.singular_values})
    paths.append(save_figure(fig, out / f"{stem}_singular_values.png"))
    lit = lit_outlines(bench, lens, range_mm, range_rad)
    paths.append(save_figure(plot_sag_maps(lens, lit=lit), out / f"{stem}_sag.png"))
    modes = lenslet_pupil(bench.sensor).modes
    paths.append(save_figure(plot_zernike_response(m.S, modes, bench.pose_scales), out / f"{stem}_zernike_response.png"))
    paths.append(save_figure(plot_beam_footprint(lens, lit, range_mm, range_rad), out / f"{stem}_footprint.png"))
    paths.append(save_figure(plot_lenslet_field(bench, lens), out / f"{stem}_lenslet_field.png"))
    paths.append(save_figure(plot_cross_section(lens), out / f"{stem}_cross_section.png"))
    paths.append(save_figure(plot_bench_layout(bench, lens, range_mm, range_rad), out / f"{stem}_bench_layout.png"))
    if history is not None:
        title = f"{stem}: {getattr(design, 'method', '')} on criterion {getattr(design, 'criterion', '')}"
        paths.append(save_figure(plot_convergence(history, title), out / f"{stem}_convergence.png"))
    return paths
