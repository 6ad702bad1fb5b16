"""One progress bar for long work: rich on stderr, or nothing (``--no-progress``, ``--json``).

Library functions that loop take a ``tick`` callback (called once per finished unit of work,
e.g. a trial); the CLI passes ``bar.advance`` from :func:`progress_bar`, so the library never
prints and the bar looks the same in every command.
"""

from __future__ import annotations

from contextlib import contextmanager

__all__ = ["Bar", "progress_bar"]


class Bar:
    """Handle of a running bar: ``advance(n)`` and ``describe(text)``; no-ops when disabled."""

    def __init__(self, progress=None, task=None):
        self._p = progress
        self._task = task

    def advance(self, n: int = 1) -> None:
        if self._p is not None:
            self._p.advance(self._task, n)

    def update(self, done: int, total: int | None = None) -> None:
        """Set the count (and the total, once known): the ``progress(done, total)`` callback form."""
        if self._p is not None:
            self._p.update(self._task, completed=done, total=total)

    def describe(self, text: str) -> None:
        if self._p is not None:
            self._p.update(self._task, description=text)


@contextmanager
def progress_bar(total: int | None, description: str = "", enabled: bool = True):
    """Yield a :class:`Bar` counting to ``total`` (None: not known yet); it disappears when the block ends. Drawn
    only on a terminal: into a pipe or a file the transient bar left nothing but an empty line (before an error's
    one line, too)."""
    if not enabled:
        yield Bar()
        return
    from rich.console import Console
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    console = Console(stderr=True)
    if not console.is_terminal:
        yield Bar()
        return
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TimeRemainingColumn(), console=console, transient=True) as p:
        yield Bar(p, p.add_task(description, total=total))
