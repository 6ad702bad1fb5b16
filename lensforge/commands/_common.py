"""Helpers shared by the CLI command modules: output channels and argument loading."""

from __future__ import annotations

import typer

from ..errors import ConfigError
from ..fileio import dumps_json
from ..optics.bench import Bench, load_bench
from ..optics.lens import ResolvedLens


def emit_json(obj) -> None:
    """Machine-readable output on stdout."""
    typer.echo(dumps_json(obj))


def info(message: str) -> None:
    """Human text on stderr (so stdout stays machine-readable)."""
    typer.echo(message, err=True)


# help texts name the registries without importing them (scipy): `lensforge --help` stays fast
ROBOT_HELP = ("robot model: a name of calibration.robot.ROBOTS (kr10_r1100_sixx, ur5e) or a robot TOML "
              "(default kr10_r1100_sixx)")


def _bench_file(path: str) -> Bench:
    # 'paper': the paper's bench (Bench.default(): 3.5 mm beam, 0.9 mm pupil) instead of a design's own
    return Bench.default() if str(path).strip().lower() == "paper" else load_bench(path)


def bench_arg(path: str | None) -> Bench | None:
    """The bench from --bench PATH ('paper': the paper's), or None (the command then uses the design's bench)."""
    return _bench_file(path) if path else None


def load_bench_arg(path: str | None, resolved: ResolvedLens | None = None) -> Bench:
    """The bench from --bench PATH ('paper': the paper's), else the one stored in the design file, else the default."""
    override = _bench_file(path) if path else None
    return resolved.bench_or(override) if resolved is not None else (override or Bench.default())


# Trials a command runs (lenses, estimates, calibrations): a million already takes days
# on a workstation; more would only exhaust memory before the first result.
MAX_TRIALS = 1_000_000


def check_seed(seed: int, option: str = "--seed") -> int:
    """A seed numpy's SeedSequence accepts: an integer 0 .. 2**63 - 1."""
    if not 0 <= seed < 2**63:
        raise ConfigError(f"{option}: must be an integer from 0 to 2**63 - 1, got {seed}")
    return seed


def end_on_failed_check(passed: bool, reason: str | None, chi2_dof: float, accept: bool, *, mistake: str | None,
                        unexplained: str, accepted_as: str = "written as a calibration") -> None:
    """The end of a command whose fit was model-checked (issue 23's rule): nothing when it
    passed; a warning with ``--accept-failed-check``; else ModelCheckError (exit 3) with the
    statistic and the likely mistake's message, or ``unexplained`` (what to check)."""
    if passed:
        return
    if accept:
        info(f"warning: {reason}; {accepted_as} because of --accept-failed-check")
        return
    from ..errors import ModelCheckError

    head = f"model check failed (chi2/dof {chi2_dof:.3g})"
    raise ModelCheckError(f"{head}; {mistake}" if mistake is not None else f"{head}: {unexplained}")
