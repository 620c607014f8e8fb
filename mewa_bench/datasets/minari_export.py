"""Export a training dataset (LeRobot format) as a Minari dataset (arrow storage), with Minari's own metadata.

What maps where:
- a Minari episode is one inner episode (LeRobot's `episode_index`, same order): `observations` the
  18 floats of every frame plus the last `next.observation.state` (L + 1 rows), `actions`, `rewards`
  (the env's float64 values), `terminations` (`next.terminated`), `truncations` (`next.truncated`; a
  dataset built before that column existed, version 1.0.0, gives `next.done` and not `next.terminated`,
  the same values);
- `infos` (L + 1 rows: the reset's, then each step's): the meta-episode fields `meta_episode_index`,
  `episode_in_meta_episode`, `block_index`, `episode_in_block`, `suite_task_index`, `worker`,
  `luck_key`, `behaviour_policy` (constant over the episode), `optimal_action` of each observation
  (-1 on the last, where no action is taken) and, where the dataset has them, `expected_return` and
  `expected_score`;
- each episode's `options` (Minari's episode metadata) are `{"task", "worker", "luck_key"}`: `reset(options=...)`
  of the recovered env replays the episode with the stored actions;
- metadata: `env_spec` = `mewa/MEWA-v0` over the suite's tasks (meta-train workers sampled per reset, the
  data's distribution), the spaces, `algorithm_name` (the tier's behaviour), `ref_min_score` /
  `ref_max_score` on the raw-return scale Minari's `get_normalized_score` expects (the dataset's random
  and max-expected references: means over its meta-episodes of R_min + v (R_max - R_min)), `author`,
  `description` (source dataset, suite, build command), `requirements` (this package's version).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from mewa_bench.datasets.training_data import check_training_dataset
from mewa_bench.datasets.training_keys import TrainingDataError
from mewa_bench.design.suites import load_suite
from mewa_bench.extras import require
from mewa_bench.game.normalise import return_bounds
from mewa_bench.game.task import Task

ENV_ID = "mewa/MEWA-v0"
FEATURE = "`mewa-bench datasets export --format minari`"
PER_EPISODE = ("meta_episode_index", "episode_in_meta_episode", "block_index", "episode_in_block",
               "suite_task_index", "luck_key", "behaviour_policy", "expected_return", "expected_score")


@dataclass(frozen=True)
class MinariExport:
    """Where an export went and what it holds."""

    dataset_id: str
    path: Path  # the dataset's folder: <out>/<dataset_id>
    episodes: int
    steps: int


def find_training_dataset(name_or_dir: str | Path, datasets_dir: Path | str = "mewa-datasets") -> Path:
    """A training dataset's folder: `name_or_dir` itself if it is a folder, else `datasets_dir/name_or_dir`."""
    for candidate in (Path(name_or_dir), Path(datasets_dir) / str(name_or_dir)):
        if candidate.is_dir():
            return candidate
    raise TrainingDataError(f"no dataset folder {name_or_dir!r} (nor {Path(datasets_dir) / str(name_or_dir)}): "
                            f"download it first, `mewa-bench datasets download {name_or_dir}`, or give its folder")


def exact_rewards(task: Task, stored: np.ndarray) -> np.ndarray:
    """The env's float64 rewards from the dataset's float32 ones (each is one of the task's rewards, or 0)."""
    values = np.array(sorted(set(task.rewards) | {0.0}))
    index = np.searchsorted(values.astype(np.float32), stored.astype(np.float32))
    index = np.clip(index, 0, len(values) - 1)
    if not np.array_equal(values[index].astype(np.float32), stored.astype(np.float32)):
        raise TrainingDataError("a reward that is none of the task's rewards: not a MEWA training dataset")
    return values[index]


def raw_reference_scores(meta: dict[str, Any], tasks: list[Task]) -> tuple[float, float]:
    """(ref_min_score, ref_max_score) as raw returns: each meta-episode's normalised reference mapped back
    through its task's bounds, averaged over the meta-episodes (each has the same number of episodes)."""
    low, high = [], []
    for record in meta["meta_episodes"]:
        r_min, r_max = return_bounds(tasks[record["task"]])
        low.append(r_min + record["random"] * (r_max - r_min))
        high.append(r_min + record["max_expected"] * (r_max - r_min))
    return float(np.mean(low)), float(np.mean(high))


def _frames(root: Path) -> dict[str, np.ndarray]:
    """Every frame's columns, in (episode, frame) order."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.concat_tables([pq.read_table(f) for f in sorted((root / "data").rglob("*.parquet"))])
    out: dict[str, np.ndarray] = {}
    for name in table.column_names:
        column = table.column(name).combine_chunks()
        if pa.types.is_fixed_size_list(column.type):
            out[name] = column.flatten().to_numpy(zero_copy_only=False).reshape(len(column), column.type.list_size)
        else:
            out[name] = column.to_numpy(zero_copy_only=False)
    order = np.lexsort((out["frame_index"], out["episode_index"]))
    return {k: v[order] for k, v in out.items()}


def _episode_buffers(frames: dict[str, np.ndarray], tasks: list[Task]) -> Iterator[Any]:
    """One Minari EpisodeBuffer per inner episode (see the module docstring)."""
    buffer_type = require("minari.data_collector", "interop", FEATURE).EpisodeBuffer
    episodes = frames["episode_index"]
    starts = np.flatnonzero(np.r_[True, episodes[1:] != episodes[:-1]])
    ends = np.r_[starts[1:], len(episodes)]
    for start, end in zip(starts.tolist(), ends.tolist()):
        rows = slice(start, end)
        task = tasks[int(frames["suite_task_index"][start])]
        worker = frames["worker"][start][: task.N].astype(float).tolist()
        n = end - start + 1
        # Scalars as lists: Minari's arrow storage reads 1-D numpy infos back wrongly (an empty shape).
        infos: dict[str, Any] = {k: np.full(n, frames[k][start]).tolist() for k in PER_EPISODE if k in frames}
        infos["worker"] = np.repeat(frames["worker"][start:start + 1], n, axis=0)
        infos["optimal_action"] = np.r_[frames["optimal_action"][rows].reshape(-1), -1].astype(np.int64).tolist()
        terminated = frames["next.terminated"][rows].astype(bool)
        truncated = (frames["next.truncated"][rows].astype(bool) if "next.truncated" in frames
                     else frames["next.done"][rows].astype(bool) & ~terminated)
        yield buffer_type(
            id=int(episodes[start]),
            options={"task": task.to_dict(), "worker": worker, "luck_key": int(frames["luck_key"][start])},
            observations=np.vstack([frames["observation.state"][rows], frames["next.observation.state"][end - 1]]),
            actions=frames["action"][rows].reshape(-1).astype(np.int64),
            rewards=exact_rewards(task, frames["next.reward"][rows].reshape(-1)),
            terminations=terminated, truncations=truncated,
            infos=infos)


@contextmanager
def _minari_root(path: Path) -> Iterator[None]:
    """Point Minari at `path` (MINARI_DATASETS_PATH) for the block."""
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(path)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = before


def export_minari(source: Path | str, out: Path | str, dataset_id: str | None = None) -> MinariExport:
    """Write the training dataset at `source` as a Minari dataset under `out` (use it with
    MINARI_DATASETS_PATH=out); built in a temporary folder beside it, then moved into place."""
    import gymnasium as gym

    minari = require("minari", "interop", FEATURE)
    source, out = Path(source), Path(out)
    meta = check_training_dataset(source)
    dataset_id = dataset_id or meta["dataset_id"]
    target = out / dataset_id
    if target.exists():
        raise TrainingDataError(f"{target} already exists: remove it or export to another --out")
    suite = load_suite(meta["suite"]["name"])
    tasks = list(suite.tasks)
    ref_min, ref_max = raw_reference_scores(meta, tasks)
    env_spec = replace(gym.spec(ENV_ID), kwargs={"tasks": [t.to_dict() for t in tasks]})
    behaviour = meta["behaviour"]
    algorithm = f"{meta['tier']} ({behaviour['expert_agent']})" if behaviour.get("expert_agent") else meta["tier"]
    description = (f"mewa-bench training dataset {meta['dataset_id']} (LeRobot format, exported to Minari): "
                   f"suite {suite.name} sha256 {suite.sha256}, {meta['episodes_per_meta_episode']} episodes per "
                   f"meta-episode on one meta-train (task, worker) pair; built by `{meta['build_command']}`. "
                   "Minari episodes are the inner episodes; meta-episode fields are in `infos`, each episode's "
                   "reset options replay it. Rank agents with `mewa-bench evaluate`.")
    out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".minari-", dir=out))
    try:
        with _minari_root(staging):
            dataset = minari.create_dataset_from_buffers(
                dataset_id, list(_episode_buffers(_frames(source), tasks)), env=env_spec, eval_env=env_spec,
                algorithm_name=algorithm,
                author="mewa-bench", ref_min_score=ref_min, ref_max_score=ref_max, description=description,
                requirements=[f"mewa-bench=={meta['mewa_bench_version']}"], data_format="arrow")
            episodes, steps = dataset.total_episodes, dataset.total_steps
        for folder in sorted(p for p in staging.rglob("*") if p.is_dir()):
            if (folder / "data").is_dir() and folder.relative_to(staging).as_posix() == dataset_id:
                target.parent.mkdir(parents=True, exist_ok=True)
                for extra in folder.parent.glob("*.json"):  # a namespace's metadata file, if Minari wrote one
                    if not (target.parent / extra.name).exists():
                        shutil.copy2(extra, target.parent / extra.name)
                folder.rename(target)
                break
        else:  # pragma: no cover - Minari's layout changed
            raise TrainingDataError(f"Minari wrote no dataset folder {dataset_id} under {staging}")
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return MinariExport(dataset_id, target, episodes, steps)
