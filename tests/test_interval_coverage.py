"""Within-run intervals on synthetic runs: coverage of the corrected stratified bootstrap at 3, 5 and 16 seeds."""

from __future__ import annotations

import numpy as np
import pytest

from mewa_bench.protocol.scoring import MIN_SEEDS_COVERED, control_variates, stratified_estimates

P, K = 16, 10
REPS = 300  # the SE of a coverage of 0.95 over 300 repetitions is 0.013


def synthetic_run(rng: np.random.Generator, seeds: int, mu: np.ndarray, gain: float) -> dict:
    """Units of a frozen set of pairs: three references on coupled luck, an agent partly driven by the same luck,
    with skewed noise (rare big deviations, like a worker's mistakes). E[s_k] = mu[pair] + gain * k / (K - 1)."""
    pairs = np.repeat(np.arange(P), seeds)
    units = len(pairs)
    expected = np.tile([0.8, 0.6, 0.9], (units, 1))
    luck = rng.binomial(1, 0.3, size=(units, K)) - 0.3
    realised = expected[:, None, :] + luck[:, :, None] * np.array([0.5, 0.3, 0.1]) + rng.normal(0, 0.02, (units, K, 3))
    noise = rng.binomial(1, 0.2, size=(units, K)) * rng.normal(0.0, 0.3, (units, K))
    y = mu[pairs][:, None] + gain * np.arange(K) / (K - 1) + 0.45 * luck + noise
    adjusted, _ = control_variates(y, realised, expected, pairs)
    columns = {"mean": adjusted.mean(axis=1), "adaptability": adjusted[:, -1] - adjusted[:, 0],
               "raw_mean": y.mean(axis=1), "raw_adaptability": y[:, -1] - y[:, 0]}
    return stratified_estimates(columns, pairs, samples=300, seed=int(rng.integers(1 << 31)))


@pytest.mark.parametrize("seeds", [3, 5, 16])
def test_coverage_of_within_run_intervals(seeds: int) -> None:
    """Without control variates the corrected interval covers ~95% at every seed count; with them (chosen on the
    pair's other seeds) it covers ~95% from MIN_SEEDS_COVERED seeds per pair and a little less below, where the
    scores carry a warning."""
    rng = np.random.default_rng(seeds)
    mu, gain = rng.uniform(0.5, 0.9, P), 0.05
    truth = {"mean": mu.mean() + gain / 2, "adaptability": gain}
    hits = {f"{prefix}{k}": 0 for prefix in ("", "raw_") for k in truth}
    for _ in range(REPS):
        est = synthetic_run(rng, seeds, mu, gain)
        for name in hits:
            value = truth[name.removeprefix("raw_")]
            hits[name] += est[name].low <= value <= est[name].high
    coverage = {k: v / REPS for k, v in hits.items()}
    assert 0.91 <= coverage["raw_mean"] <= 0.99 and 0.91 <= coverage["raw_adaptability"] <= 0.99, coverage
    if seeds >= MIN_SEEDS_COVERED:
        assert 0.92 <= coverage["mean"] <= 0.99 and 0.92 <= coverage["adaptability"] <= 0.99, coverage
    else:
        assert coverage["mean"] >= 0.85 and coverage["adaptability"] >= 0.85, coverage
