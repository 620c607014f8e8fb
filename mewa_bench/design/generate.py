"""Generate the versioned suites (`narrow-v1`, `wide-v1`, `narrow-v2`, `wide-v2`) from the task-design method.

Pipeline per task: Eq. 1 average worker and rewards (shared by all tasks with the same N and M),
curated meta-test workers, then every reference value of every curated pair, all exact. The
output is a plain dict; `suites.suite_text` turns it into the exact bytes of the shipped file.
v1 is the paper's design. v2 adds the overloaded worker family (non-decreasing workers) beside the
paper's, a meta-train mixture that covers both families, and a phase 2 that maximises the
non-adaptive gap (docs/suites.md).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Callable

import numpy as np

from mewa_bench.design import exact, optimum
from mewa_bench.design.average_worker import DELTAS, EPSILONS, AverageWorkerDesign, design_average_worker
from mewa_bench.design.curate import (BEST_FIXED, DECIMALS, GAP, MIN_BEST_RETURN, P_THRESHOLD, curate,
                                      mean_absolute_deviation, ratios_to_best)
from mewa_bench.design.policies import RANDOM, RANDOM_TASK_SPECIFIC, policy_names
from mewa_bench.design.references import round_floats, summarise
from mewa_bench.design.suites import SUITE_FORMAT_VERSION, canonical_json
from mewa_bench.game.distributions import (family_names, meta_test_candidates, overloaded_family, paper_family,
                                           worker_families)
from mewa_bench.game.task import Task, default_sigma

GENERATOR_VERSION = 1
GRID_STEP = 0.05
CANONICAL = dict(colors=(0, 1, 2, 3), order=(3, 1, 2, 0), K=5, M=3, worker_blocks=(2, 2, 4, 0))
WORKER_BLOCK_TOTAL = 8  # wide tasks: a random composition of 8 into N - 1 positive parts, then 0
# A task is adaptive when no single t-optimal policy reaches this ratio to the per-worker best on
# every curated worker; sampled wide tasks that are not are rejected (and recorded) and resampled.
ADAPTIVE_RATIO = 0.99
# v2 choices (docs/suites.md): curated workers need a best t-optimal return >= 0.5 (so a pair's
# score, return / max expected, stays <= 2 per episode) and, in phase 2, an L-inf distance >= 0.2
# (4 grid steps) from every worker already chosen; meta-train: each family with probability 1/2,
# then its box sampler or its cover sampler with probability 1/2, 0.01 clear of the 0.05 grid.
V2_MIN_BEST_RETURN = 0.5
V2_MIN_DISTANCE = 0.2
GAP_TARGETS = {"narrow-v2": 0.06, "wide-v2": 0.04}  # non-adaptive gap each v2 suite must reach
V2_META_TRAIN = {"family_weights": [0.5, 0.5], "cover_weight": 0.5, "grid_step": GRID_STEP, "grid_clearance": 0.01}

Progress = Callable[[str], None]


@dataclass(frozen=True)
class SuiteSpec:
    """What a suite is generated from."""

    name: str
    kind: str  # "narrow" or "wide"
    version: int
    seed: int | None
    n_tasks: int
    cap: int
    families: bool = False  # v2: the paper's and the overloaded worker family
    min_best_return: float = MIN_BEST_RETURN
    phase2: str = BEST_FIXED
    min_distance: float = 0.0
    # hidden suites (service.hidden): curate from the grid without these workers, then from a random
    # fraction of what is left, drawn from `seed` and the task (the shipped suites keep every candidate)
    excluded_workers: tuple[tuple[float, ...], ...] = ()
    candidate_fraction: float = 1.0


SPECS = {
    "narrow": SuiteSpec("narrow-v1", "narrow", 1, None, 1, 16),
    "wide": SuiteSpec("wide-v1", "wide", 1, 20231105, 10, 8),
    "narrow-v2": SuiteSpec("narrow-v2", "narrow", 2, None, 1, 16, True, V2_MIN_BEST_RETURN, GAP, V2_MIN_DISTANCE),
    "wide-v2": SuiteSpec("wide-v2", "wide", 2, 20231105, 10, 8, True, V2_MIN_BEST_RETURN, GAP, V2_MIN_DISTANCE),
}


def reference_task(n: int, m: int, rewards: tuple[float, ...]) -> Task:
    """The task on which Eq. 1's (delta, epsilon) choice is scored for (N, M).

    N = 4, M = 3 is the canonical task; otherwise the canonical shape cut to N colours with K = 5 and
    worker blocks (2, 2, 4, 0) / (4, 4, 0). Colour labels do not change any value, only N, M, K,
    the worker blocks and the rewards do.
    """
    if n == 4:
        return Task(**{**CANONICAL, "M": m}, rewards=rewards)
    return Task(colors=tuple(range(n)), order=tuple(range(n)), K=5, M=m, rewards=rewards,
                worker_blocks=(4, 4, 0) if n == 3 else (8, 0))


def mad_at(task: Task, w: np.ndarray) -> float:
    """MAD of the t-optimal policies' exact normalised returns at one worker."""
    values = exact.expected_returns(task, policy_names(task.N, baselines=False), np.asarray(w)[None, :])
    return float(mean_absolute_deviation(values[:, 0]))


@lru_cache(maxsize=None)
def average_worker_design(n: int, m: int) -> AverageWorkerDesign:
    """Eq. 1 for (N, M), the (delta, epsilon) choice scored on `reference_task`."""
    return design_average_worker(n, m, mad_of=lambda w, r: mad_at(reference_task(n, m, tuple(r)), w))


def non_adaptive_ratio(pairs: list[dict]) -> float:
    """The best single policy's worst ratio to the per-worker best over a task's curated pairs."""
    ratio = ratios_to_best(np.array([p["toptimal"] for p in pairs]))
    return float(ratio.min(axis=0).max())


def sample_wide_task(rng: np.random.Generator, index: int) -> Task:
    """One wide task (SPEC section 4), drawing from `rng` in a fixed order."""
    n = int(rng.choice([3, 4]))
    colors = tuple(sorted(int(c) for c in rng.choice(4, size=n, replace=False)))
    order = tuple(int(c) for c in rng.permutation(colors))
    k = int(rng.choice([3, 4, 5]))
    m = int(rng.choice([3, 4, 5]))
    while m > k:
        m = int(rng.choice([3, 4, 5]))
    cuts = np.sort(rng.choice(np.arange(1, WORKER_BLOCK_TOTAL), size=n - 2, replace=False))
    parts = np.diff(np.concatenate([[0], cuts, [WORKER_BLOCK_TOTAL]]))
    blocks = tuple(int(b) for b in parts) + (0,)
    name = f"wide-{index:02d}-n{n}-k{k}-m{m}"
    placeholder = tuple(-1.0 + 0.1 * i for i in range(n))  # replaced by Eq. 1's rewards below
    return Task(colors=colors, order=order, K=k, M=m, rewards=placeholder, worker_blocks=blocks, name=name)


def designed(task: Task, families: bool = False) -> tuple[Task, AverageWorkerDesign]:
    """The task with Eq. 1's average worker, rewards and the default sigma (+ v2's worker distribution)."""
    d = average_worker_design(task.N, task.M)
    out = task.with_rewards(d.r).with_distribution(d.w, default_sigma(task.N))
    if families:
        out = Task.from_dict({**out.to_dict(), "worker_distribution": v2_worker_distribution(out)})
    return out, d


def v2_worker_distribution(task: Task) -> dict[str, Any]:
    """A v2 task's worker families (the paper's and its mirror, the overloaded one) and meta-train mixture."""
    return {"families": [paper_family(task).to_dict(), overloaded_family(task).to_dict()],
            "test_region": "grid workers outside the 2-sigma box of every family",
            "meta_train": dict(V2_META_TRAIN)}


def task_entry(task: Task, design: AverageWorkerDesign, mad_here: float, curation_info: dict) -> dict[str, Any]:
    """The suite's record of a task: parameters plus how they were designed."""
    entry = task.to_dict()
    entry["design"] = {
        "eq1_objective": design.objective, "delta": design.delta, "epsilon": design.epsilon,
        "mad_at_average_worker": round_floats(mad_here), "eq1_selection_mad": design.mad,
        "eq1_candidates": [{"delta": c.delta, "epsilon": c.epsilon, "w": round_floats(c.w), "r": round_floats(c.r),
                            "objective": c.objective, "mad": c.mad} for c in design.candidates],
    }
    entry["curation"] = curation_info
    return entry


def allowed_candidates(task: Task, candidates: np.ndarray, spec: SuiteSpec) -> np.ndarray:
    """The candidate workers `spec` lets curation choose from, still in lexicographic order.

    Without `spec.excluded_workers`; then, if `spec.candidate_fraction` < 1, that fraction of them drawn
    from a generator seeded by `spec.seed` and the task's parameters (not the order tasks are designed in).
    """
    if spec.excluded_workers:
        excluded = {tuple(np.round(w, 6)) for w in spec.excluded_workers if len(w) == candidates.shape[1]}
        candidates = candidates[[tuple(np.round(c, 6)) not in excluded for c in candidates]]
    if spec.candidate_fraction >= 1.0:
        return candidates
    if spec.seed is None or not 0.0 < spec.candidate_fraction:
        raise ValueError(f"{spec.name}: a candidate fraction of {spec.candidate_fraction} needs a seed and a fraction > 0")
    parameters = {k: v for k, v in task.to_dict().items() if k != "name"}
    key = int.from_bytes(hashlib.sha256(canonical_json(parameters).encode()).digest()[:8], "little")
    rng = np.random.default_rng([spec.seed, key])
    keep = max(1, round(spec.candidate_fraction * len(candidates)))
    return candidates[np.sort(rng.choice(len(candidates), size=keep, replace=False))]


def curate_task(task: Task, task_index: int, spec: SuiteSpec, progress: Progress) -> tuple[dict, list[dict]]:
    """Curated workers of one task and every reference value of its pairs."""
    names = policy_names(task.N, baselines=False)
    candidates = allowed_candidates(task, meta_test_candidates(task, GRID_STEP), spec)
    progress(f"{task.name}: exact returns of {len(names)} policies on {len(candidates):,} candidate workers")
    values = exact.expected_returns(task, names, candidates).T  # [C, P]
    cur = curate(values, spec.cap, spec.min_best_return, spec.phase2, candidates, spec.min_distance)
    chosen = candidates[list(cur.selected)]
    progress(f"{task.name}: {len(chosen)} curated workers; baselines and known-worker optimum")
    pairs, best_fixed, ratio = pair_records(task, task_index, chosen, values[list(cur.selected)], spec.families)
    for pair, phase in zip(pairs, cur.phase):
        pair["phase"] = phase
    info = {"candidates": int(len(candidates)), "usable_candidates": cur.kept_candidates,
            "phase2_policy": names[cur.phase2_policy], "best_fixed_policy": names[best_fixed],
            "best_fixed_mean_ratio": round_floats(ratio),
            "workers": len(chosen), "phase1_workers": cur.phase.count(1)}
    return info, pairs


def pair_records(task: Task, task_index: int, workers: np.ndarray, values: np.ndarray,
                 families: bool) -> tuple[list[dict], int, float]:
    """A suite's pair entries for `workers` of one task, given the t-optimal policies' exact returns `values`
    [W, P]: every reference value, exact. Also the best fixed policy's index and its mean ratio to the best."""
    names = policy_names(task.N, baselines=False)
    v = np.round(values, DECIMALS)
    baselines = np.round(exact.expected_returns(task, [RANDOM, RANDOM_TASK_SPECIFIC], workers), DECIMALS)
    best_known = np.round(optimum.known_worker_optimum(task, workers), DECIMALS)
    ratio = ratios_to_best(v)
    best_fixed = int(np.argmax(np.round(ratio.mean(axis=0), DECIMALS)))
    pairs = []
    for i, w in enumerate(workers):
        pairs.append({
            "task": task_index, "worker": round_floats(w),
            "toptimal": round_floats(v[i]), "best_policy": names[int(np.argmax(v[i]))],
            "baselines": {"random": round_floats(baselines[0, i]), "random_task_specific": round_floats(baselines[1, i]),
                          "max_expected": round_floats(v[i].max())},
            "best_fixed": round_floats(v[i, best_fixed]), "known_worker_optimum": round_floats(best_known[i]),
        })
        if families:
            pairs[-1]["family"] = "+".join(family_names(task, w))
    return pairs, best_fixed, float(ratio[:, best_fixed].mean())


@dataclass(frozen=True)
class Candidate:
    """A sampled task, designed (Eq. 1) and curated: everything the suite needs if it is accepted."""

    raw: Task
    task: Task
    design: AverageWorkerDesign
    info: dict[str, Any]
    pairs: list[dict]  # their "task" index is set when the candidate is accepted
    worst: float  # the best single policy's worst ratio (a wide task is rejected at >= ADAPTIVE_RATIO)
    family_mads: dict[str, float]


def suite_spec(kind: str | SuiteSpec) -> SuiteSpec:
    """The spec of suite `kind` (a key of SPECS), or `kind` itself if it is a spec (e.g. a hidden suite's)."""
    if isinstance(kind, SuiteSpec):
        return kind
    if kind not in SPECS:
        raise ValueError(f"unknown suite kind {kind!r}: expected one of {', '.join(SPECS)}")
    return SPECS[kind]


def design_candidate(raw: Task, kind: str | SuiteSpec, progress: Progress = lambda msg: None) -> Candidate:
    """Design and curate one sampled task (independent of every other task: safe to run in parallel)."""
    spec = suite_spec(kind)
    progress(f"{raw.name}: Eq. 1 average worker and rewards for N={raw.N}, M={raw.M}")
    task, design = designed(raw, spec.families)
    info, pairs = curate_task(task, -1, spec, progress)
    mads = {f.name: round_floats(mad_at(task, np.array(f.centre))) for f in worker_families(task)} if spec.families else {}
    return Candidate(raw, task, design, info, pairs, non_adaptive_ratio(pairs), mads)


def renamed(task: Task, index: int) -> Task:
    """A wide task named after its place in the suite (the name is all that depends on it)."""
    name = f"wide-{index:02d}-n{task.N}-k{task.K}-m{task.M}"
    return task if task.name == name else Task.from_dict({**task.to_dict(), "name": name})


MapTasks = Callable[[Callable[..., Candidate], list[Task], str | SuiteSpec], list[Candidate]]


def in_order(design: Callable[..., Candidate], raws: list[Task], kind: str | SuiteSpec,
             progress: Progress) -> list[Candidate]:
    """The default way to design candidates: one after the other, in this process."""
    return [design(raw, kind, progress) for raw in raws]


def generate_suite(kind: str | SuiteSpec, progress: Progress = lambda msg: None,
                   map_tasks: MapTasks | None = None) -> dict[str, Any]:
    """Build the content of suite `kind` (a key of SPECS: narrow, wide, narrow-v2, wide-v2, or a SuiteSpec), without its hash.

    Candidate tasks are sampled in a fixed order and designed as many at a time as the suite still
    needs; `map_tasks(design_candidate, raws, kind)` may design them in parallel (e.g. as Ray tasks):
    the suite is the same bytes either way.
    """
    spec = suite_spec(kind)
    rng = np.random.default_rng(spec.seed)
    tasks: list[dict] = []
    pairs: list[dict] = []
    rejected: list[dict] = []
    samples = 0
    while len(tasks) < spec.n_tasks:
        if spec.kind == "narrow":
            raws = [Task(**CANONICAL, rewards=(-1.0, -0.5, -0.2, -0.1), name="canonical-n4-k5-m3")]
        else:  # as many as still needed; each named after the place it would take (fixed below)
            raws = [sample_wide_task(rng, len(tasks)) for _ in range(spec.n_tasks - len(tasks))]
        designed_ = (map_tasks(design_candidate, raws, kind) if map_tasks is not None
                     else in_order(design_candidate, raws, kind, progress))
        for c in designed_:
            samples += 1
            index = len(tasks)
            raw, task = (c.raw, c.task) if spec.kind == "narrow" else (renamed(c.raw, index), renamed(c.task, index))
            if spec.kind == "wide" and c.worst >= ADAPTIVE_RATIO:
                rejected.append({"sample": samples - 1, "task": {k: v for k, v in raw.to_dict().items() if k != "rewards"},
                                 "best_single_policy_worst_ratio": round_floats(c.worst)})
                continue
            info = {**c.info, "best_single_policy_worst_ratio": round_floats(c.worst)}
            tasks.append(task_entry(task, c.design, mad_at(task, np.array(task.average_worker)), info))
            if spec.families:
                tasks[-1]["design"]["family_mad_at_average_worker"] = c.family_mads
            pairs += [{**p, "task": index} for p in c.pairs]
            if len(tasks) == spec.n_tasks:
                break
    generator = {
        "command": f"mewa-bench generate {kind}" if isinstance(kind, str) else None,
        "generator_version": GENERATOR_VERSION, "seed": spec.seed,
        "n_tasks": spec.n_tasks, "cap": spec.cap, "grid_step": GRID_STEP, "deltas": list(DELTAS),
        "epsilons": list(EPSILONS), "p_threshold": P_THRESHOLD, "min_best_return": spec.min_best_return,
        "decimals": DECIMALS, "adaptive_ratio": ADAPTIVE_RATIO, "tasks_sampled": samples,
        "rejected_tasks": rejected,
    }
    if spec.families:
        generator.update({"worker_families": ["paper", "overloaded"], "phase2": spec.phase2,
                          "min_distance": spec.min_distance, "meta_train": dict(V2_META_TRAIN)})
    return {
        "format_version": SUITE_FORMAT_VERSION, "name": spec.name, "suite": spec.kind, "version": spec.version,
        "env_id": "mewa/MEWA-v0", "env_version": "v0",
        "description": f"MEWA {spec.kind} suite: curated meta-test (task, worker) pairs with exact reference values"
                       + (" (paper and overloaded worker families)" if spec.families else ""),
        "generator": generator,
        "policies": {str(n): list(policy_names(n, baselines=False)) for n in sorted({len(t["colors"]) for t in tasks})},
        "tasks": tasks, "pairs": pairs, "summary": summarise(pairs),
    }
