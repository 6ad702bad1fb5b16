"""Sensor model figures: S(p) cost of the sub-aperture quadrature, and what a WFS40 can measure.

Run: .venv/bin/python benchmarks/bench_sensor_range.py
1. wall time of one S(p) per paper lens with lenslet-centre sampling (quadrature 1,
   the old model) and the default 2x2 Gauss-Legendre sub-aperture rule;
2. per paper lens at the nominal pose: max centroid slope and lenslets out of range
   for lenslet focal lengths 4.1-6.7 mm (the focal length is an assumption), fixed
   windows and tracking;
3. bench geometry: per lens and pupil radius the lens-sensor distances (10-60 mm) on
   which it is measurable with fixed windows at f = 5.2 mm, and the best one;
4. what the old lenslet-centre model would do on real data: the pose it estimates
   (noise-free, nominal pose) from the centroid model's Zernikes, in CRLB units.
"""

from __future__ import annotations

import numpy as np

import lensforge as lf
from lensforge.design.sensor_bench import best_distance, measurable_geometry
from lensforge.optics.sensitivity import sensitivity_from_model
from lensforge.optics.shack_hartmann import ForwardModel

from bench_optics import best_of  # the script's folder is on sys.path

LENSES = ["spherical", "polynomial", "extended_polynomial", "zernike"]


def main():
    bench = lf.Bench.default()
    print("1. S(p) cost (best of 5 x 10)")
    for name in LENSES:
        lens = lf.paper_lens(name)
        t = {}
        for q in (1, 2):
            m = ForwardModel(bench.replace(sensor={"subaperture_quadrature": q}), lens)
            sensitivity_from_model(m)
            t[q] = best_of(lambda: sensitivity_from_model(m), repeat=5, number=10)
        print(f"  {name:20s} centre {t[1] * 1e3:6.2f} ms  2x2 quadrature {t[2] * 1e3:6.2f} ms  ratio {t[2] / t[1]:.2f}")
    print("2. nominal pose vs lenslet focal length (max slope mrad; lenslets out of 113: fixed / tracking)")
    for name in LENSES:
        lens = lf.paper_lens(name)
        cells = []
        for f in (4.1, 5.2, 6.0, 6.7):
            out = []
            for mode in ("fixed", "tracking"):
                sr = ForwardModel(bench.replace(sensor={"lenslet_focal_mm": f, "spot_assignment": mode}), lens).sensor_range()
                out.append(sr.lenslets_out)
            cells.append(f"f={f}: {out[0]:3d}/{out[1]:d}")
        print(f"  {name:20s} max {sr.max_slope_mrad:5.1f} mrad  " + "  ".join(cells))
    print("3. fixed windows, f = 5.2 mm: measurable lens-sensor distances per pupil radius")
    fixed = bench.replace(sensor={"spot_assignment": "fixed"})
    for name in LENSES:
        rows = measurable_geometry(fixed, lf.paper_lens(name), np.arange(10.0, 61.0, 2.5), (0.45, 0.6, 0.9))
        for r, best in best_distance(rows).items():
            txt = "none" if best is None else (f"{min(best['measurable_mm']):.1f}-{max(best['measurable_mm']):.1f} mm, "
                                               f"best {best['distance_mm']:.1f} mm (use {best['max_use']:.2f})")
            print(f"  {name:20s} pupil radius {r:.2f} mm: {txt}")
    centre_model_bias()


def centre_model_bias():
    from lensforge.calibration.pose_estimation import estimate_pose_model

    bench = lf.Bench.default()
    old = bench.replace(sensor={"subaperture_quadrature": 1, "centroid_window_px": 0, "spot_assignment": "none"})
    print("4. old centre model fitted to centroid-model data (nominal pose): pose bias / CRLB, chi2 (8 dof)")
    for name in ["polynomial", "extended_polynomial"]:
        lens = lf.paper_lens(name)
        z = ForwardModel(bench, lens).zernike(np.zeros(6))
        r = estimate_pose_model(ForwardModel(old, lens), z, np.zeros(6))
        print(f"  {name:20s} tz bias {r.pose[2] * 1e3:6.1f} um  bias/CRLB {np.round(r.pose / r.std, 1)}  chi2 {r.chi2:.3g}")


if __name__ == "__main__":
    main()
