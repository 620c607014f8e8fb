"""The suites: `generate` (design one from the paper's method) and `suites list/show/verify/report`."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import typer
from rich.table import Table

from mewa_bench.cli.options import RAY_ADDRESS_HELP, _ray_option
from mewa_bench.cli.typer_app import _or_exit, app, console

suites_app = typer.Typer(no_args_is_help=True, help="List, show and verify the versioned suites.")


@app.command()
def generate(kind: str = typer.Argument(..., metavar="KIND", help="narrow, wide, narrow-v2 or wide-v2"),
             out: Path = typer.Option(None, "--out", help="Where to write the suite (default: ./<name>.json; "
                                                           "with --check, nothing is written unless --out is given)."),
             check: bool = typer.Option(False, "--check", metavar="", help="Compare the result byte for byte with the shipped suite."),
             validation: bool = typer.Option(False, "--validation", metavar="", help="Make the suite's validation "
                                              "suite instead: its tasks with workers curated from held-out meta-train "
                                              "draws, for tuning (<name>-validation)."),
             ray: bool = typer.Option(False, "--ray", metavar="", help="Design the candidate tasks as Ray tasks on a local Ray "
                                                           "instance (wide suites: one task per Ray task)."),
             ray_address: str = typer.Option(None, "--ray-address", help=RAY_ADDRESS_HELP)) -> None:
    """Regenerate a suite from the paper's task-design method (exact; reproduces the shipped file byte for byte)."""
    from mewa_bench.design.generate import SPECS
    from mewa_bench.design.suites import shipped_path, suite_text
    from mewa_bench.files import write_atomic

    if kind not in SPECS:
        raise typer.BadParameter(f"expected one of {', '.join(SPECS)}", param_hint="KIND")
    address = _ray_option(ray, ray_address)
    start = time.perf_counter()
    name = SPECS[kind].name + ("-validation" if validation else "")
    with console.status(f"generating {name}") as status:
        content = _or_exit(lambda: _suite_content(kind, validation, address, status.update))
    text = suite_text(content)
    if out is not None or not check:
        target = out or Path(f"{name}.json")
        write_atomic(target, text)
        console.print(f"wrote [bold]{target}[/bold] ({len(text):,} bytes) in {time.perf_counter() - start:.1f} s")
    else:
        console.print(f"generated {name} ({len(text):,} bytes) in {time.perf_counter() - start:.1f} s")
    if check:
        shipped = shipped_path(name)
        same = shipped.exists() and shipped.read_text() == text
        console.print(f"byte-identical to the shipped {shipped.name}: " + ("[green]yes[/green]" if same else "[red]NO[/red]"))
        if not same:
            raise typer.Exit(1)


def _suite_content(kind: str, validation: bool, address: str | None, progress: Callable[[str], None]) -> dict:
    """The content of suite `kind`, or of its validation suite, designed here or on Ray at `address`."""
    from mewa_bench.design.generate import SPECS, generate_suite

    if validation:
        from mewa_bench.design.validation import validation_suite_content

        return validation_suite_content(SPECS[kind].name)
    if address is None:
        return generate_suite(kind, progress=progress)
    from mewa_bench.protocol.ray_backend import ray_map, session

    with session(address):
        return generate_suite(kind, progress=progress, map_tasks=lambda design, raws, kind_: ray_map(
            design, raws, kind_, on_done=lambda c: progress(f"{c.task.name}: designed and curated")))


@suites_app.command("list")
def suites_list() -> None:
    """The shipped suites, their size, hash and non-adaptive gap."""
    from mewa_bench.design.suites import ALL_SUITES, load_suite

    table = Table("suite", "tasks", "pairs", "non-adaptive gap", "sha256")
    for name in ALL_SUITES:
        s = load_suite(name)
        table.add_row(name, str(len(s.tasks)), str(len(s.pairs)), f"{s.summary['non_adaptive_gap']:.4f}", s.sha256[:16])
    console.print(table)


@suites_app.command("show")
def suites_show(name: str = typer.Argument(..., metavar="NAME", help="Suite name or path.")) -> None:
    """Tasks, curated workers and baselines of a suite."""
    from mewa_bench.design.suites import load_suite
    from mewa_bench.cli.suite_tables import pair_table, summary_table, task_table

    suite = _or_exit(load_suite, name)
    console.print(f"[bold]{suite.name}[/bold]  sha256 {suite.sha256}")
    console.print(task_table(suite))
    console.print(pair_table(suite))
    console.print(summary_table(suite))


@suites_app.command("verify")
def suites_verify(path: Path = typer.Argument(None, metavar="PATH", help="A suite file (default: every shipped suite).")) -> None:
    """Check that suite files match their recorded content hash."""
    from mewa_bench.design.suites import ALL_SUITES, load_suite

    for target in ([path] if path else list(ALL_SUITES)):
        suite = _or_exit(load_suite, target)
        console.print(f"[green]ok[/green] {suite.name}: content matches sha256 {suite.sha256[:16]}… ({suite.path})")


@suites_app.command("report")
def suites_report(out: Path = typer.Option(Path("docs"), "--out", help="Folder for suites.md and the figures.")) -> None:
    """Write the task-design report (docs/suites.md and a Fig. 2-style PNG per suite)."""
    from mewa_bench.reports.suite_report import write_report

    for path in write_report(out):
        console.print(f"wrote {path}")
