"""`mewa-bench compare`: algorithms compared over their training runs (how each run was grouped, a rich table, PNGs)."""

from __future__ import annotations

from pathlib import Path

import typer
from rich import box
from rich.console import Console
from rich.markup import escape
from rich.table import Table

console = Console()

DEFINITIONS = (
    ("gap won", "(mean score - best fixed) / (1 - best fixed): the share of what only adaptation can win"),
    ("mean score", "mean of the (run, pair) cells: each run's mean adjusted score s_1..s_10 on a pair"),
    ("IQM", "interquartile mean: the mean of the middle 50% of the (run, pair) cells (rliable's)"),
    ("adaptability", "mean(s_10 - s_1): the gain from the first to the tenth episode with the same worker"),
    ("P(X > Y)", "probability of improvement: the chance that a run of X beats a run of Y on a pair "
                 "(over pairs, ties 1/2)"),
    ("verdicts", "one-sided tests decided together by Holm's weighted procedure over every test shown here "
                 "(per-run checkpoints, algorithms, X better both ways; each of the three an equal share): at "
                 "most 2.5% chance of any false yes"),
)


def compare(runs: list[str] = typer.Argument(None, metavar="[RUN]...", help="Run folders (submissions/<name>/), "
                                             "results files or glob patterns (quote them), e.g. 'runs/rl2-*'."),
            algorithm: list[str] = typer.Option(None, "--algorithm", metavar="NAME=GLOB",
                                                help="Name the runs a pattern matches as one algorithm, e.g. "
                                                     "--algorithm 'mine=runs/mine-seed*/results-narrow-v2.json' "
                                                     "(repeatable; first in the output)."),
            suite: str = typer.Option(None, help="Compare the runs on this suite (needed when a folder holds "
                                                 "results for several)."),
            out: Path = typer.Option(None, help="PNG of the curves, a panel per algorithm (default: "
                                                "compare-<suite>.png); the gap won plot goes beside it.")) -> None:
    """Compare algorithms, not checkpoints: runs grouped by --algorithm, run.json or name, CIs over training runs."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from mewa_bench.leaderboard.algorithm_tables import gap_cell, gap_note, verdict_cell
    from mewa_bench.leaderboard.compare import CompareError, compare as compare_runs, compare_figure, verdict

    try:
        with Progress(TextColumn("scoring runs"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                      TextColumn("{task.description}"), console=console, transient=True) as bar:
            task = bar.add_task("", total=None)
            compared = compare_runs(runs or [], suite, algorithm or [],
                                    progress=lambda done, total, path: bar.update(
                                        task, completed=done, total=total, description=escape(path.parent.name)))
    except (CompareError, OSError) as e:
        console.print(f"[red]error:[/red] {escape(str(e))}")
        raise typer.Exit(1) from None
    console.print(f"[bold]{len(compared.entries)} runs on {compared.suite.name}, grouped:[/bold]")
    for g in compared.groupings:
        console.print(f"  {escape(g.algorithm)} <- {escape(str(g.path))} (by {g.by})", soft_wrap=True)
    c = compared.comparison
    best_fixed = float(compared.suite.summary["score"]["best_fixed"])
    table = Table(title=f"{compared.suite.name}: {len(c.algorithms)} algorithm(s), in the order given",
                  box=box.SIMPLE_HEAD)
    for name in ("algorithm", "runs", "gap won", "mean score", "IQM", "adaptability", "adapts", "beats best fixed"):
        table.add_column(name, justify="left" if name == "algorithm" else "right", overflow="fold",
                         min_width=min(len(name), 12))  # a name is wrapped, never cut to an ellipsis
    notes = []
    for a, row in zip(c.algorithms, compared.algorithms):
        table.add_row(escape(a.algorithm), str(len(a.runs)), gap_cell(row.gap_won), _ci(row.mean), _ci(a.iqm),
                      _ci(row.adaptability), verdict_cell(row, row.adapts, adapts=True),
                      verdict_cell(row, row.beats_best_fixed))
        if row.note:
            notes.append(f"{a.algorithm}: {row.note}")
    table.caption = (f"95% CIs resample whole training runs (seed {c.seed}, {c.samples} samples, small-sample "
                     f"corrected); best fixed policy's exact score {best_fixed:.4f}." + "".join(f"\n{n}" for n in notes))
    table.caption_justify = "left"
    console.print(table)
    names = [a.algorithm for a in c.algorithms]
    for i, x in enumerate(names):
        for y in names[i + 1:]:
            p = c.improvement[(x, y)]
            console.print(f"{escape(x)} vs {escape(y)}: P(X > Y) {_ci(p)}: {escape(verdict(x, y, p, compared))}",
                          soft_wrap=True)
    note = gap_note(compared.suite)
    for term, text in DEFINITIONS:
        console.print(f"[dim]{term}: {text}[/dim]", soft_wrap=True)
    if note:
        console.print(f"[dim]{escape(note)}[/dim]", soft_wrap=True)
    path = out or Path(f"compare-{compared.suite.name}.png")
    written = compare_figure(compared, path)
    console.print(f"wrote {' and '.join(str(p) for p in written)}")


def _ci(e) -> str:
    """`0.9512 [0.9401, 0.9600]`, or the value with "(no CI)"."""
    return f"{e.mean:.4f} (no CI)" if e.low is None else f"{e.mean:.4f} [{e.low:.4f}, {e.high:.4f}]"
