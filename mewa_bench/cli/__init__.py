"""The `mewa-bench` command line: parses arguments, calls library functions, prints with rich.

A module per command group, each registering its commands on the one Typer app (`typer_app`) as it
is imported, in the order `mewa-bench --help` lists them:
- `evaluate_commands`: info, rollout, evaluate, record, view;
- `leaderboard_commands`: leaderboard, results convert;
- `suite_commands`: generate, suites list/show/verify/report;
- `train_command`: train (its runs are `mewa_bench.training_runs`);
- `compare_command`: compare; `service_commands`: submit, status, serve;
- `dataset_commands`: datasets list/info/download/pack/build.
`options` parses the options several commands share; the `*_tables` modules build their rich tables.
"""

from __future__ import annotations

from mewa_bench.cli.typer_app import app, console
# importing a command module registers its commands
from mewa_bench.cli import evaluate_commands, leaderboard_commands, suite_commands, train_command  # noqa: F401
from mewa_bench.cli.compare_command import compare
from mewa_bench.cli.dataset_commands import datasets_app
from mewa_bench.cli.leaderboard_commands import results_app
from mewa_bench.cli.service_commands import serve_app, status, submit
from mewa_bench.cli.suite_commands import suites_app

__all__ = ["app", "console", "main"]

app.command()(compare)
app.command()(submit)
app.command()(status)
app.add_typer(suites_app, name="suites")
app.add_typer(results_app, name="results")
app.add_typer(datasets_app, name="datasets")
app.add_typer(serve_app, name="serve")


def main() -> None:
    """Entry point of the `mewa-bench` console script."""
    app()


if __name__ == "__main__":
    main()
