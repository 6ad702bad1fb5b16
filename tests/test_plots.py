"""Plots: the beam footprint geometry against analytic cases, and every design plot is written."""

import numpy as np
import pytest

import lensforge as lf
from lensforge.optics.surfaces import Conic
from lensforge.optics.footprint import beam_footprint, working_range_poses
from lensforge.plots.calibration import plot_handeye_residuals
from lensforge.plots.design import design_plots, plot_convergence
from lensforge.plots.figure import save_figure


def _flat(thickness=4.0):
    return lf.Lens(front=Conic(), back=Conic(), thickness=thickness, aperture=20.0, material="N-BK7").validate()


def test_footprint_on_a_flat_front_is_the_beam_circle_moved_by_the_pose():
    bench = lf.Bench.default()
    lens = _flat()
    a = 0.5 * bench.laser.beam_diameter_mm
    poses = np.array([[0, 0, 0, 0, 0, 0], [0.7, -0.4, 0.3, 0, 0, 0], [0, 0, 0, 0, 0, 0.3]], dtype=float)
    fp = beam_footprint(bench, lens, poses, n_edge=36)
    phi = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    circle = a * np.stack([np.cos(phi), np.sin(phi)], axis=-1)
    np.testing.assert_allclose(fp[0], circle, atol=1e-12)
    np.testing.assert_allclose(fp[1], circle - [0.7, -0.4], atol=1e-12)  # lens moved +t: beam moves -t in {O}
    c, s = np.cos(-0.3), np.sin(-0.3)  # lens rotated +rz: beam rotated -rz in {O}
    np.testing.assert_allclose(fp[2], circle @ np.array([[c, s], [-s, c]]), atol=1e-12)


def test_footprint_of_a_tilted_flat_is_an_ellipse_and_follows_the_sag():
    bench = lf.Bench.default()
    a = 0.5 * bench.laser.beam_diameter_mm
    rx = 0.15
    fp = beam_footprint(bench, _flat(), [[0, 0, 0, rx, 0, 0]], n_edge=8)[0]
    # a plane tilted by rx about x stretches the footprint along y by 1/cos(rx); the beam
    # hits it off the {O} origin because the vertex plane sits l/2 before the origin
    h = 0.5 * _flat().thickness
    np.testing.assert_allclose(fp[:, 0], a * np.cos(np.linspace(0, 2 * np.pi, 8, endpoint=False)), atol=1e-12)
    y_expected = a * np.sin(np.linspace(0, 2 * np.pi, 8, endpoint=False)) / np.cos(rx) - h * np.tan(rx)
    np.testing.assert_allclose(fp[:, 1], y_expected, atol=1e-12)
    # a curved front: the hit points satisfy the ray equation (checked through the sag)
    lens = lf.paper_lens("zernike")
    pose = np.array([0.4, 0.2, -0.5, 0.01, -0.02, 0.05])
    hit = beam_footprint(bench, lens, [pose], n_edge=16)[0]
    from lensforge.optics.trace import pose_frames

    R, t = pose_frames(bench, [pose])
    z = -0.5 * lens.thickness + lens.front.sag(hit[:, 0], hit[:, 1])
    p_s = np.column_stack([hit, z]) @ R[0].T + t[0]  # back to {S}: on the beam circle
    np.testing.assert_allclose(np.hypot(p_s[:, 0], p_s[:, 1]), a, atol=1e-9)


def test_working_range_poses_span_the_box():
    P = working_range_poses(1.0, np.radians(1.0), n_random=10)
    assert P.shape == (1 + 12 + 8 + 10, 6)
    np.testing.assert_allclose(np.max(np.abs(P), axis=0), [1, 1, 1] + [np.radians(1)] * 3)


def test_design_plots_writes_every_png(tmp_path):
    lens = lf.paper_lens("extended_polynomial").replace(edge_diameter=27.4)
    paths = design_plots(lens, tmp_path, stem="ep")
    names = {p.name for p in paths}
    assert names == {f"ep_{k}.png" for k in ("singular_values", "sag", "zernike_response", "footprint",
                                             "lenslet_field", "cross_section", "bench_layout")}
    assert all(p.stat().st_size > 10_000 for p in paths)


def test_convergence_and_handeye_residual_figures(tmp_path):
    hist = [{"iteration": i, "n_evals": 5 * i, "best": 10.0 / (i + 1), "feasible": i > 2} for i in range(20)]
    fig = plot_convergence(hist)
    ax = fig.axes[0]
    assert ax.get_yscale() == "log" and "evaluations" in ax.get_xlabel()
    assert save_figure(plot_convergence([]), tmp_path / "empty.png").stat().st_size > 0
    e = np.random.default_rng(0).normal(size=(7, 6)) * np.array([1e-3] * 3 + [1e-5] * 3)
    fig = plot_handeye_residuals(e, np.arange(7.0))
    assert len(fig.axes) == 3 and "um" in fig.axes[0].get_ylabel() and "mrad" in fig.axes[1].get_ylabel()
    bars = [p.get_height() for p in fig.axes[0].patches[:7]]
    np.testing.assert_allclose(bars, e[:, 0] * 1e3)


@pytest.mark.parametrize("rows", [[{"component": "a", "p95_rot_deg": 0.5, "p95_trans_mm": 2.0},
                                   {"component": "b", "p95_rot_deg": 0.01, "p95_trans_mm": None}]])
def test_sensitivity_bars_start_at_zero_and_budget_has_a_legend(rows, tmp_path):
    from lensforge.plots import study as study_plots

    study_plots.plot_sensitivity(rows, tmp_path / "s.png")
    study_plots.plot_budget([{"component": "a", "max_scale": 0.1}, {"component": "b", "max_scale": 3.0}],
                            tmp_path / "b.png")
    assert (tmp_path / "s.png").exists() and (tmp_path / "b.png").exists()
