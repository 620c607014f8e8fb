"""Results files on the boards: `leaderboard` (validate submissions/, write the boards) and `results convert`."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.markup import escape

from mewa_bench.cli.typer_app import _or_exit, _print_error, app, console


@app.command()
def leaderboard(submissions: Path = typer.Option(Path("submissions"), help="Folder of submissions/<name>/ results."),
                out: Path = typer.Option(Path("leaderboards"), help="Where to write the tables, plots and page."),
                strict: bool = typer.Option(True, metavar="", help="Exit with code 1 when a results file was skipped "
                                                       "(the boards are written either way).")) -> None:
    """Validate every results file in submissions/ and write leaderboards/<suite>.md, .csv, .png and index.html."""
    from mewa_bench.leaderboard import build_leaderboards

    report = _or_exit(build_leaderboards, submissions, out)
    if not any(report.entries.values()) and not report.invalid:
        console.print(f"[yellow]no results files found in {submissions}/*/ (expected submissions/<name>/results-<suite>.json)[/yellow]")
    for path, reason in report.invalid:
        console.print(f"[yellow]skipped[/yellow] {path}: {reason}")
    for path in report.written:
        console.print(f"wrote {path}")
    if report.invalid:
        console.print(f"[yellow]{len(report.invalid)} results file(s) were invalid and skipped[/yellow]")
        if strict:
            raise typer.Exit(1)


results_app = typer.Typer(no_args_is_help=True, help="Results files: convert to the compact layout.")


@results_app.command("convert")
def results_convert(files: list[Path] = typer.Argument(..., metavar="FILE", help="Results files to rewrite."),
                    rescore: bool = typer.Option(False, "--rescore", metavar="", help="Recompute the scores from the units (for a file scored "
                                                 "by an older mewa-bench) instead of checking the stored ones.")) -> None:
    """Rewrite schema-2 results files as schema 3 (compact units), each after checking it: its units, env seeds
    and scores must come back exactly; a file that fails a check is left as it was."""
    from mewa_bench.protocol.results_convert import convert_results

    failed = 0
    for path in files:
        try:
            done = convert_results(path, rescore=rescore)
        except (ValueError, OSError) as e:
            _print_error(e)
            failed += 1
            continue
        if done.schema_before == 3:
            console.print(f"{escape(str(path))}: schema 3 already, left as it is")
        else:
            console.print(f"{escape(str(path))}: schema {done.schema_before} -> 3, {done.bytes_before / 1e6:.2f} MB -> "
                          f"{done.bytes_after / 1e6:.2f} MB")
        if done.rescored:
            console.print(f"  re-scored: {len(done.rescored)} score fields changed or added, numbers by at most "
                          f"{done.largest_change:.6f} (first: {escape(done.rescored[0])})")
    if failed:
        raise typer.Exit(1)
