"""What adaptation can win per episode under the worker distributions an agent may expect.

The non-adaptive gap of a worker distribution is 1 - max_p E[v_p(w) / max_q v_q(w)] over the
t-optimal policies p (exact values): the most that knowing the worker adds, per episode, to the
best fixed policy for that distribution, i.e. the expected value of perfect information of an agent
whose prior it is. A suite's shipped gap is the one over its curated pairs, and the protocol's best
fixed policy is chosen on those pairs; an agent may only expect the public distributions (SPEC
section 6): the task's meta-train sampler, or the meta-test region as a whole.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mewa_bench.design.curate import best_fixed_policy, non_adaptive_gap
from mewa_bench.design.exact import expected_returns
from mewa_bench.design.policies import toptimal_family
from mewa_bench.design.suites import Suite
from mewa_bench.game.distributions import meta_test_candidates, sample_meta_train_workers
from mewa_bench.game.task import Task

CURATED, META_TRAIN, TEST_REGION = "curated", "meta-train", "test region"
DISTRIBUTIONS = (CURATED, META_TRAIN, TEST_REGION)
DRAWS = 4000  # meta-train draws per task (the gap's Monte Carlo error is about 1e-4 at this size)
SEED = 20261125


@dataclass(frozen=True)
class PriorGap:
    """One suite under one distribution: the gap (mean over tasks) and its best fixed policies' curated score."""

    distribution: str
    gap: float
    on_curated: float  # mean over the suite's pairs of the ratio of each task's best fixed policy for this distribution
    workers: int  # workers the gap averages over (all tasks)


def usable_values(task: Task, workers: np.ndarray, min_best: float) -> np.ndarray:
    """[W, P] exact expected returns of the t-optimal family, for workers whose best return >= min_best."""
    values = expected_returns(task, toptimal_family(task.N), workers).T
    return values[values.max(axis=1) >= min_best]


def task_workers(suite: Suite, t: int, distribution: str, draws: int, seed: int) -> np.ndarray:
    """Workers of task t under a distribution: its curated ones, meta-train draws, or its test-region grid."""
    task = suite.tasks[t]
    if distribution == CURATED:
        return np.array([p.worker.w for p in suite.pairs if p.task_index == t])
    if distribution == META_TRAIN:
        return sample_meta_train_workers(task, np.random.default_rng([seed, t]), draws)
    if distribution == TEST_REGION:
        return meta_test_candidates(task)
    raise ValueError(f"unknown distribution {distribution!r}; expected one of {DISTRIBUTIONS}")


def prior_gaps(suite: Suite, draws: int = DRAWS, seed: int = SEED) -> list[PriorGap]:
    """The suite's non-adaptive gap under each distribution of DISTRIBUTIONS (tasks weighted by their pairs)."""
    min_best = float(suite.content["generator"]["min_best_return"])  # curation kept only such workers too
    tasks = range(len(suite.tasks))
    weights = np.array([sum(p.task_index == t for p in suite.pairs) for t in tasks], dtype=float)
    weights /= weights.sum()
    values = {d: [usable_values(suite.tasks[t], task_workers(suite, t, d, draws, seed), min_best) for t in tasks]
              for d in DISTRIBUTIONS}
    curated_ratios = [best_fixed_policy(v)[1] for v in values[CURATED]]
    out = []
    for distribution, per_task in values.items():
        gaps = [non_adaptive_gap(v) for v in per_task]
        on_curated = [float(ratios[:, best_fixed_policy(v)[0]].mean()) for ratios, v in zip(curated_ratios, per_task)]
        out.append(PriorGap(distribution, float(weights @ gaps), float(weights @ on_curated),
                            sum(len(v) for v in per_task)))
    return out
