"""The one Typer app every command registers on, the console they print to, and their error helpers."""

from __future__ import annotations

import typer
from rich.console import Console
from rich.markup import escape

from mewa_bench.extras import MissingExtra

app = typer.Typer(no_args_is_help=True, add_completion=False,
                  help="MEWA meta-RL benchmark: evaluate agents on frozen suites, generate suites, record data.")
console = Console()


def _print_error(error: Exception) -> None:
    """Print a library error's message as it is (not as rich markup, which would eat `mewa-bench[datasets]`)."""
    console.print(f"[red]error:[/red] {escape(str(error))}")


def _or_exit(call, *args):
    """Call, turning a library error (bad suite, catalog, download, missing extra...) into a message and exit 1."""
    try:
        return call(*args)
    except (ValueError, RuntimeError, OSError, MissingExtra) as e:
        _print_error(e)
        raise typer.Exit(1) from None
