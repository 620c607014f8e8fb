"""`mewa-bench datasets build NAME`: build a named training dataset, pack it, record its sha256 in a catalog.

The folder `<out>/<name>/` is the LeRobot dataset (`<name>-frames<N>` when `--frames N` differs from the
dataset's own target: the first rounds of the full dataset, the same seeds, under a name of its own); `<out>/<name>-<version>.tar.gz` its deterministic
archive, whose sha256 goes into the catalog (default `<out>/index.json`), from which `datasets
download NAME --catalog <out>/index.json` or `mewa-bench serve --catalog ...` hand it out verified.
When the shipped catalog's `builds` section records the same dataset, the new sha256 is compared
with it (the bytes depend on the package, numpy, pyarrow and pandas versions).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mewa_bench.datasets.expert_rollout import MapTasks
from mewa_bench.datasets.catalog import DatasetError, add_to_catalog, default_catalog_path, load_catalog, recorded_build
from mewa_bench.datasets.pack import pack_dataset
from mewa_bench.datasets.training_data import BuildProgress, TrainingSpec, build_training_dataset, training_spec

BEHAVIOUR_NAMES = {"random": "random", "random-task-specific": "random-task-specific",
                   "learning-histories": "posterior-sampling-toptimal",
                   "task-inferring-histories": "posterior-sampling-task-and-toptimal"}


@dataclass(frozen=True)
class BuildResult:
    """What a build made and how long it took."""

    spec: TrainingSpec
    root: Path
    entry: dict[str, Any]
    catalog: Path
    build_seconds: float
    pack_seconds: float
    recorded_sha256: str | None  # the shipped catalog's sha256 of this build, if it records one

    @property
    def matches_record(self) -> bool | None:
        """Whether the archive's sha256 is the recorded one (None: nothing recorded)."""
        return None if self.recorded_sha256 is None else self.recorded_sha256 == self.entry["sha256"]


def behaviour_name(spec: TrainingSpec) -> str:
    """The catalog's `policy` of a training dataset."""
    return spec.expert_agent if spec.tier == "expert" else BEHAVIOUR_NAMES[spec.tier]


def build_named(name: str, out_dir: Path | str, frames: int | None = None, jobs: int = 2,
                catalog: Path | str | None = None, map_tasks: MapTasks | None = None,
                progress: BuildProgress = lambda phase, done, total: None) -> BuildResult:
    """Build, pack and catalog the training dataset `name` under `out_dir` (its parallel work in `jobs` processes, or
    as `map_tasks`, e.g. `training_data.ray_tasks`); `progress` as `build_training_dataset`'s, and ("pack", 0|1, 1)."""
    spec = training_spec(name, frames)
    out_dir = Path(out_dir)
    root = out_dir / spec.built_name
    catalog_path = Path(catalog) if catalog is not None else out_dir / "index.json"
    if catalog_path.exists():
        load_catalog(catalog_path)  # a broken catalog fails before the build
    start = time.perf_counter()
    build_training_dataset(spec, root, jobs, map_tasks=map_tasks, progress=progress)
    built = time.perf_counter()
    progress("pack", 0, 1)
    entry = pack_dataset(root, out_dir, spec.built_name, spec.version, spec.suite, behaviour_name(spec),
                         catalog_dir=catalog_path.parent)
    add_to_catalog(catalog_path, entry)
    packed = time.perf_counter()
    progress("pack", 1, 1)
    return BuildResult(spec, root, entry, catalog_path, built - start, packed - built, _recorded(spec))


def _recorded(spec: TrainingSpec) -> str | None:
    """The shipped catalog's sha256 of this exact build (same name, version and frame target), if any."""
    try:
        shipped = load_catalog(default_catalog_path(), resolve=False)
    except DatasetError:
        return None
    record = recorded_build(shipped, spec.built_name, spec.version)
    if record is not None and record.get("frames_target") == spec.frames:
        return record.get("sha256")
    entry = next((e for e in shipped["datasets"] if (e["name"], e["version"]) == (spec.built_name, spec.version)), None)
    return None if entry is None else entry.get("sha256")
