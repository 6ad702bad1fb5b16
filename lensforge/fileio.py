"""File I/O shared by every layer: atomic writes and JSON/TOML reads with one clear error.

Sits beside ``errors.py`` at the bottom of the import graph (imports nothing of lensforge
but the errors), so optics, design, manufacturing, verification and the CLI all use it.
"""

from __future__ import annotations

import json
import os
import tempfile
import tomllib
from pathlib import Path

from .errors import ConfigError

__all__ = ["write_atomic", "read_json", "read_toml", "json_default", "dumps_json"]


def write_atomic(path, data: bytes | str) -> Path:
    """Write a file atomically: temp file in the same folder, fsync, rename.

    The file gets the permissions the umask gives a new file (mkstemp's are 0600).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(data, str):
        data = data.encode()
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def read_json(path, what: str):
    """Parsed JSON of ``path``; ConfigError naming ``what`` (e.g. "design file") otherwise."""
    p = Path(path)
    try:
        return json.loads(p.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{what} {p}: not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{what} {p}: cannot be read ({e})") from None
    except json.JSONDecodeError as e:
        raise ConfigError(f"{what} {p}: not valid JSON ({e.msg} at line {e.lineno})") from None


def read_toml(path, what: str) -> dict:
    """Parsed TOML of ``path``; ConfigError naming ``what`` (e.g. "bench file") otherwise."""
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{what} {p}: not found") from None
    except OSError as e:
        raise ConfigError(f"{what} {p}: cannot be read ({e})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{what} {p}: not valid TOML ({e})") from None


def json_default(o):
    """``json.dumps`` default for numpy arrays and scalars and paths."""
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def dumps_json(obj) -> str:
    """Strict (no NaN) indented JSON with numpy support."""
    return json.dumps(obj, indent=2, allow_nan=False, default=json_default)
