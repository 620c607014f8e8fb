"""Scores of an evaluation run (SPEC section 6), from per-(pair, seed, episode) normalised returns.

Score of episode k of a pair: s_k = normalised return / the pair's max-expected baseline
(1.0 = as good as the best t-optimal policy that knows the worker). A unit is one (pair, seed):
the curve s_1..s_10 is averaged over units with a percentile bootstrap CI over units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BOOTSTRAP_SEED = 20231105
BOOTSTRAP_SAMPLES = 2000
CONFIDENCE = 0.95


@dataclass(frozen=True)
class Estimate:
    """A mean with its bootstrap confidence interval."""

    mean: float
    low: float
    high: float

    def to_dict(self) -> dict[str, float]:
        """JSON-ready form."""
        return {"mean": self.mean, "low": self.low, "high": self.high}


def episode_scores(normalised: np.ndarray, max_expected: np.ndarray) -> np.ndarray:
    """s[u, k] = normalised[u, k] / max_expected[u] for units u and episodes k."""
    normalised = np.asarray(normalised, dtype=np.float64)
    max_expected = np.asarray(max_expected, dtype=np.float64)
    if normalised.ndim != 2 or max_expected.shape != normalised.shape[:1]:
        raise ValueError(f"expected normalised [units, episodes] and max_expected [units], got "
                         f"{normalised.shape} and {max_expected.shape}")
    if (max_expected <= 0).any():
        raise ValueError("max-expected baselines must be positive")
    return normalised / max_expected[:, None]


def bootstrap_means(values: np.ndarray, seed: int = BOOTSTRAP_SEED, samples: int = BOOTSTRAP_SAMPLES) -> np.ndarray:
    """Means of `samples` bootstrap resamples of the rows of `values` ([units, ...] -> [samples, ...])."""
    values = np.asarray(values, dtype=np.float64)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(values), size=(samples, len(values)))
    return values[idx].mean(axis=1)


def estimate(values: np.ndarray, boot: np.ndarray) -> Estimate:
    """Mean of `values` over units with the percentile interval of its bootstrap means."""
    alpha = (1.0 - CONFIDENCE) / 2.0
    low, high = np.quantile(boot, [alpha, 1.0 - alpha])
    return Estimate(float(np.mean(values)), float(low), float(high))


@dataclass(frozen=True)
class Scores:
    """Everything reported about a run."""

    curve: tuple[Estimate, ...]  # s_1..s_K
    mean: Estimate  # mean over the K episodes
    adaptability: Estimate  # mean(s_K - s_1)
    skill: Estimate  # (S - S_rts) / (1 - S_rts)
    units: int

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return {"curve": [e.to_dict() for e in self.curve], "mean": self.mean.to_dict(),
                "adaptability": self.adaptability.to_dict(), "skill": self.skill.to_dict(), "units": self.units}


def skill_of(score: np.ndarray | float, rts_score: float) -> np.ndarray | float:
    """skill = (S - S_rts) / (1 - S_rts): 0 = random task-specific, 1 = best t-optimal per worker."""
    return (score - rts_score) / (1.0 - rts_score)


def score_run(normalised: np.ndarray, max_expected: np.ndarray, rts_score: float,
              seed: int = BOOTSTRAP_SEED, samples: int = BOOTSTRAP_SAMPLES) -> Scores:
    """Scores of a run: `normalised` [units, episodes], `max_expected` [units], the suite's rts mean score."""
    s = episode_scores(normalised, max_expected)
    per_unit = np.column_stack([s, s.mean(axis=1), s[:, -1] - s[:, 0]])  # curve, mean, adaptability
    boot = bootstrap_means(per_unit, seed, samples)
    k = s.shape[1]
    curve = tuple(estimate(per_unit[:, i], boot[:, i]) for i in range(k))
    mean = estimate(per_unit[:, k], boot[:, k])
    adapt = estimate(per_unit[:, k + 1], boot[:, k + 1])
    skill = Estimate(float(skill_of(mean.mean, rts_score)), float(skill_of(mean.low, rts_score)),
                     float(skill_of(mean.high, rts_score)))
    return Scores(curve, mean, adapt, skill, len(s))
