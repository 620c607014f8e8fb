"""`mewa-bench compare`: algorithms compared over their training runs (a rich table and a PNG)."""

from __future__ import annotations

from pathlib import Path

import typer
from rich import box
from rich.console import Console
from rich.markup import escape
from rich.table import Table

console = Console()


def _ci(e) -> str:
    """`0.9512 [0.9401, 0.9600]`, or the value with "(no CI)"."""
    return f"{e.mean:.4f} (no CI)" if e.low is None else f"{e.mean:.4f} [{e.low:.4f}, {e.high:.4f}]"


def compare(runs: list[str] = typer.Argument(..., metavar="RUN...", help="Run folders (submissions/<name>/), "
                                             "results files or glob patterns (quote them), e.g. 'runs/rl2-*'."),
            suite: str = typer.Option(None, help="Compare the runs on this suite (needed when a folder holds "
                                                 "results for several)."),
            out: Path = typer.Option(None, help="PNG of the curves and performance profiles "
                                                "(default: compare-<suite>.png).")) -> None:
    """Compare algorithms, not checkpoints: runs grouped by algorithm (run.json), CIs over training runs."""
    from mewa_bench.leaderboard.compare import CompareError, compare as compare_runs, compare_figure, verdict

    try:
        compared = compare_runs(runs, suite)
    except (CompareError, OSError) as e:
        console.print(f"[red]error:[/red] {escape(str(e))}")
        raise typer.Exit(1) from None
    c = compared.comparison
    best_fixed = float(compared.suite.summary["score"]["best_fixed"])
    table = Table(title=f"{compared.suite.name}: {len(compared.entries)} runs of {len(c.algorithms)} algorithm(s)",
                  box=box.SIMPLE_HEAD)
    for name in ("algorithm", "runs", "IQM", "mean score", "adaptability", "optimality gap", "P(> best fixed)",
                 "beats best fixed"):
        table.add_column(name, justify="left" if name == "algorithm" else "right")
    notes = []
    for a in c.algorithms:
        beats = "—" if a.mean.low is None else ("yes" if a.verdicts(best_fixed)["beats_best_fixed"] else "no")
        table.add_row(escape(a.algorithm), str(len(a.runs)), _ci(a.iqm), _ci(a.mean), _ci(a.adaptability),
                      _ci(a.optimality_gap), _ci(a.over_lines["best_fixed"]), beats)
        if a.note:
            notes.append(f"{a.algorithm}: {a.note}")
    table.caption = (f"95% CIs resample whole training runs (seed {c.seed}, {c.samples} samples, small-sample "
                     f"corrected); best fixed policy's exact score {best_fixed:.4f}."
                     + "".join(f"\n{n}" for n in notes))
    table.caption_justify = "left"
    console.print(table)
    names = [a.algorithm for a in c.algorithms]
    for i, x in enumerate(names):
        for y in names[i + 1:]:
            p = c.improvement[(x, y)]
            console.print(f"{escape(x)} vs {escape(y)} on {compared.suite.name}: probability of improvement "
                          f"{_ci(p)}: {escape(verdict(x, y, p))}")
    path = out or Path(f"compare-{compared.suite.name}.png")
    compare_figure(compared, path)
    console.print(f"wrote {path}")
