"""Curated meta-test workers (SPEC section 4): MAD + Mann-Whitney phase 1, then one of two phase 2s.

Phase 2 `best-fixed` (v1, the paper's): add the workers where the policy fixed after phase 1 does
worst. Phase 2 `gap` (v2): add the worker that most raises the set's non-adaptive gap (what only
adaptation can win), optionally at least `min_distance` (L-inf) from every worker already chosen.
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
BEST_FIXED, GAP = "best-fixed", "gap"  # phase-2 rules


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


def curate(values: np.ndarray, cap: int, min_best_return: float = MIN_BEST_RETURN, phase2: str = BEST_FIXED,
           workers: np.ndarray | None = None, min_distance: float = 0.0) -> Curation:
    """Select up to `cap` candidate rows of `values` ([C, P], candidates in lexicographic order).

    `workers` ([C, N]) is needed only for phase 2 `gap` with a `min_distance`.
    """
    v = np.round(np.asarray(values, dtype=np.float64), DECIMALS)
    usable = np.flatnonzero(v.max(axis=1) >= min_best_return)
    if len(usable) == 0:
        raise ValueError(f"no candidate worker lets any t-optimal policy score >= {min_best_return}")
    vu = v[usable]
    chosen = _phase1(vu, cap)
    ratio = ratios_to_best(vu)
    pi_star = int(np.argmax(np.round(ratio[chosen].mean(axis=0), DECIMALS)))
    if phase2 == BEST_FIXED:
        added = _phase2_best_fixed(ratio[:, pi_star], chosen, cap)
    elif phase2 == GAP:
        wu = None if workers is None else np.asarray(workers, dtype=np.float64)[usable]
        added = _phase2_gap(1.0 - ratio, chosen, cap, wu, min_distance)
    else:
        raise ValueError(f"unknown phase 2 {phase2!r}: expected {BEST_FIXED!r} or {GAP!r}")
    phase = (1,) * len(chosen) + (2,) * len(added)
    return Curation(tuple(int(usable[i]) for i in chosen + added), phase, pi_star, len(usable))


def _phase1(vu: np.ndarray, cap: int) -> list[int]:
    """Walk candidates by decreasing MAD; take one when it differs (p <= 0.05) from every one taken.

    p-values only grow as the set grows, so one pass suffices.
    """
    mad = mean_absolute_deviation(vu)
    by_mad = np.argsort(-mad, kind="stable")  # highest MAD first; ties keep lexicographic order
    chosen: list[int] = []
    worst_p = np.zeros(len(vu))  # max p-value against the chosen set so far
    for i in by_mad:
        if len(chosen) == cap:
            break
        if chosen and worst_p[i] > P_THRESHOLD:
            continue
        chosen.append(int(i))
        worst_p = np.maximum(worst_p, _p_values_against(vu, vu[i]))
    return chosen


def _phase2_best_fixed(r_star: np.ndarray, chosen: list[int], cap: int) -> list[int]:
    """Add the workers where pi* does worst while that is below its mean ratio over the current set."""
    current, added = list(chosen), []
    taken = set(chosen)
    for i in np.argsort(r_star, kind="stable"):
        if len(current) == cap:
            break
        if int(i) in taken:
            continue
        if r_star[i] >= np.round(r_star[current].mean(), DECIMALS):
            break
        current.append(int(i))
        taken.add(int(i))
        added.append(int(i))
    return added


def _phase2_gap(loss: np.ndarray, chosen: list[int], cap: int, workers: np.ndarray | None,
                min_distance: float) -> list[int]:
    """Repeatedly add the candidate that maximises the set's gap min_p mean(1 - ratio_p); first of ties."""
    if min_distance > 0.0 and workers is None:
        raise ValueError("phase 2 with a min_distance needs the candidate workers")
    allowed = np.ones(len(loss), dtype=bool)
    allowed[chosen] = False
    total = loss[chosen].sum(axis=0)
    added: list[int] = []
    for i in chosen:
        allowed &= _far_from(workers, i, min_distance)
    while len(chosen) + len(added) < cap and allowed.any():
        gain = np.round(((total[None, :] + loss) / (len(chosen) + len(added) + 1)).min(axis=1), DECIMALS)
        i = int(np.argmax(np.where(allowed, gain, -np.inf)))
        added.append(i)
        total = total + loss[i]
        allowed[i] = False
        allowed &= _far_from(workers, i, min_distance)
    return added


def _far_from(workers: np.ndarray | None, i: int, min_distance: float) -> np.ndarray | bool:
    """True where a candidate is at L-inf distance >= min_distance from candidate i (all True without a distance)."""
    if workers is None or min_distance <= 0.0:
        return True
    return np.round(np.abs(workers - workers[i]).max(axis=1), DECIMALS) >= min_distance


def non_adaptive_gap(values: np.ndarray) -> float:
    """1 - the best single policy's mean ratio to the per-worker best over `values` rows."""
    _, ratio = best_fixed_policy(values)
    return float(1.0 - np.round(ratio.mean(axis=0), DECIMALS).max())


def best_fixed_policy(values: np.ndarray) -> tuple[int, np.ndarray]:
    """pi*: the policy with the highest mean ratio to the per-worker best over `values` rows, and the ratios."""
    ratio = ratios_to_best(values)
    mean = np.round(ratio.mean(axis=0), DECIMALS)
    return int(np.argmax(mean)), ratio
