"""The ``lensforge`` command line: a thin layer over the library.

Every command that reports numbers has ``--json`` (stable keys on stdout; human
text on stderr). A user's mistake prints one line ``error: ...`` and exits 2.
Command groups live in ``lensforge/commands/*.py``; each module has
``register(app)``.
"""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path

import typer

from .errors import LensforgeError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Design, export and verify freeform lenses for Shack-Hartmann pose estimation.")

DEFAULT_OUT = Path("exports")

_COMMAND_MODULES = ["evaluate", "design", "export", "estimate", "handeye", "study", "demo"]


def fail(message: str, code: int = 2):
    """Print one line to stderr and exit non-zero."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def emit_json(obj) -> None:
    """Machine-readable output on stdout."""
    typer.echo(json.dumps(obj, indent=2, allow_nan=False, default=_json_default))


def _json_default(o):
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def info(message: str) -> None:
    """Human text on stderr (so stdout stays machine-readable)."""
    typer.echo(message, err=True)


for _name in _COMMAND_MODULES:
    try:
        _mod = importlib.import_module(f"lensforge.commands.{_name}")
    except ModuleNotFoundError as _e:
        if _e.name != f"lensforge.commands.{_name}":
            raise
        continue
    _mod.register(app)


def main() -> None:
    """Entry point: run the app, turning LensforgeError into one line + exit 2."""
    try:
        app(standalone_mode=False)
    except LensforgeError as e:
        typer.echo(f"error: {e}", err=True)
        sys.exit(2)
    except typer.Exit as e:
        sys.exit(e.exit_code)
    except typer.Abort:
        typer.echo("error: aborted", err=True)
        sys.exit(1)
    except Exception as e:  # click usage errors
        import click

        if isinstance(e, click.exceptions.UsageError):
            typer.echo(f"error: {e.format_message()}", err=True)
            sys.exit(2)
        if isinstance(e, click.exceptions.ClickException):
            typer.echo(f"error: {e.format_message()}", err=True)
            sys.exit(e.exit_code)
        raise
