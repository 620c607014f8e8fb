"""Verdicts that hold for everything one board or one comparison shows: Holm's weighted step-down over one-sided tests.

A board shows many rows, each with two verdicts ("adapts": adaptability > 0; "beats the best fixed
policy": mean score > the best fixed policy's), and `compare` adds "X better" between algorithms.
Each verdict is a one-sided test of its row's own estimate: the p-value of the estimate's interval
statistic, t = (estimate - threshold) / SE with the interval's Student t degrees of freedom (so a
row's interval excludes the threshold exactly when its own p-value is below FAMILY_ALPHA). All the
tests one display shows form one family, and Holm's step-down procedure (Holm 1979, in its weighted
form) says "yes" to a test only while the family-wise error stays at FAMILY_ALPHA: the chance that a
board (or a comparison) shows any false "yes" is at most 2.5%, whatever the dependence between its rows.
A "yes" therefore never contradicts the 95% interval printed beside it; a "no" means "not shown at this
level".

The weights: each table of the display (a board's checkpoint rows and its algorithms of several runs;
`compare` adds its comparisons) holds an equal share of the family, split equally between its tests.
Unweighted, a table of many tests sets the bar for a table of few: among narrow-v2's 72 checkpoint tests
(each on hundreds of degrees of freedom), the strongest learned adapter's algorithm row, +0.46 [+0.40,
+0.52] over its three runs (p = 0.0005 on Student t with 2 degrees of freedom), read "no": it needed 38
smaller p-values before it. With one table the procedure is Holm's classic one.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Hashable, Iterable, Mapping

import numpy as np

from mewa_bench.protocol.scoring import CONFIDENCE, Estimate

FAMILY_ALPHA = (1.0 - CONFIDENCE) / 2  # 0.025: one side of the 95% intervals, for the whole family
PROCEDURE = "Holm's weighted step-down"
CHECKPOINTS, ALGORITHMS, COMPARISONS = "checkpoint rows", "algorithms of several runs", "comparisons"  # tables


@dataclass(frozen=True)
class Hypothesis:
    """One one-sided test: is `estimate` above `threshold`? `key` names it (tests with one key are one test);
    `table` is the table of the display that shows it (its share of the family's weight)."""

    key: Hashable
    estimate: Estimate
    threshold: float
    table: str = CHECKPOINTS


@lru_cache(maxsize=None)
def _t_quantile(df: int) -> float:
    """Student's t quantile of the two-sided CONFIDENCE interval."""
    from scipy.stats import t

    return float(t.ppf(0.5 + CONFIDENCE / 2.0, df))


def read_back(mean: float, low: float | None, high: float | None, df: int) -> Estimate:
    """An estimate read back from JSON (mean, low, high) with the SE its unclipped interval was made with."""
    se = None if low is None or high is None else (high - low) / (2.0 * _t_quantile(df))
    return Estimate(mean, low, high, se, df)


def p_value(estimate: Estimate, threshold: float) -> float | None:
    """One-sided p-value of "estimate > threshold" from the estimate's interval statistic (None: no interval)."""
    from scipy.stats import t

    if estimate.se is None or estimate.df is None:
        return None
    if estimate.se <= 0.0:
        return 0.0 if estimate.mean > threshold else 1.0
    return float(t.sf((estimate.mean - threshold) / estimate.se, estimate.df))


def holm(p_values: Mapping[Hashable, float], alpha: float = FAMILY_ALPHA,
         weights: Mapping[Hashable, float] | None = None) -> dict[Hashable, bool]:
    """Holm's weighted step-down: sorted by p / w, "yes" to the first i with p_(j) <= alpha w_(j) / (the weights of
    the tests j..m) for every j <= i; family-wise error <= alpha under any dependence. Equal weights (the default):
    p_(j) <= alpha / (m - j + 1), the classic procedure. Ties are ordered by key text (deterministic)."""
    w = dict.fromkeys(p_values, 1.0) if weights is None else {k: float(weights[k]) for k in p_values}
    order = sorted(p_values, key=lambda k: (p_values[k] / w[k], repr(k)))
    decided = dict.fromkeys(order, False)
    for j, key in enumerate(order):
        if not p_values[key] <= alpha * w[key] / math.fsum(w[k] for k in order[j:]):
            break
        decided[key] = True
    return decided


def table_weights(tables: Mapping[Hashable, str]) -> dict[Hashable, float]:
    """Each test's weight: its table's equal share of the family, split equally between the table's tests."""
    sizes = Counter(tables.values())
    return {key: 1.0 / (len(sizes) * sizes[table]) for key, table in tables.items()}


@dataclass(frozen=True)
class Family:
    """The decisions of a family of tests, and what the family was."""

    decisions: dict[Hashable, bool]
    p_values: dict[Hashable, float]
    alpha: float
    tables: dict[Hashable, str] = field(default_factory=dict)  # each test's table (its share of the weight)

    @property
    def size(self) -> int:
        """How many distinct tests the family holds."""
        return len(self.p_values)

    @property
    def table_sizes(self) -> dict[str, int]:
        """How many tests each table holds, in the order the tables first appear."""
        return dict(Counter(self.tables.values()))

    def decision(self, key: Hashable) -> bool | None:
        """yes / no for a tested key, None for a key with no interval (not in the family)."""
        return self.decisions.get(key)


def judge(tests: Iterable[Hypothesis], alpha: float = FAMILY_ALPHA) -> Family:
    """Weighted Holm over every test with an interval (the others get no verdict), each table an equal share. Two
    tests with one key must be the same test in the same table (a one-run algorithm's and its checkpoint's): it
    counts once."""
    p_values: dict[Hashable, float] = {}
    tables: dict[Hashable, str] = {}
    for test in tests:
        p = p_value(test.estimate, test.threshold)
        if p is None:
            continue
        if test.key in p_values and (not np.isclose(p_values[test.key], p, rtol=1e-9, atol=1e-15)
                                     or tables[test.key] != test.table):
            raise ValueError(f"two different tests share the key {test.key!r}")
        p_values[test.key], tables[test.key] = p, test.table
    return Family(holm(p_values, alpha, table_weights(tables)), p_values, alpha, tables)
