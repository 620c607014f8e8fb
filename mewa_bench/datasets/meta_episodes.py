"""Whole meta-episodes of a training dataset as token sequences, for in-context methods (SPEC section 8).

A training dataset's frames are single steps; an in-context learner needs them grouped the way it
plays: one meta-train worker's episodes in play order. `MetaEpisodeDataset` is a map-style torch
dataset (use it with `torch.utils.data.DataLoader(..., collate_fn=pad_batch)`) whose items are
sequences of frames:

- `unit="meta-episode"`: a whole meta-episode (the expert tier's 10 episodes, a learning history's 50);
  `unit="block"`: one 10-episode block (a learning history is 5 of them), a fresh sequence as the
  protocol starts a pair afresh.
- `episodes=N`: only the first N episodes of each sequence.
- `window=N`: fixed-length context windows of N frames instead, every `stride` frames of each sequence
  (the last window of a sequence may be shorter; `pad_batch` pads and marks `valid`).

Each frame t of an item holds, per key (tensors of length L):
- `inputs` float32 [L, 24]: exactly what a recurrent agent of this package sees when it plays
  (`envs.meta_episode.meta_observation`, as `agents.lanes.RecurrentLanes` builds it): the observation,
  the previous action one-hot, the previous reward and the new-episode flag. The previous action and
  reward carry across episode boundaries within the sequence; the sequence's first frame has none.
- `observation` [L, 18], `previous_action` (-1: none), `previous_reward`, `new_episode`: the same, apart;
- `episode`: the episode's index within the sequence; `first`: True on the sequence's first frame (where
  a recurrent state starts from zero); `sequence`: which sequence; `frame`: the dataset's frame `index`;
- labels: `action` (what the behaviour did: for the expert tier, what an agent that does not know the
  worker chose from what it had seen) and `optimal_action` (the known-worker optimum, privileged).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mewa_bench.envs.meta_episode import meta_observation

UNITS = ("meta-episode", "block")
COLUMNS = ["index", "observation.state", "action", "next.reward", "optimal_action", "meta_episode_index",
           "episode_in_meta_episode", "block_index", "episode_in_block"]


@dataclass(frozen=True)
class SequenceFrames:
    """A dataset's frames in play order; sequence s is frames starts[s]:starts[s + 1]."""

    frame: np.ndarray  # int64 [F]: the dataset's `index`
    observation: np.ndarray  # float32 [F, 18]
    action: np.ndarray  # int64 [F]
    reward: np.ndarray  # float32 [F]
    optimal_action: np.ndarray  # int64 [F]
    episode: np.ndarray  # int64 [F]: episode within its sequence
    starts: np.ndarray  # int64 [S + 1]

    def __len__(self) -> int:
        return len(self.starts) - 1

    def lengths(self) -> np.ndarray:
        """Frames of each sequence."""
        return np.diff(self.starts)


def read_sequences(root: Path | str, unit: str = "meta-episode", suite: str | None = None) -> SequenceFrames:
    """The frames of a training dataset on disk, grouped by `unit`, after the dataset's checks (no test worker,
    no protocol luck key); with `suite`, an error unless the dataset is of that suite."""
    import pyarrow.parquet as pq

    from mewa_bench.datasets.training_data import check_training_dataset

    if unit not in UNITS:
        raise ValueError(f"unit {unit!r}: expected one of {', '.join(UNITS)}")
    meta = check_training_dataset(root)
    if suite is not None and meta["suite"]["name"] != suite:
        raise ValueError(f"{root}: a dataset of {meta['suite']['name']}, not of {suite}")
    tables = [pq.read_table(path, columns=COLUMNS) for path in sorted((Path(root) / "data").rglob("*.parquet"))]
    flat = {c: np.concatenate([_column(t, c) for t in tables]) for c in COLUMNS}
    order = np.argsort(flat["index"], kind="stable")
    col = {c: v.reshape(len(order), -1)[order] if c == "observation.state" else v[order] for c, v in flat.items()}
    if unit == "block":
        group = col["meta_episode_index"] * (int(col["block_index"].max()) + 1) + col["block_index"]
        episode = col["episode_in_block"]
    else:
        group, episode = col["meta_episode_index"], col["episode_in_meta_episode"]
    return frames_in_sequences(col["index"], col["observation.state"], col["action"], col["next.reward"],
                               col["optimal_action"], group, episode)


def frames_in_sequences(frame: np.ndarray, observation: np.ndarray, action: np.ndarray, reward: np.ndarray,
                        optimal_action: np.ndarray, group: np.ndarray, episode: np.ndarray) -> SequenceFrames:
    """Frames in play order (a new sequence wherever `group` changes) as `SequenceFrames`."""
    group = np.asarray(group)
    starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1], True]).astype(np.int64)
    return SequenceFrames(np.asarray(frame, dtype=np.int64), np.asarray(observation, dtype=np.float32),
                          np.asarray(action, dtype=np.int64), np.asarray(reward, dtype=np.float32),
                          np.asarray(optimal_action, dtype=np.int64), np.asarray(episode, dtype=np.int64), starts)


def first_episodes(data: SequenceFrames, episodes: int) -> SequenceFrames:
    """Each sequence cut to its first `episodes` episodes (the protocol plays 10 from scratch; a learning history's
    later episodes follow more experience than a pair gives)."""
    if episodes < 1:
        raise ValueError(f"episodes {episodes}: at least 1")
    keep = data.episode < episodes
    sequence = np.repeat(np.arange(len(data)), data.lengths())[keep]
    return frames_in_sequences(data.frame[keep], data.observation[keep], data.action[keep], data.reward[keep],
                               data.optimal_action[keep], sequence, data.episode[keep])


def _column(table: Any, name: str) -> np.ndarray:
    """A parquet column as a flat numpy array (list columns flattened)."""
    column = table.column(name).combine_chunks()
    return (column.flatten() if hasattr(column, "flatten") else column).to_numpy(zero_copy_only=False)


def previous_transition(data: SequenceFrames) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per frame: the previous action (-1 on a sequence's first frame), the previous reward (0 there), the
    new-episode flag (a new episode that is not the sequence's first) and whether it is the sequence's first."""
    first = np.zeros(len(data.action), dtype=bool)
    first[data.starts[:-1]] = True
    previous_action = np.where(first, -1, np.r_[-1, data.action[:-1]])
    previous_reward = np.where(first, 0.0, np.r_[0.0, data.reward[:-1]]).astype(np.float32)
    new_episode = (np.r_[True, data.episode[1:] != data.episode[:-1]] & ~first).astype(np.float32)
    return previous_action, previous_reward, new_episode, first


def lane_inputs(data: SequenceFrames) -> np.ndarray:
    """float32 [F, 24]: every frame's input as a recurrent agent's lane builds it when playing."""
    previous_action, previous_reward, new_episode, _ = previous_transition(data)
    return meta_observation(data.observation, previous_action, previous_reward, new_episode)


class MetaEpisodeDataset:
    """A map-style torch dataset of whole sequences (meta-episodes or blocks) or of fixed-length windows of them."""

    def __init__(self, source: Path | str | SequenceFrames, unit: str = "meta-episode", window: int | None = None,
                 stride: int | None = None, suite: str | None = None, episodes: int | None = None) -> None:
        self.data = source if isinstance(source, SequenceFrames) else read_sequences(source, unit, suite)
        if episodes is not None:
            self.data = first_episodes(self.data, episodes)
        previous_action, previous_reward, new_episode, first = previous_transition(self.data)
        self.columns = {"inputs": lane_inputs(self.data), "observation": self.data.observation,
                        "previous_action": previous_action, "previous_reward": previous_reward,
                        "new_episode": new_episode, "episode": self.data.episode, "first": first,
                        "frame": self.data.frame, "action": self.data.action,
                        "optimal_action": self.data.optimal_action}
        self.sequence = np.repeat(np.arange(len(self.data)), self.data.lengths())
        if window is None:
            self.spans = np.stack([self.data.starts[:-1], self.data.starts[1:]], axis=1)
        else:
            if window < 1 or (stride is not None and stride < 1):
                raise ValueError(f"window {window} and stride {stride}: both must be at least 1")
            step = stride or window
            self.spans = np.array([(begin, min(begin + window, end))
                                   for begin, end in zip(self.data.starts[:-1].tolist(), self.data.starts[1:].tolist())
                                   for begin in range(begin, end, step)], dtype=np.int64).reshape(-1, 2)

    def __len__(self) -> int:
        return len(self.spans)

    def __getitem__(self, item: int) -> dict[str, Any]:
        """The tensors of item `item` (see the module docstring)."""
        import torch

        if not -len(self) <= item < len(self):
            raise IndexError(f"item {item} of a MetaEpisodeDataset of {len(self)}")
        begin, end = self.spans[item]
        out = {key: torch.as_tensor(values[begin:end]) for key, values in self.columns.items()}
        out["sequence"] = torch.as_tensor(self.sequence[begin:end])
        return out


def pad_batch(items: list[dict[str, Any]]) -> dict[str, Any]:
    """Items of different lengths as one batch [B, L_max, ...], zero-padded, with `valid` [B, L_max] (a DataLoader's
    `collate_fn`)."""
    import torch

    length = max(len(item["action"]) for item in items)
    out = {}
    for key in items[0]:
        first = items[0][key]
        batch = torch.zeros((len(items), length, *first.shape[1:]), dtype=first.dtype)
        for row, item in enumerate(items):
            batch[row, :len(item[key])] = item[key]
        out[key] = batch
    out["valid"] = torch.zeros((len(items), length), dtype=torch.bool)
    for row, item in enumerate(items):
        out["valid"][row, :len(item["action"])] = True
    return out
