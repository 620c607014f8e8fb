"""Rich summary table of an evaluation's results (printed by `mewa-bench evaluate`).

The table holds point estimates in short columns so that it fits an 80-column terminal; the
confidence intervals, verdicts and the legend are in its caption, which wraps.
"""

from __future__ import annotations

from typing import Any

from rich import box
from rich.table import Table

REFERENCE_LINES = (("random", "random"), ("random_task_specific", "random task-specific"),
                   ("best_fixed", "best fixed policy"), ("max_expected", "max expected"),
                   ("known_worker_optimum", "known-worker optimum"))
COLUMNS = ("score", "IQM", "s_1", "s_10", "adapt.", "skill")


def _interval(e: dict[str, float | None]) -> str:
    """`[low, high]`, or why there is no interval."""
    if e["low"] is None or e["high"] is None:
        return "[CI needs 2+ seeds per pair]"
    return f"[{e['low']:.4f}, {e['high']:.4f}]"


def _verdicts(scores: dict[str, Any]) -> str:
    """The two verdicts of protocol 2 in words."""
    v = scores.get("verdicts")
    if v is None:
        return "protocol 1 results: no verdicts"
    adapts = "adapts" if v["adapts"] else "no evidence of adaptation"
    beats = "beats the best fixed policy" if v["beats_best_fixed"] else "does not beat the best fixed policy"
    d = scores["comparisons"]["best_fixed"]["difference"]
    return f"verdicts: {adapts}; {beats} (paired difference {d['mean']:.4f} {_interval(d)})"


def _caption(results: dict[str, Any], s: dict[str, Any]) -> str:
    """CIs, verdicts and what the columns mean."""
    warning = f"[yellow]warning: {s['warning']}[/yellow]\n" if s.get("warning") else ""
    return (f"{warning}95% CIs: score {_interval(s['mean'])}, adapt. {_interval(s['adaptability'])}\n{_verdicts(s)}\n"
            f"protocol {results['protocol_version']}; score: normalised return / the pair's max-expected baseline "
            "(the best t-optimal policy per worker); IQM: interquartile mean of pair means; s_k: episode k; "
            "adapt.: adaptability, mean(s_10 - s_1); skill: 0 = random task-specific, 1 = best t-optimal per "
            "worker. Reference lines are exact.")


def results_table(results: dict[str, Any]) -> Table:
    """The agent's scores beside the suite's exact reference lines (score = ratio to max expected)."""
    agent = results["agent"]
    privileged = " (privileged)" if agent.get("privileged") else ""
    title = f"{agent['name']}{privileged} on {results['suite']['name']}: {len(results['units'])} pair x seed units"
    table = Table(title=title, box=box.SIMPLE_HEAD, pad_edge=False)
    table.add_column("", overflow="fold")
    for name in COLUMNS:
        table.add_column(name, justify="right", no_wrap=True)
    if "scores" in results:
        s = results["scores"]
        iqm = f"{s['iqm']['mean']:.4f}" if "iqm" in s else ""
        table.add_row(f"[bold]{agent['name']}[/bold]", f"{s['mean']['mean']:.4f}", iqm, f"{s['curve'][0]['mean']:.4f}",
                      f"{s['curve'][-1]['mean']:.4f}", f"{s['adaptability']['mean']:.4f}", f"{s['skill']['mean']:.4f}")
        for key, label in REFERENCE_LINES:
            score, skill = results["baselines"]["score"][key], results["baselines"]["skill"][key]
            table.add_row(f"[dim]{label}[/dim]", f"[dim]{score:.4f}[/dim]", "", "", "", "", f"[dim]{skill:.4f}[/dim]")
        table.caption = _caption(results, s)
        table.caption_justify = "left"
    return table
