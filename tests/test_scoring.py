"""Protocol 2 scoring: control variates are unbiased, CIs come from seeds within pairs, verdicts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from mewa_bench.design.exact import expected_returns
from mewa_bench.design.policies import policy_names
from mewa_bench.design.replay import replay_returns
from mewa_bench.design.suites import Suite, load_suite
from mewa_bench.game import luck
from mewa_bench.game.normalise import normalised_return
from mewa_bench.protocol import policy_agent
from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.runner import evaluate
from mewa_bench.protocol.scoring import (CV_MIN_SEEDS, control_variates, episode_scores, interquartile_mean, resampled_sums, score_units,
                                         skill_of, stratified_resamples)

K = 10


@pytest.fixture(scope="module")
def narrow() -> Suite:
    return load_suite("narrow-v1")


def test_scores_by_hand() -> None:
    s = episode_scores(np.array([[0.4, 0.5, 0.6], [0.2, 0.2, 0.5]]), np.array([0.8, 0.5]))
    np.testing.assert_allclose(s, [[0.5, 0.625, 0.75], [0.4, 0.4, 1.0]])
    assert skill_of(0.5, 0.5) == 0.0 and skill_of(1.0, 0.5) == 1.0 and skill_of(0.75, 0.5) == 0.5


def test_interquartile_mean_is_the_25_percent_trimmed_mean() -> None:
    v = np.random.default_rng(0).normal(size=(5, 42))
    np.testing.assert_allclose(interquartile_mean(v), stats.trim_mean(v, 0.25, axis=1))
    assert interquartile_mean(np.array([1.0, 2.0, 3.0, 4.0, 100.0])) == 3.0  # floor(5 / 4) = 1 cut at each end


def test_a_runs_iqm_is_rliables_over_its_pair_means(narrow: Suite) -> None:
    rliable = pytest.importorskip("rliable.metrics")
    units, _ = _synthetic_units(narrow, [0, 3, 5, 8, 9, 13], 4, np.random.default_rng(8))
    scores = score_units(narrow, units, 0.5, samples=50)
    assert scores.pair_curves.shape == (6, K) and scores.pairs == (0, 3, 5, 8, 9, 13)
    assert scores.iqm.mean == rliable.aggregate_iqm(scores.pair_curves.mean(axis=1)[None, :])
    assert scores.mean.mean == pytest.approx(scores.pair_curves.mean(), abs=1e-12)
    assert scores.seeds_per_pair == 4 and "4 seeds per pair" in scores.warning
    assert scores.mean.mean == scores.raw["mean"]["mean"]  # fewer than CV_MIN_SEEDS: no control variates


def test_stratified_resamples_stay_within_their_pair() -> None:
    strata = np.repeat(np.arange(5), 4)
    idx = stratified_resamples(strata, samples=300, seed=3)
    assert np.array_equal(strata[idx], np.broadcast_to(strata, idx.shape))
    assert np.array_equal(idx, stratified_resamples(strata, samples=300, seed=3))


@pytest.mark.parametrize("units,columns", [(7, 1), (500, 1), (7, 2), (300, 3), (960, 30)])
def test_resampled_sums_have_the_bytes_of_numpys_sum_of_the_gathered_units(units: int, columns: int) -> None:
    rng = np.random.default_rng(units * columns)  # values over 16 decades: any other order of the additions shows
    values = rng.normal(size=(units, columns)) * 10.0 ** rng.integers(-8, 8, size=(units, 1))
    idx = rng.integers(0, units, size=(200, units))
    assert resampled_sums(values, idx).tobytes() == values[idx].sum(axis=1).tobytes()


def test_control_variate_with_an_identical_reference_removes_all_noise() -> None:
    rng = np.random.default_rng(1)
    x = rng.normal(0.8, 0.1, size=(2 * CV_MIN_SEEDS + 1, K, 3))
    y = x[:, :, 1].copy()  # the agent plays reference 1 exactly
    expected = np.tile([0.7, 0.8, 0.9], (len(x), 1))
    pairs = np.repeat([0, 1, 2], [CV_MIN_SEEDS, CV_MIN_SEEDS, 1])
    adjusted, chosen = control_variates(y, x, expected, pairs)
    assert np.all(chosen[:-1] == 1) and np.all(chosen[-1] == -1)  # pair 2 has too few seeds to choose on
    np.testing.assert_allclose(adjusted[:-1], 0.8)
    np.testing.assert_array_equal(adjusted[-1], y[-1])


def _synthetic_units(suite: Suite, pairs: list[int], seeds: int, rng: np.random.Generator) -> tuple[list[dict], float]:
    """A randomised adapting agent: per episode a t-optimal policy drawn by its own generator (episodes
    1-3 from all of them, later ones from the two best for the worker), plus its own score noise.
    Returns the units and the agent's exact expected mean score."""
    units, exact = [], []
    for p in pairs:
        pair = suite.pairs[p]
        task = suite.tasks[pair.task_index]
        names = policy_names(task.N, baselines=False)
        values = np.array(pair.data["toptimal"])
        top2 = np.argsort(-values, kind="stable")[:2]
        for s in range(seeds):
            keys = rng.integers(0, luck.KEY_BOUND, size=K, dtype=np.uint64)
            played = replay_returns(task, names, pair.worker.w, keys)
            choice = [int(rng.integers(len(names))) if k < 3 else int(rng.choice(top2)) for k in range(K)]
            norm = normalised_return(task, played[np.arange(K), choice]) + rng.normal(0.0, 0.02, K)
            units.append({"pair": p, "seed": s, "task": pair.task_index, "env_seeds": [int(k) for k in keys],
                          "normalised_returns": norm.tolist()})
        exact.append((3 * values.mean() + 7 * values[top2].mean()) / K / pair.max_expected)
    return units, float(np.mean(exact))


def test_control_variate_scores_are_unbiased_monte_carlo(narrow: Suite) -> None:
    """Over many independent runs the adjusted mean score averages to the agent's exact expectation,
    and its spread is far below the raw score's."""
    rng = np.random.default_rng(2024)
    pairs = [0, 5, 9, 13]
    adjusted, raw, truth = [], [], None
    for _ in range(60):
        units, truth = _synthetic_units(narrow, pairs, CV_MIN_SEEDS, rng)
        scores = score_units(narrow, units, 0.5, samples=20)
        adjusted.append(scores.mean.mean)
        raw.append(scores.raw["mean"]["mean"])
    adjusted, raw = np.array(adjusted), np.array(raw)
    se = adjusted.std(ddof=1) / np.sqrt(len(adjusted))
    assert abs(adjusted.mean() - truth) <= 4 * se + 1e-12, (adjusted.mean(), truth, se)
    assert abs(raw.mean() - truth) <= 4 * raw.std(ddof=1) / np.sqrt(len(raw))
    assert adjusted.std() < 0.6 * raw.std()


def test_one_seed_per_pair_gives_no_interval_rather_than_a_zero_width_one(narrow: Suite) -> None:
    units, _ = _synthetic_units(narrow, [0, 1], 1, np.random.default_rng(0))
    scores = score_units(narrow, units, 0.5, samples=50)
    assert scores.mean.low is None and scores.adaptability.high is None
    assert scores.verdicts == {"adapts": False, "beats_best_fixed": False}


def _policy_run(tmp_path: Path, policy: str, seeds: int) -> dict:
    results, _ = evaluate(EvalConfig(agent_path=policy_agent.AGENT_FILE, suite="narrow-v1", seeds=tuple(range(seeds)),
                                     out=tmp_path / f"{policy}.json", isolated=False, privileged=True,
                                     agent_args={"policy": policy, "seed": "0"}))
    return results["scores"]


def test_a_fixed_policy_scores_its_exact_expectation_and_does_not_adapt(narrow: Suite, tmp_path: Path) -> None:
    policy = "toptimal(rho1=2,rho2=1,q=0)"
    scores = _policy_run(tmp_path, policy, 10)
    index = policy_names(4).index(policy)
    exact = np.mean([p.data["toptimal"][index] / p.max_expected for p in narrow.pairs])
    assert scores["mean"]["mean"] == pytest.approx(exact, abs=1e-9)
    a = scores["adaptability"]
    assert a["low"] <= 0.0 <= a["high"] and not scores["verdicts"]["adapts"]
    # the raw scores still carry the luck the adjusted ones removed
    assert abs(scores["raw"]["mean"]["mean"] - exact) > 1e-6


def test_oracle_adaptability_is_zero_within_a_narrow_interval(tmp_path: Path) -> None:
    scores = _policy_run(tmp_path, policy_agent.MAX_EXPECTED, 10)
    a = scores["adaptability"]
    assert a["low"] <= 0.0 <= a["high"] and (a["high"] - a["low"]) / 2 <= 0.002
    assert scores["mean"]["mean"] == pytest.approx(1.0, abs=1e-9)


def test_random_task_specific_reference_replays_match_the_exact_baseline(narrow: Suite) -> None:
    pair = narrow.pairs[4]
    task = narrow.tasks[pair.task_index]
    keys = np.random.default_rng(5).integers(0, luck.KEY_BOUND, size=4000, dtype=np.uint64)
    r = normalised_return(task, replay_returns(task, ["random-task-specific"], pair.worker.w, keys)[:, 0])
    exact = expected_returns(task, ["random-task-specific"], [pair.worker.w])[0, 0]
    assert exact == pytest.approx(pair.data["baselines"]["random_task_specific"], abs=1e-9)
    assert abs(r.mean() - exact) <= 4 * r.std() / np.sqrt(len(r))
