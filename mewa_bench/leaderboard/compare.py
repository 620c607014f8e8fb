"""`mewa-bench compare`: runs given as folders, results files or globs, grouped by algorithm, compared as algorithms.

Every run must be a complete protocol run on the one suite, with the same seeds as the others, and
listed once; anything else is refused with a message naming the file. Grouping follows run.json.
"""

from __future__ import annotations

import glob
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from mewa_bench.design.suites import Suite
from mewa_bench.leaderboard.algorithms import entry_runs
from mewa_bench.leaderboard.validate import Entry, InvalidResults, SuiteCache, check_run, finished_date, verified_scores
from mewa_bench.protocol.aggregate import AlgorithmComparison, aggregate
from mewa_bench.protocol.results import ResultsError, read_results
from mewa_bench.protocol.run_info import RunInfoError, read_run_info
from mewa_bench.protocol.scoring import Estimate, reference_line_cells


class CompareError(ValueError):
    """A run that cannot be compared; the message names the file."""


@dataclass(frozen=True)
class Compared:
    """The suite, the runs (entries) and the algorithm-level comparison."""

    suite: Suite
    entries: tuple[Entry, ...]
    comparison: AlgorithmComparison


def expand(items: Sequence[str], suite: str | None) -> list[Path]:
    """Results files named by folders (their results-*.json), files or glob patterns, in the order given."""
    paths: list[Path] = []
    for item in items:
        matches = sorted(glob.glob(item)) if any(c in item for c in "*?[") else [item]
        if not matches:
            raise CompareError(f"{item}: no file or folder matches")
        for match in map(Path, matches):
            if match.is_dir():
                found = sorted(match.glob(f"results-{suite}.json" if suite else "results-*.json"))
                if not found:
                    raise CompareError(f"{match}: no results{'-' + suite if suite else '-*'}.json in this folder")
                if len(found) > 1:
                    raise CompareError(f"{match}: results for several suites ({', '.join(p.name for p in found)}): "
                                       f"pass --suite")
                paths += found
            elif match.is_file():
                paths.append(match)
            else:
                raise CompareError(f"{match}: no such file or folder")
    return paths


def load_run(path: Path, suites: SuiteCache, suite: str | None, seeds: tuple[int, ...] | None) -> Entry:
    """One run checked for comparison: complete, ranked-kind, on `suite`, with `seeds` (when given)."""
    try:
        results = read_results(path)
    except ResultsError as e:
        raise CompareError(str(e)) from None
    if results.get("pairs") is not None or results.get("complete") is not True:
        raise CompareError(f"{path}: an unranked partial run (--pairs, or not finished): only complete runs are "
                           f"compared")
    name = results["suite"]["name"]
    if suite is not None and name != suite:
        raise CompareError(f"{path}: a run on {name}, not {suite}: runs of different suites are never compared")
    try:
        checked_suite, run_seeds, units = check_run(results, suites, seeds if seeds is not None else
                                                    tuple(results["seeds"]))
        scores = verified_scores(units, checked_suite, results["scores"])
        agent = results["agent"]
        folder_named = (path.parent / "agent.py").is_file()
        info = read_run_info(path.parent, path.parent.name if folder_named else str(agent["name"]))
    except (InvalidResults, RunInfoError) as e:
        raise CompareError(f"{path}: {e}") from None
    return Entry(suite=name, agent=str(agent["name"]), path=path, privileged=agent.get("privileged") is True,
                 scores=scores, seeds=run_seeds, date=finished_date(results),
                 package_version=str(results["package_version"]), agent_sha256=str(agent.get("sha256") or ""),
                 algorithm=info.algorithm)


def compare(items: Sequence[str], suite: str | None = None) -> Compared:
    """Load, check and compare the runs; CompareError naming the file on the first run that cannot be compared."""
    paths = expand(items, suite)
    if not paths:
        raise CompareError("no runs given")
    seen: dict[str, Path] = {}
    suites = SuiteCache()
    entries: list[Entry] = []
    for path in paths:
        key = str(path.resolve())
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        for earlier in (seen.get(key), seen.get(digest)):
            if earlier is not None:
                raise CompareError(f"{path}: listed twice (the same run as {earlier}): each run counts once")
        seen[key] = seen[digest] = path
        entry = load_run(path, suites, suite or (entries[0].suite if entries else None),
                         entries[0].seeds if entries else None)
        entries.append(entry)
    the_suite = suites.get(entries[0].suite)
    return Compared(the_suite, tuple(entries), aggregate(entry_runs(entries), reference_line_cells(the_suite)))


def verdict(name_x: str, name_y: str, p: Estimate) -> str:
    """The algorithm-level verdict of P(X > Y) and its interval."""
    if p.low is None:
        return "no interval (an algorithm has a single run)"
    if p.low > 0.5:
        return f"{name_x} better"
    if p.high < 0.5:
        return f"{name_y} better"
    return "no significant difference"


def compare_figure(compared: Compared, path: Path) -> None:
    """Curves s_1..s_K with run-level bands, and performance profiles with bands; PNG written atomically."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from mewa_bench.leaderboard.plot import line_style
    from mewa_bench.protocol.aggregate import PROFILE_THRESHOLDS
    from mewa_bench.reports.figures import save_png

    fig = Figure(figsize=(12, 4.8), dpi=100)
    FigureCanvasAgg(fig)
    curves, profiles = fig.subplots(1, 2)
    for i, algo in enumerate(compared.comparison.algorithms):
        c, style = line_style(i)
        name = algo.algorithm.replace("$", r"\$")  # a name is text, never mathtext
        label = f"{name} ({len(algo.runs)} run{'s' if len(algo.runs) > 1 else ''})"
        for ax, xs, estimates in ((curves, np.arange(1, len(algo.curve) + 1), algo.curve),
                                  (profiles, np.array(PROFILE_THRESHOLDS), algo.profile)):
            ax.plot(xs, [e.mean for e in estimates], color=c, ls=style, label=label,
                    marker="o" if ax is curves else None, ms=3)
            if estimates[0].low is not None:
                ax.fill_between(xs, [e.low for e in estimates], [e.high for e in estimates], color=c,
                                alpha=0.15, lw=0)
    curves.axhline(float(compared.suite.summary["score"]["best_fixed"]), color="#333333", ls=(0, (6, 2)), lw=1.2,
                   label="best fixed policy (exact)")
    curves.set_xlabel("episode k with the same hidden worker")
    curves.set_ylabel("score s_k (1 = max expected)")
    curves.set_title("adaptation curves (95% CI over training runs)", fontsize=10)
    profiles.set_xlabel("threshold tau on a (run, pair) mean score")
    profiles.set_ylabel("fraction of run x pair cells > tau")
    profiles.set_title("performance profiles (95% CI over training runs)", fontsize=10)
    for ax in (curves, profiles):
        ax.grid(alpha=0.3)
    curves.legend(fontsize=8)
    fig.suptitle(f"{compared.suite.name}: algorithms compared", fontsize=11)
    save_png(fig, path)


def summary(compared: Compared) -> dict[str, Any]:
    """A JSON-ready record of the comparison (algorithms, probabilities of improvement, bootstrap)."""
    return {"suite": compared.suite.name, "runs": [str(e.path) for e in compared.entries],
            "algorithms": [a.to_dict() for a in compared.comparison.algorithms],
            "improvement": [{"x": x, "y": y, **p.to_dict()} for (x, y), p in compared.comparison.improvement.items()],
            "bootstrap": compared.comparison.bootstrap()}
