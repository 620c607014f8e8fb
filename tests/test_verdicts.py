"""Board-wide verdicts: Holm's step-down, p-values that agree with the intervals, and the false-verdict rate of
synthetic boards whose rows do not adapt and do not beat the best fixed policy."""

from __future__ import annotations

import numpy as np
import pytest

from mewa_bench.protocol.scoring import Estimate, bootstrap_interval, stratified_estimates
from mewa_bench.protocol.verdicts import (ALGORITHMS, CHECKPOINTS, FAMILY_ALPHA, Hypothesis, holm, judge, p_value,
                                          read_back, table_weights)


def test_holm_steps_down_and_stops_at_the_first_failure() -> None:
    # m = 4 at alpha 0.05: thresholds 0.0125, 0.0167, 0.025, 0.05 for the sorted p-values
    assert holm({"a": 0.01, "b": 0.016, "c": 0.03, "d": 0.04}, 0.05) == {"a": True, "b": True, "c": False, "d": False}
    assert holm({"a": 0.013, "b": 0.001}, 0.05) == {"a": True, "b": True}
    assert holm({"a": 0.02, "b": 0.02, "c": 0.02}, 0.05) == {"a": False, "b": False, "c": False}  # 0.02 > 0.05/3
    assert holm({}, 0.05) == {}


def test_weighted_holm_orders_by_p_over_weight_and_spends_what_the_rejected_tests_held() -> None:
    w = {"a": 0.2, "b": 0.8}
    # p / w: a 0.02 first (bar 0.05 x 0.2 / 1 = 0.01), then b alone (bar 0.05 x 0.8 / 0.8 = 0.05)
    assert holm({"a": 0.004, "b": 0.02}, 0.05, w) == {"a": True, "b": True}
    # p / w: b 0.025 first (bar 0.04), then a with the whole of what is left (bar 0.05)
    assert holm({"a": 0.012, "b": 0.02}, 0.05, w) == {"a": True, "b": True}
    # b first fails its bar (0.045 > 0.04): the procedure stops, a is never reached
    assert holm({"a": 0.012, "b": 0.045}, 0.05, w) == {"a": False, "b": False}
    rng = np.random.default_rng(7)
    for _ in range(200):  # equal weights: the classic procedure, p_(j) <= alpha / (m - j + 1)
        p = dict(enumerate(rng.uniform(0, 0.02, int(rng.integers(1, 30))) ** 2))
        order = sorted(p, key=lambda k: (p[k], k))
        passed = [p[k] <= 0.025 / (len(p) - j) for j, k in enumerate(order)]
        first_failure = passed.index(False) if False in passed else len(p)
        classic = {k: j < first_failure for j, k in enumerate(order)}
        assert holm(p, 0.025) == classic == holm(p, 0.025, dict.fromkeys(p, 3.0))


def test_each_table_holds_an_equal_share_and_a_few_run_algorithm_is_not_drowned_by_many_checkpoints() -> None:
    weights = table_weights({"c1": CHECKPOINTS, "c2": CHECKPOINTS, "c3": CHECKPOINTS, "a": ALGORITHMS})
    assert weights == pytest.approx({"c1": 1 / 6, "c2": 1 / 6, "c3": 1 / 6, "a": 1 / 2})
    # narrow-v2's shape: 72 checkpoint tests, 34 of them clear, and an algorithm of 3 runs at p = 0.0005
    # (t = 31 on 2 degrees of freedom); unweighted it would need 38 smaller p-values before it
    p = {("run", i): (1e-12 if i < 34 else 0.4) for i in range(72)} | {("algorithm", j): 0.3 for j in range(13)}
    p[("algorithm", "ad")] = 0.0005
    tables = {k: ALGORITHMS if k[0] == "algorithm" else CHECKPOINTS for k in p}
    assert holm(p, FAMILY_ALPHA)[("algorithm", "ad")] is False
    weighted = holm(p, FAMILY_ALPHA, table_weights(tables))
    assert weighted[("algorithm", "ad")] is True
    assert [k for k in p if weighted[k] != holm(p, FAMILY_ALPHA)[k]] == [("algorithm", "ad")]
    e = bootstrap_interval(0.1, np.random.default_rng(0).normal(0, 0.01, 300), 5, 4)
    with pytest.raises(ValueError, match="share the key"):  # one key, one test, in one table
        judge([Hypothesis("x", e, 0.0, CHECKPOINTS), Hypothesis("x", e, 0.0, ALGORITHMS)])


def test_a_p_value_agrees_with_the_interval_printed_beside_it() -> None:
    """p <= 2.5% exactly when the 95% interval lies above the threshold, for computed and read-back estimates."""
    rng = np.random.default_rng(1)
    for _ in range(200):
        n = int(rng.integers(2, 12))
        e = bootstrap_interval(float(rng.normal(0.01, 0.01)), rng.normal(0, 0.01, 500), n, n - 1)
        p = p_value(e, 0.0)
        assert (p <= FAMILY_ALPHA) == (e.low > 0.0), (e, p)
        again = p_value(read_back(e.mean, e.low, e.high, n - 1), 0.0)
        assert again == pytest.approx(p, rel=1e-9, abs=1e-15)
    assert p_value(Estimate(0.1, None, None), 0.0) is None


def test_one_key_is_one_test_and_a_key_may_not_name_two() -> None:
    e = bootstrap_interval(0.1, np.random.default_rng(0).normal(0, 0.01, 300), 5, 4)
    family = judge([Hypothesis("x", e, 0.0), Hypothesis("x", e, 0.0), Hypothesis("y", Estimate(0.0, None, None), 0.0)])
    assert family.size == 1 and family.decision("x") is True and family.decision("y") is None
    with pytest.raises(ValueError, match="share the key"):
        judge([Hypothesis("x", e, 0.0), Hypothesis("x", e, 0.05)])


P, K, SEEDS = 16, 10, 12


def null_checkpoint(rng: np.random.Generator, mu: np.ndarray, shift: float) -> tuple[dict[str, Estimate], np.ndarray]:
    """A synthetic run that neither adapts nor beats the best fixed policy (E[s_k] = mu[pair] + shift, shift <= 0):
    its within-run estimates from the protocol's stratified bootstrap, and its pair curves [P, K]."""
    pairs = np.repeat(np.arange(P), SEEDS)
    y = mu[pairs][:, None] + shift + rng.normal(0, 0.1, (len(pairs), K)) * rng.binomial(1, 0.5, (len(pairs), 1))
    columns = {"mean": y.mean(axis=1), "adaptability": y[:, -1] - y[:, 0], "diff_best_fixed": y.mean(axis=1) - mu[pairs]}
    curves = np.stack([y[pairs == p].mean(axis=0) for p in range(P)])
    return stratified_estimates(columns, pairs, samples=200), curves  # one resampling for every run, as a board


def synthetic_board(rng: np.random.Generator, mu: np.ndarray) -> tuple[dict, dict]:
    """A board of 24 checkpoints (6 algorithms of 4 runs), none adapting, none above the best fixed policy
    (whose exact pair scores are mu); (board-wide decisions, decisions of each row on its own)."""
    from mewa_bench.leaderboard.algorithms import rows_of
    from mewa_bench.leaderboard.board import AGENT, Row
    from mewa_bench.leaderboard.judging import judge_board, with_gap_won
    from mewa_bench.protocol.aggregate import Run, aggregate

    best_fixed = float(mu.mean())
    runs, rows = [], {}
    for a in range(6):
        for r in range(4):
            name = f"algo{a}-seed{r}"
            est, curves = null_checkpoint(rng, mu, shift=min(0.0, rng.normal(0, 0.01)))
            row = Row(kind=AGENT, rank=None, name=name, mean=est["mean"].mean, mean_low=est["mean"].low,
                      mean_high=est["mean"].high, s_first=0.0, s_last=0.0, adaptability=est["adaptability"].mean,
                      adaptability_low=est["adaptability"].low, adaptability_high=est["adaptability"].high,
                      skill=0.0, vs_best_fixed=est["diff_best_fixed"].mean, vs_best_fixed_low=est["diff_best_fixed"].low,
                      vs_best_fixed_high=est["diff_best_fixed"].high, seeds=SEEDS)
            rows[name] = with_gap_won(row, best_fixed)
            runs.append(Run(name, f"algo{a}", curves))
    comparison = aggregate(runs, {}, samples=200, pairwise=False)
    algorithms = rows_of(best_fixed, comparison, set(), runs=rows, pairs=P)
    judged = judge_board(list(rows.values()), algorithms, rows, P)
    each = {key: p <= FAMILY_ALPHA for key, p in judged.family.p_values.items()}
    return judged.family.decisions, each


def test_boards_of_rows_that_do_not_adapt_make_a_false_verdict_at_most_5_percent_of_the_time() -> None:
    """60 synthetic boards (24 checkpoints and 6 algorithms, two tests each: 60 tests, every null true at or past
    its boundary): Holm says any "yes" on a board at most 5% of the time; each row's own 2.5% test, which the
    boards used before, would say one on most boards."""
    rng = np.random.default_rng(2026)
    mu = rng.uniform(0.5, 0.9, P)
    boards = 60
    any_holm = any_alone = 0
    for _ in range(boards):
        decisions, alone = synthetic_board(rng, mu)
        assert len(decisions) == 24 * 2 + 6 * 2
        any_holm += any(decisions.values())
        any_alone += any(alone.values())
    assert any_holm / boards <= 0.05, any_holm
    assert any_alone / boards >= 0.3, any_alone
