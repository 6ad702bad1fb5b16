"""lensforge's fast sensor model against the full-array physical reference (issue 21).

Run: PYTHONPATH=. .venv/bin/python benchmarks/bench_sensor_physics.py [--design DESIGN.json]
     [--lenses polynomial,extended_polynomial] [--poses 4] [--variants base,cut5,round,noxtalk]
     [--spp 4] [--json OUT.json]
     ... --design DESIGN.json --sessions 6 --spp 4 [--calibration-tolerances default] [--calibration-crosstalk neighbours]:
         the session study (calibrate with the cross-talk model against the physical sensor)
         [--focal-sigma 0.01] [--true-focal 5.226]: calibrate estimates the focal-length gain; the physical
         lenslets' true focal length differs from the bench's, which the device converts with
     ... --combine S0.json S1.json ... [--json ALL.json]: session-study runs (e.g. one seed a run, both sensors)
         reported as one study, with the physical / own-model Z error ratio over the seeds both measured
     ... --design DESIGN.json --validate COMPARE.json [--assume centroid_threshold=0]: the cross-talk model at a
         compare run's poses (--assume: the model takes another sensor setting than the reference: a wrong one)
     ... --pose-bias COMPARE.json [--models none,cells]: the poses estimated from the physical Zernikes (Table 1)
     ... --round-parts [--lenses polynomial] [--poses 2]: round 140 um lenslets against square ones, every third
         lit: the physical Zernike shift and the own spot's share of it (the own centroid over the disc)
     ... --cost: S(p) with and without the cross-talk model, one physical pose
     ... --fit-cost [--no-whole]: one pose estimate on 'cells', the frozen cross-talk correction against the
         trust region on the whole model (time, difference in sigma)
     ... --cut-scan [--lenses polynomial] [--poses 1] [--cuts 0.03,0.04,...] [--cut-ref 0.05]: the noise cut's effect,
         physical reference and 'cells' at each cut, in sigma against the same sensor at --cut-ref (is the cut a
         smooth nuisance a fit could estimate?)
     ... --estimate-mc N [--pupil 0.5] [--zernike-order 3] [--seed 0]: pose estimates of N noisy draws measured by
         'cells' at one pose (by default a small pupil: 'cells' costs seconds a pose), by the 'cells' estimator and
         the own-centroid one: RMSE / CRLB per DOF, NEES, bias (the estimate study, old against new)
     ... --spheres [--design D] [--radii 1e9,100,-100] [--beam-offset 0,3] [--tilt 30,0] [--hessian 0,-10.7,0]:
         analytic spherical waves (R = +-20 ... 100 mm, uniform and Gaussian beam, optionally off-centre, a tilt and
         a quadratic added; --hessian alone: that quadratic, e.g. a saddle) through the physical reference against
         the fast models, no lens (what the cross-talk kernel misses, isolated)
     ... --gradient-coupling --hessian 0,-10.7,0 --beam-offset 0,2 [--beam-scale 0.5] [--pupil 0.4] [--ring 4]
         [--margin 5] [--spp 4] [--design D]: the slopes' part odd in the beam's offset (the curvature weighted by
         the irradiance gradient), physical reference against 'cells' (a block of --ring rings) and the own window

Per lens (the design file's and paper lenses) at nominal and at the calibration plan's most
extreme poses (largest |pose| scaled by the bench's pose scales, ``plan`` with 12 poses, seed 0):
the per-mode difference physical - model in sigma of lensforge's own measurement noise (sqrt of
diag R) and in nm, per reference-model variant:
  base     square, fully filled lenslets, no noise cut (the bench's defaults)
  cut5     a 5 % per-spot noise cut (sensor.centroid_threshold = 0.05, model and reference alike)
  round    round 140 um lenslets with dark gaps
  noxtalk  cross-talk taken out (every 3rd lenslet lit at a time): what remains is pixelisation,
           whole-pixel window placement and truncation
  f41/f67  lenslet focal length 4.1 / 6.7 mm (model and reference alike)
  beamref  the user reference recorded with the bench's laser and no lens (WFS_SetSpotsToUserReference)
  widebeam a 100 mm beam (no Gaussian irradiance gradient; the lens's own flux gradient stays), model alike
Also the cost of one physical pose and of the fast model's S(p).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

import lensforge as lf
from lensforge.calibration.session import load_design_lens
from lensforge.errors import ConfigError
from lensforge.optics.shack_hartmann import ForwardModel
from lensforge.fileio import check_output, write_atomic
from lensforge.verification.physical_sensor import PhysicalSensor, physical_measure
from lensforge.verification.session_sim import extreme_poses

VARIANTS = {
    "base": ({}, {}),
    "cut5": ({"centroid_threshold": 0.05}, {}),
    "round": ({}, {"aperture": "round"}),
    "noxtalk": ({}, {"lit_stride": 3}),
    "f41": ({"lenslet_focal_mm": 4.1}, {}),
    "f67": ({"lenslet_focal_mm": 6.7}, {}),
    "beamref": ({}, {"reference": "beam"}),
    "widebeam": ({"laser": {"beam_diameter_mm": 100.0}}, {}),
}
# what a variant changes in the fast models that render it ('cells' only: round lenslets), not in the own-centroid
# model the compare run scores as 'old'
FAST_CHANGES = {"round": {"lenslet_aperture": "round"}}


def compare(lens, bench, poses, variant: str, spp: int, margin: int = 5) -> dict:
    sensor_changes, phys_changes = VARIANTS[variant]
    changes = dict(sensor_changes)
    laser = changes.pop("laser", None)
    b = bench.replace(**({"sensor": changes} if changes else {}), **({"laser": laser} if laser else {}))
    model = ForwardModel(b, lens)
    cfg = PhysicalSensor(samples_per_pixel=spp, **{"margin_lenslets": margin, **phys_changes})
    sig = np.sqrt(np.diag(model.noise_cov))
    res = model.evaluate(poses, check_range=False)
    rows = []
    for i, x in enumerate(poses):
        t0 = time.perf_counter()
        r = physical_measure(model, x, cfg)
        dt = time.perf_counter() - t0
        dz = r.z - res.z[i]
        rows.append({"pose": x.tolist(), "valid": bool(res.valid[i]), "max_slope_mrad": float(np.abs(res.slopes[i]).max() * 1e3),
                     "dz_sigma": (dz / sig).tolist(), "dz_nm": (dz * 1e3).tolist(), "seconds": dt,
                     "z_model_um": res.z[i].tolist(), "z_physical_um": r.z.tolist(),
                     "potential_residual_urad": list(r.potential_residual_urad)})
    return {"modes": model.modes.tolist(), "sigma_nm": (sig * 1e3).tolist(), "rows": rows}


def _worst(sig, modes) -> str:
    """'value(Z mode)' of the largest |dz| / sigma of one pose."""
    i = int(np.argmax(np.abs(sig)))
    return f"{sig[i]:+5.1f}(Z{modes[i]})"


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a number")


def _read_json(path: str, fix: str, what: str) -> dict:
    """A JSON object of at least one entry (no NaN or infinity) from path; else a ConfigError naming it and fix."""
    try:
        with open(path, encoding="utf-8") as fh:
            d = json.load(fh, parse_constant=_reject_constant)
    except OSError as e:
        raise ConfigError(f"{path}: cannot read it ({e.strerror}): {fix}") from None
    except (ValueError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: not valid JSON ({e}): {fix}") from None
    if not isinstance(d, dict) or not d:
        raise ConfigError(f"{path}: no {what}: {fix}")
    return d


_SESSION_LISTS = ("nees", "chi2_dof", "p_values", "z_translation_error_mm", "z_rotation_error_deg", "seeds")


def load_sessions(path: str) -> dict:
    """A session-study JSON (``--sessions ... --json``), checked: per sensor, the lists of ``_SESSION_LISTS``, finite
    and of one length, and the inside-3-sigma fractions. A bad file is a ConfigError naming the file, the entry and
    the fix."""
    fix = "give the --json files session-study runs wrote (--sessions N ... --json FILE)"
    d = _read_json(path, fix, "sensors")
    for sensor, r in d.items():
        where = f"{path}: sensor {sensor!r}"
        if not isinstance(r, dict):
            raise ConfigError(f"{where}: not a session-study record: {fix}")
        lengths = set()
        for key in _SESSION_LISTS:
            v = r.get(key)
            if not (isinstance(v, list) and v and all(isinstance(x, (int, float)) for x in v) and np.all(np.isfinite(v))):
                raise ConfigError(f"{where}: {key!r} must be a non-empty list of finite numbers: {fix}")
            lengths.add(len(v))
        if len(lengths) > 1:
            raise ConfigError(f"{where}: the lists {', '.join(_SESSION_LISTS)} differ in length: {fix}")
        for key in ("inside_3sigma", "inside_3sigma_each_axis"):
            if not (isinstance(r.get(key), (int, float)) and 0.0 <= r[key] <= 1.0):
                raise ConfigError(f"{where}: {key!r} must be a fraction in [0, 1]: {fix}")
    return d


def load_compare(path: str) -> dict:
    """A compare JSON (this script's --json of a compare run), checked: every key 'label/variant' with its Noll
    ``modes`` and ``rows`` of a finite 6-vector ``pose`` and finite ``z_physical_um`` / ``z_model_um`` per mode.
    A bad file is a ConfigError naming the file, the entry and the fix."""
    fix = "give the --json file a compare run wrote (--lenses/--design ... --json FILE)"
    d = _read_json(path, fix, "compare entries")
    for key, r in d.items():
        where = f"{path}: entry {key!r}"
        if key.count("/") != 1 or not isinstance(r, dict):
            raise ConfigError(f"{where}: not a 'label/variant' compare entry: {fix}")
        modes, rows = r.get("modes"), r.get("rows")
        if not (isinstance(modes, list) and modes and all(isinstance(m, int) for m in modes)):
            raise ConfigError(f"{where}: 'modes' must be a list of Noll indices: {fix}")
        if not (isinstance(rows, list) and rows):
            raise ConfigError(f"{where}: 'rows' must be a non-empty list of poses: {fix}")
        for i, row in enumerate(rows):
            for field, n in (("pose", 6), ("z_physical_um", len(modes)), ("z_model_um", len(modes))):
                v = row.get(field) if isinstance(row, dict) else None
                ok = isinstance(v, list) and len(v) == n and all(isinstance(x, (int, float)) for x in v)
                if not ok or not np.all(np.isfinite(v)):
                    raise ConfigError(f"{where}: rows[{i}].{field} must be {n} finite numbers: {fix}")
    return d


def _check_modes(path: str, key: str, r: dict, model: ForwardModel) -> None:
    if list(model.modes) != r["modes"]:
        raise ConfigError(f"{path}: entry {key!r}: its modes {r['modes']} are not the model's {model.modes.tolist()}: "
                          "the file was written for another bench or Zernike order; rerun the compare")


def _entry_lens(path: str, key: str, design: str | None):
    """(variant, lens, bench) of a compare entry 'label/variant': the label's paper lens, or the --design file's."""
    label, variant = key.split("/")
    if variant not in VARIANTS:
        raise ConfigError(f"{path}: entry {key!r}: unknown variant {variant!r} (one of {sorted(VARIANTS)})")
    if label == "design" and not design:
        raise ConfigError(f"{path}: entry {key!r} is a design's: give its file with --design")
    return (variant, *load_design_lens(design if label == "design" else label))


def validate(path: str, design: str | None, models=("neighbours", "cells"), assume: dict | None = None) -> dict:
    """The fast cross-talk models (sensor.crosstalk, ``models``) at the poses of a compare() JSON: per pose
    max |dz|/sigma of the old model (the compare run's own-centroid model) and of each, against the physical
    reference. assume: sensor settings the fast models take instead of the compare's (e.g. centroid_threshold 0
    against a cut5 reference: what a wrong noise-cut setting costs)."""
    d = load_compare(path)
    out = {}
    for key, r in d.items():
        variant, lens, bench = _entry_lens(path, key, design)
        if variant == "noxtalk":  # a diagnostic
            continue
        sensor_changes, _ = VARIANTS[variant]
        changes = dict(sensor_changes)
        laser = changes.pop("laser", None)
        poses = np.array([row["pose"] for row in r["rows"]])
        rows = [{"old_sigma": None} for _ in r["rows"]]
        line = f"{key:28s} max |dz|/sigma old: "
        fast = FAST_CHANGES.get(variant, {})
        mods = [m for m in models if m == "cells" or not fast]  # round lenslets: 'cells' alone renders them
        if not mods:
            continue
        for mname in mods:
            b = bench.replace(sensor={**changes, **fast, **(assume or {}), "crosstalk": mname},
                              **({"laser": laser} if laser else {}))
            model = ForwardModel(b, lens)
            _check_modes(path, key, r, model)
            sig = np.sqrt(np.diag(model.noise_cov))
            t0 = time.perf_counter()
            z_new = model.evaluate(poses, check_range=False).z
            dt = (time.perf_counter() - t0) / len(poses)
            for i, row in enumerate(r["rows"]):
                zp, zo = np.array(row["z_physical_um"]), np.array(row["z_model_um"])
                rows[i]["old_sigma"] = ((zp - zo) / sig).tolist()
                rows[i][f"{mname}_sigma"] = ((zp - z_new[i]) / sig).tolist()
                rows[i][f"z_{mname}_um"] = z_new[i].tolist()
            rows_m = [max(np.abs(x[f"{mname}_sigma"])) for x in rows]
            out.setdefault(key, {"modes": r["modes"], "rows": rows})[f"seconds_per_pose_{mname}"] = dt
        line += " ".join(f"{max(np.abs(x['old_sigma'])):6.1f}" for x in rows)
        for mname in mods:
            line += f" | {mname}: " + " ".join(_worst(x[f"{mname}_sigma"], r["modes"]) for x in rows)
        print(line, flush=True)
        print("  per mode (sigma), modes " + " ".join(f"{m:>6d}" for m in r["modes"]), flush=True)
        for i, x in enumerate(rows):  # the issue's table: old model, new model(s), against the physical reference
            for mname in ("old", *mods):
                print(f"  pose {i} {mname:>10s}" + " " * 12 + " ".join(f"{v:+6.2f}" for v in x[f"{mname}_sigma"]),
                      flush=True)
    return out


def pose_bias(path: str, models=("none", "cells"), design: str | None = None) -> dict:
    """The Table-1 analogue on the physical sensor: each pose of a compare() JSON estimated from the physical
    reference's noise-free Zernikes with each sensor model (started at the truth); the error in units of the
    estimate's own 1-sigma per DOF and its NEES (6 DOF; noise-free data: 0 for a model that matched the physics).
    design: the design file of the JSON's 'design/...' entries (as --validate)."""
    from lensforge.calibration.pose_estimation import estimate_poses_batch

    d = load_compare(path)
    out = {}
    for key, r in d.items():
        variant, lens, bench = _entry_lens(path, key, design)
        if variant not in ("base", *FAST_CHANGES):
            continue
        label = key if variant != "base" else key.split("/")[0]
        fast = FAST_CHANGES.get(variant, {})
        poses = np.array([row["pose"] for row in r["rows"]])
        z = np.array([row["z_physical_um"] for row in r["rows"]])
        for mname in models:
            model = ForwardModel(bench.replace(sensor={"crosstalk": mname, **(fast if mname == "cells" else {})}),
                                 lens)
            _check_modes(path, key, r, model)
            est = estimate_poses_batch(model, z, poses)
            sig = np.sqrt(np.einsum("pii->pi", est.cov))
            err = (est.poses - poses) / sig
            nees = np.einsum("pi,pij,pj->p", est.poses - poses, np.linalg.pinv(est.cov), est.poses - poses)
            out[f"{label}/{mname}"] = {"error_sigma": err.tolist(), "nees": nees.tolist(),
                                      "converged": est.converged.tolist()}
            print(f"{label:20s} {mname:6s} worst |error| / sigma per pose: "
                  + " ".join(f"{v:6.2f}" for v in np.abs(err).max(axis=1))
                  + " | NEES: " + " ".join(f"{v:8.2f}" for v in nees), flush=True)
    return out


def cost(lens_name: str = "zernike", repeat: int = 3) -> dict:
    """Wall time of one S(p) (sensitivity_from_model at nominal) and of one physical pose, per sensor model."""
    from lensforge.optics.sensitivity import sensitivity_from_model

    out = {}
    for xt in ("none", "neighbours", "cells"):
        model = ForwardModel(lf.Bench.default().replace(sensor={"crosstalk": xt}), lf.paper_lens(lens_name))
        sensitivity_from_model(model)  # warm (compiles, caches)
        best = np.inf
        for _ in range(repeat if xt != "cells" else 1):  # 'cells' is ~10^4 x the others: one timing
            t0 = time.perf_counter()
            sensitivity_from_model(model)
            best = min(best, time.perf_counter() - t0)
        out[xt] = best
        print(f"S(p), {lens_name} lens, crosstalk={xt}: {best * 1e3:.1f} ms", flush=True)
    model = ForwardModel(lf.Bench.default(), lf.paper_lens(lens_name))
    for spp in (3, 4):  # the Zernike lens's 56 mrad need >= 3 (physical_sensor refuses fewer)
        t0 = time.perf_counter()
        physical_measure(model, np.zeros(6), PhysicalSensor(samples_per_pixel=spp))
        out[f"physical_spp{spp}"] = time.perf_counter() - t0
        print(f"physical sensor, one pose, {spp} samples/pixel: {out[f'physical_spp{spp}']:.1f} s", flush=True)
    return out


def fit_cost(lens_name: str = "polynomial", whole: bool = True, seed: int = 0) -> dict:
    """Wall time of one pose estimate on the 'cells' model (a noisy measurement at the plan's most extreme pose,
    started 0.3 mm / 1 deg off): the frozen cross-talk correction (``estimate_poses_batch``'s default) and, with
    whole, the trust region on the whole model; their estimates' difference in sigma."""
    from lensforge.calibration.pose_estimation import estimate_poses_batch

    bench = lf.Bench.default().replace(sensor={"crosstalk": "cells"})
    model = ForwardModel(bench, lf.paper_lens(lens_name))
    x_true = extreme_poses(model.lens, lf.Bench.default(), 1)[1:]
    z = model.evaluate(x_true, check_range=False).z
    z = z + np.random.default_rng(seed).standard_normal(z.shape) @ np.linalg.cholesky(model.noise_cov).T
    x0 = x_true + np.array([0.3, -0.2, 0.2, 0.01, -0.01, 0.02])
    out = {}
    for frozen in (True, False) if whole else (True,):
        t0 = time.perf_counter()
        est = estimate_poses_batch(model, z, x0, frozen_crosstalk=frozen)
        label = "frozen" if frozen else "whole"
        out[label] = {"seconds": time.perf_counter() - t0, "pose": est.poses[0].tolist(), "chi2": float(est.chi2[0]),
                      "status": str(est.status[0]), "std": np.sqrt(np.diag(est.cov[0])).tolist()}
        print(f"pose estimate on 'cells', {lens_name} lens, {label}: {out[label]['seconds']:.0f} s, chi2 "
              f"{est.chi2[0]:.3f}, {est.status[0]}", flush=True)
    if whole:
        d = (np.array(out["frozen"]["pose"]) - out["whole"]["pose"]) / np.array(out["whole"]["std"])
        out["difference_sigma"] = d.tolist()
        print(f"frozen - whole: {np.round(d, 4).tolist()} sigma", flush=True)
    return out


def cut_scan(lens_name: str = "polynomial", n_poses: int = 1, cuts=(0.03, 0.04, 0.045, 0.049, 0.051, 0.055, 0.06),
             cut_ref: float = 0.05, spp: int = 4, margin: int = 5) -> dict:
    """The noise cut's effect on the reported Zernikes: at nominal and the plan's most extreme poses, the physical
    reference and 'cells' at each cut c minus the same sensor at cut_ref, per mode in sigma of lensforge's own noise
    ('cells' with its windows frozen at cut_ref's: the cut alone), and 'cells' - physical at each cut."""
    lens, bench = load_design_lens(lens_name)
    poses = extreme_poses(lens, bench, n_poses)
    ref_bench = bench.replace(sensor={"crosstalk": "cells", "centroid_threshold": cut_ref})
    ref_model = ForwardModel(ref_bench, lens)
    sig = np.sqrt(np.diag(ref_model.noise_cov))
    ref = ref_model.evaluate(poses, check_range=False)
    cfg = PhysicalSensor(samples_per_pixel=spp, margin_lenslets=margin)  # takes each model's cut
    models = {c: ForwardModel(ref_bench.replace(sensor={"centroid_threshold": c}), lens) for c in cuts}
    rows = []
    for i, x in enumerate(poses):
        phys_ref = physical_measure(ref_model, x, cfg).z
        for c, model in models.items():
            zc = model.evaluate(x[None], check_range=False, windows=ref.windows[i:i + 1]).z[0]
            zp = physical_measure(model, x, cfg).z
            d = {"physical_sigma": (zp - phys_ref) / sig, "cells_sigma": (zc - ref.z[i]) / sig,
                 "cells_minus_physical_sigma": (zc - zp) / sig}
            rows.append({"pose": i, "cut": c, **{k: v.tolist() for k, v in d.items()}})
            print(f"pose {i} cut {c:.4f}: physical {_worst(d['physical_sigma'], ref_model.modes)} "
                  f"cells {_worst(d['cells_sigma'], ref_model.modes)} "
                  f"cells - physical {_worst(d['cells_minus_physical_sigma'], ref_model.modes)}", flush=True)
    return {"modes": ref_model.modes.tolist(), "cut_ref": cut_ref, "rows": rows}


def estimate_mc(n_draws: int = 24, pupil_mm: float = 0.5, seed: int = 0, order: int = 3) -> dict:
    """Monte Carlo of the pose estimate on data the 'cells' model measures (the paper polynomial lens, a pupil of
    radius pupil_mm, Zernike order ``order``, one pose 0.5 mm / 1.7 deg off nominal, n_draws noise draws of the bench's
    Zernike covariance), estimated with the 'cells' model (new) and the own-centroid model (old) from a start
    beyond the noise: per DOF the RMSE over the CRLB (the exact 'cells' Jacobian's at the truth), the mean error
    over the CRLB, and the NEES with each estimator's reported covariance (6 expected); the RMSE / CRLB and mean
    NEES are the estimate study's (``LensStudy.summary``); and how many estimates fit their data worse than the truth
    does (an estimator at its objective's minimum has none)."""
    from lensforge.calibration.pose_estimation import estimate_poses_batch
    from lensforge.verification.estimation_study import NOT_CONVERGED, OK, LensStudy

    bench = lf.Bench.default().replace(sensor={"crosstalk": "cells", "pupil_radius_mm": pupil_mm,
                                               "zernike_order": order})
    lens = lf.paper_lens("polynomial")
    cells = ForwardModel(bench, lens)
    own = ForwardModel(bench.replace(sensor={"crosstalk": "none"}), lens)
    x_true = np.array([0.2, -0.1, 0.4, np.radians(0.8), np.radians(-0.5), np.radians(1.5)])
    rng = np.random.default_rng(seed)
    clean = cells.evaluate(x_true[None], check_range=False).z[0]
    z = clean + rng.standard_normal((n_draws, clean.size)) @ np.linalg.cholesky(cells.noise_cov).T
    x0 = np.tile(x_true + np.array([0.1, -0.08, 0.2, 4e-3, -3e-3, 8e-3]), (n_draws, 1))
    Jw = cells.whitener @ cells.jacobians(x_true[None], exact=True)[0][0]
    info = Jw.T @ Jw
    crlb = np.sqrt(np.diag(np.linalg.inv(info)))
    out = {"crlb": crlb.tolist(), "n_draws": n_draws, "pupil_mm": pupil_mm, "zernike_order": order,
           "information_condition": float(np.linalg.cond(info))}
    truth = np.tile(x_true, (n_draws, 1))
    # the objective at the truth (the draw's noise, whitened): an estimate above it has missed the minimum
    w = (z - clean) @ cells.whitener.T
    chi2_truth = np.sum(w * w, axis=1)
    out["chi2_truth"] = chi2_truth.tolist()
    for name, model in (("cells", cells), ("own", own)):
        t0 = time.perf_counter()
        est = estimate_poses_batch(model, z, x0)
        e = est.poses - x_true
        ok = np.asarray(est.converged, bool)
        study = LensStudy(name=name, method="lm", errors=np.where(ok[:, None], e, np.nan), true_poses=truth,
                          status=np.where(ok, OK, NOT_CONVERGED),
                          reported_std=np.sqrt(np.clip(np.diagonal(est.cov, 0, 1, 2), 0.0, None)),
                          crlb_var=np.tile(crlb ** 2, (n_draws, 1)), chi2=np.asarray(est.chi2, float),
                          nees=est.nees(truth), n_evals=np.full(n_draws, est.n_evals / n_draws), dof=clean.size - 6,
                          seconds=time.perf_counter() - t0)
        summary = study.summary()
        nees = study.nees[ok]
        r = {"converged": int(ok.sum()), "rmse_over_crlb": list(summary["rmse_over_crlb"].values()),
             "bias_over_crlb": (np.mean(e[ok], axis=0) / crlb).tolist(),
             "nees_mean": summary["mean_nees_per_dof"] * int(study.observable.sum()),
             "nees": nees.tolist(), "error_over_crlb": (e / crlb).tolist(), "status": list(map(str, est.status)),
             "chi2": study.chi2.tolist(), "seconds": study.seconds,
             "above_truth_chi2": int(np.sum(ok & (study.chi2 > chi2_truth)))}
        out[name] = r
        print(f"{name:5s} estimator, {ok.sum()}/{n_draws} converged ({r['above_truth_chi2']} with chi2 above the "
              f"truth's): RMSE/CRLB "
              f"{np.round(r['rmse_over_crlb'], 2).tolist()} | bias/CRLB {np.round(r['bias_over_crlb'], 2).tolist()} | "
              f"NEES mean {r['nees_mean']:.2f} (6), median {np.median(nees):.2f} (5.35), max {np.max(nees):.1f} | "
              f"{r['seconds']:.0f} s", flush=True)
    return out


def _disc_rule(diameter_rel: float, n_r: int = 4, n_t: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """(offsets (n_r n_t, 2) in pitches, weights summing to 1): a polar rule over a centred disc of diameter
    diameter_rel pitches, Gauss-Legendre in r^2 (uniform in area) and the midpoint rule in angle."""
    u, wu = np.polynomial.legendre.leggauss(n_r)
    rho = 0.5 * diameter_rel * np.sqrt(0.5 * (u + 1.0))
    th = 2 * np.pi * (np.arange(n_t) + 0.5) / n_t
    off = np.stack([np.outer(rho, np.cos(th)).ravel(), np.outer(rho, np.sin(th)).ravel()], axis=1)
    return off, np.repeat(0.5 * wu / n_t, n_t)


def round_parts(lens_name: str = "polynomial", n_poses: int = 2, spp: int = 4, margin: int = 5) -> dict:
    """Where round lenslets (140 um, dark gaps) move the physical Zernikes, with every third lenslet lit (no near
    cross-talk): physical round - square, against the own spot's share, the own-centroid model's irradiance-weighted
    slope over the disc instead of the square (``_disc_rule``), at nominal and the plan's extreme poses; sigma of
    lensforge's own noise."""
    lens, bench = load_design_lens(lens_name)
    poses = extreme_poses(lens, bench, n_poses)
    model = ForwardModel(bench, lens)
    cfg = {a: PhysicalSensor(samples_per_pixel=spp, margin_lenslets=margin, lit_stride=3, aperture=a)
           for a in ("square", "round")}
    disc = ForwardModel(bench, lens, quadrature=_disc_rule(cfg["round"].shape(bench.sensor)[1] / bench.sensor.pitch_mm))
    sig = np.sqrt(np.diag(model.noise_cov))
    z_sq, z_disc = model.evaluate(poses, check_range=False).z, disc.evaluate(poses, check_range=False).z
    rows = []
    for i, x in enumerate(poses):
        phys = {a: physical_measure(model, x, c).z for a, c in cfg.items()}
        row = {"pose": x.tolist(), "physical_round_minus_square": ((phys["round"] - phys["square"]) / sig).tolist(),
               "own_disc_minus_square": ((z_disc[i] - z_sq[i]) / sig).tolist()}
        rows.append(row)
        print(f"{lens_name} pose {i}: physical round - square "
              + " ".join(f"Z{m}:{v:+.1f}" for m, v in zip(model.modes, row["physical_round_minus_square"]))
              + " | own spot's share (disc - square): "
              + " ".join(f"Z{m}:{v:+.1f}" for m, v in zip(model.modes, row["own_disc_minus_square"]) if abs(v) >= 0.1),
              flush=True)
    return {"modes": model.modes.tolist(), "rows": rows}


def _check_wave(bench, lit: np.ndarray, radius, tilt, hessian) -> None:
    """ConfigError unless the analytic wave's slopes over the lit lenslets (L, 2) stay within the sensor's
    validated range (a steeper one would make NaN slopes or a reference the sampling refuses, after the work)."""
    from lensforge.verification.physical_sensor import analytic_wave_quadratures

    lim = 1e-3 * bench.sensor.validated_slope_mrad
    with np.errstate(invalid="ignore"):
        sq = analytic_wave_quadratures(bench, lit, radius, False, (0.0, 0.0), tilt, hessian)[0]
    if not np.all(np.abs(sq) <= lim):
        raise ConfigError(f"--radii/--tilt/--hessian: the wave's slopes over the lit lenslets exceed the sensor's "
                          f"validated {bench.sensor.validated_slope_mrad:g} mrad (radius {radius}); give a gentler wave")


def spheres(radii=(20.0, 30.0, -30.0, 60.0, 100.0, -100.0), spp: int = 4, margin: int = 5,
            design: str | None = None, beam_offset_mm=(0.0, 0.0), tilt=(0.0, 0.0), hessian=None) -> dict:
    """Physical reference minus fast model (sigma per mode) for spherical waves converging to R mm after
    the lenslets (R < 0 diverging; None: no sphere), uniform or with the bench's Gaussian beam (centred at
    beam_offset_mm: an irradiance gradient across the pupil), over the bench's pupil (the design file's bench, else
    the default); tilt (tan) and hessian (2, 2) 1/mm (a saddle: the cross curvature alone) added to each wave."""
    from lensforge.optics.centroid import cell_crosstalk_slopes, centroid_slopes, crosstalk_slopes, lit_lenslets
    from lensforge.verification.physical_sensor import analytic_wave_quadratures, field_slopes, plane_field


    bench = load_design_lens(design)[1] if design else lf.Bench.default()
    if np.hypot(*beam_offset_mm) >= 0.5 * bench.laser.beam_diameter_mm:
        raise ConfigError(f"--beam-offset {beam_offset_mm}: the beam's centre must lie within its 1/e^2 radius "
                          f"({0.5 * bench.laser.beam_diameter_mm:g} mm) of the sensor axis, or the pupil goes dark")
    m = ForwardModel(bench, lf.paper_lens("polynomial"))  # its pupil, rule and fit only: no lens is traced
    c, p, off, w = m.pupil.centres, bench.sensor.pitch_mm, m.quad_offsets, m.quad_weights
    lit, nbrs = lit_lenslets(bench.sensor, c)  # 'cells' traces every lit lenslet's own quadrature rays
    for R in radii:  # the waves the sensor can take over its lit lenslets, before any work
        _check_wave(bench, lit, R, tilt, hessian)
    out = {}
    for gauss in (False, True):
        for R in radii:
            row = {}
            for xt in ("none", "neighbours", "cells"):
                X = (lit if xt == "cells" else c)[:, None, :] + p * off[None]
                sq, irr = analytic_wave_quadratures(bench, X, R, gauss, beam_offset_mm, tilt, hessian)
                wi = w * irr
                if xt == "cells":
                    row[xt] = m.pupil.fit(cell_crosstalk_slopes(sq, wi, off, w, lit, nbrs, bench.sensor,
                                                                bench.laser.wavelength_nm))
                    continue
                s = centroid_slopes(sq, wi, off, w, m.window_gain)
                if xt == "neighbours":
                    s = crosstalk_slopes(s[None], sq[None], wi[None], off, w, c, bench.sensor, bench.laser.wavelength_nm)[0]
                row[xt] = m.pupil.fit(s)
            cfg = PhysicalSensor(samples_per_pixel=spp, margin_lenslets=margin)
            zp = m.pupil.fit(field_slopes(plane_field(bench, cfg, c, tilt, gauss, R, beam_offset_mm, hessian),
                                          bench, cfg, c)[0])
            sig = np.sqrt(np.diag(m.noise_cov))
            j3, j4 = list(m.modes).index(3), list(m.modes).index(4)
            res = {k: ((zp - z) / sig) for k, z in row.items()}
            key = f"{'gaussian' if gauss else 'uniform'}/" + ("plane" if R is None else f"R{R:+.0f}")
            out[key] = {k: {"z3_sigma": float(v[j3]), "z4_sigma": float(v[j4]), "max_sigma": float(np.abs(v).max()),
                            "sigma": v.tolist()} for k, v in res.items()}
            print(f"{key:16s} " + " | ".join(f"{k}: Z3 {v[j3]:6.2f} Z4 {v[j4]:7.2f} max {np.abs(v).max():6.2f} "
                                             f"(Z{m.modes[np.argmax(np.abs(v))]})" for k, v in res.items()), flush=True)
            if hessian is not None:  # a saddle's residual is not only Z3/Z4: every mode
                for k, v in res.items():
                    print(f"    {k:10s} " + " ".join(f"Z{j}:{x:+.2f}" for j, x in zip(m.modes, v)), flush=True)
    return out


def gradient_coupling(hessian, beam_offset_mm, beam_scale: float = 0.5, pupil_mm: float = 0.4, spp: int = 4,
                      margin: int = 5, ring: int = 4, design: str | None = None) -> dict:
    """How each model weights a quadratic wave's curvature by the beam's irradiance gradient: the slopes' part odd
    in the Gaussian beam's offset (+-beam_offset_mm), averaged over a small pupil (pupil_mm radius, the beam's
    diameter scaled by beam_scale: a steep gradient), in units of the complete spot's weighting f K g p^2 / 12
    (K the wave's curvature coupling the offset's axis into the slope's, g the gradient of ln I at the centre).
    The physical reference lights ``margin`` rings, 'cells' a block of ``ring`` rings (``lit_lenslets``)."""
    from lensforge.optics.centroid import cell_crosstalk_slopes, centroid_slopes, lit_lenslets
    from lensforge.verification.physical_sensor import analytic_wave_quadratures, field_slopes, plane_field

    bench = load_design_lens(design)[1] if design else lf.Bench.default()
    bench = bench.replace(sensor={"pupil_radius_mm": pupil_mm},
                          laser={"beam_diameter_mm": bench.laser.beam_diameter_mm * beam_scale})
    H = np.asarray(hessian, float)
    bo = np.asarray(beam_offset_mm, float)
    if not np.any(bo):
        raise ConfigError("--beam-offset: the coupling needs an off-centre beam (an irradiance gradient)")
    radius = 0.5 * bench.laser.beam_diameter_mm
    if np.hypot(*bo) + pupil_mm > radius:  # the sensor's own rule: a lenslet below 1/e^2 of the peak is not used
        raise ConfigError(f"--beam-offset/--pupil/--beam-scale: the pupil's edge lies {np.hypot(*bo) + pupil_mm:g} mm "
                          f"from the beam's centre, beyond its 1/e^2 radius {radius:g} mm (lenslets the sensor would "
                          "not use); give a smaller offset or pupil, or a wider beam")
    m = ForwardModel(bench, lf.paper_lens("polynomial"))  # its pupil and rule only
    c, p, off, w = m.pupil.centres, bench.sensor.pitch_mm, m.quad_offsets, m.quad_weights
    lit, nbrs = lit_lenslets(bench.sensor, c, ring)
    _check_wave(bench, lit, None, (0.0, 0.0), H)
    g = 4.0 * bo / radius**2  # grad ln I at the centre, 1/mm
    kg = H @ g  # the weighting's slope shift per unit p^2 / 12, each axis
    if not np.any(kg):
        raise ConfigError("--hessian/--beam-offset: the wave has no curvature along the beam's offset: nothing to weight")
    cfg = PhysicalSensor(samples_per_pixel=spp, margin_lenslets=margin)
    wl = bench.laser.wavelength_nm
    runs = {}
    for sgn in (1.0, -1.0):
        b = tuple(sgn * bo)
        sq, irr = analytic_wave_quadratures(bench, lit[:, None, :] + p * off[None], None, True, b, (0.0, 0.0), H)
        n = len(c)
        runs[sgn] = {"physical": field_slopes(plane_field(bench, cfg, c, (0.0, 0.0), True, None, b, H), bench, cfg,
                                              c)[0],
                     "cells": cell_crosstalk_slopes(sq, w * irr, off, w, lit, nbrs, bench.sensor, wl),
                     "own window": centroid_slopes(sq[:n], (w * irr)[:n], off, w, m.window_gain),
                     "complete spot": centroid_slopes(sq[:n], (w * irr)[:n], off, w, (1.0, 1.0))}
    ax = int(np.argmax(np.abs(kg)))
    unit = kg[ax] * p * p / 12
    out = {"unit_urad": float(unit * 1e6), "axis": "xy"[ax]}
    print(f"K {np.round(H * 1e3, 2).tolist()} mrad/mm, beam {bench.laser.beam_diameter_mm:g} mm at +-{bo.tolist()} mm, "
          f"pupil {pupil_mm:g} mm ({len(c)} lenslets), reference {spp} samples/px and {margin} lit rings, 'cells' "
          f"{ring} rings: the s_{'xy'[ax]} part odd in the offset over f K g p^2/12 = {unit * 1e6:.3f} urad", flush=True)
    for name in runs[1.0]:
        odd = 0.5 * (runs[1.0][name] - runs[-1.0][name])[:, ax] / unit
        out[name] = {"mean": float(odd.mean()), "spread": float(odd.std())}
        print(f"  {name:14s} {odd.mean():+.4f} (lenslets' spread {odd.std():.4f})", flush=True)
    return out


def _hessian(xx_xy_yy) -> np.ndarray | None:
    """The symmetric H (2, 2) 1/mm of --hessian xx,xy,yy (mrad/mm); None for None."""
    if xx_xy_yy is None:
        return None
    xx, xy, yy = xx_xy_yy
    return 1e-3 * np.array([[xx, xy], [xy, yy]])


def _floats(n: int | None = None):
    """argparse type: comma-separated finite numbers (n of them when given); a bad one is a usage error (exit 2)."""
    def parse(text: str) -> tuple:
        try:
            v = tuple(float(t) for t in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
        if not all(np.isfinite(v)) or (n is not None and len(v) != n):
            raise argparse.ArgumentTypeError(f"expected {n or 'some'} finite comma-separated numbers, got {text!r}")
        return v
    return parse


_ASSUMABLE = ("centroid_threshold", "lenslet_focal_mm", "centroid_window_px")


def _setting(text: str) -> tuple:
    """argparse type: 'name=value' for a numeric sensor setting of ``_ASSUMABLE``; else a usage error (exit 2)."""
    name, _, value = text.partition("=")
    if name not in _ASSUMABLE:
        raise argparse.ArgumentTypeError(f"expected one of {', '.join(_ASSUMABLE)} as NAME=VALUE, got {text!r}")
    try:
        v = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{name}: expected a number, got {value!r}") from None
    if not np.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"{name}: expected a finite number >= 0, got {value!r}")
    return name, (int(v) if name == "centroid_window_px" else v)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--design", default=None)
    ap.add_argument("--lenses", default="polynomial,extended_polynomial")
    ap.add_argument("--poses", type=int, default=4)
    ap.add_argument("--variants", default="base,cut5,round,noxtalk")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--json", default=None)
    ap.add_argument("--sessions", type=int, default=0, help="run the session study (N sessions per sensor) instead")
    ap.add_argument("--margin", type=int, default=5,
                    help="the physical sensor's lit lenslet rings beyond the pupil (its default 3 "
                         "truncates the cross-talk at an unlucky ring; 5 converges to 0.7 urad)")
    ap.add_argument("--seed", type=int, default=0,
                    help="session study: the first session's seed (the plan keeps seed 0, so runs split over seeds "
                         "share it)")
    ap.add_argument("--calibration-tolerances", default="none", help="'none' (lens known) or 'default'")
    ap.add_argument("--sensors", default="model,physical", help="session study: which sensors measure")
    ap.add_argument("--calibration-crosstalk", default=None, help="session study: calibrate's cross-talk model ('neighbours')")
    ap.add_argument("--true-focal", type=float, default=None,
                    help="session study: the physical lenslets' true focal length, mm (default the bench's, which "
                         "the device converts with)")
    ap.add_argument("--focal-sigma", type=float, default=None,
                    help="session study: calibrate's relative prior 1-sigma of the focal length (estimates the gain)")
    ap.add_argument("--combine", nargs="+", default=None, metavar="SESSIONS.json",
                    help="merge session-study JSONs (e.g. one seed a run) and report them as one study")
    ap.add_argument("--validate", default=None, help="a compare JSON: score the cross-talk models at its poses")
    ap.add_argument("--models", default=None, help="--validate: the cross-talk models to score (default "
                    "neighbours,cells); --pose-bias: the sensor models to estimate with (default none,cells)")
    ap.add_argument("--assume", type=_setting, action="append", default=[], metavar="SETTING=VALUE",
                    help="--validate: a sensor setting the fast models take instead of the compare's (repeatable; "
                         "e.g. centroid_threshold=0 against a cut5 reference)")
    ap.add_argument("--pose-bias", default=None, help="a compare JSON: estimate its poses from the physical "
                    "Zernikes with each --models model (the Table-1 analogue; default none,cells)")
    ap.add_argument("--round-parts", action="store_true", help="round lenslets against square, every third lit: "
                    "the physical shift and the own spot's share (first of --lenses, --poses)")
    ap.add_argument("--cost", action="store_true", help="time S(p) with and without cross-talk, and a physical pose")
    ap.add_argument("--fit-cost", action="store_true", help="time one pose estimate on 'cells': frozen cross-talk "
                    "correction against the whole model (--no-whole: the frozen one only)")
    ap.add_argument("--no-whole", action="store_true", help="--fit-cost: skip the whole model's (slow) fit")
    ap.add_argument("--cut-scan", action="store_true", help="the noise cut's effect over --cuts against --cut-ref, "
                    "physical and 'cells' (first of --lenses, --poses)")
    ap.add_argument("--cuts", type=_floats(), default=(0.03, 0.04, 0.045, 0.049, 0.051, 0.055, 0.06),
                    help="--cut-scan: the cuts (fractions of the spot peak)")
    ap.add_argument("--cut-ref", type=float, default=0.05, help="--cut-scan: the reference cut")
    ap.add_argument("--estimate-mc", type=int, default=0, metavar="N",
                    help="Monte Carlo of N pose estimates on 'cells' data: 'cells' against the own-centroid estimator")
    ap.add_argument("--pupil", type=float, default=0.5, help="--estimate-mc, --gradient-coupling: the pupil radius, mm")
    ap.add_argument("--zernike-order", type=int, default=3, help="--estimate-mc: the Zernike order (the bench's: 4)")
    ap.add_argument("--spheres", action="store_true", help="spherical waves: physical reference against the fast models")
    ap.add_argument("--radii", type=_floats(), default=None, help="--spheres: the waves' radii, mm (a huge one: "
                    "a plane wave; default 20,30,-30,60,100,-100, none with --hessian)")
    ap.add_argument("--tilt", type=_floats(2), default=(0.0, 0.0), help="--spheres: a tilt x,y (mrad) added to each wave")
    ap.add_argument("--hessian", type=_floats(3), default=None, help="--spheres: a quadratic xx,xy,yy (mrad/mm) "
                    "added to each wave (0,-10.7,0: the default design's cross curvature alone, a saddle)")
    ap.add_argument("--beam-offset", type=_floats(2), default=(0.0, 0.0), help="--spheres: the Gaussian beam's centre x,y on the lenslets, "
                    "mm (an irradiance gradient across the pupil); --gradient-coupling: the offset, taken + and -")
    ap.add_argument("--gradient-coupling", action="store_true", help="the part of the slopes odd in the beam's offset "
                    "under --hessian, physical against 'cells' and the own window, on a small pupil (--pupil 0.4)")
    ap.add_argument("--beam-scale", type=float, default=0.5, help="--gradient-coupling: the beam's diameter x this")
    ap.add_argument("--ring", type=int, default=4, help="--gradient-coupling: 'cells'' block rings")
    a = ap.parse_args(argv)
    if a.json:  # before the work: a read-only or full folder is refused at once
        check_output(a.json, folder=False, option="--json")
    if a.estimate_mc < 0 or not 1 <= a.zernike_order <= 10:
        ap.error("--estimate-mc: a number of draws >= 1; --zernike-order: 1 to 10")
    if not 0 < a.pupil <= 5.0:
        ap.error(f"--pupil: a radius in (0, 5] mm, got {a.pupil}")
    if a.cut_scan and not all(0 <= c < 1 for c in (*a.cuts, a.cut_ref)):
        ap.error("--cuts/--cut-ref: a noise cut is a fraction of the spot peak, 0 <= cut < 1")
    if a.radii is None:
        a.radii = (None,) if a.hessian is not None else (20.0, 30.0, -30.0, 60.0, 100.0, -100.0)
    if a.spheres and any(r == 0 for r in a.radii):
        ap.error("--radii: a radius of 0 is no wave (a huge one is a plane wave)")
    if a.cost:
        cost()
        return
    ct = None if a.calibration_tolerances == "none" else a.calibration_tolerances
    if a.gradient_coupling and (a.hessian is None or not 0 < a.beam_scale <= 10 or not 1 <= a.ring <= 16):
        ap.error("--gradient-coupling: needs --hessian xx,xy,yy; --beam-scale in (0, 10]; --ring 1 to 16")
    studies = [  # (chosen, the study): the first chosen runs, its record goes to --json
        (a.gradient_coupling, lambda: gradient_coupling(_hessian(a.hessian), a.beam_offset, a.beam_scale, a.pupil,
                                                        a.spp, a.margin, a.ring, a.design)),
        (a.spheres, lambda: spheres(a.radii, spp=a.spp, margin=a.margin, design=a.design,
                                    beam_offset_mm=a.beam_offset, tilt=tuple(1e-3 * np.asarray(a.tilt)),
                                    hessian=_hessian(a.hessian))),
        (a.estimate_mc, lambda: estimate_mc(a.estimate_mc, a.pupil, a.seed, a.zernike_order)),
        (a.cut_scan, lambda: cut_scan(a.lenses.split(",")[0], a.poses, a.cuts, a.cut_ref, a.spp, a.margin)),
        (a.round_parts, lambda: round_parts(a.lenses.split(",")[0], a.poses, a.spp, a.margin)),
        (a.fit_cost, lambda: fit_cost(whole=not a.no_whole, seed=a.seed)),
        (a.pose_bias, lambda: pose_bias(a.pose_bias, tuple((a.models or "none,cells").split(",")), a.design)),
        (a.validate, lambda: validate(a.validate, a.design, tuple((a.models or "neighbours,cells").split(",")),
                                      dict(a.assume))),
        (a.combine, lambda: combine(a.combine)),
        (a.sessions, lambda: sessions(a.design, a.sessions, a.spp, sensors=tuple(a.sensors.split(",")),
                                      calibration_tolerances=ct, calibration_crosstalk=a.calibration_crosstalk,
                                      true_focal_mm=a.true_focal, focal_sigma=a.focal_sigma, seed=a.seed,
                                      margin=a.margin)),
    ]
    for chosen, study in studies:
        if chosen:
            out = study()
            if a.json:
                write_atomic(a.json, json.dumps(out))
            return
    lenses = ([("design", a.design)] if a.design else []) + [(n, n) for n in a.lenses.split(",") if n]
    out = {}
    for label, spec in lenses:
        lens, bench = load_design_lens(spec)
        poses = extreme_poses(lens, bench, a.poses)
        for v in a.variants.split(","):
            r = compare(lens, bench, poses, v, a.spp, a.margin)
            out[f"{label}/{v}"] = r
            worst = [max(np.abs(row["dz_sigma"])) for row in r["rows"]]
            z4 = [row["dz_nm"][r["modes"].index(4)] for row in r["rows"]]
            print(f"{label:10s} {v:8s} max |dz|/sigma per pose: " + " ".join(f"{w:6.1f}" for w in worst)
                  + " | Z4 (nm): " + " ".join(f"{z:6.2f}" for z in z4)
                  + f" | {np.mean([row['seconds'] for row in r['rows']]):.1f} s/pose", flush=True)
            if a.json:
                write_atomic(a.json, json.dumps(out))


def sessions(design: str, n_sessions: int, spp: int, sensors=("model", "physical"), seed: int = 0,
             tolerances=None, calibration_tolerances=None, calibration_crosstalk: str | None = None,
             true_focal_mm: float | None = None, focal_sigma: float | None = None, margin: int = 5) -> dict:
    """Session study: n_sessions 12-pose sessions per sensor (same seeds, same plan), calibrated
    (joint; calibration_tolerances None = the lens known; calibration_crosstalk: calibrate's sensor model,
    e.g. 'neighbours', default the design bench's; focal_sigma: its focal-length prior, estimating the gain),
    scored on Z (session_sim.check_sessions). true_focal_mm: the physical lenslets' (the device converts with the
    bench's)."""
    from lensforge.verification.session_sim import check_sessions

    cal_bench = None
    changes = {**({"crosstalk": calibration_crosstalk} if calibration_crosstalk else {}),
               **({"focal_length_rel_sigma": focal_sigma} if focal_sigma is not None else {})}
    if changes:
        cal_bench = load_design_lens(design)[1].replace(sensor=changes)
    out = {}
    for s in sensors:
        sensor = PhysicalSensor(samples_per_pixel=spp, focal_mm=true_focal_mm, margin_lenslets=margin) if s == "physical" else "model"
        t0 = time.perf_counter()
        r = check_sessions(design, n_sessions, seed=seed, plan_seed=0, tolerances=tolerances, sensor=sensor,
                           calibration_tolerances=calibration_tolerances, calibration_bench=cal_bench,
                           progress=lambda k, n: print(f"  {s}: session {k}/{n}", flush=True))
        r = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in r.items()}
        r["seconds"] = time.perf_counter() - t0
        out[s] = r
        print(session_summary(s, r), flush=True)
    return out


def session_summary(sensor: str, r: dict) -> str:
    """The session study's line for one sensor's record (``sessions``, ``combine``): NEES, chi2, Z error, inside
    3 sigma, and the joint fit's focal-length estimates against the simulated sensor's where it estimated them."""
    nees = np.array(r["nees"])
    line = (f"{sensor:9s} {nees.size} sessions | NEES median {np.median(nees):6.2f} mean/6 {np.mean(nees) / 6:5.2f} | "
            f"chi2/dof {np.min(r['chi2_dof']):.2f}-{np.max(r['chi2_dof']):.2f} | p<0.05 "
            f"{np.mean(np.array(r['p_values']) < 0.05):.2f} | Z err {np.median(r['z_translation_error_mm']) * 1e3:.1f} um, "
            f"{np.radians(np.median(r['z_rotation_error_deg'])) * 1e3:.2f} mrad | inside 3 sigma {r['inside_3sigma']:.2f} | "
            f"failed {len(r['failed'])}")
    est = [(e["lenslet_focal_mm"], e["lenslet_focal_std_mm"], t) for e, t in
           zip(r.get("sensor", []), r.get("lenslet_focal_true_mm", [])) if e]
    if est:  # the joint fit's focal-length estimates against the simulated sensor's
        f_est, f_std, f_true = (np.array(v) for v in zip(*est))
        line += (f"\n{'':9s} lenslet focal length (true {f_true[0]:.4f} mm): estimates {np.round(f_est, 4).tolist()} "
                 f"mm, sigma {np.round(f_std, 4).tolist()}, error/sigma {np.round((f_est - f_true) / f_std, 2).tolist()}")
    return line


def combine(paths) -> dict:
    """Session-study JSONs (``--sessions ... --json``, e.g. one seed a run) merged per sensor: the per-session lists
    joined, the inside-3-sigma fractions weighted by their sessions' counts, the seconds summed. A seed that occurs
    twice for one sensor is refused (the same session counted twice)."""
    merged = {}
    for path in paths:
        for sensor, r in load_sessions(path).items():
            m = merged.setdefault(sensor, {})
            n0, n = len(m.get("nees", [])), len(r["nees"])
            dup = set(m.get("seeds", [])) & set(r["seeds"])
            if dup:
                raise ConfigError(f"{path}: sensor {sensor!r} seeds {sorted(dup)} already read from another file; "
                                  "combine each session once")
            for key in ("inside_3sigma", "inside_3sigma_each_axis"):
                m[key] = (m.get(key, 0.0) * n0 + r[key] * n) / (n0 + n)
            for key, v in r.items():
                if isinstance(v, list):
                    m.setdefault(key, []).extend(v)
            m["seconds"] = m.get("seconds", 0.0) + r.get("seconds", 0.0)
    for sensor, m in merged.items():
        print(session_summary(sensor, m), flush=True)
    if {"model", "physical"} <= merged.keys():  # the issue's yardstick: physical Z error / own-model Z error
        common = sorted(set(merged["model"]["seeds"]) & set(merged["physical"]["seeds"]))
        if common:  # the same sessions (seeds: the same robot and sensor noise draws) measured both ways
            med = {s: {key: np.median([v for seed, v in zip(merged[s]["seeds"], merged[s][key]) if seed in common])
                       for key in ("z_translation_error_mm", "z_rotation_error_deg")} for s in ("model", "physical")}
            t, r = (med["physical"][key] / med["model"][key] for key in ("z_translation_error_mm", "z_rotation_error_deg"))
            print(f"median Z error physical / model over the {len(common)} seeds both measured: translation {t:.2f}, "
                  f"rotation {r:.2f}", flush=True)
    return merged


if __name__ == "__main__":
    import sys

    from lensforge.errors import LensforgeError

    from threadpoolctl import threadpool_limits

    try:  # one BLAS thread, as the CLI: two runs sharing two cores spent ~1.8x the CPU on a 'cells' pose threaded
        with threadpool_limits(limits=1):
            main()
    except LensforgeError as e:  # a bad option or setting: one line, as the CLI
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        sys.exit(130)
