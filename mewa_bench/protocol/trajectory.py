"""Trajectories of an evaluation run, as handed to log writers and dataset recorders (sinks).

The runner collects the steps of each (pair, seed) unit when sinks are attached and passes the
finished unit to every sink, in the parent process (also with --jobs), so sinks write while the
run progresses and never see a half-played unit.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from mewa_bench.game.rules import Event


@dataclass(frozen=True)
class StepRecord:
    """One env step of an episode."""

    step: int  # 0-based within the episode
    obs: np.ndarray  # float32[18], before the action
    action: int
    reward: float
    next_obs: np.ndarray
    terminated: bool
    truncated: bool
    progress: int  # sub-goals reached after the step
    events: tuple[Event, ...]
    image: np.ndarray | None = None  # uint8[H, W, 3] of `next_obs` in sapien mode


@dataclass(frozen=True)
class EpisodeRecord:
    """One episode of a unit, with its outcome."""

    episode: int  # 0-based within the pair
    env_seed: int
    steps: tuple[StepRecord, ...]
    episode_return: float
    normalised_return: float
    score: float  # normalised return / the pair's max-expected baseline
    first_image: np.ndarray | None = None  # image of the initial observation in sapien mode


@dataclass(frozen=True)
class UnitRecord:
    """All episodes of one (pair, seed) unit and the pair they were played on."""

    pair: int
    seed: int
    task_index: int
    task: dict[str, Any]  # Task.to_dict()
    worker: tuple[float, ...]
    episodes: tuple[EpisodeRecord, ...] = field(default_factory=tuple)


@dataclass(frozen=True)
class RunInfo:
    """What a sink records about the whole run (MCAP metadata, dataset info)."""

    agent: str
    agent_sha256: str
    suite: str
    suite_sha256: str
    seeds: tuple[int, ...]
    episodes_per_pair: int
    env_id: str
    env_version: str
    package_version: str
    mode: str = "vector"
    extra: dict[str, Any] = field(default_factory=dict)


class TrajectorySink(Protocol):
    """Receives a run's trajectories unit by unit; `close()` must leave a valid file even if interrupted."""

    def start(self, run: RunInfo) -> None: ...

    def add_unit(self, unit: UnitRecord) -> None: ...

    def close(self) -> None: ...
