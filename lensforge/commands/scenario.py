"""``lensforge scenario``: the paper's hand-eye calibration procedure, simulated (random against
optimally chosen poses)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from ..errors import ConfigError
from ..fileio import check_output, write_atomic
from ..progress import progress_bar
from ._common import MAX_TRIALS, check_seed, emit_json, info, load_bench_arg


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
