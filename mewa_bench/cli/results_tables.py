"""Rich summary table of an evaluation's results (printed by `mewa-bench evaluate`)."""

from __future__ import annotations

from typing import Any

from rich.table import Table

REFERENCE_LINES = (("random", "random"), ("random_task_specific", "random task-specific"),
                   ("best_fixed", "best fixed policy"), ("max_expected", "max expected (best t-optimal)"),
                   ("known_worker_optimum", "known-worker optimum"))


def _ci(e: dict[str, float | None]) -> str:
    if e["low"] is None or e["high"] is None:
        return f"{e['mean']:.4f} [CI needs 2+ seeds per pair]"
    return f"{e['mean']:.4f} [{e['low']:.4f}, {e['high']:.4f}]"


def _verdicts(scores: dict[str, Any]) -> str:
    """The two verdicts of protocol 2 in words."""
    v = scores.get("verdicts")
    if v is None:
        return "protocol 1 results: no verdicts"
    adapts = "adapts" if v["adapts"] else "no evidence of adaptation"
    beats = "beats the best fixed policy" if v["beats_best_fixed"] else "does not beat the best fixed policy"
    d = scores["comparisons"]["best_fixed"]["difference"]
    return f"verdicts: {adapts}; {beats} (paired difference {_ci(d)})"


def results_table(results: dict[str, Any]) -> Table:
    """The agent's scores beside the suite's exact reference lines (score = ratio to max expected)."""
    agent = results["agent"]
    title = f"{agent['name']} on {results['suite']['name']} ({len(results['units'])} pair x seed units)"
    table = Table("", "mean score (95% CI)", "IQM", "s_1", "s_10", "adaptability", "skill", title=title)
    if "scores" in results:
        s = results["scores"]
        label = agent["name"] + (" (privileged)" if agent.get("privileged") else "")
        iqm = f"{s['iqm']['mean']:.4f}" if "iqm" in s else ""
        table.add_row(f"[bold]{label}[/bold]", _ci(s["mean"]), iqm, f"{s['curve'][0]['mean']:.4f}",
                      f"{s['curve'][-1]['mean']:.4f}", _ci(s["adaptability"]), f"{s['skill']['mean']:.4f}")
        for key, label in REFERENCE_LINES:
            score, skill = results["baselines"]["score"][key], results["baselines"]["skill"][key]
            table.add_row(f"[dim]{label}[/dim]", f"[dim]{score:.4f}[/dim]", "", "", "", "", f"[dim]{skill:.4f}[/dim]")
        table.caption = (f"{_verdicts(s)}\nprotocol {results['protocol_version']}; score: normalised return / the "
                         "pair's max-expected baseline; adaptability: mean(s_10 - s_1); skill: 0 = random "
                         "task-specific, 1 = best t-optimal per worker. Reference lines are exact.")
    return table
