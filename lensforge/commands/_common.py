"""Helpers shared by the CLI command modules: output channels and argument loading."""

from __future__ import annotations

import typer

from ..fileio import dumps_json
from ..optics.bench import Bench, load_bench
from ..optics.lens import PAPER_LENSES, Lens, load_lens


def emit_json(obj) -> None:
    """Machine-readable output on stdout."""
    typer.echo(dumps_json(obj))


def info(message: str) -> None:
    """Human text on stderr (so stdout stays machine-readable)."""
    typer.echo(message, err=True)


def load_lens_arg(arg: str) -> tuple[Lens, dict]:
    """A lens from a CLI argument: paper lens name, design JSON (key "lens") or lens JSON."""
    return load_lens(arg)


def lens_labels(args: list[str]) -> list[str]:
    """Row labels for lens arguments: ``paper:NAME`` for a paper lens, the file name for a design
    file (the path as given when two files share a name), so no two rows look alike."""
    from pathlib import Path

    def paper(a: str) -> str | None:
        key = a.split(":", 1)[1] if a.lower().startswith("paper:") else a
        key = key.lower().replace("-", "_")
        return key if key in PAPER_LENSES and not Path(a).exists() else None

    names = [f"paper:{paper(a)}" if paper(a) else Path(a).name for a in args]
    return [n if names.count(n) == 1 or n.startswith("paper:") else a for n, a in zip(names, args)]


def load_bench_arg(path: str | None, data: dict | None = None) -> Bench:
    """The bench from --bench PATH, else the one stored in a design file, else the default."""
    if path:
        return load_bench(path)
    if data and isinstance(data.get("bench"), dict):
        return Bench.from_dict(data["bench"], "design.bench")
    return Bench.default()
