"""Helpers shared by the CLI command modules: output channels and argument loading."""

from __future__ import annotations

import typer

from ..fileio import dumps_json
from ..optics.bench import Bench, load_bench
from ..optics.lens import ResolvedLens


def emit_json(obj) -> None:
    """Machine-readable output on stdout."""
    typer.echo(dumps_json(obj))


def info(message: str) -> None:
    """Human text on stderr (so stdout stays machine-readable)."""
    typer.echo(message, err=True)


def load_bench_arg(path: str | None, resolved: ResolvedLens | None = None) -> Bench:
    """The bench from --bench PATH, else the one stored in the design file, else the default."""
    override = load_bench(path) if path else None
    return resolved.bench_or(override) if resolved is not None else (override or Bench.default())
