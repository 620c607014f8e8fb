"""The `mewa-bench` command line: parses arguments, calls library functions, prints with rich."""

from __future__ import annotations

import time
from pathlib import Path

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


suites_app = typer.Typer(no_args_is_help=True, help="List, show and verify the versioned suites.")
app.add_typer(suites_app, name="suites")


@app.command()
def generate(kind: str = typer.Argument(..., help="narrow or wide"),
             out: Path = typer.Option(None, "--out", help="Where to write the suite (default: ./<name>.json)."),
             check: bool = typer.Option(False, help="Also compare the result byte for byte with the shipped suite.")) -> None:
    """Regenerate a suite from the paper's task-design method (exact; reproduces the shipped file byte for byte)."""
    from mewa_bench.design.generate import SPECS, generate_suite
    from mewa_bench.design.suites import shipped_path, suite_text, write_atomic

    if kind not in SPECS:
        raise typer.BadParameter(f"expected one of {', '.join(SPECS)}", param_hint="KIND")
    start = time.perf_counter()
    with console.status(f"generating {SPECS[kind].name}") as status:
        content = generate_suite(kind, progress=lambda msg: status.update(msg))
    text = suite_text(content)
    target = out or Path(f"{SPECS[kind].name}.json")
    write_atomic(target, text)
    console.print(f"wrote [bold]{target}[/bold] ({len(text):,} bytes) in {time.perf_counter() - start:.1f} s")
    if check:
        shipped = shipped_path(SPECS[kind].name)
        same = shipped.exists() and shipped.read_text() == text
        console.print(f"byte-identical to the shipped {shipped.name}: " + ("[green]yes[/green]" if same else "[red]NO[/red]"))
        if not same:
            raise typer.Exit(1)


@suites_app.command("list")
def suites_list() -> None:
    """The shipped suites, their size, hash and non-adaptive gap."""
    from mewa_bench.design.suites import SHIPPED_SUITES, load_suite

    table = Table("suite", "tasks", "pairs", "non-adaptive gap", "sha256")
    for name in SHIPPED_SUITES:
        s = load_suite(name)
        table.add_row(name, str(len(s.tasks)), str(len(s.pairs)), f"{s.summary['non_adaptive_gap']:.4f}", s.sha256[:16])
    console.print(table)


@suites_app.command("show")
def suites_show(name: str = typer.Argument(..., help="Suite name or path.")) -> None:
    """Tasks, curated workers and baselines of a suite."""
    from mewa_bench.design.suites import load_suite
    from mewa_bench.suite_tables import pair_table, summary_table, task_table

    suite = _load_or_exit(load_suite, name)
    console.print(f"[bold]{suite.name}[/bold]  sha256 {suite.sha256}")
    console.print(task_table(suite))
    console.print(pair_table(suite))
    console.print(summary_table(suite))


@suites_app.command("verify")
def suites_verify(path: Path = typer.Argument(None, help="A suite file (default: every shipped suite).")) -> None:
    """Check that suite files match their recorded content hash."""
    from mewa_bench.design.suites import SHIPPED_SUITES, load_suite

    for target in ([path] if path else list(SHIPPED_SUITES)):
        suite = _load_or_exit(load_suite, target)
        console.print(f"[green]ok[/green] {suite.name}: content matches sha256 {suite.sha256[:16]}… ({suite.path})")


@suites_app.command("report")
def suites_report(out: Path = typer.Option(Path("docs"), "--out", help="Folder for suites.md and the figures.")) -> None:
    """Write the task-design report (docs/suites.md and a Fig. 2-style PNG per suite)."""
    from mewa_bench.reports.suite_report import write_report

    for path in write_report(out):
        console.print(f"wrote {path}")


def _load_or_exit(load, name):
    from mewa_bench.design.suites import SuiteError

    try:
        return load(name)
    except SuiteError as e:
        console.print(f"[red]error:[/red] {e}")
        raise typer.Exit(1) from None


def main() -> None:
    """Entry point of the `mewa-bench` console script."""
    app()


if __name__ == "__main__":
    main()
