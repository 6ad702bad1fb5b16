"""``lensforge estimate-study`` (pose-estimation study, Fig. 5 / Table 2) and
``lensforge scenario`` (the paper's hand-eye calibration procedure, simulated)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from ..errors import ConfigError
from ..fileio import check_output, staged_dir, write_atomic
from ..progress import progress_bar
from ._common import MAX_TRIALS, check_seed, emit_json, info, load_bench_arg


def estimate_study(
    lenses: List[str] = typer.Argument(..., help="paper lens names (spherical, polynomial, extended_polynomial, zernike) or design JSON files"),
    trials: int = typer.Option(100, "--trials", help="estimates per lens"),
    method: str = typer.Option("lm", "--method", help="pose estimator: lm (least squares) | ukf (the paper's baseline); the registry ESTIMATORS in calibration/pose_estimation.py"),
    ukf_repeats: int = typer.Option(12, "--ukf-repeats", help="ukf: updates on the same measurement (paper: 12)"),
    seed: int = typer.Option(0, "--seed", help="random seed (SeedSequence; same trials for every lens)"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML (default: the design's bench or the built-in default)"),
    out: Path = typer.Option(Path("exports/estimate"), "-o", "--out", help="output folder (JSON, per-trial CSV, box plot PNG)"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable JSON on stdout"),
    no_progress: bool = typer.Option(False, "--no-progress", help="no progress bar"),
) -> None:
    """Pose-estimation accuracy against the Cramer-Rao bound.

    Estimates each lens's pose from noisy measurements TRIALS times, reports the error
    statistics (um, urad) against the CRLB and writes a Fig. 5-style box plot."""
    from ..calibration.pose_estimation import ESTIMATORS
    from ..optics.lens import resolve_lens
    from ..verification.estimation_study import format_table, save_study, study_lens, study_to_dict

    # ConfigError, not typer.Exit: under main()'s standalone_mode=False a typer.Exit
    # comes back as a return value and the exit status is lost
    if method not in ESTIMATORS:
        raise ConfigError(f"--method: {method!r} is not one of {', '.join(ESTIMATORS)}")
    if trials < 1 or ukf_repeats < 1:
        raise ConfigError(f"--trials and --ukf-repeats: must be >= 1, got {trials} and {ukf_repeats}")
    check_seed(seed)
    if trials > MAX_TRIALS:
        raise ConfigError(f"--trials: {trials} is over the limit of {MAX_TRIALS} estimates per lens")
    opts = {"ukf_repeats": ukf_repeats} if method == "ukf" else {}
    loaded = [resolve_lens(arg) for arg in lenses]  # every input validated before any work
    benches = [load_bench_arg(bench, r) for r in loaded]
    check_output(out, folder=True, need_mb=5)
    results = []
    with progress_bar(trials * len(lenses), "estimates", not (no_progress or json_out)) as bar:
        for r, b in zip(loaded, benches):
            bar.describe(f"{r.label}: {method} estimates")
            results.append(study_lens(b, r.lens, r.label, trials, method, seed, tick=bar.advance, **opts))
    meta = {"method": method, "trials": trials, "seed": seed,
            **({"ukf_repeats": ukf_repeats} if method == "ukf" else {})}
    with staged_dir(out) as st:  # JSON, CSV and PNG together or not at all
        paths = {k: st.final(v) for k, v in save_study(results, st.tmp, **meta).items()}
    if json_out:
        emit_json({**study_to_dict(results, **meta), "files": {k: str(v) for k, v in paths.items()}})
    else:
        info(format_table(results))
        info("files: " + ", ".join(str(p) for p in paths.values()))

def scenario(
    lens: str = typer.Argument("extended_polynomial", help="paper lens name or design JSON file"),
    design: str = typer.Option("both", "--poses", help="calibration poses: random, oed or both"),
    runs: int = typer.Option(20, "--runs", help="simulated calibrations per pose set (for the observed spread)"),
    method: str = typer.Option("lm", "--method", help="pose estimator: lm | ukf (the registry ESTIMATORS in calibration/pose_estimation.py)"),
    seed: int = typer.Option(0, "--seed", help="random seed"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML (default: the design's bench or the built-in default)"),
    out: Path = typer.Option(Path("exports/scenario"), "-o", "--out", help="output folder (JSON)"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable JSON on stdout"),
    no_progress: bool = typer.Option(False, "--no-progress", help="no progress bar"),
) -> None:
    """The paper's calibration procedure in simulation.

    12 convergence poses, 12 calibration poses, lens poses estimated from noisy measurements, hand-eye
    solved with the estimator covariances; Z error vs its predicted bound."""
    from ..calibration.pose_estimation import ESTIMATORS
    from ..optics.lens import resolve_lens
    from ..verification.scenario import ScenarioConfig, compare_pose_designs, format_comparison

    if design not in ("random", "oed", "both"):
        raise ConfigError(f"--poses: {design!r} is not random, oed or both")
    if method not in ESTIMATORS:
        raise ConfigError(f"--method: {method!r} is not one of {', '.join(ESTIMATORS)}")
    if runs < 1:
        raise ConfigError(f"--runs: must be >= 1, got {runs}")
    check_seed(seed)
    if runs > MAX_TRIALS:
        raise ConfigError(f"--runs: {runs} is over the limit of {MAX_TRIALS}")
    r = resolve_lens(lens)
    lens_obj = r.lens
    b = load_bench_arg(bench, r)
    check_output(Path(out) / "scenario.json", folder=False)
    cfg = ScenarioConfig(estimator=method)
    designs = ("random", "oed") if design == "both" else (design,)
    with progress_bar(runs * len(designs), f"calibrations ({', '.join(designs)} poses)",
                      not (no_progress or json_out)) as bar:
        rep = compare_pose_designs(b, lens_obj, cfg, designs=designs, runs=runs, seed=seed, tick=bar.advance)
    rep = {"schema_version": 1, "lens": lens, **rep}
    path = write_atomic(Path(out) / "scenario.json", json.dumps(rep, indent=2, allow_nan=False))
    if json_out:
        emit_json({**rep, "files": {"json": str(path)}})
    else:
        info(format_comparison(rep))
        info(f"files: {path}")
