"""Algorithm-level statistics: several training runs of each algorithm on one suite (rliable's estimators).

A run contributes its (run, pair) cells: the pair's mean of control-variate-adjusted scores, per
episode (`Scores.pair_curves`, unbiased per pair). Over the cells of an algorithm's runs:

- mean and IQM (the 25% trimmed mean of all run x pair cells, as rliable's `aggregate_iqm`),
  optimality gap (1 - mean(min(cell, 1)), rliable's with gamma = 1), the curve s_1..s_10 and
  adaptability mean(s_10 - s_1);
- probability of improvement of X over Y: per pair, P(X's run > Y's run) with ties 1/2 (the
  Mann-Whitney statistic over the runs' cells, as rliable's), averaged over pairs; over an exact
  reference line, the fraction of X's cells above the line's pair value;
- performance profile: the fraction of run x pair cells above each threshold.

Intervals resample whole training runs (all pairs of a resampled run together) with a generator
seeded by (BOOTSTRAP_SEED, the algorithm's name), so each algorithm's interval is reproducible to
the byte and does not depend on which other algorithms are compared. They are the bootstrap's
standard error x sqrt(n / (n - 1)) x Student's t(n - 1) for n runs (`scoring.bootstrap_interval`).
Why whole runs, not runs stratified by pair: a training seed is better or worse on every pair at
once, and resampling pairs' runs independently averages that away (synthetic runs: ~60-70%
coverage of 95% intervals at 3 to 10 runs; whole runs with the correction: ~95%; see
tests/test_aggregate.py). Skewed run effects (a fifth of the seeds failing) bring the coverage down to
87-91% at 3 to 10 runs, and the bootstrap's percentile and BCa intervals do worse
(benchmarks/interval_coverage.py, docs/protocol.md section 3b). Fewer than MIN_RUNS runs: a note that the
interval cannot include training variance (one run: no interval at all).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from mewa_bench.protocol.scoring import CONFIDENCE, INTERVAL_METHOD, Estimate, bootstrap_interval, interquartile_mean

BOOTSTRAP_SEED = 20250601
BOOTSTRAP_SAMPLES = 2000
MIN_RUNS = 3
PROFILE_THRESHOLDS = tuple(round(0.01 * i, 2) for i in range(0, 111))  # score thresholds 0.00..1.10
UNIT = "training run (every pair of a resampled run together)"


@dataclass(frozen=True)
class Run:
    """One training run's cells: `curves[p, k]` = the pair's mean adjusted score at episode k."""

    name: str
    algorithm: str
    curves: np.ndarray = field(compare=False, repr=False)


@dataclass(frozen=True)
class AlgorithmScores:
    """Everything reported about an algorithm on a suite."""

    algorithm: str
    runs: tuple[str, ...]
    mean: Estimate
    iqm: Estimate
    optimality_gap: Estimate
    adaptability: Estimate
    curve: tuple[Estimate, ...]
    over_lines: dict[str, Estimate]  # probability of improvement over each exact reference line
    profile: tuple[Estimate, ...]  # at PROFILE_THRESHOLDS
    note: str

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (without the profile, which is for figures)."""
        return {"algorithm": self.algorithm, "runs": list(self.runs), "mean": self.mean.to_dict(),
                "iqm": self.iqm.to_dict(), "optimality_gap": self.optimality_gap.to_dict(),
                "adaptability": self.adaptability.to_dict(), "curve": [e.to_dict() for e in self.curve],
                "over_lines": {k: e.to_dict() for k, e in self.over_lines.items()}, "note": self.note}


@dataclass(frozen=True)
class AlgorithmComparison:
    """Algorithms of one suite, best mean first, and P(X > Y) for every ordered pair (X, Y)."""

    algorithms: tuple[AlgorithmScores, ...]
    improvement: dict[tuple[str, str], Estimate]
    samples: int
    seed: int

    def bootstrap(self) -> dict[str, Any]:
        """How the intervals were made."""
        return {"seed": self.seed, "samples": self.samples, "confidence": CONFIDENCE, "unit": UNIT,
                "interval": INTERVAL_METHOD}


def few_runs_note(runs: int) -> str:
    """What an algorithm with fewer than MIN_RUNS runs cannot tell ("" from MIN_RUNS on)."""
    if runs >= MIN_RUNS:
        return ""
    if runs == 1:
        return "1 run: no interval over training runs (it cannot include training variance)"
    return f"{runs} runs: fewer than {MIN_RUNS}, so the interval cannot include training variance reliably"


def algorithm_resamples(algorithm: str, runs: int, samples: int, seed: int) -> np.ndarray:
    """Run indices [samples, runs] drawn with replacement from a generator seeded by (seed, algorithm name)."""
    key = int.from_bytes(hashlib.sha256(algorithm.encode()).digest()[:8], "little")
    return np.random.default_rng([seed, key]).integers(0, runs, size=(samples, runs))


def mean_score(cells: np.ndarray) -> np.ndarray:
    """rliable's aggregate_mean over the last two axes [..., runs, pairs]."""
    return np.mean(np.mean(cells, axis=-2), axis=-1)


def optimality_gap(cells: np.ndarray, gamma: float = 1.0) -> np.ndarray:
    """rliable's optimality gap over the last two axes: gamma - mean(min(cells, gamma))."""
    return gamma - np.mean(np.minimum(cells, gamma), axis=(-2, -1))


def improvement_probability(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y) over the last two axes [..., runs, pairs]: per pair over all run pairs (ties 1/2), averaged."""
    diff = x[..., :, None, :] - y[..., None, :, :]  # [..., Rx, Ry, P]
    per_pair = ((diff > 0).sum(axis=(-3, -2)) + 0.5 * (diff == 0).sum(axis=(-3, -2))) / (x.shape[-2] * y.shape[-2])
    return np.mean(per_pair, axis=-1)


def aggregate(runs: Sequence[Run], lines: dict[str, np.ndarray], samples: int = BOOTSTRAP_SAMPLES,
              seed: int = BOOTSTRAP_SEED, pairwise: bool = True) -> AlgorithmComparison:
    """Group runs by algorithm and estimate everything; `lines` maps a reference line to its exact score per pair.
    `pairwise=False` leaves out P(X > Y) between algorithms (quadratic in their number; a board's table has no use
    for it)."""
    groups: dict[str, list[Run]] = {}
    for run in sorted(runs, key=lambda r: (r.algorithm, r.name)):
        groups.setdefault(run.algorithm, []).append(run)
    shapes = {r.curves.shape for r in runs}
    if len(shapes) > 1:
        raise ValueError(f"runs of different shapes (pairs x episodes) cannot be compared: {sorted(shapes)}")
    curves = {a: np.stack([r.curves for r in g]) for a, g in groups.items()}  # [R, P, K]
    idx = {a: algorithm_resamples(a, len(c), samples, seed) for a, c in curves.items()}
    scores = [_algorithm(a, [r.name for r in groups[a]], curves[a], idx[a], lines) for a in groups]
    scores.sort(key=lambda s: (-s.mean.mean, s.algorithm))
    improvement: dict[tuple[str, str], Estimate] = {}
    for a in curves if pairwise else ():
        for b in curves:
            if a != b:
                x, y = curves[a].mean(axis=-1), curves[b].mean(axis=-1)
                point = float(improvement_probability(x, y))
                boot = improvement_probability(x[idx[a]], y[idx[b]])
                n = min(len(x), len(y))
                improvement[(a, b)] = bootstrap_interval(point, boot, n, n - 1, (0.0, 1.0))
    return AlgorithmComparison(tuple(scores), improvement, samples, seed)


def _algorithm(name: str, run_names: list[str], curves: np.ndarray, idx: np.ndarray,
               lines: dict[str, np.ndarray]) -> AlgorithmScores:
    """One algorithm's estimates from its runs' curves [R, P, K] and run resamples idx [B, R]."""
    n = len(curves)
    cells = curves.mean(axis=-1)  # [R, P]
    boot_cells = cells[idx]  # [B, R, P]

    def estimate(point: float, replicates: np.ndarray, bounds: tuple[float, float] = (-np.inf, np.inf)) -> Estimate:
        return bootstrap_interval(point, replicates, n, n - 1, bounds)

    run_curve = curves.mean(axis=1)  # [R, K]
    curve = tuple(estimate(float(np.mean(curves[:, :, k])), run_curve[idx, k].mean(axis=1))
                  for k in range(curves.shape[-1]))
    run_adapt = (curves[:, :, -1] - curves[:, :, 0]).mean(axis=1)  # [R]
    adaptability = estimate(float(np.mean(curves[:, :, -1] - curves[:, :, 0])), run_adapt[idx].mean(axis=1))
    over_lines = {}
    for line, values in lines.items():
        ref = np.asarray(values, dtype=np.float64)[None, :]
        over_lines[line] = estimate(float(improvement_probability(cells, ref)),
                                    improvement_probability(boot_cells, ref[None]), (0.0, 1.0))
    above = cells[:, :, None] > np.array(PROFILE_THRESHOLDS)  # [R, P, T]
    boot_above = above.mean(axis=1)[idx].mean(axis=1)  # [B, T]
    profile = [estimate(float(np.mean(above[:, :, j])), boot_above[:, j], (0.0, 1.0))
               for j in range(len(PROFILE_THRESHOLDS))]
    return AlgorithmScores(
        algorithm=name, runs=tuple(run_names),
        mean=estimate(float(mean_score(cells)), mean_score(boot_cells)),
        iqm=estimate(float(interquartile_mean(cells, axis=None)),
                     interquartile_mean(boot_cells.reshape(len(idx), -1))),
        optimality_gap=estimate(float(optimality_gap(cells)), optimality_gap(boot_cells), (0.0, np.inf)),
        adaptability=adaptability, curve=curve, over_lines=over_lines, profile=tuple(profile),
        note=few_runs_note(n))
