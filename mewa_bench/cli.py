"""The `mewa-bench` command line: parses arguments, calls library functions, prints with rich."""

from __future__ import annotations

import typer
from rich.console import Console
from rich.table import Table

app = typer.Typer(no_args_is_help=True, add_completion=False,
                  help="MEWA meta-RL benchmark: evaluate agents on frozen suites, generate suites, record data.")
console = Console()


@app.command()
def info() -> None:
    """Show versions of mewa-bench and its key dependencies, the env ids, Python and the platform."""
    from mewa_bench.system_info import system_info

    table = Table(show_header=False, box=None)
    for key, value in system_info().items():
        table.add_row(f"[bold]{key}[/bold]", str(value))
    console.print(table)


@app.command()
def rollout(episodes: int = typer.Option(3, min=1, help="Episodes to play."),
            seed: int = typer.Option(0, help="Seed of the env and the policy."),
            render: bool = typer.Option(False, help="Print every step as text.")) -> None:
    """Play a few episodes of the default env (narrow-v1 task, meta-train workers) with random actions."""
    from mewa_bench.envs.rollout import random_rollouts

    table = Table("episode", "worker", "steps", "return", "normalised")
    for ep in random_rollouts(episodes, seed, render=console.print if render else None):
        table.add_row(str(ep.index), ", ".join(f"{w:.2f}" for w in ep.worker), str(ep.steps),
                      f"{ep.episode_return:.2f}", f"{ep.normalised_return:.3f}")
    console.print(table)


def main() -> None:
    """Entry point of the `mewa-bench` console script."""
    app()


if __name__ == "__main__":
    main()
