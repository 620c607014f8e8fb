"""Curated worker selection on hand-built return matrices (independent of the exact engine)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import mannwhitneyu

from mewa_bench.design.curate import _p_values_against, curate, mean_absolute_deviation, ratios_to_best


def test_vectorised_p_values_equal_scipy_pair_by_pair() -> None:
    rng = np.random.default_rng(0)
    values = np.round(rng.random((40, 19)) * 0.2 + 0.7, 2)  # many ties, as in real data
    values[3] = values[5]  # identical rows: p = 1
    values[7] = 0.5  # all tied inside a row
    for ref in (values[0], values[7]):
        vec = _p_values_against(values, ref)
        for i, row in enumerate(values):
            p = mannwhitneyu(row, ref).pvalue
            assert vec[i] == pytest.approx(1.0 if np.isnan(p) else p, rel=1e-12, abs=1e-15)


def test_mad_and_ratios_by_hand() -> None:
    v = np.array([[0.2, 0.4, 0.6], [0.5, 0.5, 0.5]])
    np.testing.assert_allclose(mean_absolute_deviation(v), [0.4 / 3, 0.0])
    np.testing.assert_allclose(ratios_to_best(v), [[1 / 3, 2 / 3, 1.0], [1.0, 1.0, 1.0]])


def test_hopeless_candidates_are_dropped_and_first_pick_is_highest_mad() -> None:
    v = np.array([
        [0.05, 0.02, 0.01],  # best < 0.1: dropped even though its MAD is high-ish
        [0.9, 0.9, 0.9],
        [0.2, 0.9, 0.5],     # highest MAD among usable
        [0.9, 0.2, 0.5],     # same MAD: comes later in lexicographic order
    ])
    cur = curate(v, cap=1)
    assert cur.kept_candidates == 3
    assert cur.selected == (2,)


def test_phase1_requires_significant_difference_and_phase2_targets_pi_star() -> None:
    rng = np.random.default_rng(1)
    p = 19
    base = np.linspace(0.5, 0.95, p)
    rows = [base + 0.0, base + 0.001 * rng.random(p), base[::-1] * 0.5 + 0.2, base * 0.3 + 0.1]
    # Workers where policy 18 (best on average) does relatively badly:
    weak = base.copy()
    weak[18] = 0.55
    rows += [weak, weak * 0.99]
    v = np.array(rows)
    cur = curate(v, cap=16)
    phase1 = [i for i, ph in zip(cur.selected, cur.phase) if ph == 1]
    # Row 1 is statistically indistinguishable from row 0 (same ranks): never in phase 1.
    assert 0 in phase1 or 1 in phase1
    assert not (0 in phase1 and 1 in phase1)
    # Every phase-1 pair differs significantly.
    for a in phase1:
        for b in phase1:
            if a != b:
                assert mannwhitneyu(v[a], v[b]).pvalue <= 0.05
    # Phase 2 only adds workers where pi* is below its running mean ratio.
    ratio = ratios_to_best(v)[:, cur.phase2_policy]
    chosen = list(phase1)
    for i, ph in zip(cur.selected, cur.phase):
        if ph == 2:
            assert ratio[i] < ratio[chosen].mean()
            chosen.append(i)


def test_cap_and_determinism() -> None:
    rng = np.random.default_rng(2)
    v = rng.random((300, 19))
    a, b = curate(v, cap=8), curate(v.copy(), cap=8)
    assert a == b and len(a.selected) <= 8
    assert len(set(a.selected)) == len(a.selected)
