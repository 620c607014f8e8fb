"""Imitation of an adaptive expert with the whole meta-episode in context: in-context adaptation from data alone.

One file, top to bottom: settings, the network, the supervised training loop over a training dataset
(`mewa-bench datasets build`), checkpoints, and `ImitationVectorAgent`, which plays a checkpoint under
the evaluation protocol.

- What it learns: the behaviour's own actions (`action`), not `optimal_action`. On the expert tier the
  behaviour is bayes-explorer, which is told neither task nor worker: its action at a frame depends only
  on what it has seen so far in the meta-episode, so a sequence model that sees the same history can
  copy it exactly, adaptation included. DPT's `optimal_action` labels are the known-worker optimum:
  privileged, so copying them from a history that does not determine the worker teaches at best to
  guess (posterior sampling over optimal policies), never to explore on purpose. On the learning-histories
  tier the behaviour is a posterior-sampling learner (also told nothing of the worker); its first 10
  episodes (`episodes`) are what a pair's 10 episodes from scratch look like.
- Inputs: per frame exactly what the recurrent agents see when they play (the observation, the previous
  action one-hot, the previous reward, the new-episode flag: `datasets.meta_episodes.lane_inputs`); the
  GRU's state starts from zero on a meta-episode's first frame and carries across its 10 episodes.
- Training: cross-entropy on every frame of `batch` whole meta-episodes per update, drawn uniformly with
  the run's generator; AdamW; `total_steps` counts meta-episodes seen. Deterministic for its seed on one
  machine (torch's CPU kernels, one thread). No environment interaction.
- Playing: `agents.lanes.RecurrentLanes` (as RL^2's agent), one GRU step per step for all lanes; the
  action is the most likely one (`greedy`, what a run's agent.py asks for when `Settings.greedy`) or one
  sampled from the predicted distribution with the lane's generator.

Learning test (tests/test_imitation.py): trained on posterior-sampling learners' play on the two-worker task
(256 histories, 300 updates), it adapts in context: adaptability +0.50 (its first episode suits one worker of
the two, its tenth both). Runs on the shipped suites: docs/baselines.md.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from mewa_bench.agents.lanes import RecurrentLanes, truthy
from mewa_bench.agents.training_io import (CHECKPOINT, METRICS, fit_labels, load_for_play, offline_settings,
                                           restore, resumed, torch_module, torch_threads)
from mewa_bench.agents.training_io import write_submission as write_submission_files
from mewa_bench.protocol.agent import SingleLane

__all__ = ["CHECKPOINT", "METRICS", "ImitationAgent", "ImitationVectorAgent", "STEP_UNIT", "Settings", "make_policy",
           "settings_from", "train", "train_run"]

STEP_UNIT = "meta-episodes"  # what `total_steps` counts (`train --steps`)
OBS_SCALE = 8.0  # the 18 env floats are block counts up to about 8; the rest is already in [-1, 1]
INPUTS = 24
ACTIONS = 4
LABELS = ("action", "optimal_action")


@dataclass
class Settings:
    suite: str = "narrow-v2"  # the dataset's suite (checked against it)
    seed: int = 1
    total_steps: int = 40_000  # meta-episodes seen in training (STEP_UNIT)
    dataset: str = ""  # folder of a training dataset (mewa-bench datasets build NAME)
    label: str = "action"  # what it imitates: the behaviour's actions, or optimal_action (privileged)
    episodes: int = 10  # the first episodes of each meta-episode it learns from (a learning history's 50: its first 10)
    batch: int = 32  # meta-episodes per update
    hidden: int = 128
    learning_rate: float = 1e-3
    weight_decay: float = 0.0
    max_grad_norm: float = 1.0
    greedy: bool = True  # how the submission's agent.py plays: the most likely action (false: sampled)
    checkpoint_every: int = 100  # updates
    workers: list[list[float]] = field(default_factory=list)  # not used: the dataset decides the workers

    @property
    def steps_per_update(self) -> int:
        return self.batch


def _torch() -> Any:
    return torch_module("the imitation baseline")


def make_policy(hidden: int) -> Any:
    """The network: an encoder, a GRU over the meta-episode and an action head."""
    torch = _torch()
    nn = torch.nn

    class ImitationPolicy(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.encoder = nn.Sequential(nn.Linear(INPUTS, hidden), nn.ReLU())
            self.gru = nn.GRU(hidden, hidden, batch_first=True)
            self.head = nn.Sequential(nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, ACTIONS))

        def encode(self, x: Any) -> Any:
            return self.encoder(torch.cat([x[..., :18] / OBS_SCALE, x[..., 18:]], dim=-1))

        def forward(self, x: Any) -> Any:
            """Logits [B, L, 4] for whole sequences x [B, L, 24] (each starting from a zero state)."""
            out, _ = self.gru(self.encode(x))
            return self.head(out)

        def step(self, x: Any, h: Any, reset: Any) -> tuple[Any, Any]:
            """One step for a batch of lanes: logits [n, 4] and the next state [n, H] (zero where `reset`)."""
            h = h * (~reset).unsqueeze(1)
            out, h = self.gru(self.encode(x)[:, None], h[None].contiguous())
            return self.head(out[:, 0]), h[0]

    return ImitationPolicy()


@torch_threads(1)
def train(settings: Settings, out: Path, resume: bool = False, data: Any = None,
          progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> Path:
    """Train (or resume) a run in `out` on `data` (a `MetaEpisodeDataset`; default: the settings' dataset's
    meta-episodes); the checkpoint path."""
    from mewa_bench.datasets.meta_episodes import MetaEpisodeDataset, pad_batch

    torch = _torch()
    if settings.label not in LABELS:
        raise ValueError(f"label {settings.label!r}: expected one of {', '.join(LABELS)}")
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(settings.seed)
    state = resumed(out, settings, resume)
    policy = make_policy(settings.hidden)
    optimizer = torch.optim.AdamW(policy.parameters(), lr=settings.learning_rate, weight_decay=settings.weight_decay)
    start_update = 0 if state is None else restore(out, state, policy, {"optimizer": optimizer})
    if data is None:
        if not settings.dataset:
            raise ValueError("imitation learns from a training dataset: give --dataset (a folder that `mewa-bench "
                             "datasets build NAME` wrote)")
        data = MetaEpisodeDataset(settings.dataset, suite=settings.suite, episodes=settings.episodes)
    updates = settings.total_steps // settings.steps_per_update
    rng = np.random.default_rng([settings.seed, start_update])
    for update in range(start_update, updates):
        began = time.perf_counter()
        chosen = rng.choice(len(data), size=settings.batch, replace=len(data) < settings.batch)
        batch = pad_batch([data[int(i)] for i in chosen])
        valid, label = batch["valid"], batch[settings.label]
        logits = policy(batch["inputs"])
        fit_labels(policy, optimizer, logits, label, valid, settings, update, updates, began, out, progress)
    return out / CHECKPOINT


class ImitationVectorAgent(RecurrentLanes):
    """Plays an imitation checkpoint on many lanes at once under the evaluation protocol (SPEC section 6): per lane
    the GRU state and the previous action, reward and new-episode flag (`agents.lanes.RecurrentLanes`)."""

    def __init__(self, checkpoint: str | Path, num_lanes: int = 1, seed: int | str = 0,
                 greedy: bool | str = False, sample_episodes: int | str = 0) -> None:
        self.settings, self.policy = load_for_play(checkpoint, Settings, lambda s: make_policy(s.hidden))
        super().__init__(self.policy.step, self.settings.hidden, int(num_lanes), int(seed), truthy(greedy),
                         int(sample_episodes))


def ImitationAgent(checkpoint: str | Path, seed: int | str = 0, greedy: bool | str = False) -> SingleLane:
    """A one-lane imitation agent (the protocol's `Agent`): lane 0 of an `ImitationVectorAgent`."""
    return SingleLane(ImitationVectorAgent(checkpoint, 1, seed, greedy))


def settings_from(values: dict[str, Any], base: Settings | None = None) -> Settings:
    """Settings with some fields replaced (names checked); the suite is the dataset's when one is named."""
    return offline_settings(Settings, values, base, "imitation")


def write_submission(out: Path, command: str, settings: Settings) -> list[Path]:
    """Make the run folder a submission: agent.py (plays checkpoint.pt) and a README with the command."""
    return write_submission_files(out, command, settings, "imitation", "Imitation", "ImitationVectorAgent",
                                  "Imitation (a GRU over whole meta-episodes trained offline to copy a training "
                                  f"dataset's `{settings.label}` labels; `mewa_bench/agents/imitation.py`).",
                                  settings.greedy)


def train_run(settings: Settings, folder: Path, resume: bool, command: str,
              progress: Callable[[int, int, dict[str, float]], None] = lambda steps, total, row: None) -> list[Path]:
    """Train one seed into `folder` and make it a submission; the files written."""
    checkpoint = train(settings, folder, resume, progress=progress)
    return [checkpoint, folder / METRICS, *write_submission(folder, command, settings)]
