"""Rich summary table of an evaluation's results (printed by `mewa-bench evaluate`)."""

from __future__ import annotations

from typing import Any

from rich.table import Table

REFERENCE_LINES = (("random", "random"), ("random_task_specific", "random task-specific"),
                   ("best_fixed", "best fixed policy"), ("max_expected", "max expected (best t-optimal)"),
                   ("known_worker_optimum", "known-worker optimum"))


def _ci(e: dict[str, float]) -> str:
    return f"{e['mean']:.4f} [{e['low']:.4f}, {e['high']:.4f}]"


def results_table(results: dict[str, Any]) -> Table:
    """The agent's scores beside the suite's exact reference lines (score = ratio to max expected)."""
    agent = results["agent"]
    title = f"{agent['name']} on {results['suite']['name']} ({len(results['units'])} pair x seed units)"
    table = Table("", "mean score (95% CI)", "s_1", "s_10", "adaptability", "skill", title=title)
    if "scores" in results:
        s = results["scores"]
        label = agent["name"] + (" (privileged)" if agent.get("privileged") else "")
        table.add_row(f"[bold]{label}[/bold]", _ci(s["mean"]), f"{s['curve'][0]['mean']:.4f}",
                      f"{s['curve'][-1]['mean']:.4f}", _ci(s["adaptability"]), f"{s['skill']['mean']:.4f}")
        for key, label in REFERENCE_LINES:
            score, skill = results["baselines"]["score"][key], results["baselines"]["skill"][key]
            table.add_row(f"[dim]{label}[/dim]", f"[dim]{score:.4f}[/dim]", "", "", "", f"[dim]{skill:.4f}[/dim]")
        table.caption = ("score: normalised return / the pair's max-expected baseline; adaptability: mean(s_10 - s_1); "
                         "skill: 0 = random task-specific, 1 = best t-optimal per worker. Reference lines are exact.")
    return table
