"""Curated meta-test workers (SPEC section 4): MAD + Mann-Whitney phase 1, best-fixed-policy phase 2.

Works on the matrix of exact expected normalised returns of the t-optimal policies over candidate
workers, so it is a pure, deterministic function of numbers. Conventions that make it deterministic:
values rounded to 12 decimals before any comparison, ties broken by the lexicographically smallest
worker (candidates arrive in lexicographic order and every sort is stable), a NaN p-value counts as
not significant.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import mannwhitneyu

from mewa_bench.design.references import DECIMALS

MIN_BEST_RETURN = 0.1  # candidates where even the best policy scores below this are dropped
P_THRESHOLD = 0.05


@dataclass(frozen=True)
class Curation:
    """Selected candidate rows, in selection order, and how they were chosen."""

    selected: tuple[int, ...]  # row indices into the candidate matrix
    phase: tuple[int, ...]  # 1 or 2 per selected row
    phase2_policy: int  # pi*: the policy fixed after phase 1
    kept_candidates: int  # candidates left after dropping hopeless ones


def mean_absolute_deviation(values: np.ndarray) -> np.ndarray:
    """MAD along the last axis: mean |v - mean(v)|, rounded."""
    v = np.round(values, DECIMALS)
    return np.round(np.abs(v - v.mean(axis=-1, keepdims=True)).mean(axis=-1), DECIMALS)


def ratios_to_best(values: np.ndarray) -> np.ndarray:
    """ratio_p(w) = v_p(w) / max_q v_q(w), rounded (rows = workers)."""
    v = np.round(values, DECIMALS)
    return np.round(v / v.max(axis=1, keepdims=True), DECIMALS)


def _p_values_against(values: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Two-sided Mann-Whitney U p-value of every row of `values` against one row (scipy defaults)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        p = mannwhitneyu(values, np.broadcast_to(row, values.shape), axis=1).pvalue
    return np.where(np.isnan(p), 1.0, p)  # all values tied: not significant


def curate(values: np.ndarray, cap: int) -> Curation:
    """Select up to `cap` candidate rows of `values` ([C, P], candidates in lexicographic order)."""
    v = np.round(np.asarray(values, dtype=np.float64), DECIMALS)
    usable = np.flatnonzero(v.max(axis=1) >= MIN_BEST_RETURN)
    if len(usable) == 0:
        raise ValueError("no candidate worker lets any t-optimal policy score >= 0.1")
    vu = v[usable]
    mad = mean_absolute_deviation(vu)
    by_mad = np.argsort(-mad, kind="stable")  # highest MAD first; ties keep lexicographic order

    # Phase 1: walk candidates by decreasing MAD; take one when it differs (p <= 0.05) from every
    # worker already taken. p-values only grow as the set grows, so one pass suffices.
    chosen: list[int] = []
    worst_p = np.zeros(len(vu))  # max p-value against the chosen set so far
    for i in by_mad:
        if len(chosen) == cap:
            break
        if chosen and worst_p[i] > P_THRESHOLD:
            continue
        chosen.append(int(i))
        worst_p = np.maximum(worst_p, _p_values_against(vu, vu[i]))
    phase = [1] * len(chosen)

    # Phase 2: fix the best non-adaptive policy on the phase-1 set, then add the workers where it
    # does worst while that is below its mean ratio over the current set.
    ratio = ratios_to_best(vu)
    pi_star = int(np.argmax(np.round(ratio[chosen].mean(axis=0), DECIMALS)))
    r_star = ratio[:, pi_star]
    by_ratio = np.argsort(r_star, kind="stable")
    taken = set(chosen)
    for i in by_ratio:
        if len(chosen) == cap:
            break
        if int(i) in taken:
            continue
        if r_star[i] >= np.round(r_star[chosen].mean(), DECIMALS):
            break
        chosen.append(int(i))
        taken.add(int(i))
        phase.append(2)
    return Curation(tuple(int(usable[i]) for i in chosen), tuple(phase), pi_star, len(usable))


def best_fixed_policy(values: np.ndarray) -> tuple[int, np.ndarray]:
    """pi*: the policy with the highest mean ratio to the per-worker best over `values` rows, and the ratios."""
    ratio = ratios_to_best(values)
    mean = np.round(ratio.mean(axis=0), DECIMALS)
    return int(np.argmax(mean)), ratio
