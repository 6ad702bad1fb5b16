"""``lensforge demo``: the main job on the built-in default bench and lenses."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def demo(
        out: Path = typer.Option(Path("exports"), "-o", "--out", help="output folder"),
        quick: bool = typer.Option(False, "--quick", help="smaller budgets (for smoke tests)"),
    ):
        """Evaluate the paper lenses on the default bench (grows into design -> export -> verify)."""
        from rich.console import Console

        from .evaluate import evaluate_lenses, metrics_table

        console = Console(stderr=True, width=160)
        console.rule("1. The paper's lenses on the default bench")
        rows = evaluate_lenses(["spherical", "polynomial", "extended_polynomial", "zernike"])
        console.print(metrics_table(rows))
