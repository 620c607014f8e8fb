"""Trajectories of an evaluation run, as handed to log writers and dataset recorders (sinks).

The runner collects the steps of each (pair, seed) unit when sinks are attached and passes the
finished unit to every sink, in the parent process (also with --jobs), so sinks write while the
run progresses and never see a half-played unit.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass, field
from typing import Any, Protocol, Sequence

import numpy as np

from mewa_bench.game.rules import Event
from mewa_bench.protocol.agent import Transition, state_vector
from mewa_bench.protocol.results import PROTOCOL_VERSION


@dataclass(frozen=True)
class StepRecord:
    """One env step of an episode: the transition the agent was shown, and what the env reported beside it."""

    step: int  # 0-based within the episode
    transition: Transition  # observations are {"state", "image"} dicts in sapien mode
    progress: int  # sub-goals reached after the step
    events: tuple[Event, ...]

    @property
    def obs(self) -> np.ndarray:
        """float32[18] state before the action."""
        return state_vector(self.transition.obs)

    @property
    def next_obs(self) -> np.ndarray:
        """float32[18] state after the action."""
        return state_vector(self.transition.next_obs)

    @property
    def action(self) -> int:
        return self.transition.action

    @property
    def reward(self) -> float:
        return self.transition.reward

    @property
    def terminated(self) -> bool:
        return self.transition.terminated

    @property
    def truncated(self) -> bool:
        return self.transition.truncated

    @property
    def image(self) -> np.ndarray | None:
        """uint8[H, W, 3] camera image of `next_obs` in sapien mode, else None."""
        return self.transition.next_obs["image"] if isinstance(self.transition.next_obs, dict) else None


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
    protocol_version: int = PROTOCOL_VERSION  # how worker luck was drawn (protocol 2: coupled to the episode seed)
    extra: dict[str, Any] = field(default_factory=dict)


class TrajectorySink(Protocol):
    """Receives a run's trajectories unit by unit; `close()` must leave a valid file even if interrupted."""

    def start(self, run: RunInfo) -> None: ...

    def add_unit(self, unit: UnitRecord) -> None: ...

    def close(self) -> None: ...


_STOP = object()


class BackgroundSinks:
    """Feeds sinks from a background thread, in unit order, so writing logs overlaps playing.

    The runner spends most of an isolated run waiting for the agent process (with the GIL
    released), which is when this thread writes. `close()` drains every queued unit, closes every
    sink, and re-raises the first error a sink raised.
    """

    def __init__(self, sinks: Sequence[TrajectorySink]) -> None:
        self.sinks = list(sinks)
        self._queue: queue.Queue = queue.Queue(maxsize=8)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._work, name="mewa-sinks", daemon=True)
        self._started = False

    def start(self, run: RunInfo) -> None:
        """Start every sink (in the caller's thread, so a bad path fails at once), then the writer thread."""
        for started, sink in enumerate(self.sinks):
            try:
                sink.start(run)
            except BaseException:
                for earlier in self.sinks[:started]:  # leave no open file behind
                    earlier.close()
                raise
        self._thread.start()
        self._started = True

    def add_unit(self, unit: UnitRecord | None) -> None:
        """Queue a finished unit for every sink (None: trajectories were not collected, nothing to do)."""
        if unit is None or not self.sinks:
            return
        if self._error is not None:
            raise RuntimeError(f"a log/dataset sink failed: {self._error}") from self._error
        self._queue.put(unit)

    def _work(self) -> None:
        while (unit := self._queue.get()) is not _STOP:
            if self._error is None:
                try:
                    for sink in self.sinks:
                        sink.add_unit(unit)
                except BaseException as e:  # reported by add_unit / close in the runner's thread
                    self._error = e

    def close(self) -> None:
        """Write what is queued, close every sink, and raise a sink's error if there was one."""
        if self._started:
            self._queue.put(_STOP)
            self._thread.join()
            self._started = False
        errors = []
        for sink in self.sinks:
            try:
                sink.close()
            except BaseException as e:
                errors.append(e)
        if self._error is not None:
            raise RuntimeError(f"a log/dataset sink failed: {self._error}") from self._error
        if errors:
            raise errors[0]
