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

from .commands.calibrate import calibrate_cmd
from .commands.demo import demo
from .commands.design import compare, design, plot
from .commands.estimate import estimate_cmd, estimate_study
from .commands.evaluate import evaluate
from .commands.export import export_cmd
from .commands.handeye import handeye_cmd
from .commands.plan import plan_cmd
from .commands.scenario import scenario
from .commands.session import simulate_session_cmd
from .commands.study import budget_cmd, study_cmd
from .errors import LensforgeError
from .interrupts import Interrupted, hard_exit, sigint_guard

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False, rich_markup_mode=None,
                  help="Design, export and verify freeform lenses for Shack-Hartmann pose estimation.")

_COMMANDS = {  # command name -> function, in the order of ``lensforge --help``
    "evaluate": evaluate,
    "design": design,
    "plot": plot,
    "compare": compare,
    "export": export_cmd,
    "estimate": estimate_cmd,
    "estimate-study": estimate_study,
    "scenario": scenario,
    "handeye": handeye_cmd,
    "plan": plan_cmd,
    "calibrate": calibrate_cmd,
    "simulate-session": simulate_session_cmd,
    "study": study_cmd,
    "budget": budget_cmd,
    "demo": demo,
}
for _name, _fn in _COMMANDS.items():
    app.command(_name)(_fn)


def _is_click_exception(e: BaseException, name: str) -> bool:
    """True if e is click's (or Typer's bundled click's) exception class ``name``."""
    return any(cls.__name__ == name and "click" in cls.__module__ for cls in type(e).__mro__)


def _os_error_line(e: OSError) -> str:
    """One line for an operating-system error (disk full, read-only folder, path under a file)."""
    import errno
    import tempfile

    from .fileio import public_path

    where = public_path(e.filename) if e.filename else "output"
    tmpdir = os.path.realpath(tempfile.gettempdir())
    in_tmp = bool(e.filename) and os.path.realpath(str(e.filename)).startswith(tmpdir + os.sep)
    if in_tmp and e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES):
        return (f"the temporary folder {tmpdir} (TMPDIR) is full or not writable ({e.strerror}); free space there "
                "or set TMPDIR to a folder with room")
    why = {errno.ENOSPC: "the disk is full; free space or choose another -o/--out",
           errno.EDQUOT: "the disk quota is exhausted; free space or choose another -o/--out",
           errno.EROFS: "the file system is read-only; choose another -o/--out",
           errno.EACCES: "permission denied; choose a folder you can write",
           errno.EPERM: "operation not permitted; choose a folder you can write",
           errno.ENOTDIR: "a part of the path is a file, not a folder; choose another path",
           errno.EISDIR: "is a folder; give a file name",
           errno.EEXIST: "already exists; choose another path"}.get(e.errno, e.strerror or str(e))
    return f"{where}: {why}"


def main(args: list[str] | None = None) -> None:
    """Entry point: run the app; a user's mistake prints one line ``error: ...`` and exits 2;
    a fit that fails its model check exits 3 (``errors.ModelCheckError``, diagnostics written);
    Ctrl-C prints ``error: interrupted`` and exits 130, SIGTERM ``error: terminated`` and 143
    (see ``lensforge.interrupts``)."""
    with sigint_guard() as interrupted:
        try:
            rc = app(args=args, prog_name="lensforge", standalone_mode=False)
        except Interrupted:
            hard_exit()
        except LensforgeError as e:
            _fail(interrupted, f"error: {' '.join(str(e).split())}", getattr(e, "exit_code", 2))
        except KeyboardInterrupt:
            hard_exit()
        except OSError as e:
            _fail(interrupted, f"error: {_os_error_line(e)}", 2)
        except MemoryError:
            _fail(interrupted, "error: out of memory; reduce the problem size (lenses, poses, mesh tolerance)", 2)
        except Exception as e:
            # click / Typer-bundled click: usage errors, bad option values, aborts, exits
            if interrupted():
                hard_exit()
            if _is_click_exception(e, "Exit") or type(e).__name__ == "Exit":
                sys.exit(getattr(e, "exit_code", 0))
            if _is_click_exception(e, "Abort"):
                if isinstance(e.__context__, KeyboardInterrupt):
                    hard_exit()
                typer.echo("error: aborted", err=True)
                sys.exit(1)
            if _is_click_exception(e, "ClickException"):
                msg = " ".join((e.format_message() if hasattr(e, "format_message") else str(e)).split())
                if type(e).__name__ == "NoArgsIsHelpError":  # bare `lensforge` (click >= 8.2): help, then one line
                    ctx = getattr(e, "ctx", None)
                    typer.echo(ctx.get_help() if ctx is not None else e.format_message(), err=True)
                    msg = ""
                if not msg:  # bare `lensforge`: click printed the help
                    msg = "no command given; pick one of the commands listed above"
                typer.echo(f"error: {msg}", err=True)
                sys.exit(2 if _is_click_exception(e, "UsageError") else getattr(e, "exit_code", 1) or 1)
            raise
        if interrupted():
            hard_exit()
    # with standalone_mode=False, typer.Exit(code) comes back as the return value
    if isinstance(rc, int) and rc != 0:
        sys.exit(rc)


def _fail(interrupted, line: str, code: int) -> None:
    from .fileio import public_text

    if interrupted():  # an error raised while unwinding from Ctrl-C is the interrupt's
        hard_exit()
    typer.echo(public_text(line), err=True)
    sys.exit(code)
