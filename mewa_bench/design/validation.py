"""Validation suites: a suite's tasks with curated held-out meta-train workers, for choosing a learned
baseline's settings without looking at the test pairs.

`<suite>-validation` has the tasks of `<suite>` and, per task, workers curated by the suite's own
method (`curate.curate` with the suite's cap, minimum best return, phase 2 and distance) from a
pool of workers drawn from the task's meta-train distribution (`sample_meta_train_workers`) by a
fixed seed, instead of from the meta-test grid. So its pairs are ones where adaptation matters, as
in the suite, but they lie in the training distribution: a training run draws from the same
continuous distribution yet meets any given worker with probability 0, and tuning on them never
sees a curated test pair. Every reference value is exact (`generate.pair_records`).
On v1 suites the meta-train box leaves little to adapt to (the best fixed policy scores about 0.99
there); the v2 suites' validation pairs leave it 0.71 (narrow) and 0.81 (wide).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mewa_bench.design import exact
from mewa_bench.design.curate import curate
from mewa_bench.design.generate import GENERATOR_VERSION, SPECS, SuiteSpec, pair_records
from mewa_bench.design.policies import policy_names
from mewa_bench.design.references import round_floats, summarise
from mewa_bench.design.suites import ALL_SUITES, SUITE_FORMAT_VERSION, VALIDATION_SUITES, load_suite
from mewa_bench.game.distributions import sample_meta_train_workers
from mewa_bench.game.task import Task

VALIDATION_SEED = 20261125
POOL = {"narrow": 1024, "wide": 256}  # meta-train workers drawn per task, curated down to the suite's cap
WORKER_DECIMALS = 6  # workers are rounded before their values are computed: the file holds what was computed


def validation_suite_content(name: str, seed: int = VALIDATION_SEED) -> dict[str, Any]:
    """The content of `<name>-validation` (without its hash) for shipped suite `name`."""
    if name not in ALL_SUITES:
        raise ValueError(f"unknown suite {name!r}: validation suites exist for {', '.join(ALL_SUITES)}")
    suite = load_suite(name)
    kind, spec = next((k, s) for k, s in SPECS.items() if s.name == name)
    pairs: list[dict] = []
    tasks = [dict(t) for t in suite.content["tasks"]]
    for index, task in enumerate(suite.tasks):
        task_pairs, tasks[index]["curation"] = _curated_pairs(task, index, spec, np.random.default_rng([seed, index]))
        pairs += task_pairs
    content = {k: v for k, v in suite.content.items() if k not in ("sha256", "pairs", "summary", "generator")}
    content["tasks"] = tasks  # each with the curation of its validation workers, not its test ones
    return {
        **content, "format_version": SUITE_FORMAT_VERSION, "name": VALIDATION_SUITES[ALL_SUITES.index(name)],
        "description": f"validation pairs of {name}: its tasks with workers curated from held-out draws of each "
                       f"task's meta-train distribution, for tuning (never the test pairs)",
        "generator": {"command": f"mewa-bench generate {kind} --validation", "generator_version": GENERATOR_VERSION,
                      "validation_of": name, "suite_sha256": suite.sha256, "seed": seed, "pool": POOL[spec.kind],
                      "cap": spec.cap, "min_best_return": spec.min_best_return, "phase2": spec.phase2,
                      "min_distance": spec.min_distance, "worker_decimals": WORKER_DECIMALS},
        "pairs": pairs, "summary": summarise(pairs),
    }


def _curated_pairs(task: Task, index: int, spec: SuiteSpec, rng: np.random.Generator) -> tuple[list[dict], dict]:
    """The pairs of one task (a pool of meta-train workers, curated as the suite curates its grid) and the
    curation's figures."""
    drawn = np.round(sample_meta_train_workers(task, rng, POOL[spec.kind]), WORKER_DECIMALS) + 0.0
    pool = drawn[np.lexsort(drawn.T[::-1])]  # lexicographic order, as curation expects its candidates
    values = exact.expected_returns(task, policy_names(task.N, baselines=False), pool).T
    chosen = curate(values, spec.cap, spec.min_best_return, spec.phase2, pool, spec.min_distance)
    rows = list(chosen.selected)
    pairs, best_fixed, ratio = pair_records(task, index, pool[rows], values[rows], spec.families)
    for pair, phase in zip(pairs, chosen.phase):
        pair["phase"] = phase
    names = policy_names(task.N, baselines=False)
    info = {"candidates": len(pool), "usable_candidates": chosen.kept_candidates,
            "phase2_policy": names[chosen.phase2_policy], "best_fixed_policy": names[best_fixed],
            "best_fixed_mean_ratio": round_floats(ratio), "workers": len(rows),
            "phase1_workers": chosen.phase.count(1)}
    return pairs, info
