"""Helpers shared by the CLI command modules: output channels and argument loading."""

from __future__ import annotations

import typer

from ..errors import ConfigError
from ..fileio import dumps_json
from ..optics.bench import Bench, load_bench
from ..optics.lens import Lens, load_lens


def emit_json(obj) -> None:
    """Machine-readable output on stdout."""
    typer.echo(dumps_json(obj))


def info(message: str) -> None:
    """Human text on stderr (so stdout stays machine-readable)."""
    typer.echo(message, err=True)


def load_lens_arg(arg: str) -> tuple[Lens, dict]:
    """A lens from a CLI argument: paper lens name, design JSON (key "lens") or lens JSON."""
    return load_lens(arg)


def load_bench_arg(path: str | None, data: dict | None = None) -> Bench:
    """The bench from --bench PATH, else the one stored in a design file, else the default."""
    if path:
        return load_bench(path)
    if data and isinstance(data.get("bench"), dict):
        return Bench.from_dict(data["bench"], "design.bench")
    return Bench.default()


# Trials a command runs (lenses, estimates, calibrations): a million already takes days
# on a workstation; more would only exhaust memory before the first result.
MAX_TRIALS = 1_000_000


def check_seed(seed: int, option: str = "--seed") -> int:
    """A seed numpy's SeedSequence accepts: an integer 0 .. 2**63 - 1."""
    if not 0 <= seed < 2**63:
        raise ConfigError(f"{option}: must be an integer from 0 to 2**63 - 1, got {seed}")
    return seed
