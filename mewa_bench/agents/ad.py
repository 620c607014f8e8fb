"""Algorithm Distillation (Laskin et al. 2022) on MEWA: a transformer that learns a learning algorithm from its
learning histories, offline.

One file, top to bottom: settings, the training windows (from a training dataset of `mewa-bench
datasets build`, by default a learning-histories tier), the supervised training loop, checkpoints, and
`ADVectorAgent`, which plays a checkpoint under the evaluation protocol.

- Data: a learning history is one meta-train worker faced for many episodes by a posterior-sampling learner
  that is told nothing of the worker (`datasets.learning_histories`): it improves episode by episode.
  Every window is `episodes` consecutive episodes of one history (the protocol's 10), starting at an
  episode drawn uniformly from 0..`max_start` (0: only the history's start, exactly what a pair's 10 episodes
  from scratch look like; larger: AD's across-the-history windows, whose earlier episodes the learner had
  already seen, so the model learns to improve faster than its context alone would justify). Several datasets
  of one suite pool their histories (`more_datasets`, `train ad --dataset A --dataset B`), e.g. a wide suite's
  own tasks and tasks its generator draws (`<suite>-train-generated-tasks`).
- Label: the learner's own action (`action`), a function of what it had seen; never the known-worker
  optimum (`optimal_action`, privileged: DPT's label) unless asked.
- Tokens and model: DPT's (`agents.causal_transformer`): per frame the observation and the whole previous
  transition, an episode-index embedding counted from the window's first episode, a pre-norm causal
  transformer without position embeddings. `context` (default 1,000 = 10 episodes of at most 100 steps)
  is at least a window's length, so every token attends to the whole window before it. `kv_heads` below
  `heads` shares each key/value head among several query heads: a step of play reads heads / kv_heads
  times fewer bytes of cache, which is what a step costs on a CPU.
- Colour renaming (`rename_colours`, off by default): the rules do not care which palette colour is which
  (`game.relabel`), so a history with its colours renamed is a history of the renamed task with the same
  worker. Each window is then seen under a renaming drawn with the run's generator: on a wide suite a model
  meets every colouring of the task structures (N, K, M, worker blocks) it is trained on, not only the
  colourings in its data.
- Training: cross-entropy on every frame of `batch` windows per update, drawn with the run's generator;
  AdamW; `total_steps` counts windows seen. Deterministic for its seed and `threads` on one machine
  (torch's CPU kernels on that many threads, one by default; another count sums in another order, so its
  bytes differ, as reproducibly). No environment interaction.
- Playing: `causal_transformer.TransformerLanes` (as DPT's agent): per lane a key/value cache allocated
  once, one token's pass per step for all lanes. Greedy by default (the most likely action), except that
  the first `sample_episodes` episodes of a pair sample from the predicted distribution with the lane's
  generator: a posterior-sampling learner's first choice carries no information, and its most likely
  action is the same on every pair, so sampling it is what lets the context tell the workers apart.

Learning test (tests/test_ad.py): trained on posterior-sampling histories on the two-worker task, it adapts in
context. Runs on the shipped suites: docs/baselines.md.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from mewa_bench.agents.causal_transformer import (EPISODES, OBS, TOKEN, TransformerLanes, make_tokens, make_transformer,
                                                  token_gather)
from mewa_bench.agents.lanes import truthy
from mewa_bench.agents.training_io import (CHECKPOINT, METRICS, fit_labels, load_for_play, offline_settings,
                                           restore, resumed, torch_module, torch_threads)
from mewa_bench.agents.training_io import write_submission as write_submission_files
from mewa_bench.game.relabel import renamings
from mewa_bench.protocol.agent import SingleLane

__all__ = ["ADAgent", "ADVectorAgent", "CHECKPOINT", "METRICS", "STEP_UNIT", "Settings", "Windows", "make_model",
           "pooled", "read_windows", "settings_from", "train", "train_run", "windows_from"]

STEP_UNIT = "windows"  # what `total_steps` counts (`train --steps`)
LABELS = ("action", "optimal_action")


@dataclass
class Settings:
    suite: str = "narrow-v2"  # the dataset's suite (checked against it)
    seed: int = 1
    total_steps: int = 32_000  # windows seen in training (STEP_UNIT)
    dataset: str = ""  # folder of a training dataset (mewa-bench datasets build NAME)
    more_datasets: list[str] = field(default_factory=list)  # further datasets of the suite, pooled (--dataset again)
    label: str = "action"  # what it predicts: the behaviour's actions, or optimal_action (privileged)
    episodes: int = 10  # episodes per window (a pair's 10)
    max_start: int = 0  # windows start at a history's episode 0..max_start
    batch: int = 16  # windows per update
    context: int = 1000  # tokens a lane's cache holds (and each token's attention span in training)
    d_model: int = 64
    layers: int = 2
    heads: int = 4
    kv_heads: int = 0  # key/value heads, each shared by heads / kv_heads query heads (0: one per query head)
    learning_rate: float = 1e-3
    anneal: bool = False  # the learning rate falls to 0 along a cosine over the run (false: constant)
    rename_colours: bool = False  # each window under a random renaming of the palette's colours (game.relabel)
    weight_decay: float = 0.01
    max_grad_norm: float = 1.0
    greedy: bool = True  # how the submission's agent.py plays: the most likely action (false: sampled)
    sample_episodes: int = 1  # when greedy: the first episodes of a pair that still sample
    checkpoint_every: int = 100  # updates
    threads: int = 1  # torch's CPU threads while training (a run is deterministic for its seed and this count)
    workers: list[list[float]] = field(default_factory=list)  # not used: the dataset decides the workers

    @property
    def steps_per_update(self) -> int:
        return self.batch


@dataclass(frozen=True)
class Windows:
    """Frames of whole sequences in play order, for cutting windows of episodes: tokens float32 [F, TOKEN] (their
    previous transition within the sequence), the episode index within the sequence and both labels int64 [F];
    `episode_starts` int64 [E + 1]: episode e is frames episode_starts[e]:episode_starts[e + 1]; sequence s is
    episodes first_episode[s]:first_episode[s + 1]."""

    tokens: np.ndarray
    episode: np.ndarray
    labels: dict[str, np.ndarray]
    episode_starts: np.ndarray
    first_episode: np.ndarray

    def __len__(self) -> int:
        return len(self.first_episode) - 1

    def episode_counts(self) -> np.ndarray:
        """Episodes of each sequence."""
        return np.diff(self.first_episode)


def windows_from(data: Any) -> Windows:
    """`Windows` of a `datasets.meta_episodes.SequenceFrames` (whole meta-episodes or learning histories)."""
    from mewa_bench.datasets.meta_episodes import previous_transition

    previous_action, previous_reward, new_episode, first = previous_transition(data)
    previous_obs = np.where(first[:, None], 0.0, np.r_[np.zeros((1, OBS)), data.observation[:-1]])
    tokens = make_tokens(data.observation, previous_obs, previous_action, previous_reward, new_episode)
    starts = np.flatnonzero(np.r_[True, (data.episode[1:] != data.episode[:-1]) | first[1:]])
    first_episode = np.searchsorted(starts, data.starts)
    return Windows(tokens, data.episode, {"action": data.action, "optimal_action": data.optimal_action},
                   np.r_[starts, len(tokens)].astype(np.int64), first_episode.astype(np.int64))


def pooled(parts: list[Windows]) -> Windows:
    """The sequences of several `Windows` as one, in order."""
    if len(parts) == 1:
        return parts[0]
    frames = np.cumsum([0] + [len(p.tokens) for p in parts[:-1]])
    episodes = np.cumsum([0] + [len(p.episode_starts) - 1 for p in parts[:-1]])
    return Windows(np.concatenate([p.tokens for p in parts]), np.concatenate([p.episode for p in parts]),
                   {k: np.concatenate([p.labels[k] for p in parts]) for k in parts[0].labels},
                   np.r_[np.concatenate([p.episode_starts[:-1] + f for p, f in zip(parts, frames)]),
                         frames[-1] + len(parts[-1].tokens)].astype(np.int64),
                   np.r_[np.concatenate([p.first_episode[:-1] + e for p, e in zip(parts, episodes)]),
                         episodes[-1] + len(parts[-1].episode_starts) - 1].astype(np.int64))


def read_windows(settings: Settings) -> Windows:
    """The windows of the settings' datasets (their histories pooled), cut where a window can reach."""
    from mewa_bench.datasets.meta_episodes import first_episodes, read_sequences

    if not settings.dataset:
        raise ValueError("AD learns from a training dataset: give --dataset (a folder that `mewa-bench datasets "
                         "build NAME` wrote, e.g. narrow-v2-train-learning-histories)")
    reach = settings.max_start + settings.episodes
    return pooled([windows_from(first_episodes(read_sequences(folder, "meta-episode", settings.suite), reach))
                   for folder in (settings.dataset, *settings.more_datasets)])


def make_model(settings: Settings) -> Any:
    """The causal transformer (`agents.causal_transformer`), as DPT's."""
    return make_transformer(settings.d_model, settings.heads, settings.layers, settings.context,
                            kv_heads=settings.kv_heads)


def _torch() -> Any:
    return torch_module("the AD baseline")


def window_batch(data: Windows, sequences: np.ndarray, first: np.ndarray, episodes: int, label: str,
                 renamed: np.ndarray | None = None) -> tuple[Any, Any, Any, Any]:
    """Padded tensors of the windows of `episodes` episodes of `sequences` starting at their episode `first`: tokens
    [B, L, TOKEN] (each window's first token without a previous transition, as a pair's first), episode (counted
    from the window's first), label and valid [B, L]; window b with colour c renamed renamed[b, c] if given."""
    torch = _torch()
    begin_episode = data.first_episode[sequences] + first
    end_episode = np.minimum(begin_episode + episodes, data.first_episode[sequences + 1])
    begin, end = data.episode_starts[begin_episode], data.episode_starts[end_episode]
    shape = (len(sequences), int((end - begin).max()))
    tokens = np.zeros(shape + (TOKEN,), dtype=np.float32)
    episode, target, valid = np.zeros(shape, np.int64), np.zeros(shape, np.int64), np.zeros(shape, dtype=bool)
    for row, (b, e, e0) in enumerate(zip(begin.tolist(), end.tolist(), first.tolist())):
        n = e - b
        tokens[row, :n] = data.tokens[b:e]
        tokens[row, 0, OBS:] = 0.0  # no previous transition: the window is a fresh context
        episode[row, :n] = np.minimum(data.episode[b:e] - e0, EPISODES - 1)
        target[row, :n], valid[row, :n] = data.labels[label][b:e], True
        if renamed is not None:
            tokens[row, :n] = tokens[row, :n][:, token_gather(renamed[row])]
            target[row, :n] = renamed[row][target[row, :n]]
    return tuple(torch.as_tensor(a) for a in (tokens, episode, target, valid))


def train(settings: Settings, out: Path, resume: bool = False, data: Windows | None = None,
          progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> Path:
    """Train (or resume) a run in `out` on `data` (default: the settings' datasets' sequences); the checkpoint
    path."""
    if settings.label not in LABELS:
        raise ValueError(f"label {settings.label!r}: expected one of {', '.join(LABELS)}")
    with torch_threads(settings.threads):
        _fit(settings, out, resume, data, progress)
    return out / CHECKPOINT


def _fit(settings: Settings, out: Path, resume: bool, data: Windows | None,
         progress: Callable[[int, int, dict[str, float]], None]) -> None:
    """The training loop of `train`, on torch's threads as they are set."""
    torch = _torch()
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(settings.seed)
    state = resumed(out, settings, resume)
    model = make_model(settings)
    optimizer = torch.optim.AdamW(model.parameters(), lr=settings.learning_rate, weight_decay=settings.weight_decay)
    start_update = 0 if state is None else restore(out, state, model, {"optimizer": optimizer})
    data = read_windows(settings) if data is None else data
    latest = np.minimum(settings.max_start, np.maximum(data.episode_counts() - settings.episodes, 0))
    updates = settings.total_steps // settings.steps_per_update
    rng = np.random.default_rng([settings.seed, start_update])
    for update in range(start_update, updates):
        began = time.perf_counter()
        sequences = rng.choice(len(data), size=settings.batch, replace=len(data) < settings.batch)
        first = rng.integers(0, latest[sequences] + 1)
        renamed = renamings(rng, settings.batch) if settings.rename_colours else None
        tokens, episode, label, valid = window_batch(data, sequences, first, settings.episodes, settings.label, renamed)
        if settings.anneal:
            for group in optimizer.param_groups:
                group["lr"] = settings.learning_rate * 0.5 * (1.0 + np.cos(np.pi * update / updates))
        logits = model(tokens, episode, valid)
        fit_labels(model, optimizer, logits, label, valid, settings, update, updates, began, out, progress)


class ADVectorAgent(TransformerLanes):
    """Plays an AD checkpoint on many lanes at once under the evaluation protocol (SPEC section 6): per lane a
    key/value cache of its pair's tokens so far and the previous transition (`causal_transformer.TransformerLanes`)."""

    def __init__(self, checkpoint: str | Path, num_lanes: int = 1, seed: int | str = 0, greedy: bool | str = False,
                 sample_episodes: int | str | None = None) -> None:
        self.settings, model = load_for_play(checkpoint, Settings, make_model)
        s = self.settings
        sample = s.sample_episodes if sample_episodes is None else int(sample_episodes)
        super().__init__(model, int(num_lanes), int(seed), truthy(greedy), sample)


def ADAgent(checkpoint: str | Path, seed: int | str = 0, greedy: bool | str = False) -> SingleLane:
    """A one-lane AD agent (the protocol's `Agent`): lane 0 of an `ADVectorAgent`."""
    return SingleLane(ADVectorAgent(checkpoint, 1, seed, greedy))


def settings_from(values: dict[str, Any], base: Settings | None = None) -> Settings:
    """Settings with some fields replaced (names checked); the suite is the dataset's when one is named."""
    return offline_settings(Settings, values, base, "AD")


def write_submission(out: Path, command: str, settings: Settings) -> list[Path]:
    """Make the run folder a submission: agent.py (plays checkpoint.pt) and a README with the command."""
    return write_submission_files(out, command, settings, "ad", "AD", "ADVectorAgent",
                                  "AD (Algorithm Distillation: a causal transformer trained offline to continue a "
                                  f"training dataset's learning histories, predicting their `{settings.label}` labels; "
                                  "`mewa_bench/agents/ad.py`).", settings.greedy)


def train_run(settings: Settings, folder: Path, resume: bool, command: str,
              progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> list[Path]:
    """Train one seed into `folder` and make it a submission; the files written."""
    checkpoint = train(settings, folder, resume, progress=progress)
    return [checkpoint, folder / METRICS, *write_submission(folder, command, settings)]
