"""The ``lensforge`` command line: a thin layer over the library.

Every command that reports numbers has ``--json`` (stable keys on stdout; human
text on stderr). A user's mistake prints one line ``error: ...`` and exits 2.
Each command is a top-level function in ``lensforge/commands/*.py``, registered
below by name.
"""

from __future__ import annotations

import os

# The CLI's linear algebra is on small matrices (<= 300 x 12) where multi-threaded BLAS
# only adds overhead (a 24-pose hand-eye solve: ~200 ms threaded vs ~14 ms single);
# parallelism comes from numba (trace) and Dask workers. Users can override.
for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import sys

import typer

from .commands.demo import demo
from .commands.design import compare, design, plot
from .commands.estimate import estimate_study, scenario
from .commands.evaluate import evaluate
from .commands.export import export_cmd
from .commands.handeye import handeye_cmd
from .commands.study import budget_cmd, study_cmd
from .errors import LensforgeError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False, rich_markup_mode=None,
                  help="Design, export and verify freeform lenses for Shack-Hartmann pose estimation.")

_COMMANDS = {  # command name -> function, in the order of ``lensforge --help``
    "evaluate": evaluate,
    "design": design,
    "plot": plot,
    "compare": compare,
    "export": export_cmd,
    "estimate-study": estimate_study,
    "scenario": scenario,
    "handeye": handeye_cmd,
    "study": study_cmd,
    "budget": budget_cmd,
    "demo": demo,
}
for _name, _fn in _COMMANDS.items():
    app.command(_name)(_fn)


def _is_click_exception(e: BaseException, name: str) -> bool:
    """True if e is click's (or Typer's bundled click's) exception class ``name``."""
    return any(cls.__name__ == name and "click" in cls.__module__ for cls in type(e).__mro__)


def main() -> None:
    """Entry point: run the app; a user's mistake prints one line ``error: ...`` and exits 2."""
    try:
        rc = app(standalone_mode=False)
    except LensforgeError as e:
        typer.echo(f"error: {e}", err=True)
        sys.exit(2)
    except KeyboardInterrupt:
        typer.echo("error: interrupted", err=True)
        sys.exit(130)
    except Exception as e:
        # click / Typer-bundled click: usage errors, bad option values, aborts, exits
        if _is_click_exception(e, "Exit") or type(e).__name__ == "Exit":
            sys.exit(getattr(e, "exit_code", 0))
        if _is_click_exception(e, "Abort"):
            typer.echo("error: aborted", err=True)
            sys.exit(1)
        if _is_click_exception(e, "ClickException"):
            msg = e.format_message() if hasattr(e, "format_message") else str(e)
            typer.echo(f"error: {' '.join(msg.split())}", err=True)
            sys.exit(2 if _is_click_exception(e, "UsageError") else getattr(e, "exit_code", 1) or 1)
        raise
    # with standalone_mode=False, typer.Exit(code) comes back as the return value
    if isinstance(rc, int) and rc != 0:
        sys.exit(rc)
