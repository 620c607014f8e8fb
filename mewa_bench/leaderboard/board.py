"""A suite's leaderboard as rows: ranked agents, unranked privileged agents and the suite's reference lines."""

from __future__ import annotations

from dataclasses import dataclass

from mewa_bench.design.suites import Suite
from mewa_bench.leaderboard.validate import Entry
from mewa_bench.protocol.aggregate import AlgorithmComparison
from mewa_bench.protocol.verdicts import Family

AGENT, PRIVILEGED, REFERENCE = "agent", "privileged", "reference"
# The suite's reference lines (keys of suite.summary["score"] and ["skill"]) and their labels.
REFERENCES = (
    ("known_worker_optimum", "known-worker optimum"),
    ("max_expected", "max expected"),
    ("best_fixed", "best fixed policy"),
    ("random_task_specific", "random task-specific"),
    ("random", "random"),
)
_KIND_ORDER = {AGENT: 0, PRIVILEGED: 1, REFERENCE: 2}


@dataclass(frozen=True)
class Row:
    """One line of a leaderboard table; CI bounds and run details are None or "" for reference lines."""

    kind: str
    rank: int | None
    name: str
    mean: float
    mean_low: float | None
    mean_high: float | None
    s_first: float
    s_last: float
    adaptability: float
    adaptability_low: float | None
    adaptability_high: float | None
    skill: float
    iqm: float | None = None
    adapts: bool | None = None  # the board's verdicts (`leaderboard.judging`; None for reference lines)
    beats_best_fixed: bool | None = None
    vs_best_fixed: float | None = None  # paired difference with the best fixed policy, and its CI
    vs_best_fixed_low: float | None = None
    vs_best_fixed_high: float | None = None
    seeds: int | None = None
    date: str = ""
    package_version: str = ""
    agent_sha256: str = ""
    file: str = ""
    gap_won: float | None = None  # (mean - best fixed) / (1 - best fixed), from the paired difference, and its CI
    gap_won_low: float | None = None
    gap_won_high: float | None = None


@dataclass(frozen=True)
class Board:
    """A suite with its valid entries (best first), its checkpoint rows and its algorithms (best first)."""

    suite: Suite
    entries: tuple[Entry, ...]
    rows: tuple[Row, ...]
    comparison: AlgorithmComparison | None = None
    algorithms: tuple = ()  # leaderboard.algorithms.AlgorithmRow
    family: Family | None = None  # the verdicts' family: every test the board shows

    @property
    def best_fixed(self) -> float:
        """The best fixed policy's exact mean score on the suite."""
        return float(self.suite.summary["score"]["best_fixed"])


def run_name(entry: Entry) -> str:
    """A run's name on a board and in a comparison: its results file's path (unique)."""
    return str(entry.path)


def competition_ranks(means: list[float]) -> list[int]:
    """Ranks of means sorted best first; equal means share a rank ("1224")."""
    ranks: list[int] = []
    for i, m in enumerate(means):
        ranks.append(ranks[-1] if i and m == means[i - 1] else i + 1)
    return ranks


def entry_row(entry: Entry, rank: int | None, root_label: str) -> Row:
    """The row of a valid results file."""
    s = entry.scores
    return Row(kind=PRIVILEGED if entry.privileged else AGENT, rank=rank, name=entry.agent,
               mean=s.mean.mean, mean_low=s.mean.low, mean_high=s.mean.high,
               s_first=s.curve[0].mean, s_last=s.curve[-1].mean,
               adaptability=s.adaptability.mean, adaptability_low=s.adaptability.low,
               adaptability_high=s.adaptability.high, skill=s.skill.mean, iqm=s.iqm.mean,
               vs_best_fixed=s.comparisons["best_fixed"].difference.mean,
               vs_best_fixed_low=s.comparisons["best_fixed"].difference.low,
               vs_best_fixed_high=s.comparisons["best_fixed"].difference.high, seeds=len(entry.seeds),
               date=entry.date, package_version=entry.package_version, agent_sha256=entry.agent_sha256,
               file=f"{root_label}/{entry.path.parent.name}/{entry.path.name}")


def reference_rows(suite: Suite) -> list[Row]:
    """The suite's exact reference lines: fixed policies, so s_1 = s_10 and adaptability is 0."""
    score, skill = suite.summary["score"], suite.summary["skill"]
    best_fixed = float(score["best_fixed"])
    return [Row(kind=REFERENCE, rank=None, name=label, mean=float(score[key]), mean_low=None, mean_high=None,
                s_first=float(score[key]), s_last=float(score[key]), adaptability=0.0, adaptability_low=None,
                adaptability_high=None, skill=float(skill[key]),
                gap_won=(float(score[key]) - best_fixed) / (1.0 - best_fixed))
            for key, label in REFERENCES]
