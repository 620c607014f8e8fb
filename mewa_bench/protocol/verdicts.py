"""Verdicts that hold for everything one board or one comparison shows: Holm's step-down over one-sided tests.

A board shows many rows, each with two verdicts ("adapts": adaptability > 0; "beats the best fixed
policy": mean score > the best fixed policy's), and `compare` adds "X better" between algorithms.
Each verdict is a one-sided test of its row's own estimate: the p-value of the estimate's interval
statistic, t = (estimate - threshold) / SE with the interval's Student t degrees of freedom (so a
row's interval excludes the threshold exactly when its own p-value is below FAMILY_ALPHA). All the
tests one display shows form one family, and Holm's step-down procedure (Holm 1979) says "yes" to a
test only while the family-wise error stays at FAMILY_ALPHA: the chance that a board (or a comparison)
shows any false "yes" is at most 2.5%, whatever the dependence between its rows. A "yes" therefore
never contradicts the 95% interval printed beside it; a "no" means "not shown at this level".
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Hashable, Iterable, Mapping

import numpy as np

from mewa_bench.protocol.scoring import CONFIDENCE, Estimate

FAMILY_ALPHA = (1.0 - CONFIDENCE) / 2  # 0.025: one side of the 95% intervals, for the whole family
PROCEDURE = "Holm's step-down"


@dataclass(frozen=True)
class Hypothesis:
    """One one-sided test: is `estimate` above `threshold`? `key` names it (tests with one key are one test)."""

    key: Hashable
    estimate: Estimate
    threshold: float


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


def holm(p_values: Mapping[Hashable, float], alpha: float = FAMILY_ALPHA) -> dict[Hashable, bool]:
    """Holm's step-down: sorted p_(1) <= ... <= p_(m), "yes" to the first i with p_(j) <= alpha / (m - j + 1) for
    every j <= i; family-wise error <= alpha under any dependence. Ties are ordered by key text (deterministic)."""
    order = sorted(p_values, key=lambda k: (p_values[k], repr(k)))
    m = len(order)
    decided = dict.fromkeys(order, False)
    for j, key in enumerate(order):
        if not p_values[key] <= alpha / (m - j):
            break
        decided[key] = True
    return decided


@dataclass(frozen=True)
class Family:
    """The decisions of a family of tests, and what the family was."""

    decisions: dict[Hashable, bool]
    p_values: dict[Hashable, float]
    alpha: float

    @property
    def size(self) -> int:
        """How many distinct tests the family holds."""
        return len(self.p_values)

    def decision(self, key: Hashable) -> bool | None:
        """yes / no for a tested key, None for a key with no interval (not in the family)."""
        return self.decisions.get(key)


def judge(tests: Iterable[Hypothesis], alpha: float = FAMILY_ALPHA) -> Family:
    """Holm over every test with an interval (the others get no verdict). Two tests with one key must be the same
    test (a one-run algorithm's and its checkpoint's): it counts once."""
    p_values: dict[Hashable, float] = {}
    for test in tests:
        p = p_value(test.estimate, test.threshold)
        if p is None:
            continue
        if test.key in p_values and not np.isclose(p_values[test.key], p, rtol=1e-9, atol=1e-15):
            raise ValueError(f"two different tests share the key {test.key!r}")
        p_values[test.key] = p
    return Family(holm(p_values, alpha), p_values, alpha)
