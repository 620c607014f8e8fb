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
- Model: a pre-norm causal transformer without position embeddings: the context is a set of
  transitions, as in the paper.
- Training: cross-entropy against the optimal labels on every frame of a span of up to
  2 x `context` tokens of each of `batch` meta-episodes, ending at a frame drawn uniformly, with
  the attention of every token limited to its last `context` tokens, as when playing; AdamW;
  `total_steps` counts spans (meta-episodes) seen. Deterministic for a given seed on one machine
  (torch's CPU kernels, one thread); a resumed run draws its spans afresh from the seed and its
  update, so it is not the bytes of an uninterrupted one.
- Playing: each lane keeps the keys and values of its last `context` tokens per layer (a ring
  buffer: without position embeddings their order does not matter; as in any sliding-window
  cache, the states of a deeper layer were made when those tokens saw their own last `context`),
  so a step costs one token's pass; the action is sampled from the predicted distribution with the lane's generator
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

from mewa_bench.agents.lanes import LaneGenerators, pick_actions, truthy
from mewa_bench.agents.training_io import (CHECKPOINT, METRICS, fit_labels, load_for_play, offline_settings,
                                           restore, resumed, torch_module)
from mewa_bench.agents.training_io import write_submission as write_submission_files
from mewa_bench.protocol.agent import SingleLane, state_vector

__all__ = ["CHECKPOINT", "METRICS", "DPTAgent", "DPTVectorAgent", "Sequences", "Settings", "STEP_UNIT",
           "dataset_sequences", "make_tokens", "settings_from", "sequences_from_frames", "train", "train_job", "train_run"]

STEP_UNIT = "meta-episodes"  # what `total_steps` counts (`train --steps`)
OBS_SCALE = 8.0  # the 18 env floats are block counts up to about 8; the rest is already in [-1, 1]
OBS = 18
TOKEN = 2 * OBS + 4 + 2  # observation, previous observation, previous action one-hot, previous reward, new episode
EPISODES = 10  # episode-index embeddings (later episodes share the last one)
ACTIONS = 4


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


def make_tokens(obs: np.ndarray, previous_obs: np.ndarray, previous_action: np.ndarray, previous_reward: np.ndarray,
                new_episode: np.ndarray) -> np.ndarray:
    """Tokens float32 [n, TOKEN] (the observations scaled by OBS_SCALE); a previous action of -1: none."""
    tokens = np.zeros((len(obs), TOKEN), dtype=np.float32)
    tokens[:, :OBS], tokens[:, OBS:2 * OBS] = np.asarray(obs) / OBS_SCALE, np.asarray(previous_obs) / OBS_SCALE
    rows = np.flatnonzero(np.asarray(previous_action) >= 0)
    tokens[rows, 2 * OBS + np.asarray(previous_action)[rows]] = 1.0
    tokens[:, -2], tokens[:, -1] = previous_reward, new_episode
    return tokens


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
    """The causal transformer: token and episode embeddings, `layers` pre-norm blocks, an action head."""
    torch = _torch()
    nn = torch.nn
    d, heads = settings.d_model, settings.heads

    class Block(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.norm1, self.norm2 = nn.LayerNorm(d), nn.LayerNorm(d)
            self.qkv, self.out = nn.Linear(d, 3 * d), nn.Linear(d, d)
            self.mlp = nn.Sequential(nn.Linear(d, 4 * d), nn.GELU(), nn.Linear(4 * d, d))

        def split(self, x: Any) -> tuple[Any, Any, Any]:
            """Queries, keys and values [B, heads, L, d / heads] of x [B, L, d]."""
            q, k, v = self.qkv(self.norm1(x)).chunk(3, dim=-1)
            shape = (x.shape[0], x.shape[1], heads, d // heads)
            return tuple(t.reshape(shape).transpose(1, 2) for t in (q, k, v))

        def attend(self, x: Any, q: Any, k: Any, v: Any, mask: Any) -> Any:
            """x + attention(q over k, v; `mask` True where allowed) + MLP."""
            attended = torch.nn.functional.scaled_dot_product_attention(q, k, v, attn_mask=mask)
            x = x + self.out(attended.transpose(1, 2).reshape(x.shape))
            return x + self.mlp(self.norm2(x))

    class DPT(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.embed, self.episode = nn.Linear(TOKEN, d), nn.Embedding(EPISODES, d)
            self.blocks = nn.ModuleList(Block() for _ in range(settings.layers))
            self.norm, self.head = nn.LayerNorm(d), nn.Linear(d, ACTIONS)

        def inputs(self, tokens: Any, episode: Any) -> Any:
            return self.embed(tokens) + self.episode(episode)

        def forward(self, tokens: Any, episode: Any, valid: Any) -> Any:
            """Logits [B, L, 4] for whole sequences (tokens [B, L, TOKEN], episode [B, L], valid [B, L] bool),
            each token attending to itself and the `context` - 1 tokens before it (as a lane's cache holds)."""
            x = self.inputs(tokens, episode)
            length = x.shape[1]
            window = torch.ones(length, length, dtype=torch.bool).tril().triu(-(settings.context - 1))
            mask = window[None, None] & valid[:, None, None, :]
            for block in self.blocks:
                x = block.attend(x, *block.split(x), mask)
            return self.head(self.norm(x))

        def step(self, tokens: Any, episode: Any, cache: list[tuple[Any, Any]], lanes: Any, lengths: Any) -> Any:
            """Logits [n, 4] for one new token of each of `lanes`, which has seen lengths[i] tokens before; `cache`
            holds per layer the keys and values of each lane's last ones ([lanes, heads, context, d / heads], a
            ring buffer); the new ones are added."""
            x = self.inputs(tokens, episode)[:, None, :]
            capacity = cache[0][0].shape[2]
            span = min(int(lengths.max()) + 1, capacity)
            allowed = (torch.arange(span)[None, :] <= lengths[:, None])[:, None, None, :]  # [n, 1, 1, span]
            slot = lengths % capacity
            for block, (keys, values) in zip(self.blocks, cache):
                q, k, v = block.split(x)
                keys[lanes, :, slot], values[lanes, :, slot] = k[:, :, 0], v[:, :, 0]
                x = block.attend(x, q, keys[lanes, :, :span], values[lanes, :, :span], allowed)
            return self.head(self.norm(x[:, 0]))

    return DPT()


def train(settings: Settings, out: Path, resume: bool = False, data: Sequences | None = None,
          progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> Path:
    """Train (or resume) a run in `out` on `data` (default: the settings' dataset); the checkpoint path."""
    torch = _torch()

    torch.set_num_threads(1)
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


class DPTVectorAgent:
    """Plays a DPT checkpoint on many lanes at once under the evaluation protocol (SPEC section 6): per lane a
    KV cache of its pair's tokens so far and the previous action, reward and new-episode flag."""

    def __init__(self, checkpoint: str | Path, num_lanes: int = 1, seed: int | str = 0,
                 greedy: bool | str = False) -> None:
        torch = _torch()
        self.settings, self.model = load_for_play(checkpoint, Settings, make_model)
        self.greedy, self.generators = truthy(greedy), LaneGenerators(int(seed), int(num_lanes))
        self.lengths = np.zeros(num_lanes, dtype=np.int64)
        self.previous_action = np.full(num_lanes, -1, dtype=np.int64)
        self.previous_reward = np.zeros(num_lanes)
        self.previous_obs = np.zeros((num_lanes, OBS))
        self.new_episode = np.zeros(num_lanes, dtype=np.float32)
        self.episode = np.zeros(num_lanes, dtype=np.int64)
        s = self.settings
        shape = (int(num_lanes), s.heads, s.context, s.d_model // s.heads)
        self.cache = [(torch.zeros(shape, dtype=torch.float64), torch.zeros(shape, dtype=torch.float64))
                      for _ in range(s.layers)]

    def reset_task(self, lanes: np.ndarray, seeds: np.ndarray) -> None:
        """New pairs: an empty context, no previous action."""
        self.generators.reset(lanes, seeds)
        self.lengths[lanes], self.previous_action[lanes], self.previous_reward[lanes] = 0, -1, 0.0
        self.previous_obs[lanes] = 0.0
        self.new_episode[lanes], self.episode[lanes] = 0.0, 0

    def act(self, lanes: np.ndarray, observations: Any) -> np.ndarray:
        """The model's actions for `lanes`, its context each lane's tokens so far."""
        torch = _torch()
        tokens = make_tokens(state_vector(observations), self.previous_obs[lanes], self.previous_action[lanes],
                             self.previous_reward[lanes], self.new_episode[lanes])
        with torch.no_grad():
            logits = self.model.step(torch.as_tensor(tokens, dtype=torch.float64),
                                     torch.as_tensor(np.minimum(self.episode[lanes], EPISODES - 1)), self.cache,
                                     torch.as_tensor(lanes), torch.as_tensor(self.lengths[lanes]))
            probs = torch.softmax(logits, dim=1).numpy()
        self.lengths[lanes] += 1
        self.new_episode[lanes] = 0.0
        return pick_actions(probs, lanes, self.generators, self.greedy)

    def observe(self, lanes: np.ndarray, transitions: Any) -> None:
        """Remember each lane's last action and reward for its next token."""
        self.previous_obs[lanes] = state_vector(transitions.obs)
        self.previous_action[lanes] = transitions.action
        self.previous_reward[lanes] = transitions.reward

    def end_episode(self, lanes: np.ndarray) -> None:
        """The next token of these lanes starts their pair's next episode."""
        self.new_episode[lanes] = 1.0
        self.episode[lanes] += 1


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


def train_job(job: tuple[Settings, Path, bool, str]) -> list[Path]:
    """`train_run` for one (settings, folder, resume, command): a unit of work for a Ray task."""
    return train_run(*job)
