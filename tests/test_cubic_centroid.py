"""The window's view of a lenslet's wavefront third derivatives (``centroid.cubic_slopes``, ``cubic_gain``)."""

from pathlib import Path

import numpy as np
import pytest

import lensforge as lf
from lensforge.calibration.session import load_design_lens
from lensforge.optics.centroid import axis_neighbours, cubic_gain, cubic_slopes, quadrature_rule
from lensforge.optics.shack_hartmann import ForwardModel

DATA = Path(__file__).parent / "data"


def _cubic_field(n_side=7, p=0.15):
    c = p * (np.stack(np.meshgrid(np.arange(n_side), np.arange(n_side), indexing="xy"), -1).reshape(-1, 2)
             - 0.5 * (n_side - 1))
    off, w = quadrature_rule(2)
    X = c[:, None, :] + p * off[None]
    x, y = X[..., 0], X[..., 1]
    a, b, cc, d = 0.7, -0.4, 0.9, 0.3  # W = a x^3 + b x^2 y + c x y^2 + d y^3 + 0.02 x^2 - 0.03 x y + 0.01 x
    sq = np.stack([3 * a * x**2 + 2 * b * x * y + cc * y**2 + 0.04 * x - 0.03 * y + 0.01,
                   b * x**2 + 2 * cc * x * y + 3 * d * y**2 - 0.03 * x], axis=-1)
    third = np.array([6 * a + 2 * cc, 6 * d + 2 * b])  # (W_xxx + W_xyy, W_yyy + W_xxy)
    return c, off, w, sq, third


def test_cubic_slopes_are_exact_on_a_cubic_wavefront():
    p = 0.15
    c, off, w, sq, third = _cubic_field(p=p)
    nb = axis_neighbours(c, p)
    wi = np.broadcast_to(w, sq.shape[:-1]).copy()
    want = -p * p / 24 * third
    np.testing.assert_allclose(cubic_slopes(sq, wi, off, w, nb, p, (0.0, 0.0)), np.broadcast_to(want, (len(c), 2)),
                               rtol=1e-10)
    # the gains weigh the direct and cross terms apart: W_xxx = 4.2, W_xyy = 1.8 in s_x
    got = cubic_slopes(sq, wi, off, w, nb, p, (0.9, 0.5))[0]
    np.testing.assert_allclose(got, -p * p / 24 * np.array([0.1 * 4.2 + 0.5 * 1.8, 0.1 * 1.8 + 0.5 * -0.8]),
                               rtol=1e-10)
    # a dark lenslet (a ray lost) is no neighbour: the others difference one-sided, still exact (K is linear)
    wi[24] = 0.0
    out = cubic_slopes(sq, wi, off, w, nb, p, (0.0, 0.0))
    keep = np.arange(len(c)) != 24
    np.testing.assert_allclose(out[keep], np.broadcast_to(want, (keep.sum(), 2)), rtol=1e-10)


def test_cubic_gain_of_the_default_window():
    bench = lf.Bench.default()
    g_d, g_c = cubic_gain(bench.sensor, bench.laser.wavelength_nm)
    assert g_d == pytest.approx(0.896, abs=2e-3) and g_c == pytest.approx(0.948, abs=2e-3)
    assert cubic_gain(bench.replace(sensor={"centroid_window_px": 0}).sensor, 532.0) == (1.0, 1.0)
    # a wider window cuts less of the coma, a noise cut more
    assert cubic_gain(bench.replace(sensor={"centroid_window_px": 41}).sensor, 532.0)[0] > g_d
    assert cubic_gain(bench.replace(sensor={"centroid_threshold": 0.05}).sensor, 532.0)[0] < g_d


def test_sensitivity_with_the_cubic_term_matches_central_differences():
    # the co-designed lens at its plan pose, where the cubic term moves Z3 by 2.5 sigma: S stays exact
    lens, bench = load_design_lens(DATA / "codesign-zernike.json")
    model = ForwardModel(bench, lens)
    pose = np.array([-0.5, -0.5, -0.5, np.radians(-5), np.radians(5), np.radians(5)])
    S = model.jacobians(pose[None])[0][0]
    for i, h in enumerate([2e-3, 2e-3, 2e-3, 2e-4, 2e-4, 2e-4]):
        e = np.zeros(6)
        e[i] = h
        col = (model.evaluate(pose + e).z[0] - model.evaluate(pose - e).z[0]) / (2 * h)
        np.testing.assert_allclose(S[:, i], col, rtol=1e-4, atol=1e-6 * np.abs(S).max())
    # the term's own share of S (~4e-6 of S, below what the check above resolves) against central differences of
    # the term itself: the model's Zernikes with its gain less those without it
    g = model.cubic_gain

    def delta(x):
        model.cubic_gain = g
        z = model.evaluate(x).z[0]
        model.cubic_gain = (1.0, 1.0)
        return z - model.evaluate(x).z[0]

    model.cubic_gain = (1.0, 1.0)
    S0 = model.jacobians(pose[None])[0][0]
    model.cubic_gain = g
    dS = S - S0
    for i, h in enumerate([2e-3, 2e-3, 2e-3, 2e-4, 2e-4, 2e-4]):
        e = np.zeros(6)
        e[i] = h
        np.testing.assert_allclose(dS[:, i], (delta(pose + e) - delta(pose - e)) / (2 * h), rtol=1e-3,
                                   atol=1e-3 * np.abs(dS).max())
    assert np.abs(dS).max() > 1e-6 * np.abs(S).max()


def _lone_lenslet_cells(w3_own, tilt_own, p):
    """A 3 x 3 patch of cells, only the centre one lit: its tilt (2,) and third derivatives (4,)."""
    from lensforge.optics import centroid as C

    ij = np.array([[0, 0]] + [[i, j] for j in (-1, 0, 1) for i in (-1, 0, 1) if (i, j) != (0, 0)])
    centres = p * ij.astype(float)
    off = C._neighbour_offsets(C.CELL_RING).astype(int)
    nb = np.array([[int(np.nonzero(np.all(ij == o, axis=1))[0][0]) if np.all(np.abs(o) <= 1) else -1 for o in off]])
    L = len(ij)
    lit = np.zeros(L, bool)
    lit[0] = True
    tilt, w3 = np.zeros((L, 2)), np.zeros((L, 4))
    tilt[0], w3[0] = tilt_own, w3_own
    cells = {"tilt": tilt, "K": np.zeros((L, 2, 2)), "g": np.zeros((L, 2)), "h": np.zeros((L, 2)),
             "ln_a": np.zeros(L), "lit": lit, "w3": w3}
    return cells, centres, nb


@pytest.mark.parametrize("which, axis, cross", [(0, 0, False), (2, 0, True), (3, 1, False), (1, 1, True)])
def test_cells_kernel_sees_a_lenslets_coma_with_the_fraunhofer_gain(which, axis, cross):
    # 'cells' renders each sub-aperture's coma in its field (``centroid._coma_factors``, first order in k W3); on a
    # lone lenslet its centroid must show the gain that an independent Fraunhofer computation of the same
    # sub-aperture with a cubic phase gives (``cubic_gain``: 0.896 direct, 0.948 cross); measured 0.8948 / 0.9471
    # against 0.8959 / 0.9481 (the kernel places its window on whole pixels, the Fraunhofer one centres it)
    from lensforge.optics.centroid import cell_shift

    bench = lf.Bench()
    s, wl = bench.sensor, bench.laser.wavelength_nm
    p, f = s.pitch_mm, s.lenslet_focal_mm
    c = 0.03  # 1/mm^2
    share = c * p * p / 24  # the cubic's share of the mean slope
    cen = []
    for sgn in (1, -1):
        w3, tilt = np.zeros(4), np.zeros(2)
        w3[which], tilt[axis] = sgn * c, sgn * share
        cells, centres, nb = _lone_lenslet_cells(w3, tilt, p)
        spot = centres[:1] + f * tilt
        cen.append(f * tilt[axis] + cell_shift(spot, cells, centres, nb, s, wl)[0, axis])
    gain = 0.5 * (cen[0] - cen[1]) / (f * share)
    want = cubic_gain(s, wl)[1 if cross else 0]
    assert abs(gain - want) < 3e-3, (gain, want)
    assert abs(gain - 1.0) > 0.04  # the window's cut is seen at all
