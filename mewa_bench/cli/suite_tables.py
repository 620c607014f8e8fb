"""Rich tables describing a suite (used by `mewa-bench suites show`)."""

from __future__ import annotations

from rich.table import Table

from mewa_bench.design.suites import Suite
from mewa_bench.game.palette import COLOR_NAMES


def _nums(values, fmt: str = "{:.3f}") -> str:
    return " ".join(fmt.format(v) for v in values)


def short_policy(name: str) -> str:
    """'toptimal(rho1=3,rho2=0,q=1)' -> 't(3,0,1)'."""
    if not name.startswith("toptimal("):
        return name
    return "t(" + ",".join(part.split("=")[1] for part in name[len("toptimal("):-1].split(",")) + ")"


def task_table(suite: Suite) -> Table:
    """One row per task: rules, designed average worker and rewards, design quality."""
    table = Table("task", "order", "K", "M", "rewards", "avg worker", "Eq.1 obj", "MAD@avg", title="Tasks")
    for t, raw in zip(suite.tasks, suite.content["tasks"]):
        design = raw["design"]
        table.add_row(t.name, ">".join(COLOR_NAMES[c][0].upper() for c in t.order), str(t.K), str(t.M),
                      _nums(t.rewards, "{:.3f}"), _nums(t.average_worker, "{:.3f}"),
                      f"{design['eq1_objective']:.3g}", f"{design['mad_at_average_worker']:.4f}")
    table.caption = "order: O orange, B blue, G green, R red; sigma: " + "; ".join(
        f"{t.name} {_nums(t.sigma, '{:.2f}')}" for t in suite.tasks[:1]) + (" ..." if len(suite.tasks) > 1 else "")
    return table


def pair_table(suite: Suite) -> Table:
    """One row per curated pair: worker and its exact reference values (normalised returns)."""
    many = len(suite.tasks) > 1
    table = Table("#", *(["task"] if many else []), "worker", "ph", "random", "rts", "fixed", "max-exp",
                  "optimum", "best", title="Curated pairs (exact expected normalised returns)")
    for p in suite.pairs:
        d = p.data
        table.add_row(str(p.index), *([str(p.task_index)] if many else []), _nums(p.worker.w, "{:.2f}"),
                      str(d["phase"]), f"{d['baselines']['random']:.3f}", f"{d['baselines']['random_task_specific']:.3f}",
                      f"{d['best_fixed']:.3f}", f"{d['baselines']['max_expected']:.3f}",
                      f"{d['known_worker_optimum']:.3f}", short_policy(d["best_policy"]))
    table.caption = ("ph: curation phase; rts: random task-specific; fixed: best fixed policy; max-exp: best "
                     "t-optimal policy for the worker; optimum: known-worker optimum; best: t(rho1,rho2,q)")
    return table


def summary_table(suite: Suite) -> Table:
    """Suite means of every reference line, normalised and as scores (ratio to max-expected)."""
    s = suite.summary
    table = Table("reference", "normalised return", "score", "skill", title=f"Summary over {s['pairs']} pairs")
    for key in ("random", "random_task_specific", "best_fixed", "max_expected", "known_worker_optimum"):
        table.add_row(key.replace("_", " "), f"{s['normalised'][key]:.4f}", f"{s['score'][key]:.4f}",
                      f"{s['skill'][key]:.4f}")
    table.caption = f"non-adaptive gap (1 - best fixed score): {s['non_adaptive_gap']:.4f}"
    return table
