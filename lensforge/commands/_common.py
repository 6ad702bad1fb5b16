"""Helpers shared by the CLI command modules."""

from __future__ import annotations

from ..optics.bench import Bench, load_bench
from ..optics.lens import Lens, load_lens


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
