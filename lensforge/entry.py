"""The ``lensforge`` executable's first code: Ctrl-C is handled before the heavy imports.

Importing the command modules (numpy, scipy, numba, typer, ...) takes a second or
more, and OCP's C initialisation in ``export`` holds the interpreter for seconds.
:func:`main` installs the SIGINT guard and forks a supervisor
(``lensforge.interrupts``) first, so a Ctrl-C at any moment prints
``error: interrupted`` and exits 130 within 2 s.
"""

from __future__ import annotations

from .interrupts import Interrupted, hard_exit, sigint_guard, supervise


def main() -> None:
    """Console entry point (``lensforge`` and ``python -m lensforge``)."""
    with sigint_guard() as interrupted:
        try:
            supervise()  # the parent waits here for good; the child goes on
            from .cli import main as cli_main

            cli_main()
        except Interrupted:
            hard_exit()
        except BaseException:
            if interrupted():  # whatever an interrupted import or cleanup raised
                hard_exit()
            raise
