"""Scores of an evaluation run (SPEC section 6, protocol version 2): the one home of every formula.

Score of episode k of a unit (one pair, one seed): s_k = normalised return / the pair's
max-expected baseline (1.0 = as good as the best t-optimal policy that knows the worker).

Protocol 2 removes most of the luck from these numbers without changing their expectation:

1. *Coupled luck.* Every episode is played with a luck key (its env seed), and the reference
   policies (the t-optimal family and the two random baselines) are replayed on the same keys
   (`design.replay`), so they meet the same worker mistakes wherever their paths allow.
2. *Control variates.* The adjusted score of an episode is s - x_r + E[x_r], where x_r is the
   realised score of reference r on the same key and E[x_r] its exact expectation from the suite.
   For every (pair, episode k) and every unit, r is the reference (or none) whose difference with
   the agent had the smallest variance on the *other* seeds of the same pair (cross-fitting):
   the choice never looks at the unit it adjusts, so E[adjusted] = E[s] exactly.
3. *Statistics for a frozen suite.* The pairs are fixed, so confidence intervals come from a
   bootstrap that resamples seeds within each pair (stratified), with its seed and size recorded.
   The interval is the small-sample-corrected standard-error one (`bootstrap_interval`): the
   bootstrap's standard deviation times sqrt(n / (n - 1)) (n seeds per pair: the bootstrap's
   variance is (n - 1) / n of the unbiased one) times Student's t quantile on the pooled degrees
   of freedom. Reported beside the mean: the interquartile mean (IQM, as rliable defines it: the
   25% trimmed mean of the pair means, which the control variates leave unbiased), paired
   comparisons with the reference lines (difference of means, probability of improvement on the
   same seeds) and two verdicts: *adapts* (adaptability CI above 0) and *beats the best fixed policy*.
A CI needs at least two seeds in every pair; with fewer it is reported as unknown (null), never as
a zero-width interval. Pairs with fewer than CV_MIN_SEEDS seeds are scored without control variates
(their intervals are wider and keep their coverage), and the scores say so in a warning; the
coverage is measured on synthetic runs at 2 to 16 seeds per pair (tests/test_interval_coverage.py).
These CIs are conditional on the evaluated checkpoint; training-run variance is `protocol.aggregate`'s.

The module is longer than 500 lines because it is the one home of every score formula: splitting the
adjustment from the statistics it feeds would put one formula in two rooms.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Sequence

import numpy as np

from mewa_bench.design.policies import RANDOM, RANDOM_TASK_SPECIFIC, policy_names
from mewa_bench.design.replay import replay_returns
from mewa_bench.design.suites import Suite
from mewa_bench.game.normalise import episode_score, normalised_return, skill_of

BOOTSTRAP_SEED = 20231105
BOOTSTRAP_SAMPLES = 2000
CONFIDENCE = 0.95
CV_MIN_SEEDS = 8  # seeds of a pair from which its units get control variates (chosen on the other 7)
CV_DECIMALS = 12  # variances are compared after rounding, so ties do not depend on float noise
EQUAL_TOLERANCE = 1e-9  # two realised scores closer than this count as a tie (probability 1/2)
COMPARED = ("best_fixed", "max_expected", "random_task_specific", "random")  # realised on the same keys
EXACT_ONLY = ("known_worker_optimum",)  # compared by exact expectation only (no policy to replay)


def episode_scores(normalised: np.ndarray, max_expected: np.ndarray) -> np.ndarray:
    """s[u, k] = normalised[u, k] / max_expected[u] for units u and episodes k."""
    normalised = np.asarray(normalised, dtype=np.float64)
    max_expected = np.asarray(max_expected, dtype=np.float64)
    if normalised.ndim != 2 or max_expected.shape != normalised.shape[:1]:
        raise ValueError(f"expected normalised [units, episodes] and max_expected [units], got "
                         f"{normalised.shape} and {max_expected.shape}")
    if (max_expected <= 0).any():
        raise ValueError("max-expected baselines must be positive")
    return episode_score(normalised, max_expected[:, None])


@dataclass(frozen=True)
class Estimate:
    """A point estimate with its bootstrap confidence interval (None when it cannot be estimated)."""

    mean: float
    low: float | None
    high: float | None
    # the interval's standard error and Student t degrees of freedom (what a test of the same estimate uses; unset
    # for an estimate read back from JSON, whose interval gives them: `protocol.verdicts.standard_error`)
    se: float | None = field(default=None, compare=False, repr=False)
    df: int | None = field(default=None, compare=False, repr=False)

    def to_dict(self) -> dict[str, float | None]:
        """JSON-ready form."""
        return {"mean": self.mean, "low": self.low, "high": self.high}

    @property
    def above_zero(self) -> bool:
        """True when the whole interval lies above 0."""
        return self.low is not None and self.low > 0.0


@dataclass(frozen=True)
class Comparison:
    """Agent minus one reference line, paired on the same units."""

    difference: Estimate  # mean adjusted score - the reference's exact expected score
    probability_of_improvement: Estimate | None  # P(agent episode > reference episode, same luck key)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        poi = self.probability_of_improvement
        return {"difference": self.difference.to_dict(),
                "probability_of_improvement": poi.to_dict() if poi is not None else None}


@dataclass(frozen=True)
class Scores:
    """Everything reported about a run."""

    curve: tuple[Estimate, ...]  # s_1..s_K, control-variate adjusted
    mean: Estimate  # mean over the K episodes
    iqm: Estimate  # rliable's IQM: the 25% trimmed mean of the pair means
    adaptability: Estimate  # mean(s_K - s_1)
    skill: Estimate  # (S - S_rts) / (1 - S_rts)
    raw: dict[str, Any]  # the same without control variates: curve means, mean, adaptability
    comparisons: dict[str, Comparison]
    units: int
    control_variates: dict[str, Any]  # which references were used, how often
    pairs: tuple[int, ...] = ()  # the pairs played, in order
    pair_curves: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)), compare=False, repr=False)  # [P, K]
    seeds_per_pair: int = 0
    warning: str = ""  # set when the intervals are not known to cover (too few seeds per pair)

    @property
    def verdicts(self) -> dict[str, bool]:
        """"adapts": adaptability CI above 0; "beats_best_fixed": paired difference CI above 0."""
        return {"adapts": self.adaptability.above_zero,
                "beats_best_fixed": self.comparisons["best_fixed"].difference.above_zero}

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"curve": [e.to_dict() for e in self.curve], "mean": self.mean.to_dict(), "iqm": self.iqm.to_dict(),
                "adaptability": self.adaptability.to_dict(), "skill": self.skill.to_dict(),
                "verdicts": self.verdicts, "comparisons": {k: c.to_dict() for k, c in self.comparisons.items()},
                "raw": self.raw, "control_variates": self.control_variates, "units": self.units,
                **({"pair_means": [float(v) for v in self.pair_curves.mean(axis=1)]} if self.pair_curves.size else {}),
                "bootstrap": {"seed": BOOTSTRAP_SEED, "samples": BOOTSTRAP_SAMPLES, "confidence": CONFIDENCE,
                              "unit": "(pair, seed)", "strata": "pair", "interval": INTERVAL_METHOD},
                **({"warning": self.warning} if self.warning else {})}


def gap_won(estimate: Estimate, best_fixed: float, difference: bool = False) -> Estimate:
    """(score - best fixed) / (1 - best fixed): the share of the non-adaptive gap won, with its interval (the same
    map; best fixed is exact). `difference`: the estimate is already score - best fixed (a paired comparison)."""
    gap = 1.0 - best_fixed
    if gap <= 0.0:
        raise ValueError(f"the best fixed policy scores {best_fixed}: no gap for adaptation to win")
    shift = 0.0 if difference else best_fixed

    def won(v: float | None) -> float | None:
        return None if v is None else (v - shift) / gap

    return Estimate(won(estimate.mean), won(estimate.low), won(estimate.high),
                    None if estimate.se is None else estimate.se / gap, estimate.df)


# -- reference replays -----------------------------------------------------------------------------

@dataclass(frozen=True)
class References:
    """Realised and exact scores of the reference policies for every unit's episodes.

    Column r of `realised` [U, K, R] / `expected` [U, R] is the r-th of `names[pair's task]`
    (t-optimal family, then random task-specific and random); columns past a task's own
    references are NaN (wide suites mix N = 3 and N = 4).
    """

    realised: np.ndarray
    expected: np.ndarray
    names: dict[int, tuple[str, ...]]


def reference_scores(suite: Suite, units: Sequence[dict[str, Any]]) -> References:
    """Replay every reference policy on the units' luck keys (= env seeds), grouped by pair."""
    k = len(units[0]["env_seeds"]) if units else 0
    width = max(len(policy_names(t.N)) for t in suite.tasks)
    realised = np.full((len(units), k, width), np.nan)
    expected = np.full((len(units), width), np.nan)
    names = {i: policy_names(t.N) for i, t in enumerate(suite.tasks)}
    by_pair: dict[int, list[int]] = {}
    for u, unit in enumerate(units):
        by_pair.setdefault(int(unit["pair"]), []).append(u)
    for pair, rows in by_pair.items():
        p = suite.pairs[pair]
        refs = names[p.task_index]
        keys = np.array([units[u]["env_seeds"] for u in rows], dtype=np.uint64).reshape(-1)
        realised[rows, :, : len(refs)] = replayed_scores(suite, pair, keys).reshape(len(rows), k, len(refs))
        exact = [*p.data["toptimal"], p.data["baselines"][RANDOM_TASK_SPECIFIC.replace("-", "_")],
                 p.data["baselines"][RANDOM]]
        expected[rows, : len(refs)] = episode_score(np.array(exact), p.max_expected)
    return References(realised, expected, names)


_REPLAYS: OrderedDict[tuple[str, int, bytes], np.ndarray] = OrderedDict()
REPLAYS_KEPT = 256  # (suite, pair, keys) replays kept: every pair of the shipped suites, several times over
_REPLAYS_LOCK = threading.Lock()


def replayed_scores(suite: Suite, pair: int, keys: np.ndarray) -> np.ndarray:
    """Scores [episodes, references] of the pair's reference policies replayed on the luck keys (read-only).

    A replay is a pure function of (suite, pair, keys), and every ranked run of a suite plays the same keys, so a
    board of many runs replays each pair once: kept by the suite's hash, the pair and a digest of the keys."""
    keys = np.ascontiguousarray(keys, dtype=np.uint64)
    key = (suite.sha256, int(pair), hashlib.sha256(keys.tobytes()).digest())
    with _REPLAYS_LOCK:
        if key in _REPLAYS:
            _REPLAYS.move_to_end(key)
            return _REPLAYS[key]
    p = suite.pairs[pair]
    task = suite.tasks[p.task_index]
    returns = replay_returns(task, policy_names(task.N), p.worker.w, keys)
    scores = episode_score(normalised_return(task, returns), p.max_expected)
    scores.flags.writeable = False
    with _REPLAYS_LOCK:
        _REPLAYS[key] = scores
        while len(_REPLAYS) > REPLAYS_KEPT:
            _REPLAYS.popitem(last=False)
    return scores


# -- control variates ------------------------------------------------------------------------------

def control_variates(y: np.ndarray, realised: np.ndarray, expected: np.ndarray,
                     strata: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Adjusted scores [U, K] and the reference used per unit and episode (-1: none), cross-fitted.

    For unit u of pair p and episode k, the candidates are y - realised[..., r] + expected[r] for
    every reference r (and with r scaled by its least-squares slope), and y itself (no adjustment).
    The one applied to u has the smallest variance over the *other* units of pair p at episode k;
    ties go to the smallest variance over all their episodes, then to the first candidate (plain
    references in canonical order, then scaled ones, no adjustment last). Pairs with fewer than
    CV_MIN_SEEDS units are left unadjusted: a choice made on so few other seeds narrows the interval
    without narrowing the spread (coverage 89-92% at 3-5 seeds per pair, tests/test_interval_coverage.py).
    """
    n_units, n_episodes = y.shape
    n_refs = realised.shape[2]
    centred = realised - expected[:, None, :]
    adjusted = y.copy()
    chosen = np.full((n_units, n_episodes), -1, dtype=np.int64)
    for stratum in np.unique(strata):
        rows = np.flatnonzero(strata == stratum)
        n = len(rows)
        if n < CV_MIN_SEEDS:
            continue
        beta = _leave_one_out_slope(y[rows], centred[rows])  # [n, R]
        c = np.concatenate([y[rows, :, None] - centred[rows],
                            y[rows, :, None] - beta[:, None, :] * centred[rows], y[rows, :, None]], axis=2)
        none = c.shape[2] - 1
        per_episode = _leave_one_out_variance(c)  # [n, K, C]
        pooled = np.broadcast_to(_leave_one_out_variance(c, pooled=True)[:, None, :], c.shape)
        pick = _lexicographic_argmin((per_episode, pooled))
        adjusted[rows] = np.take_along_axis(c, pick[:, :, None], axis=2)[:, :, 0]
        chosen[rows] = np.where(pick == none, -1, pick % n_refs)
    return adjusted, chosen


def _lexicographic_argmin(keys: tuple[np.ndarray, ...]) -> np.ndarray:
    """Index along the last axis minimising keys[0], ties broken by keys[1], ...; then the first index."""
    candidates = np.ones(keys[0].shape, dtype=bool)
    for key in keys:
        masked = np.where(candidates, key, np.inf)
        candidates &= masked == masked.min(axis=-1, keepdims=True)
    return np.argmax(candidates, axis=-1)


def _leave_one_out_slope(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Least-squares slope of y [n, K] on each x [n, K, R] over the other units' episodes, [n, R] (0 if x is constant)."""
    count = (len(y) - 1) * y.shape[1]
    sy, sx = y.sum(axis=(0, 1)) - y.sum(axis=1), x.sum(axis=(0, 1))[None, :] - x.sum(axis=1)
    sxy = (y[:, :, None] * x).sum(axis=(0, 1))[None, :] - (y[:, :, None] * x).sum(axis=1)
    sxx = (x * x).sum(axis=(0, 1))[None, :] - (x * x).sum(axis=1)
    cov = sxy / count - (sy[:, None] / count) * (sx / count)
    var = sxx / count - (sx / count) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = np.where(var > 1e-12, cov / var, 0.0)
    return np.round(np.nan_to_num(slope, nan=0.0), CV_DECIMALS)


def _leave_one_out_variance(c: np.ndarray, pooled: bool = False) -> np.ndarray:
    """Variance over the other units (axis 0) of each candidate, rounded; NaN candidates get +inf.

    c is [n, K, C]: per episode ([n, K, C] result), or over all the other units' episodes at once
    (`pooled`, [n, C] result).
    """
    n = len(c)
    if pooled:
        total, squares = c.sum(axis=(0, 1)), (c * c).sum(axis=(0, 1))
        mine, mine_sq = c.sum(axis=1), (c * c).sum(axis=1)
        count = (n - 1) * c.shape[1]
    else:
        total, squares, mine, mine_sq, count = c.sum(axis=0), (c * c).sum(axis=0), c, c * c, n - 1
    mean = (total - mine) / count
    var = (squares - mine_sq) / count - mean**2
    return np.where(np.isnan(var), np.inf, np.round(np.maximum(var, 0.0), CV_DECIMALS))


# -- stratified bootstrap --------------------------------------------------------------------------

def stratified_resamples(strata: np.ndarray, samples: int = BOOTSTRAP_SAMPLES,
                         seed: int = BOOTSTRAP_SEED) -> np.ndarray:
    """Unit indices [samples, U]: each pair's units resampled with replacement among themselves (read-only).

    The same for every run with the same units per pair (a board's runs): the latest few are kept."""
    strata = np.ascontiguousarray(strata, dtype=np.int64)
    return _stratified_resamples(strata.tobytes(), samples, seed)


@lru_cache(maxsize=2)  # a [2000, 4096] index array is 65 MB: the latest two only
def _stratified_resamples(strata_bytes: bytes, samples: int, seed: int) -> np.ndarray:
    """stratified_resamples, computed."""
    strata = np.frombuffer(strata_bytes, dtype=np.int64)
    rng = np.random.default_rng(seed)
    idx = np.empty((samples, len(strata)), dtype=np.int64)
    for stratum in np.unique(strata):
        rows = np.flatnonzero(strata == stratum)
        idx[:, rows] = rows[rng.integers(0, len(rows), size=(samples, len(rows)))]
    idx.flags.writeable = False
    return idx


def interquartile_mean(values: np.ndarray, axis: int | None = -1) -> np.ndarray:
    """rliable's IQM: the mean of `values` along `axis` (all of them for None) without the lowest and the highest
    floor(n / 4) (scipy.stats.trim_mean(values, 0.25))."""
    v = np.asarray(values, dtype=np.float64)
    v = v.reshape(-1) if axis is None else np.moveaxis(v, axis, -1)
    n = v.shape[-1]
    cut = int(0.25 * n)
    middle = np.partition(v, (cut, n - cut - 1), axis=-1)[..., cut:n - cut]
    return np.mean(middle, axis=-1)


INTERVAL_METHOD = "bootstrap standard error x sqrt(n / (n - 1)) x Student t (n - 1 per stratum)"


@lru_cache(maxsize=None)
def _t_quantile(df: int) -> float:
    """Student's t quantile of the two-sided CONFIDENCE interval."""
    from scipy.stats import t

    return float(t.ppf(0.5 + CONFIDENCE / 2.0, df))


def bootstrap_interval(point: float, replicates: np.ndarray, n: int, df: int,
                       bounds: tuple[float, float] = (-np.inf, np.inf)) -> Estimate:
    """point +- t(df) * sqrt(n / (n - 1)) * SD(replicates): the bootstrap's standard error corrected for n draws
    per stratum; None bounds when n < 2 (no variance can be estimated), clipped to `bounds`."""
    if n < 2 or df < 1:
        return Estimate(float(point), None, None)
    se = float(np.sqrt(n / (n - 1.0)) * np.std(replicates, ddof=1))
    half = _t_quantile(df) * se
    return Estimate(float(point), float(max(point - half, bounds[0])), float(min(point + half, bounds[1])), se, int(df))


# -- the run's scores ------------------------------------------------------------------------------

def score_units(suite: Suite, units: Sequence[dict[str, Any]], rts_score: float,
                samples: int = BOOTSTRAP_SAMPLES, seed: int = BOOTSTRAP_SEED) -> Scores:
    """Scores of a run from its units (pair, env_seeds, normalised_returns): the protocol-2 estimators."""
    if not units:
        raise ValueError("no units to score")
    pairs = np.array([int(u["pair"]) for u in units])
    best = np.array([suite.pairs[p].max_expected for p in pairs])
    y = episode_scores(np.array([u["normalised_returns"] for u in units], dtype=np.float64), best)
    refs = reference_scores(suite, units)
    adjusted, chosen = control_variates(y, refs.realised, refs.expected, pairs)
    n_units, k = y.shape

    columns: dict[str, np.ndarray] = {}
    for i in range(k):
        columns[f"s{i}"] = adjusted[:, i]
    columns["mean"] = adjusted.mean(axis=1)
    columns["adaptability"] = adjusted[:, -1] - adjusted[:, 0]
    columns["raw_mean"] = y.mean(axis=1)
    columns["raw_adaptability"] = y[:, -1] - y[:, 0]
    exact_line, realised_line = _reference_columns(suite, pairs, refs)
    for name, exact in exact_line.items():
        columns[f"diff_{name}"] = columns["mean"] - exact
        if name in realised_line:
            x = realised_line[name]
            columns[f"poi_{name}"] = ((y > x + EQUAL_TOLERANCE) + 0.5 * (np.abs(y - x) <= EQUAL_TOLERANCE)).mean(axis=1)
    est = stratified_estimates(columns, pairs, samples, seed)
    curves = pair_means(adjusted, pairs)
    iqm = stratified_iqm(columns["mean"], pairs, samples, seed, cells=curves.mean(axis=1))
    n_min = seeds_per_pair(pairs)

    skill = Estimate(float(skill_of(est["mean"].mean, rts_score)),
                     *(None if v is None else float(skill_of(v, rts_score)) for v in (est["mean"].low, est["mean"].high)))
    comparisons = {name: Comparison(est[f"diff_{name}"], est.get(f"poi_{name}")) for name in exact_line}
    used = {"none": int(np.sum(chosen < 0)), "reference": int(np.sum(chosen >= 0))}
    return Scores(
        curve=tuple(est[f"s{i}"] for i in range(k)), mean=est["mean"], iqm=iqm, adaptability=est["adaptability"],
        skill=skill,
        raw={"curve": [float(v) for v in y.mean(axis=0)], "mean": est["raw_mean"].to_dict(),
             "adaptability": est["raw_adaptability"].to_dict()},
        comparisons=comparisons, units=n_units,
        control_variates={"references": "t-optimal family, random task-specific, random (replayed on the same luck keys)",
                          "selection": "per (pair, episode): the least-variance candidate on the pair's other seeds",
                          "min_other_seeds": CV_MIN_SEEDS - 1, "episodes_adjusted": used["reference"],
                          "episodes_unadjusted": used["none"]},
        pairs=tuple(int(p) for p in np.unique(pairs)), pair_curves=curves, seeds_per_pair=n_min,
        warning=few_seeds_warning(n_min))


def few_seeds_warning(n: int) -> str:
    """What `n` seeds per pair change in the scores ("" from CV_MIN_SEEDS on)."""
    if n >= CV_MIN_SEEDS:
        return ""
    if n < 2:
        return f"{n} seed per pair: no interval can be estimated (it needs 2 seeds of every pair)"
    return (f"{n} seeds per pair: pairs with fewer than {CV_MIN_SEEDS} seeds are scored without control variates, so "
            f"their intervals are wider (about 1.4x at 3-5 seeds); the protocol's default seeds are far above")


def seeds_per_pair(pairs: np.ndarray) -> int:
    """The fewest units of any pair present."""
    return int(np.min(np.unique(pairs, return_counts=True)[1]))


def pair_means(values: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Mean of `values` [U, ...] over each pair's units, pairs in increasing order: [P, ...]."""
    order = np.unique(pairs)
    return np.stack([values[pairs == p].mean(axis=0) for p in order])


def resampled_sums(values: np.ndarray, idx: np.ndarray, chunk: int = 64) -> np.ndarray:
    """sum(values[idx[b]]) for every resample b: [B, C] from values [U, C] and indices [B, n].

    The bytes are those of numpy's `values[idx].sum(axis=1)`, never a matrix product's: BLAS splits a product by
    thread count and CPU kernel, which changes the last bits of the intervals (and the bytes of results and
    boards). With several columns numpy adds one unit after another (idx[:, 0], then idx[:, 1], ...), so the sum
    is built in that order a column of indices at a time, which keeps the [B, C] sum in cache (2-3x faster than
    gathering [chunk, n, C] blocks); a single column numpy sums pairwise, so it is gathered and summed as numpy does."""
    if values.shape[1] == 1:
        out = np.empty((len(idx), 1))
        for start in range(0, len(idx), chunk):
            out[start:start + chunk] = values[idx[start:start + chunk]].sum(axis=1)
        return out
    by_position = np.ascontiguousarray(idx.T)
    out = values[by_position[0]]
    for units in by_position[1:]:
        out += values[units]
    return out


def stratified_estimates(columns: dict[str, np.ndarray], pairs: np.ndarray, samples: int = BOOTSTRAP_SAMPLES,
                         seed: int = BOOTSTRAP_SEED) -> dict[str, Estimate]:
    """The mean of each per-unit column with its interval from a bootstrap of seeds within pairs."""
    names = list(columns)
    values = np.column_stack([columns[n] for n in names])
    n_units = len(pairs)
    idx = stratified_resamples(pairs, samples, seed)
    boot = resampled_sums(values, idx) / n_units
    n, df = _strata_counts(pairs)
    return {name: bootstrap_interval(float(values[:, j].mean()), boot[:, j], n, df,
                                     (0.0, 1.0) if name.startswith("poi_") else (-np.inf, np.inf))
            for j, name in enumerate(names)}


def stratified_iqm(unit_means: np.ndarray, pairs: np.ndarray, samples: int = BOOTSTRAP_SAMPLES,
                   seed: int = BOOTSTRAP_SEED, cells: np.ndarray | None = None) -> Estimate:
    """rliable's IQM over the pair means of `unit_means` (or the given pair `cells`, the same up to rounding),
    with its interval from the same bootstrap."""
    order = np.unique(pairs)
    idx = stratified_resamples(pairs, samples, seed)  # each pair's units resampled in its own columns
    boot_means = np.column_stack([resampled_sums(unit_means[:, None], idx[:, pairs == p])[:, 0] / np.sum(pairs == p)
                                  for p in order])  # [samples, P]
    n, df = _strata_counts(pairs)
    point = interquartile_mean(pair_means(unit_means, pairs) if cells is None else cells)
    return bootstrap_interval(float(point), interquartile_mean(boot_means), n, df)


def _strata_counts(pairs: np.ndarray) -> tuple[int, int]:
    """(fewest seeds in a pair, pooled degrees of freedom sum over pairs of (seeds - 1))."""
    counts = np.unique(pairs, return_counts=True)[1]
    return int(counts.min()), int((counts - 1).sum())


def _reference_columns(suite: Suite, pairs: np.ndarray,
                       refs: References) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Per unit: each reference line's exact expected score, and its realised scores [U, K] where replayed."""
    exact: dict[str, np.ndarray] = {}
    realised: dict[str, np.ndarray] = {}
    column = {name: np.empty(len(pairs), dtype=np.int64) for name in COMPARED}
    for u, pair in enumerate(pairs):
        p = suite.pairs[pair]
        names = refs.names[p.task_index]
        toptimal = p.data["toptimal"]
        column["best_fixed"][u] = names.index(suite.content["tasks"][p.task_index]["curation"]["best_fixed_policy"])
        column["max_expected"][u] = int(np.argmax(toptimal))
        column["random_task_specific"][u] = names.index(RANDOM_TASK_SPECIFIC)
        column["random"][u] = names.index(RANDOM)
    rows = np.arange(len(pairs))
    for name in COMPARED:
        exact[name] = refs.expected[rows, column[name]]
        realised[name] = refs.realised[rows, :, column[name]]
    for name in EXACT_ONLY:
        exact[name] = np.array([episode_score(suite.pairs[p].data[name], suite.pairs[p].max_expected) for p in pairs])
    return exact, realised


def reference_line_cells(suite: Suite) -> dict[str, np.ndarray]:
    """Each exact reference line's expected score per pair of the suite (pairs in order), on the score scale."""
    out: dict[str, list[float]] = {name: [] for name in (*COMPARED, *EXACT_ONLY)}
    for p in suite.pairs:
        names = policy_names(suite.tasks[p.task_index].N)
        toptimal = p.data["toptimal"]
        best_fixed = names.index(suite.content["tasks"][p.task_index]["curation"]["best_fixed_policy"])
        values = {"best_fixed": toptimal[best_fixed], "max_expected": max(toptimal),
                  "random_task_specific": p.data["baselines"][RANDOM_TASK_SPECIFIC.replace("-", "_")],
                  "random": p.data["baselines"][RANDOM], "known_worker_optimum": p.data["known_worker_optimum"]}
        for name, value in values.items():
            out[name].append(float(episode_score(value, p.max_expected)))
    return {name: np.array(v) for name, v in out.items()}
