"""Write a whole LeRobot v3.0 dataset at once from column arrays (lerobot's per-frame path is ~2,000 frames/s).

The files are those lerobot 0.6.1's own writer (`add_frame` / `save_episode`) makes, with the same
schemas: `data/chunk-XXX/file-YYY.parquet` (the frames, row groups of whole episodes, snappy, the
`huggingface` features metadata; a new file past `data_files_size_in_mb`), `meta/info.json`,
`meta/stats.json`, `meta/tasks.parquet` and `meta/episodes/chunk-000/file-000.parquet` (one row per
episode: tasks, length, data file and frame range, per-episode statistics). Differences, all within
the format (lerobot's reader never relies on them): a data row group may hold several episodes
(`episodes_per_row_group`; lerobot writes one each, and ~3 ms per row group made that most of the
writing time; training datasets use a row group per round of meta-episodes, ~10-20k frames), the
episodes file is one row group (lerobot flushes every 10 episodes), statistics quantiles
are exact (numpy's linear interpolation) where lerobot approximates them with histograms,
`stats.json` has sorted keys, and the parquet metadata has no random `fingerprint`, so the same
columns always give the same bytes.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

DEFAULT_FEATURES = {  # lerobot.utils.constants.DEFAULT_FEATURES, in its order
    "timestamp": {"dtype": "float32", "shape": (1,), "names": None},
    "frame_index": {"dtype": "int64", "shape": (1,), "names": None},
    "episode_index": {"dtype": "int64", "shape": (1,), "names": None},
    "index": {"dtype": "int64", "shape": (1,), "names": None},
    "task_index": {"dtype": "int64", "shape": (1,), "names": None},
}
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
CHUNKS_SIZE = 1000
DATA_FILE_MB = 100
VIDEO_FILE_MB = 200
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"


def info_dict(features: dict[str, dict], fps: int, robot_type: str | None, episodes: int, frames: int,
              tasks: int) -> dict[str, Any]:
    """`meta/info.json` as lerobot writes it (keys in its order)."""
    return {"codebase_version": "v3.0", "fps": fps,
            "features": {k: {**v, "shape": list(v["shape"])} for k, v in features.items()},
            "total_episodes": episodes, "total_frames": frames, "total_tasks": tasks, "chunks_size": CHUNKS_SIZE,
            "data_files_size_in_mb": DATA_FILE_MB, "video_files_size_in_mb": VIDEO_FILE_MB,
            "data_path": DATA_PATH, "video_path": None, "robot_type": robot_type,
            "splits": {"train": f"0:{episodes}"}}


def _arrow_type(pa: Any, ft: dict) -> Any:
    """The arrow type lerobot's `datasets` features give a feature of shape (1,) or (k,)."""
    value = {"float32": pa.float32(), "float64": pa.float64(), "int64": pa.int64(), "bool": pa.bool_()}[ft["dtype"]]
    return value if tuple(ft["shape"]) == (1,) else pa.list_(value, int(ft["shape"][0]))


def _hf_metadata(features: dict[str, dict]) -> bytes:
    """The `huggingface` schema metadata `datasets` writes (features only, no fingerprint)."""
    out = {}
    for key, ft in features.items():
        value = {"dtype": ft["dtype"], "_type": "Value"}
        out[key] = value if tuple(ft["shape"]) == (1,) else {"feature": value, "length": int(ft["shape"][0]),
                                                             "_type": "List"}
    return json.dumps({"info": {"features": out}}).encode()


def _column(pa: Any, values: np.ndarray, ft: dict) -> Any:
    """One arrow column from a numpy array [F] or [F, k]."""
    kind = _arrow_type(pa, ft)
    if tuple(ft["shape"]) == (1,):
        return pa.array(values.reshape(-1), type=kind)
    flat = pa.array(np.ascontiguousarray(values).reshape(-1), type=kind.value_type)
    return pa.FixedSizeListArray.from_arrays(flat, int(ft["shape"][0]))


def episode_stats(values: np.ndarray, starts: np.ndarray, lengths: np.ndarray) -> dict[str, np.ndarray]:
    """Per-episode min, max, mean, std, count and quantiles of a column [F, k] (float64 [E, k] each)."""
    x = values.reshape(len(values), -1)
    n_eps = len(lengths)
    owner = np.repeat(np.arange(n_eps), lengths)
    out = {k: np.zeros((n_eps, x.shape[1])) for k in ("min", "max", "mean", "std", *_quantile_keys())}
    for j in range(x.shape[1]):
        column = x[:, j].astype(np.float64)
        mean = np.bincount(owner, weights=column, minlength=n_eps) / lengths
        out["mean"][:, j] = mean
        out["std"][:, j] = np.sqrt(np.bincount(owner, weights=(column - mean[owner]) ** 2, minlength=n_eps) / lengths)
        ranked = _ranked(column, owner, starts, lengths)  # ranked(e, r): the r-th smallest value of episode e
        out["min"][:, j], out["max"][:, j] = ranked(np.zeros(n_eps, dtype=np.int64)), ranked(lengths - 1)
        for q, key in zip(QUANTILES, _quantile_keys()):
            pos = q * (lengths - 1)
            lo = np.floor(pos).astype(np.int64)
            low, high = ranked(lo), ranked(np.minimum(lo + 1, lengths - 1))
            out[key][:, j] = low + (pos - lo) * (high - low)
    out["count"] = lengths[:, None].astype(np.int64)
    return out


SMALL_RANGE = 64  # integer columns spanning fewer values are ranked by counting, not sorting


def _ranked(column: np.ndarray, owner: np.ndarray, starts: np.ndarray, lengths: np.ndarray) -> Any:
    """A function (episodes' ranks [E] -> values [E]) giving each episode's r-th smallest value."""
    n_eps = len(lengths)
    low, high = float(column.min()), float(column.max())
    if high - low < SMALL_RANGE and np.array_equal(column, np.round(column)):
        levels = int(high - low) + 1
        counts = np.bincount(owner * levels + (column - low).astype(np.int64), minlength=n_eps * levels)
        cumulative = np.cumsum(counts.reshape(n_eps, levels), axis=1)
        return lambda rank: low + (cumulative <= rank[:, None]).sum(axis=1)
    padded = np.full((n_eps, int(lengths.max())), np.inf)
    padded[owner, np.arange(len(column)) - starts[owner]] = column
    padded.sort(axis=1)  # the padding (inf) goes last
    rows = np.arange(n_eps)
    return lambda rank: padded[rows, rank]


def _quantile_keys() -> tuple[str, ...]:
    """"q01", "q10", ... for QUANTILES."""
    return tuple(f"q{int(round(q * 100)):02d}" for q in QUANTILES)


def aggregate(stats: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Dataset statistics from per-episode ones, by lerobot's `aggregate_feature_stats` formulas."""
    counts = stats["count"].astype(np.float64)  # [E, 1]
    total = counts.sum()
    mean = (stats["mean"] * counts).sum(axis=0) / total
    variance = ((stats["std"] ** 2 + (stats["mean"] - mean) ** 2) * counts).sum(axis=0) / total
    out = {"min": stats["min"].min(axis=0), "max": stats["max"].max(axis=0), "mean": mean, "std": np.sqrt(variance),
           "count": np.array([int(total)])}
    for key in stats:
        if key.startswith("q"):
            out[key] = (stats[key] * counts).sum(axis=0) / total
    return out


STAT_ORDER = ("min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99")


def write_lerobot_dataset(root: Path, features: dict[str, dict], columns: dict[str, np.ndarray],
                          lengths: np.ndarray, episode_tasks: list[str], fps: int, robot_type: str | None,
                          episodes_per_row_group: int = 1) -> None:
    """Write a LeRobot v3.0 dataset to `root` (which must not exist) from user feature columns.

    `features` and `columns` hold the user features (not lerobot's default ones, which are filled in);
    `lengths` gives the frames of each episode in order, `episode_tasks` each episode's task string.
    """
    import pandas as pd
    import pyarrow as pa
    import pyarrow.parquet as pq

    root = Path(root)
    root.mkdir(parents=True, exist_ok=False)
    lengths = np.asarray(lengths, dtype=np.int64)
    n_frames, n_eps = int(lengths.sum()), len(lengths)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
    task_names = list(dict.fromkeys(episode_tasks))  # first appearance order, as lerobot numbers them
    task_of = {t: i for i, t in enumerate(task_names)}
    episode = np.repeat(np.arange(n_eps, dtype=np.int64), lengths)
    frame_index = np.arange(n_frames, dtype=np.int64) - starts[episode]
    all_features = {**features, **DEFAULT_FEATURES}
    all_columns = {**columns, "timestamp": (frame_index / fps).astype(np.float32), "frame_index": frame_index,
                   "episode_index": episode, "index": np.arange(n_frames, dtype=np.int64),
                   "task_index": np.array([task_of[t] for t in episode_tasks], dtype=np.int64)[episode]}
    for key, ft in all_features.items():
        if len(all_columns[key]) != n_frames:
            raise ValueError(f"column {key!r} has {len(all_columns[key])} rows, the episodes hold {n_frames} frames")
    schema = pa.schema([pa.field(k, _arrow_type(pa, ft)) for k, ft in all_features.items()],
                       metadata={b"huggingface": _hf_metadata(all_features)})
    table = pa.Table.from_arrays([_column(pa, all_columns[k], ft) for k, ft in all_features.items()], schema=schema)
    placement = _write_data(pq, pa, root, table, starts, lengths, episodes_per_row_group)
    stats = {k: episode_stats(all_columns[k], starts, lengths) for k in all_features}
    _write_episodes(pa, pq, root, all_features, stats, placement, starts, lengths, episode_tasks)
    (root / "meta").mkdir(exist_ok=True)
    pd.DataFrame({"task_index": range(len(task_names))}, index=pd.Index(task_names, name="task")).to_parquet(
        root / "meta" / "tasks.parquet")
    summary = {k: {s: aggregate(v)[s].tolist() for s in STAT_ORDER} for k, v in stats.items()}
    (root / "meta" / "stats.json").write_text(json.dumps(summary, indent=4, sort_keys=True))
    info = info_dict(all_features, fps, robot_type, n_eps, n_frames, len(task_names))
    with open(root / "meta" / "info.json", "w", encoding="utf-8") as f:
        json.dump(info, f, indent=4, ensure_ascii=False)


def _write_data(pq: Any, pa: Any, root: Path, table: Any, starts: np.ndarray, lengths: np.ndarray,
                per_group: int) -> np.ndarray:
    """Frames to data files, `per_group` episodes per row group; returns each episode's (chunk, file) [E, 2]."""
    placement = np.zeros((len(lengths), 2), dtype=np.int64)
    chunk, file, writer, sink, file_frames = 0, 0, None, None, 0
    firsts = np.arange(0, len(lengths), per_group)
    try:
        for e in firsts.tolist():
            start, length = int(starts[e]), int(lengths[e : e + per_group].sum())
            if writer is not None:
                size_mb = sink.tell() / 1e6
                if size_mb + size_mb / file_frames * length >= DATA_FILE_MB:
                    writer.close()
                    sink.close()
                    writer = None
                    file += 1
                    if file >= CHUNKS_SIZE:
                        chunk, file = chunk + 1, 0
            if writer is None:
                path = root / DATA_PATH.format(chunk_index=chunk, file_index=file)
                path.parent.mkdir(parents=True, exist_ok=True)
                sink = pa.OSFile(str(path), "wb")
                writer = pq.ParquetWriter(sink, table.schema, compression="snappy", use_dictionary=True)
                file_frames = 0
            writer.write_table(table.slice(start, length))
            file_frames += length
            placement[e : e + per_group] = chunk, file
    finally:
        if writer is not None:
            writer.close()
            sink.close()
    return placement


def _write_episodes(pa: Any, pq: Any, root: Path, features: dict[str, dict], stats: dict[str, dict],
                    placement: np.ndarray, starts: np.ndarray, lengths: np.ndarray, tasks: list[str]) -> None:
    """`meta/episodes/chunk-000/file-000.parquet`: one row per episode."""
    n = len(lengths)

    def lists(values: np.ndarray, kind: Any) -> Any:
        offsets = pa.array(np.arange(0, values.size + 1, values.shape[1], dtype=np.int32))
        return pa.ListArray.from_arrays(offsets, pa.array(values.reshape(-1), type=kind))

    names = ["episode_index", "tasks", "length", "data/chunk_index", "data/file_index", "dataset_from_index",
             "dataset_to_index"]
    arrays = [pa.array(np.arange(n, dtype=np.int64)),
              pa.ListArray.from_arrays(pa.array(np.arange(n + 1, dtype=np.int32)), pa.array(tasks, type=pa.string())),
              pa.array(lengths), pa.array(placement[:, 0]), pa.array(placement[:, 1]), pa.array(starts),
              pa.array(starts + lengths)]
    for key in features:
        for stat in STAT_ORDER:
            names.append(f"stats/{key}/{stat}")
            arrays.append(lists(stats[key][stat], pa.int64() if stat == "count" else pa.float64()))
    names += ["meta/episodes/chunk_index", "meta/episodes/file_index"]
    arrays += [pa.array(np.zeros(n, dtype=np.int64)), pa.array(np.zeros(n, dtype=np.int64))]
    table = pa.Table.from_arrays(arrays, names=names)
    path = root / EPISODES_PATH.format(chunk_index=0, file_index=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path, compression="snappy", use_dictionary=True)
