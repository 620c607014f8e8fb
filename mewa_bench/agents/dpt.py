"""Decision-Pretrained Transformer (Lee et al. 2023) on MEWA: in-context adaptation learnt from offline data alone.

One file, top to bottom: settings, the training sequences (from a training dataset of
`mewa-bench datasets build`, or from frames in memory), a small causal transformer, the supervised
training loop, checkpoints, and `DPTVectorAgent`, which plays a checkpoint under the evaluation protocol.

- Data: every frame of a training dataset carries the exact known-worker optimal action for its
  state and step (`optimal_action`, from `design.optimum`): the label DPT learns to predict. The
  frames come from meta-train workers only (the dataset's own checks run when it is opened), so
  the test pairs are never seen.
- Sequences: one per 10-episode block of a meta-episode (a meta-train worker's episodes, in play
  order; a learning history's 50 episodes are 5 blocks, as the protocol plays 10); token t is
  frame t's observation and the whole previous transition (its observation, action one-hot and
  reward: with the next observation, which is frame t's own within an episode, a token holds what
  the worker did), the new-episode flag, plus an embedding of the episode's index. The model
  predicts the optimal action of frame t from tokens 0..t: what the behaviour did so far is its
  context, the worker it must infer.
- Model: a pre-norm causal transformer without position embeddings (`agents.causal_transformer`, shared
  with AD): the context is a set of transitions, as in the paper.
- Training: cross-entropy against the optimal labels on every frame of a span of up to
  2 x `context` tokens of each of `batch` meta-episodes, ending at a frame drawn uniformly, with
  the attention of every token limited to its last `context` tokens, as when playing; AdamW;
  `total_steps` counts spans (meta-episodes) seen. Deterministic for a given seed on one machine
  (torch's CPU kernels, one thread); a resumed run draws its spans afresh from the seed and its
  update, so it is not the bytes of an uninterrupted one.
- Playing: each lane keeps the keys and values of its last `context` tokens per layer
  (`causal_transformer.LaneCache`, a ring buffer allocated once: without position embeddings their order
  does not matter; as in any sliding-window cache, the states of a deeper layer were made when those tokens
  saw their own last `context`), so a step costs one token's pass; the action is sampled from the predicted distribution with the lane's generator
  (posterior-sampling-like, as in the paper's online deployment), or the most likely one with
  `greedy`.

Learning test (tests/test_dpt.py): trained on random play on the two-worker task, labelled with
the exact optimal actions, it adapts in context (adaptability +0.10 +- 0.04) and scores 0.60
against the best fixed policy's 0.5. Playing greedily instead loops (a wrong most-likely action in
a state its own play keeps returning to), so it samples. Runs on the shipped suites: docs/baselines.md.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from mewa_bench.agents.causal_transformer import EPISODES, OBS, TOKEN, TransformerLanes, make_tokens, make_transformer
from mewa_bench.agents.lanes import truthy
from mewa_bench.agents.training_io import (CHECKPOINT, METRICS, fit_labels, load_for_play, offline_settings,
                                           restore, resumed, torch_module, torch_threads)
from mewa_bench.agents.training_io import write_submission as write_submission_files
from mewa_bench.protocol.agent import SingleLane

__all__ = ["CHECKPOINT", "METRICS", "DPTAgent", "DPTVectorAgent", "Sequences", "Settings", "STEP_UNIT",
           "dataset_sequences", "make_tokens", "settings_from", "sequences_from_frames", "train", "train_run"]

STEP_UNIT = "meta-episodes"  # what `total_steps` counts (`train --steps`)


@dataclass
class Settings:
    suite: str = "narrow-v2"  # the dataset's suite (checked against it)
    seed: int = 1
    total_steps: int = 40_000  # meta-episodes seen in training (STEP_UNIT)
    dataset: str = ""  # folder of a training dataset (mewa-bench datasets build NAME)
    batch: int = 16  # meta-episodes per update
    context: int = 256  # tokens the model attends to: training windows, and each lane's most recent ones when playing
    d_model: int = 64
    layers: int = 2
    heads: int = 4
    learning_rate: float = 1e-3
    weight_decay: float = 0.01
    max_grad_norm: float = 1.0
    checkpoint_every: int = 100  # updates
    workers: list[list[float]] = field(default_factory=list)  # not used: the dataset decides the workers

    @property
    def steps_per_update(self) -> int:
        return self.batch


@dataclass(frozen=True)
class Sequences:
    """Training sequences: tokens float32 [F, TOKEN], episode index and label int64 [F], in play order;
    `starts` int64 [M + 1]: sequence m (a 10-episode block of a meta-episode) is frames starts[m]:starts[m + 1]."""

    tokens: np.ndarray
    episode: np.ndarray
    label: np.ndarray
    starts: np.ndarray

    def __len__(self) -> int:
        return len(self.starts) - 1


def sequences_from_frames(obs: np.ndarray, action: np.ndarray, reward: np.ndarray, label: np.ndarray,
                          meta: np.ndarray, episode: np.ndarray) -> Sequences:
    """Sequences from frames in play order: observation [F, 18], action, reward, optimal label, meta-episode
    index and episode index within it [F]."""
    meta, episode, obs = np.asarray(meta), np.asarray(episode), np.asarray(obs, dtype=np.float32)
    starts = np.flatnonzero(np.r_[True, meta[1:] != meta[:-1], True])
    first_of_meta = np.zeros(len(meta), dtype=bool)
    first_of_meta[starts[:-1]] = True
    new_episode = np.r_[True, episode[1:] != episode[:-1]] & ~first_of_meta
    previous_obs = np.where(first_of_meta[:, None], 0.0, np.r_[np.zeros((1, OBS)), obs[:-1]])
    previous_action = np.where(first_of_meta, -1, np.r_[-1, action[:-1]]).astype(np.int64)
    previous_reward = np.where(first_of_meta, 0.0, np.r_[0.0, reward[:-1]])
    tokens = make_tokens(obs, previous_obs, previous_action, previous_reward, new_episode)
    return Sequences(tokens, np.minimum(episode, EPISODES - 1).astype(np.int64), np.asarray(label, dtype=np.int64),
                     starts.astype(np.int64))


def dataset_sequences(root: Path | str, suite: str | None = None) -> Sequences:
    """The sequences of a training dataset on disk, after the dataset's checks (no test worker, no protocol key)."""
    import pyarrow.parquet as pq

    from mewa_bench.datasets.training_data import check_training_dataset

    meta = check_training_dataset(root)
    if suite is not None and meta["suite"]["name"] != suite:
        raise ValueError(f"{root}: a dataset of {meta['suite']['name']}, not of {suite}")
    columns = ["index", "observation.state", "action", "next.reward", "optimal_action", "meta_episode_index",
               "block_index", "episode_in_block"]
    tables = [pq.read_table(path, columns=columns) for path in sorted((Path(root) / "data").rglob("*.parquet"))]
    flat = {c: np.concatenate([_column(t, c) for t in tables]) for c in columns}
    order = np.argsort(flat["index"], kind="stable")
    obs = flat["observation.state"].reshape(len(order), -1)[order]
    block = flat["meta_episode_index"][order] * (int(flat["block_index"].max()) + 1) + flat["block_index"][order]
    return sequences_from_frames(obs, flat["action"][order], flat["next.reward"][order],
                                 flat["optimal_action"][order], block, flat["episode_in_block"][order])


def _column(table: Any, name: str) -> np.ndarray:
    """A parquet column as a flat numpy array (list columns flattened)."""
    column = table.column(name).combine_chunks()
    return (column.flatten() if hasattr(column, "flatten") else column).to_numpy(zero_copy_only=False)


def _torch() -> Any:
    return torch_module("the DPT baseline")


def make_model(settings: Settings) -> Any:
    """The causal transformer (`agents.causal_transformer`): token and episode embeddings, `layers` pre-norm
    blocks, an action head."""
    return make_transformer(settings.d_model, settings.heads, settings.layers, settings.context)


@torch_threads(1)
def train(settings: Settings, out: Path, resume: bool = False, data: Sequences | None = None,
          progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> Path:
    """Train (or resume) a run in `out` on `data` (default: the settings' dataset); the checkpoint path."""
    torch = _torch()
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(settings.seed)
    state = resumed(out, settings, resume)
    model = make_model(settings)
    optimizer = torch.optim.AdamW(model.parameters(), lr=settings.learning_rate, weight_decay=settings.weight_decay)
    start_update = 0 if state is None else restore(out, state, model, {"optimizer": optimizer})
    if data is None:  # the run's own dataset
        if not settings.dataset:
            raise ValueError("DPT learns from a training dataset: give --dataset (a folder that `mewa-bench datasets "
                             "build NAME` wrote)")
        data = dataset_sequences(settings.dataset, settings.suite)
    updates = settings.total_steps // settings.steps_per_update
    rng = np.random.default_rng([settings.seed, start_update])
    lengths = np.diff(data.starts)
    for update in range(start_update, updates):
        began = time.perf_counter()
        chosen = rng.choice(len(data), size=settings.batch, replace=len(data) < settings.batch)
        end = rng.integers(0, lengths[chosen])  # the span's last frame, uniform over the sequence's frames
        begin = np.maximum(0, end + 1 - 2 * settings.context)
        tokens, episode, label, valid = _batch(torch, data, data.starts[chosen] + begin, end + 1 - begin)
        logits = model(tokens, episode, valid)
        fit_labels(model, optimizer, logits, label, valid, settings, update, updates, began, out, progress)
    return out / CHECKPOINT


def _batch(torch: Any, data: Sequences, first: np.ndarray, size: np.ndarray) -> tuple[Any, Any, Any, Any]:
    """Padded tensors of the spans of frames first[b]:first[b] + size[b]: tokens [B, L, TOKEN], episode, label and
    valid [B, L]."""
    shape = (len(first), int(size.max()))
    tokens = np.zeros(shape + (TOKEN,), dtype=np.float32)
    episode, label, valid = np.zeros(shape, np.int64), np.zeros(shape, np.int64), np.zeros(shape, dtype=bool)
    for row, (start, n) in enumerate(zip(first.tolist(), size.tolist())):
        frames = slice(start, start + n)
        tokens[row, :n], episode[row, :n], label[row, :n] = data.tokens[frames], data.episode[frames], data.label[frames]
        valid[row, :n] = True
    return tuple(torch.as_tensor(a) for a in (tokens, episode, label, valid))


class DPTVectorAgent(TransformerLanes):
    """Plays a DPT checkpoint on many lanes at once under the evaluation protocol (SPEC section 6): per lane a
    KV cache of its pair's tokens so far and the previous transition (`causal_transformer.TransformerLanes`)."""

    def __init__(self, checkpoint: str | Path, num_lanes: int = 1, seed: int | str = 0,
                 greedy: bool | str = False) -> None:
        self.settings, model = load_for_play(checkpoint, Settings, make_model)
        super().__init__(model, int(num_lanes), int(seed), truthy(greedy))


def DPTAgent(checkpoint: str | Path, seed: int | str = 0, greedy: bool | str = False) -> SingleLane:
    """A one-lane DPT agent (the protocol's `Agent`): lane 0 of a `DPTVectorAgent`."""
    return SingleLane(DPTVectorAgent(checkpoint, 1, seed, greedy))


def settings_from(values: dict[str, Any], base: Settings | None = None) -> Settings:
    """Settings with some fields replaced (names checked); the suite is the dataset's when one is named."""
    return offline_settings(Settings, values, base, "DPT")


def write_submission(out: Path, command: str, settings: Settings) -> list[Path]:
    """Make the run folder a submission: agent.py (plays checkpoint.pt) and a README with the command."""
    return write_submission_files(out, command, settings, "dpt", "DPT", "DPTVectorAgent",
                                  "DPT (a causal transformer trained offline on a training dataset's exact optimal "
                                  "actions; `mewa_bench/agents/dpt.py`).")


def train_run(settings: Settings, folder: Path, resume: bool, command: str,
              progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> list[Path]:
    """Train one seed into `folder` and make it a submission; the files written."""
    checkpoint = train(settings, folder, resume, progress=progress)
    return [checkpoint, folder / METRICS, *write_submission(folder, command, settings)]
