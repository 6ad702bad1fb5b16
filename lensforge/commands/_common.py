"""Helpers shared by the CLI command modules."""

from __future__ import annotations

import json
from pathlib import Path

from ..errors import ConfigError
from ..optics.bench import Bench, load_bench
from ..optics.lens import PAPER_LENSES, Lens, paper_lens


def load_lens_arg(arg: str) -> tuple[Lens, dict]:
    """A lens from a CLI argument: a paper lens name, a design JSON file (key "lens")
    or a lens JSON file (Lens.to_dict()). Returns (lens, the parsed JSON or {})."""
    key = str(arg).lower().replace("-", "_")
    if key in PAPER_LENSES:
        return paper_lens(key), {}
    p = Path(arg)
    if not p.exists():
        raise ConfigError(
            f"lens: {arg!r} is neither a paper lens ({', '.join(sorted(PAPER_LENSES))}) nor an existing file"
        )
    try:
        data = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"lens file {p}: cannot be read ({e})") from None
    except json.JSONDecodeError as e:
        raise ConfigError(f"lens file {p}: not valid JSON ({e.msg} at line {e.lineno})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"lens file {p}: expected a JSON object")
    lens_d = data.get("lens", data)
    return Lens.from_dict(lens_d, where=f"{p.name}:lens").validate(), data


def load_bench_arg(path: str | None, data: dict | None = None) -> Bench:
    """The bench from --bench PATH, else the one stored in a design file, else the default."""
    if path:
        return load_bench(path)
    if data and isinstance(data.get("bench"), dict):
        return Bench.from_dict(data["bench"], "design.bench")
    return Bench.default()
