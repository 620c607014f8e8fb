"""Offline meta-RL training datasets: meta-train workers only, exact labels, byte-reproducible builds.

A dataset is named `<suite>-train-<tier>` (see `TRAINING_DATASETS`) and built by
`build_training_dataset` (CLI: `mewa-bench datasets build NAME`): meta-episodes of one (task,
meta-train worker) each, played by the tier's behaviour (`tiers`) with luck keys disjoint from the
protocol's (`training_keys`), every frame labelled with the exact known-worker optimal action
(`labels`), written in bulk as a LeRobot v3.0 dataset (`bulk_writer`) with `meta/mewa.json`
(its own metadata; `minari_export` writes Minari's). A wide suite's datasets may play tasks its
generator draws from the dataset's seed instead of the suite's ten (`generated_tasks`: to learn to adapt to
a task never seen), or every structure of its generator (`task_structures`), listed in meta/mewa.json.
Workers and keys are checked when the dataset is built and again when it is loaded
(`load_training_dataset`) or downloaded: one curated worker of any suite or one protocol luck key and the
dataset is refused.

This file is longer than 500 lines because the build and the reading share the format: the frame
columns and the metadata written here are the ones checked again on loading, beside them.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from mewa_bench.datasets.expert_rollout import MapTasks, shared_pool
from mewa_bench.datasets.generated_tasks import generated_tasks, task_structures, with_tasks
from mewa_bench.datasets.labels import optimal_labels
from mewa_bench.datasets.tiers import (ADAPTIVE, PROTOCOL_EPISODES, TIERS, TierRun, behaviour_source,
                                       episodes_per_worker, expected_of_episodes, file_sha256, play_tier,
                                       reference_policies, tier_policies)
from mewa_bench.datasets.training_keys import TrainingDataError, check_training_keys, training_luck_keys
from mewa_bench.datasets.training_workers import check_training_workers, sample_training_pairs
from mewa_bench.design.curate import MIN_BEST_RETURN
from mewa_bench.design.exact import expected_returns
from mewa_bench.design.references import round_floats
from mewa_bench.design.suites import ALL_SUITES, Suite, load_suite
from mewa_bench.game.distributions import meta_train_spec, worker_families
from mewa_bench.game.normalise import normalised_return
from mewa_bench.game.palette import NUM_COLORS
from mewa_bench.game.table import transition_table
from mewa_bench.game.task import Task

TRAINING_FORMAT = "mewa-bench-training-data"
TRAINING_FORMAT_VERSION = 1
MEWA_META_FILE = Path("meta") / "mewa.json"
FPS = 10
DEFAULT_FRAMES = 1_000_000
DEFAULT_VERSION = "1.1.0"  # 1.1.0: the `next.truncated` column (1.0.0 had the same frames without it)


@dataclass(frozen=True)
class TrainingSpec:
    """Everything a training dataset's bytes depend on (with the package and library versions)."""

    name: str
    suite: str
    tier: str
    frames: int = DEFAULT_FRAMES  # at least this many frames: whole rounds of `meta_batch` meta-episodes
    version: str = DEFAULT_VERSION
    seed: int = 0
    meta_batch: int = 64  # meta-episodes (workers) per round
    history_episodes: int = 50  # episodes per worker in the history tiers
    expert_agent: str = "bayes-explorer"  # the stronger adaptive reference (most of the v2 suites' gaps)
    generated_tasks: int = 0  # 0: the suite's tasks; n: n tasks its generator draws from this dataset's seed
    task_structures: bool = False  # the suite's tasks or the generated ones; true: every structure of its generator

    def __post_init__(self) -> None:
        if self.generated_tasks and self.task_structures:
            raise TrainingDataError(f"{self.name}: a training dataset plays generated tasks (generated_tasks="
                                    f"{self.generated_tasks}) or the generator's task structures, not both")

    @property
    def built_name(self) -> str:
        """The name of what is built: the registry name, with `-frames<N>` for another frame target than its own."""
        default = TRAINING_DATASETS.get(self.name)
        return self.name if default is None or default.frames == self.frames else f"{self.name}-frames{self.frames}"

    @property
    def dataset_id(self) -> str:
        """Minari-style id with the major version: `mewa/narrow-v2-train-random-v1`."""
        return f"mewa/{self.built_name}-v{self.version.split('.')[0]}"

    @property
    def seed_id(self) -> str:
        """What the seeds derive from: the registry dataset's id, so that a build with a smaller frame target
        holds the first rounds of the full one."""
        return f"mewa/{self.name}-v{self.version.split('.')[0]}"

    @property
    def episodes_per_worker(self) -> int:
        """Episodes in each meta-episode."""
        return episodes_per_worker(self.tier, self.history_episodes)

    def build_command(self) -> str:
        """The command that builds this dataset."""
        default = TRAINING_DATASETS.get(self.name)
        extra = "" if default is None or default.frames == self.frames else f" --frames {self.frames}"
        return f"mewa-bench datasets build {self.name}{extra}"


def _registry() -> dict[str, TrainingSpec]:
    """The named training datasets: every tier (`TIERS`) per shipped suite, 1 M frames each, plus a small one shipped."""
    out = {f"{s}-train-{t}": TrainingSpec(f"{s}-train-{t}", s, t) for s in ALL_SUITES for t in TIERS}
    for s in ALL_SUITES:  # a pair's 10 episodes from scratch per history (what AD's windows read), many histories
        name = f"{s}-train-task-inferring-histories"
        out[name] = TrainingSpec(name, s, "task-inferring-histories", frames=3_000_000, history_episodes=10)
    for s in ("wide-v1", "wide-v2"):  # the same learner on tasks the suite never lists: to adapt to a new task
        name = f"{s}-train-generated-tasks"
        out[name] = TrainingSpec(name, s, "task-inferring-histories", frames=3_000_000, history_episodes=10,
                                 meta_batch=8192, generated_tasks=200)  # one round: each task's learner model once
        name = f"{s}-train-task-structures"  # every task of the generator up to renaming its colours
        out[name] = TrainingSpec(name, s, "task-inferring-histories", frames=3_000_000, history_episodes=10,
                                 meta_batch=8192, task_structures=True)
    mini = TrainingSpec("narrow-v2-train-random-task-specific-mini", "narrow-v2", "random-task-specific",
                        frames=10_000, meta_batch=16)
    out[mini.name] = mini
    return out


TRAINING_DATASETS: dict[str, TrainingSpec] = _registry()


def training_spec(name: str, frames: int | None = None) -> TrainingSpec:
    """The spec of a named training dataset (optionally another frame target), or a clear error."""
    if name not in TRAINING_DATASETS:
        raise TrainingDataError(f"unknown training dataset {name!r}; known: {', '.join(sorted(TRAINING_DATASETS))}")
    spec = TRAINING_DATASETS[name]
    return spec if frames is None else replace(spec, frames=int(frames))


def training_suite(spec: TrainingSpec) -> Suite:
    """The suite a dataset is built for, with the tasks it plays: the suite's own, `spec.generated_tasks` tasks its
    generator draws from the dataset's seed (`generated_tasks`), or every structure of its generator
    (`task_structures`)."""
    suite = load_suite(spec.suite)
    if spec.task_structures:
        return with_tasks(suite, task_structures(suite))
    if not spec.generated_tasks:
        return suite
    rng = np.random.default_rng(_seed_int(f"{spec.seed_id}/{spec.seed}/tasks"))
    return with_tasks(suite, generated_tasks(suite, spec.generated_tasks, rng))


def _seed_int(text: str) -> int:
    """A 63-bit seed from text."""
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little") >> 1


@dataclass
class _Round:
    """One round's meta-episodes: what was played and the exact values that go with it."""

    task_idx: np.ndarray  # [M]
    workers: np.ndarray  # [M, 4]
    keys: np.ndarray  # uint64 [M, H]
    run: TierRun  # episodes in (meta-episode, episode) order
    labels: np.ndarray  # [F]
    expected: np.ndarray | None  # [E] exact expected normalised return of each episode's behaviour
    random_value: np.ndarray  # [M] exact expected normalised return of the random policy
    max_expected: np.ndarray  # [M] best t-optimal policy's
    optimum: np.ndarray  # [M] known-worker optimum


@dataclass
class _Group:
    """The meta-episodes of one task in a round, as played (before their exact values)."""

    rows: np.ndarray  # positions in the round
    run: TierRun


def _play_round(spec: TrainingSpec, suite: Suite, first: int, rng: np.random.Generator, jobs: int,
                map_tasks: MapTasks | None, played_frames: Callable[[int], None]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[_Group]]:
    """Sample `meta_batch` meta-train workers (checked) and play the tier on them, task by task (`played_frames`
    told each task's frames as they are played)."""
    m, h = spec.meta_batch, spec.episodes_per_worker
    task_idx, workers = sample_training_pairs(suite.tasks, rng, m)
    meta = np.repeat(np.arange(first, first + m), h)
    keys = training_luck_keys(spec.seed_id, meta, np.tile(np.arange(h), m)).reshape(m, h)
    check_training_keys(keys.reshape(-1), f"{spec.name}: meta-episodes {first}..{first + m - 1}")
    groups = []
    for i in range(len(suite.tasks)):
        rows = np.flatnonzero(task_idx == i)
        if len(rows):
            check_training_workers(suite.tasks[i], workers[rows], f"{spec.name}: task {i}")
            seeds = np.array([_seed_int(f"{spec.seed_id}/agent/{first + r}") for r in rows], dtype=np.int64)
            groups.append(_Group(rows, play_tier(spec.tier, suite.name, suite.tasks, i, workers[rows], keys[rows], rng,
                                                 seeds, spec.expert_agent, jobs, map_tasks, spec.task_structures)))
            played_frames(len(groups[-1].run.played.t))
    return task_idx, workers, keys, groups


def exact_values(task: Any, workers: np.ndarray, owner: np.ndarray, t: np.ndarray,
                 state: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The exact numbers of a group of meta-episodes: each frame's optimal action, each worker's known-worker
    optimum (normalised) and the reference policies' expected normalised returns [P + 2, M]."""
    labels, raw = optimal_labels(task, workers, owner, t, state)
    values = expected_returns(task, reference_policies(task.N), workers[:, : task.N])
    return labels, normalised_return(task, raw), values


def _merge_groups(spec: TrainingSpec, task_idx: np.ndarray, workers: np.ndarray, keys: np.ndarray,
                  groups: list[_Group], exact: list[tuple]) -> _Round:
    """The task groups' episodes back in meta-episode order, with their exact values."""
    from mewa_bench.datasets.chain_rollout import concat_played
    from mewa_bench.datasets.learning_histories import reorder_episodes

    h, m = spec.episodes_per_worker, len(task_idx)
    random_value, max_expected, optimum = np.zeros(m), np.zeros(m), np.zeros(m)
    expected_parts = []
    for g, (labels, opt, values) in zip(groups, exact):
        random_value[g.rows], max_expected[g.rows], optimum[g.rows] = values[-1], values[:-2].max(axis=0), opt
        expected_parts.append(expected_of_episodes(spec.tier, g.run.policy, np.repeat(np.arange(len(g.rows)), h),
                                                   values))
    rows = np.concatenate([g.rows for g in groups])
    played = concat_played([g.run.played for g in groups])
    labels = np.concatenate([e[0] for e in exact])
    policy = np.concatenate([g.run.policy for g in groups])
    expected = None if expected_parts[0] is None else np.concatenate(expected_parts)
    old_of_new = np.argsort(rows, kind="stable")  # group position of each meta-episode, in meta order
    order = (old_of_new[:, None] * h + np.arange(h)).reshape(-1)  # episodes in (meta, episode) order
    frame_order = np.argsort(np.argsort(order)[played.episode], kind="stable")
    return _Round(task_idx, workers, keys, TierRun(reorder_episodes(played, order), policy[order]),
                  labels[frame_order], None if expected is None else expected[order], random_value, max_expected,
                  optimum)


def _frame_columns(spec: TrainingSpec, suite: Suite, rounds: list[_Round]) -> tuple[dict[str, np.ndarray], dict]:
    """The per-frame columns (LeRobot user features) and the per-episode values of all rounds."""
    h = spec.episodes_per_worker
    cols: dict[str, list[np.ndarray]] = {}
    per_episode: dict[str, list[np.ndarray]] = {"lengths": [], "returns": [], "tasks": [], "policy": [],
                                                "expected": [], "keys": []}
    first = 0
    for rnd in rounds:
        p = rnd.run.played
        meta_local = p.episode // h
        meta_task = rnd.task_idx[meta_local]
        obs, next_obs = np.zeros((len(p.t), 18), np.float32), np.zeros((len(p.t), 18), np.float32)
        for i, task in enumerate(suite.tasks):
            rows = np.flatnonzero(meta_task == i)
            if len(rows):
                table = transition_table(task)
                obs[rows], next_obs[rows] = table.obs[p.state[rows]], table.obs[p.next_state[rows]]
        episode_in_meta = p.episode % h
        add = {"observation.state": obs, "action": p.action, "next.reward": p.reward.astype(np.float32),
               "next.done": p.done, "next.terminated": p.terminated, "next.truncated": p.done & ~p.terminated,
               "next.observation.state": next_obs,
               "optimal_action": rnd.labels, "meta_episode_index": first + meta_local,
               "episode_in_meta_episode": episode_in_meta, "block_index": episode_in_meta // PROTOCOL_EPISODES,
               "episode_in_block": episode_in_meta % PROTOCOL_EPISODES, "suite_task_index": meta_task,
               "worker": rnd.workers[meta_local], "luck_key": rnd.keys.reshape(-1)[p.episode].astype(np.int64),
               "behaviour_policy": rnd.run.policy[p.episode]}
        if rnd.expected is not None:
            expected = rnd.expected[p.episode]
            add["expected_return"] = expected
            add["expected_score"] = expected / np.maximum(rnd.max_expected[meta_local], MIN_BEST_RETURN)
        for k, v in add.items():
            cols.setdefault(k, []).append(v)
        per_episode["lengths"].append(p.lengths)
        per_episode["returns"].append(p.returns)
        per_episode["tasks"].append(np.repeat(rnd.task_idx, h))
        per_episode["policy"].append(rnd.run.policy)
        per_episode["keys"].append(rnd.keys.reshape(-1))
        if rnd.expected is not None:
            per_episode["expected"].append(rnd.expected)
        first += len(rnd.task_idx)
    return ({k: np.concatenate(v) for k, v in cols.items()},
            {k: np.concatenate(v) if v else None for k, v in per_episode.items()})


def frame_features(expected: bool) -> dict[str, dict]:
    """The LeRobot user features of a training dataset."""
    from mewa_bench.datasets.lerobot_recorder import state_names

    scalar = lambda dtype: {"dtype": dtype, "shape": (1,), "names": None}  # noqa: E731
    features = {
        "observation.state": {"dtype": "float32", "shape": (18,), "names": state_names()},
        "action": {"dtype": "int64", "shape": (1,), "names": ["colour"]},
        "next.reward": scalar("float32"), "next.done": scalar("bool"), "next.terminated": scalar("bool"),
        "next.truncated": scalar("bool"),
        "next.observation.state": {"dtype": "float32", "shape": (18,), "names": state_names()},
        "optimal_action": {"dtype": "int64", "shape": (1,), "names": ["colour"]},
        **{k: scalar("int64") for k in ("meta_episode_index", "episode_in_meta_episode", "block_index",
                                        "episode_in_block", "suite_task_index")},
        "worker": {"dtype": "float64", "shape": (NUM_COLORS,), "names": [f"w{x}" for x in range(NUM_COLORS)]},
        "luck_key": scalar("int64"), "behaviour_policy": scalar("int64"),
    }
    if expected:
        features["expected_return"] = scalar("float64")
        features["expected_score"] = scalar("float64")
    return features


COLUMN_DOCS = {
    "optimal_action": "exact known-worker optimal action for the frame's state with T - frame_index steps left "
                      "(design.optimum's finite-horizon optimum; ties: lowest action)",
    "meta_episode_index": "the (task, worker) group: one meta-train worker, its episodes in play order",
    "episode_in_meta_episode": "episode within the meta-episode (0..9, or 0..H-1 for learning histories)",
    "block_index": "which 10-episode block of the meta-episode (the protocol's unit; always 0 but for "
                   "learning histories)",
    "episode_in_block": "episode within its 10-episode block (0 starts a block)",
    "suite_task_index": "index of the task in the suite's `tasks`",
    "worker": "the meta-train worker's mistake probabilities (float64, unused components 0)",
    "luck_key": "the episode's luck key (training key space, never a protocol key): MewaEnv "
                "reset(options={'task', 'worker', 'luck_key'}) with the stored actions replays the episode",
    "behaviour_policy": "index into meta/mewa.json behaviour.policies[suite_task_index] of the fixed policy the "
                        f"episode played ({ADAPTIVE}: an adaptive agent, no fixed policy)",
    "expected_return": "exact expected normalised return of the episode's behaviour for this worker",
    "expected_score": "expected_return / the worker's max-expected baseline (the protocol's score scale; the "
                      f"baseline floored at {MIN_BEST_RETURN}, the curation's least usable value)",
}


GENERATED_TASK_INDEX = ("index of the task in meta/mewa.json `tasks`: tasks the suite's generator drew from the "
                        "dataset's seed, not the suite's own")
STRUCTURE_TASK_INDEX = ("index of the task in meta/mewa.json `tasks`: every structure of the suite's generator, "
                        "not the suite's own tasks")


def _spec_record(spec: TrainingSpec) -> dict[str, Any]:
    """The spec as meta/mewa.json records it (`generated_tasks` and `task_structures` only when set, as before they
    existed)."""
    record = asdict(spec)
    for name in ("generated_tasks", "task_structures"):
        if not record[name]:
            del record[name]
    return record


def _distribution(suite: Suite) -> list[dict[str, Any]]:
    """Each task's meta-train worker distribution, as its suite lists it."""
    out = []
    for task in suite.tasks:
        spec = meta_train_spec(task)
        out.append({"families": [f.to_dict() for f in worker_families(task)],
                    "sampler": "mewa_bench.game.distributions.sample_meta_train_workers",
                    "meta_train": spec if spec is not None else "v1: the paper family's box bands"})
    return out


def _metadata(spec: TrainingSpec, suite: Suite, rounds: list[_Round], per_episode: dict, frames: int,
              nearest: float) -> dict[str, Any]:
    """Content of meta/mewa.json (Minari-like names; `minari_export` maps it to Minari's own metadata)."""
    from importlib.metadata import PackageNotFoundError, version

    from mewa_bench import __version__
    from mewa_bench.envs.mewa_env import ENV_VERSION
    from mewa_bench.protocol.results import PROTOCOL_VERSION

    try:
        lerobot_version = version("lerobot")
    except PackageNotFoundError:  # pragma: no cover - the datasets extra is installed to build
        lerobot_version = None
    task_idx = np.concatenate([r.task_idx for r in rounds])
    workers = np.concatenate([r.workers for r in rounds])
    random_value = np.concatenate([r.random_value for r in rounds])
    max_expected = np.concatenate([r.max_expected for r in rounds])
    optimum = np.concatenate([r.optimum for r in rounds])
    source = behaviour_source(spec.tier, spec.expert_agent, spec.task_structures)
    h = spec.episodes_per_worker
    whose, index_doc = (("generator's task structures", STRUCTURE_TASK_INDEX) if spec.task_structures else
                        ("dataset's generated", GENERATED_TASK_INDEX) if spec.generated_tasks else ("suite's", None))
    lengths = per_episode["lengths"]
    expected = per_episode["expected"]
    n = len(task_idx)
    return {
        "format": TRAINING_FORMAT, "format_version": TRAINING_FORMAT_VERSION, "kind": "training",
        "dataset_id": spec.dataset_id, "name": spec.built_name, "version": spec.version,
        "spec": _spec_record(spec),
        "suite": {"name": suite.name, "sha256": suite.sha256},
        "eval_env_spec": {"env_id": "mewa/MEWA-v0", "env_version": ENV_VERSION, "suite": suite.name,
                          "suite_sha256": suite.sha256, "protocol_version": PROTOCOL_VERSION,
                          "episodes_per_pair": PROTOCOL_EPISODES,
                          "command": f"mewa-bench evaluate AGENT.py --suite {suite.name}"},
        "tier": spec.tier,
        "behaviour": {"tier": spec.tier, "source": source.relative_to(source.parents[2]).as_posix(),
                      "sha256": file_sha256(source),
                      "policies": [list(tier_policies(spec.tier, task.N)) for task in suite.tasks],
                      "expert_agent": spec.expert_agent if spec.tier == "expert" else None},
        "worker_distribution": {"name": "meta-train", "tasks": _distribution(suite),
                                "task_choice": f"uniform over the {whose} tasks, per meta-episode"},
        "seeds": {"build_seed": spec.seed,
                  "worker_rng": f"numpy default_rng(sha256('{spec.seed_id}/{spec.seed}') >> 1)",
                  "luck_keys": "sha256('mewa-bench/training-data/"
                               + ("<dataset_id>" if spec.seed_id == spec.dataset_id else spec.seed_id)
                               + "/<meta-episode>/<episode>') >> 1",
                  **({"generated_tasks": f"design.generate.sample_wide_task with numpy default_rng(sha256("
                                         f"'{spec.seed_id}/{spec.seed}/tasks') >> 1), then Eq. 1 (designed)"}
                     if spec.generated_tasks else {}),
                  **({"task_structures": "datasets.generated_tasks.task_structures (no draw: every structure once)"}
                     if spec.task_structures else {})},
        "checks": {"curated_workers": f"none of the {len(ALL_SUITES)} shipped suites' curated workers; "
                                      "every worker in its task's meta-train support",
                   "nearest_curated_worker_linf": round_floats(nearest),
                   "protocol_luck_keys": "none of the ranked protocol's keys (every shipped suite, its default seeds)"},
        "ref_scale": "normalised return (0 = worst, 1 = perfect episode), mean over the dataset's workers",
        "ref_min_score": round_floats(float(random_value.mean())),
        "ref_max_score": round_floats(float(max_expected.mean())),
        "ref_known_worker_optimum": round_floats(float(optimum.mean())),
        "total_meta_episodes": n, "episodes_per_meta_episode": h, "total_episodes": int(len(lengths)),
        "total_steps": frames,
        "mewa_bench_version": __version__, "lerobot_version": lerobot_version,
        "build_command": spec.build_command(),
        "columns": {k: index_doc if k == "suite_task_index" and index_doc else v
                    for k, v in COLUMN_DOCS.items() if expected is not None or not k.startswith("expected")},
        "tasks": [t.to_dict() for t in suite.tasks],
        "meta_episodes": [{"task": int(task_idx[m]), "worker": workers[m, : suite.tasks[int(task_idx[m])].N].tolist(),
                           "random": round_floats(float(random_value[m])),
                           "max_expected": round_floats(float(max_expected[m])),
                           "known_worker_optimum": round_floats(float(optimum[m])),
                           "luck_keys": [int(k) for k in per_episode["keys"][m * h:(m + 1) * h]],
                           "lengths": [int(v) for v in lengths[m * h:(m + 1) * h]],
                           "returns": round_floats(per_episode["returns"][m * h:(m + 1) * h]),
                           **({} if expected is None else
                              {"expected_returns": round_floats(expected[m * h:(m + 1) * h])})}
                          for m in range(n)],
    }


BuildProgress = Callable[[str, int, int], None]  # (phase: play, exact or write; done; total) as a build goes


def build_training_dataset(spec: TrainingSpec, root: Path | str, jobs: int = 2,
                           timings: dict[str, float] | None = None, map_tasks: MapTasks | None = None,
                           progress: BuildProgress = lambda phase, done, total: None) -> dict[str, Any]:
    """Build a training dataset into `root` (must not exist; written beside it, then renamed); returns its
    meta/mewa.json content. `timings`, if given, receives the seconds of each phase (play, exact, write);
    `progress` is told each phase's advance: frames played (of the target: whole rounds may pass it), exact jobs
    done, the dataset written. The expert's play and the exact values run in `jobs` local processes, or as
    `map_tasks` (e.g. Ray tasks: `ray_tasks`) when given, in `jobs` x 4 chunks per round; the bytes are the same
    either way."""
    import time

    from mewa_bench.datasets.bulk_writer import write_lerobot_dataset
    from mewa_bench.datasets.lerobot_recorder import task_description
    from mewa_bench.files import write_json_atomic

    root = Path(root)
    if root.exists():
        raise TrainingDataError(f"{root} already exists; pick a new folder")
    if spec.tier not in TIERS:
        raise TrainingDataError(f"{spec.name}: unknown tier {spec.tier!r}; expected one of {', '.join(TIERS)}")
    suite = training_suite(spec)
    rng = np.random.default_rng(_seed_int(f"{spec.seed_id}/{spec.seed}"))
    clock = [time.perf_counter()]
    played = []
    frames, nearest = 0, np.inf

    def played_frames(count: int) -> None:
        nonlocal frames
        frames += count
        progress("play", frames, max(spec.frames, frames))

    progress("play", 0, spec.frames)
    while frames < spec.frames:
        played.append(_play_round(spec, suite, len(played) * spec.meta_batch, rng, jobs, map_tasks, played_frames))
    clock.append(time.perf_counter())
    exact = _exact_by_group(spec, suite, played, jobs, map_tasks, lambda done, total: progress("exact", done, total))
    clock.append(time.perf_counter())
    progress("write", 0, 1)
    rounds, k = [], 0
    for task_idx, workers, keys, groups in played:
        rounds.append(_merge_groups(spec, task_idx, workers, keys, groups, exact[k : k + len(groups)]))
        k += len(groups)
    for i, task in enumerate(suite.tasks):
        rows = np.concatenate([r.workers[r.task_idx == i] for r in rounds])
        if len(rows):
            nearest = min(nearest, check_training_workers(task, rows, spec.name))
    columns, per_episode = _frame_columns(spec, suite, rounds)
    meta = _metadata(spec, suite, rounds, per_episode, frames, nearest)
    episode_tasks = [task_description(suite.name, 0, suite.tasks[int(t)].to_dict()) for t in per_episode["tasks"]]
    root.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(dir=root.parent, prefix=f".{root.name}.", suffix=".building"))
    try:
        write_lerobot_dataset(work / "ds", frame_features("expected_return" in columns), columns,
                              per_episode["lengths"], episode_tasks, FPS, "mewa/MEWA-v0",
                              spec.episodes_per_worker * spec.meta_batch)  # a row group per round of meta-episodes
        write_json_atomic(work / "ds" / MEWA_META_FILE, meta)
        (work / "ds").rename(root)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    clock.append(time.perf_counter())
    progress("write", 1, 1)
    if timings is not None:
        timings.update(zip(("play", "exact", "write"), np.diff(clock).tolist()))
    return meta


EXACT_BATCH = 256  # workers per exact job: the groups of one task are pooled across rounds up to this many


def _exact_by_group(spec: TrainingSpec, suite: Suite, played: list[tuple], jobs: int,
                    map_tasks: MapTasks | None = None,
                    progress: Callable[[int, int], None] = lambda done, total: None) -> list[tuple]:
    """`exact_values` of every (round, task) group, in order. Groups of one task are pooled into jobs of about
    EXACT_BATCH workers (a wide suite's round holds a few workers per task; each worker's numbers are
    computed column by column, so pooling changes no value); `progress` told the jobs done after every
    `jobs` x 8 of them (local processes) or all of them (`map_tasks`)."""
    h = spec.episodes_per_worker
    groups = [(int(task_idx[g.rows[0]]), workers[g.rows], g.run.played) for task_idx, workers, _, gs in played
              for g in gs]
    jobs_args, members = [], []
    for i, task in enumerate(suite.tasks):
        mine = [k for k, g in enumerate(groups) if g[0] == i]
        while mine:
            batch, count = [], 0
            while mine and (count == 0 or count + len(groups[mine[0]][1]) <= EXACT_BATCH):
                batch.append(mine.pop(0))
                count += len(groups[batch[-1]][1])
            offsets = np.cumsum([0] + [len(groups[k][1]) for k in batch[:-1]])
            jobs_args.append((task, np.concatenate([groups[k][1] for k in batch]),
                              np.concatenate([groups[k][2].episode // h + o for k, o in zip(batch, offsets)]),
                              np.concatenate([groups[k][2].t for k in batch]),
                              np.concatenate([groups[k][2].state for k in batch])))
            members.append(batch)
    out: list[tuple] = [()] * len(groups)
    results, step = [], max(1, jobs) * 8 if map_tasks is None else max(1, len(jobs_args))  # all at once on Ray
    run_jobs = map_tasks or process_map(jobs)
    progress(0, len(jobs_args))
    for first in range(0, len(jobs_args), step):
        results += run_jobs(exact_values, jobs_args[first : first + step])
        progress(len(results), len(jobs_args))
    for batch, (labels, optimum, values) in zip(members, results):
        frame_edges = np.cumsum([0] + [len(groups[k][2].t) for k in batch])
        worker_edges = np.cumsum([0] + [len(groups[k][1]) for k in batch])
        for j, k in enumerate(batch):
            w = slice(worker_edges[j], worker_edges[j + 1])
            out[k] = (labels[frame_edges[j] : frame_edges[j + 1]], optimum[w], values[:, w])
    return out


def process_map(jobs: int) -> MapTasks:
    """A `MapTasks` over `jobs` local processes, the ones the play used (in this process when `jobs` is 1)."""
    def run(function: Callable[..., Any], args: list[tuple]) -> list:
        if jobs <= 1 or len(args) < 2:
            return [function(*a) for a in args]
        return list(shared_pool(jobs).map(function, *zip(*args)))
    return run


def ray_tasks(function: Callable[..., Any], args: list[tuple]) -> list:
    """A `MapTasks` of Ray tasks, one per argument tuple (inside `ray_backend.session`)."""
    from mewa_bench.protocol.ray_backend import ray_map

    return ray_map(_call, [(function, a) for a in args])


def _call(packed: tuple[Callable[..., Any], tuple]) -> Any:
    """`function(*args)` of a packed (function, args): one Ray task."""
    function, args = packed
    return function(*args)


def read_training_meta(root: Path | str) -> dict[str, Any]:
    """A training dataset's meta/mewa.json, or a TrainingDataError saying why it is not one."""
    path = Path(root) / MEWA_META_FILE
    try:
        meta = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise TrainingDataError(f"{path}: cannot read the dataset's metadata: {e}") from None
    if meta.get("format") != TRAINING_FORMAT or meta.get("kind") != "training":
        raise TrainingDataError(f"{root}: not a mewa-bench training dataset (an evaluation recording of the test "
                                "pairs is for viewing only, never for training)")
    return meta


def dataset_suite(meta: dict[str, Any], root: Path | str) -> Suite:
    """The installed suite a dataset was built for (the same sha256, else an error), with the tasks its frames play
    (`suite_task_index` indexes them): the suite's own, or the generated tasks or structures its meta/mewa.json lists."""
    suite = load_suite(meta["suite"]["name"])
    if suite.sha256 != meta["suite"]["sha256"]:
        raise TrainingDataError(f"{root}: built for {suite.name} sha256 {meta['suite']['sha256']}, the installed "
                                f"suite is {suite.sha256}")
    if meta["spec"].get("generated_tasks") or meta["spec"].get("task_structures"):
        return with_tasks(suite, tuple(Task.from_dict(t) for t in meta["tasks"]))
    return suite


def check_training_dataset(root: Path | str) -> dict[str, Any]:
    """Re-check a training dataset on disk: every frame's worker and luck key, and the metadata's workers.

    Returns meta/mewa.json; raises TrainingDataError if any frame uses a curated worker, a worker outside the
    meta-train support or a protocol luck key."""
    import pyarrow.parquet as pq

    root = Path(root)
    meta = read_training_meta(root)
    suite = dataset_suite(meta, root)
    files = sorted((root / "data").rglob("*.parquet"))
    if not files:
        raise TrainingDataError(f"{root}: no frames under data/")
    for path in files:
        table = pq.read_table(path, columns=["worker", "luck_key", "suite_task_index"])
        workers = table.column("worker").combine_chunks().flatten().to_numpy().reshape(-1, NUM_COLORS)
        task_idx = table.column("suite_task_index").to_numpy()
        for i, task in enumerate(suite.tasks):
            rows = np.unique(workers[task_idx == i], axis=0)
            if len(rows):
                check_training_workers(task, rows, f"{path}")
        check_training_keys(np.unique(table.column("luck_key").to_numpy()), f"{path}")
    for m, record in enumerate(meta["meta_episodes"]):
        check_training_workers(suite.tasks[record["task"]], np.array([record["worker"]]),
                               f"{root / MEWA_META_FILE}: meta-episode {m}")
    return meta


def load_training_dataset(root: Path | str, repo_id: str | None = None) -> Any:
    """Check a training dataset (`check_training_dataset`) and open it with lerobot's `LeRobotDataset`."""
    from mewa_bench.extras import require

    meta = check_training_dataset(root)
    lerobot_dataset = require("lerobot.datasets.lerobot_dataset", "datasets", "loading a training dataset")
    return lerobot_dataset.LeRobotDataset(repo_id or meta["dataset_id"], root=Path(root), video_backend="pyav")
