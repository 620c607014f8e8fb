"""Record evaluation rollouts as a LeRobot v3.0 dataset (SPEC section 8), one LeRobot episode per MEWA episode.

Per frame (one env step): `observation.state` float32[18] (the observation the action was chosen
on), `action` int64[1] (the Discrete(4) action kept as an integer: LeRobot stores shape-(1,) int64 as
a plain parquet column and hands it back as an int64 tensor), `next.reward` float32[1],
`next.done` bool[1] (terminated or truncated), `next.terminated` bool[1], `next.truncated` bool[1] (the
step limit ended the episode first; Gymnasium's `truncated`),
`next.observation.state` float32[18] (so the last transition of an episode is complete), and the
meta-RL grouping columns `pair_index`, `worker_index`, `seed`, `episode_in_pair`,
`task_index_in_suite`, `env_seed` (int64[1] each). In SAPIEN mode `observation.images.top` holds the
image of `observation.state` (uint8 H x W x 3; PNG inside the parquet by default, or AV1 video).
The LeRobot `task` string describes the pair's task, never its worker.

Run provenance (suite name and hash, policy, its sha256 and the agent arguments given, seeds, versions) and
per-pair ground truth (task parameters, worker, exact float64 returns) go to `meta/mewa.json`: LeRobot rewrites
`meta/info.json` itself and drops keys it does not know, so it cannot carry them.

On disk (LeRobot v3.0; frames of many episodes share a file, `meta/episodes` says where each starts):

    <root>/
    ├── data/chunk-000/file-000.parquet       frames: the columns above, plus LeRobot's index columns
    ├── videos/observation.images.top/chunk-000/file-000.mp4   only with --video in SAPIEN mode
    └── meta/
        ├── info.json                         LeRobot's schema: features, fps, counts, path templates
        ├── stats.json                        per-feature statistics (LeRobot computes them)
        ├── tasks.parquet                     the task strings
        ├── episodes/chunk-000/file-000.parquet   one row per episode: length, data/video offsets
        └── mewa.json                         ours: provenance and per-pair ground truth (above)

Read it back with `LeRobotDataset(repo_id, root=..., video_backend="pyav")` (without the backend,
lerobot probes torchcodec, which cannot load here and prints a long traceback before falling back).
lerobot (and torch) are imported when the run starts, through `mewa_bench.extras` (the datasets extra).
"""

from __future__ import annotations

import json
import os
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from mewa_bench.extras import require
from mewa_bench.game.palette import (COLOR_NAMES, OBS_AGENT_BLOCKS, OBS_COMPLETED, OBS_MISTAKE_FLAGS, OBS_SIZE,
                                      OBS_STRUCTURE_BLOCKS, OBS_WORKER_LEFT, OBS_WORKER_PLACED)
from mewa_bench.protocol.trajectory import EpisodeRecord, RunInfo, UnitRecord

MEWA_META_FILE = Path("meta") / "mewa.json"
META_FORMAT = "mewa-bench-lerobot"
META_FORMAT_VERSION = 1
IMAGE_KEY = "observation.images.top"
MIN_VIDEO_SIDE = 32  # SVT-AV1 (lerobot's default encoder) dies with SIGFPE on 16x16 frames

TASK_KEYS = ("name", "colors", "order", "K", "M", "rewards", "worker_blocks", "T", "average_worker", "sigma")

INDEX_COLUMNS = {
    "pair_index": "index of the (task, worker) pair in the suite",
    "worker_index": "index of the distinct worker (in suite pair order) the pair uses",
    "seed": "evaluation seed of the unit",
    "episode_in_pair": "0-based episode of the unit (the agent's memory carries across them)",
    "task_index_in_suite": "index of the pair's task in the suite",
    "env_seed": "seed the env was reset with for this episode",
}


def state_names() -> list[str]:
    """Names of the 18 observation entries (SPEC section 2)."""
    names = [""] * OBS_SIZE
    for where, prefix, suffix in ((OBS_AGENT_BLOCKS, "agent_blocks", ""), (OBS_STRUCTURE_BLOCKS, "structure", ".blocks"),
                                  (OBS_MISTAKE_FLAGS, "structure", ".mistake"), (OBS_COMPLETED, "completed", "")):
        for index, colour in zip(range(OBS_SIZE)[where], COLOR_NAMES):
            names[index] = f"{prefix}.{colour}{suffix}"
    names[OBS_WORKER_LEFT], names[OBS_WORKER_PLACED] = "worker_blocks_left", "worker_blocks_placed"
    assert all(names)
    return names


def make_features(image_shape: tuple[int, int, int] | None, video: bool = False) -> dict[str, dict]:
    """The LeRobot feature spec; shapes must be tuples (lerobot compares them with `!=` to array shapes)."""
    scalar = lambda dtype: {"dtype": dtype, "shape": (1,), "names": None}  # noqa: E731
    features: dict[str, dict] = {
        "observation.state": {"dtype": "float32", "shape": (OBS_SIZE,), "names": state_names()},
        "action": {"dtype": "int64", "shape": (1,), "names": ["colour"]},
        "next.reward": scalar("float32"),
        "next.done": scalar("bool"),
        "next.terminated": scalar("bool"),
        "next.truncated": scalar("bool"),
        "next.observation.state": {"dtype": "float32", "shape": (OBS_SIZE,), "names": state_names()},
        **{key: scalar("int64") for key in INDEX_COLUMNS},
    }
    if image_shape is not None:
        features[IMAGE_KEY] = {"dtype": "video" if video else "image", "shape": tuple(image_shape),
                               "names": ["height", "width", "channels"]}
    return features


def task_description(suite: str, pair: int, task: dict[str, Any]) -> str:
    """LeRobot task string of a pair: the task's sub-goal order and sizes, never the worker or the pair.

    Pairs of one task share the string (in narrow-v1 the pair would identify the worker); group
    trajectories by pair with the per-frame `pair_index` instead.
    """
    order = ">".join(COLOR_NAMES[c] for c in task["order"])
    return f"MEWA {suite}: order {order}, K={task['K']}, M={task['M']}"


def episode_images(episode: EpisodeRecord) -> list[np.ndarray | None]:
    """Image of each frame's `observation.state`: the reset image, then each step's result but the last."""
    return [episode.first_image] + [s.image for s in episode.steps[:-1]]


def unit_image_shape(unit: UnitRecord) -> tuple[int, int, int] | None:
    """Shape of the unit's images, or None when it has none (vector mode)."""
    for episode in unit.episodes:
        for image in episode_images(episode):
            if image is not None:
                return tuple(np.asarray(image).shape)  # type: ignore[return-value]
    return None


def _int(value: int) -> np.ndarray:
    return np.array([value], dtype=np.int64)


def _worker_indices(run: RunInfo) -> dict[tuple[float, ...], int] | None:
    """Worker -> index over the suite's distinct workers in pair order, when the run's suite can be loaded."""
    from mewa_bench.design.suites import load_suite

    try:
        suite = load_suite(run.suite)
    except Exception:  # a suite given by path elsewhere: fall back to the order of appearance
        return None
    if suite.sha256 != run.suite_sha256:
        return None
    out: dict[tuple[float, ...], int] = {}
    for pair in suite.pairs:
        out.setdefault(tuple(pair.worker.w), len(out))
    return out


def _datasets_extra(module: str) -> Any:
    """A module of the datasets extra (lerobot, Hugging Face datasets), or MissingExtra."""
    return require(module, "datasets", "recording a LeRobot dataset (`mewa-bench record`)")


class LeRobotSink:
    """A `TrajectorySink` writing a LeRobot v3.0 dataset at `root` (which must not exist yet)."""

    def __init__(self, root: Path | str, repo_id: str, fps: int = 10, image_size: tuple[int, int] | None = None,
                 video: bool = False) -> None:
        self.root, self.repo_id, self.fps = Path(root), repo_id, fps
        self.image_size = tuple(image_size) if image_size is not None else None
        self.video = video
        self.image_shape: tuple[int, int, int] | None = None
        self.dataset: Any = None
        self.run: RunInfo | None = None
        self.workers: dict[tuple[float, ...], int] = {}
        self.workers_from_suite = False
        self.pairs: dict[int, dict[str, Any]] = {}
        self.units: list[dict[str, Any]] = []
        self.frames = 0
        self.seconds = 0.0
        self.closed = False

    @property
    def frames_per_second(self) -> float:
        """Recording speed so far (frames written per second spent in `add_unit`)."""
        return self.frames / self.seconds if self.seconds else 0.0

    # -- TrajectorySink ------------------------------------------------------------------------------

    def start(self, run: RunInfo) -> None:
        """Remember the run; fail now (not after the first unit) if `root` exists or lerobot is missing."""
        if self.root.exists():
            raise FileExistsError(f"dataset directory {self.root} already exists: LeRobot writes a new dataset "
                                  "into a directory that does not exist yet")
        _datasets_extra("lerobot.datasets.lerobot_dataset")
        self.run = run
        suite_workers = _worker_indices(run)
        self.workers_from_suite = suite_workers is not None
        self.workers = suite_workers or {}

    def add_unit(self, unit: UnitRecord) -> None:
        """Write the unit's episodes, one LeRobot episode each."""
        if self.run is None:
            raise RuntimeError("LeRobotSink.add_unit called before start()")
        if self.closed:
            raise RuntimeError("LeRobotSink.add_unit called after close()")
        start = time.perf_counter()
        if self.dataset is None:
            self.dataset = self._create(unit_image_shape(unit))
        first, saved = self.dataset.meta.total_episodes, 0
        try:
            for episode in unit.episodes:
                self._write_episode(unit, episode)
                saved += 1
        finally:
            if saved:  # a failure mid-unit still leaves its saved episodes described
                self.units.append(self._unit_summary(unit, first, saved))
            self.seconds += time.perf_counter() - start

    def close(self) -> None:
        """Finalize the dataset (mandatory for valid parquet footers) and write `meta/mewa.json`; idempotent."""
        if self.closed:
            return
        self.closed = True
        if self.dataset is None:
            return  # no unit finished: nothing was created
        try:
            if self.dataset.has_pending_frames():
                self.dataset.clear_episode_buffer()
            self.dataset.finalize()
            _sort_json_keys(self.root / "meta" / "stats.json")
        finally:
            self._write_meta()
            _remove_empty_dirs(self.root / "images")  # lerobot's image staging folder stays behind empty

    # -- writing -------------------------------------------------------------------------------------

    def _create(self, image_shape: tuple[int, int, int] | None) -> Any:
        """Create the LeRobot dataset; the image feature exists only if the first unit has images."""
        lerobot_dataset = _datasets_extra("lerobot.datasets.lerobot_dataset")
        _datasets_extra("datasets").disable_progress_bars()  # one "Map" bar per episode otherwise
        if image_shape is not None:
            self._check_image_shape(image_shape)
        assert self.run is not None
        ds = lerobot_dataset.LeRobotDataset.create(
            self.repo_id, self.fps, features=make_features(image_shape, self.video), root=self.root,
            robot_type=self.run.env_id, use_videos=self.video, video_backend="pyav")
        self.image_shape = image_shape
        self._write_meta()
        return ds

    def _check_image_shape(self, shape: tuple[int, ...]) -> None:
        """Images are H x W x 3, of `image_size` when given, large enough for the video encoder."""
        if len(shape) != 3 or shape[2] != 3:
            raise ValueError(f"images must be uint8 H x W x 3, got shape {shape}")
        if self.image_size is not None and shape[:2] != self.image_size:
            raise ValueError(f"images are {shape[0]}x{shape[1]}, the sink expects {self.image_size}")
        if self.video and min(shape[:2]) < MIN_VIDEO_SIDE:
            raise ValueError(f"video needs images of at least {MIN_VIDEO_SIDE}x{MIN_VIDEO_SIDE} "
                             f"(got {shape[0]}x{shape[1]}); record without video=True")

    def _worker_index(self, worker: tuple[float, ...]) -> int:
        """Index of a worker (new workers get the next index when the suite could not be read)."""
        key = tuple(worker)
        if key not in self.workers:
            self.workers[key] = len(self.workers)
        return self.workers[key]

    def _frames(self, unit: UnitRecord, episode: EpisodeRecord) -> list[dict[str, Any]]:
        """The LeRobot frames of one episode, with the exact dtypes and shapes `add_frame` insists on."""
        assert self.run is not None
        task = task_description(self.run.suite, unit.pair, unit.task)
        constant = {"pair_index": unit.pair, "worker_index": self._worker_index(unit.worker), "seed": unit.seed,
                    "episode_in_pair": episode.episode, "task_index_in_suite": unit.task_index,
                    "env_seed": episode.env_seed}
        images = episode_images(episode) if self.image_shape is not None else [None] * len(episode.steps)
        frames = []
        for step, image in zip(episode.steps, images):
            frame = {
                "observation.state": np.array(step.obs, dtype=np.float32),
                "action": _int(step.action),
                "next.reward": np.array([step.reward], dtype=np.float32),
                "next.done": np.array([step.terminated or step.truncated], dtype=bool),
                "next.terminated": np.array([step.terminated], dtype=bool),
                "next.truncated": np.array([step.truncated], dtype=bool),
                "next.observation.state": np.array(step.next_obs, dtype=np.float32),
                **{key: _int(value) for key, value in constant.items()},
                "task": task,
            }
            if self.image_shape is not None:
                frame[IMAGE_KEY] = self._image(image, unit, episode, step.step)
            frames.append(frame)
        return frames

    def _image(self, image: np.ndarray | None, unit: UnitRecord, episode: EpisodeRecord, step: int) -> np.ndarray:
        """A frame's image as uint8 of the dataset's shape, or a clear error."""
        where = f"pair {unit.pair}, seed {unit.seed}, episode {episode.episode}, step {step}"
        if image is None:
            raise ValueError(f"{where}: no image, but the dataset records images (the first unit had them)")
        image = np.asarray(image)
        if image.shape != self.image_shape or image.dtype != np.uint8:
            raise ValueError(f"{where}: image {image.dtype} {image.shape}, expected uint8 {self.image_shape}")
        return image

    def _write_episode(self, unit: UnitRecord, episode: EpisodeRecord) -> None:
        """add_frame per step, then save_episode; a failure discards the half-written episode."""
        if not episode.steps:
            raise ValueError(f"pair {unit.pair}, seed {unit.seed}, episode {episode.episode}: no steps")
        frames = self._frames(unit, episode)  # build (and check) everything before touching the dataset
        try:
            for frame in frames:
                self.dataset.add_frame(frame)
            with _batched_image_embedding():
                self.dataset.save_episode()
        except BaseException:
            if self.dataset.has_pending_frames():
                self.dataset.clear_episode_buffer()
            raise
        self.frames += len(frames)

    # -- metadata ------------------------------------------------------------------------------------

    def _unit_summary(self, unit: UnitRecord, first_episode: int, saved: int) -> dict[str, Any]:
        """Where a unit's episodes are and their exact (float64) outcomes; registers the pair."""
        assert self.run is not None
        if unit.pair not in self.pairs:
            self.pairs[unit.pair] = {"task_index_in_suite": unit.task_index,
                                     "worker_index": self._worker_index(unit.worker),
                                     "task_string": task_description(self.run.suite, unit.pair, unit.task),
                                     "task": {k: v for k, v in unit.task.items() if k in TASK_KEYS},
                                     "worker": list(unit.worker)}
        eps = unit.episodes[:saved]
        return {"pair": unit.pair, "seed": unit.seed, "first_episode_index": first_episode, "episodes": saved,
                "complete": saved == len(unit.episodes),
                "env_seeds": [e.env_seed for e in eps], "lengths": [len(e.steps) for e in eps],
                "returns": [e.episode_return for e in eps], "normalised_returns": [e.normalised_return for e in eps],
                "scores": [e.score for e in eps]}

    def metadata(self) -> dict[str, Any]:
        """Content of `meta/mewa.json`."""
        from importlib.metadata import PackageNotFoundError, version

        assert self.run is not None
        try:
            lerobot_version = version("lerobot")
        except PackageNotFoundError:  # pragma: no cover - lerobot wrote the dataset, so it is installed
            lerobot_version = None
        r = self.run
        return {
            "format": META_FORMAT, "format_version": META_FORMAT_VERSION,
            "mewa_bench_version": r.package_version, "lerobot_version": lerobot_version,
            "repo_id": self.repo_id, "fps": self.fps,
            "suite": {"name": r.suite, "sha256": r.suite_sha256},
            "policy": {"name": r.agent, "sha256": r.agent_sha256, **r.extra},
            "env": {"id": r.env_id, "version": r.env_version, "mode": r.mode},
            "protocol_version": r.protocol_version,
            "seeds": list(r.seeds), "episodes_per_pair": r.episodes_per_pair,
            "columns": INDEX_COLUMNS,
            "worker_index_order": "suite" if self.workers_from_suite else "first appearance in this recording",
            "workers": [list(w) for w, _ in sorted(self.workers.items(), key=lambda kv: kv[1])],
            "pairs": {str(p): v for p, v in sorted(self.pairs.items())},
            "units": self.units,
            "frames": self.frames,  # no timings: the same run must give the same bytes
        }

    def _write_meta(self) -> None:
        """Write `meta/mewa.json` atomically."""
        from mewa_bench.files import write_json_atomic

        write_json_atomic(self.root / MEWA_META_FILE, self.metadata())


def _embed_images_batched(dataset: Any) -> Any:
    """lerobot's `embed_images` (image files -> bytes in the table), skipped without image columns, else batched."""
    from datasets.features.features import require_storage_embed
    from datasets.table import embed_table_storage

    if not any(require_storage_embed(f) for f in dataset.features.values()):
        return dataset
    fmt = dataset.format
    return dataset.with_format("arrow").map(embed_table_storage, batched=True).with_format(**fmt)


@contextmanager
def _batched_image_embedding() -> Iterator[None]:
    """Swap in `_embed_images_batched` while lerobot saves an episode.

    lerobot 0.6.1 maps `embed_table_storage` over an episode row by row (about 2.5 ms a row, even with no
    image column), which made it most of the recording time; the result is the same table.
    """
    dataset_writer = _datasets_extra("lerobot.datasets.dataset_writer")

    original = getattr(dataset_writer, "embed_images", None)
    if original is None:  # another lerobot layout: leave it alone
        yield
        return
    dataset_writer.embed_images = _embed_images_batched
    try:
        yield
    finally:
        dataset_writer.embed_images = original


def _remove_empty_dirs(path: Path) -> None:
    """Remove `path` and its subfolders if they hold no files."""
    if not path.is_dir():
        return
    for dirpath, _, _ in sorted(os.walk(path), key=lambda w: -len(w[0])):
        try:
            os.rmdir(dirpath)
        except OSError:
            return  # not empty: leave it


def load_metadata(root: Path | str) -> dict[str, Any]:
    """Read a recorded dataset's `meta/mewa.json`."""
    return json.loads((Path(root) / MEWA_META_FILE).read_text())


def _sort_json_keys(path: Path) -> None:
    """Rewrite a JSON file with sorted keys (lerobot writes `stats.json` in an order that varies between
    runs); same content, same indentation, so the same recording gives the same bytes."""
    if path.is_file():
        from mewa_bench.files import write_atomic

        write_atomic(path, json.dumps(json.loads(path.read_text()), indent=4, sort_keys=True))
