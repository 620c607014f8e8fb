"""Which public task an agent is in, inferred from what it observes (for agents that are not told).

An agent may know the tasks listed in the suite files (the public task distribution) but never which
one it faces. `TaskBelief` keeps the listed tasks that are consistent with every observed step: the
first observation fixes the colours, K and the worker's blocks; rewards, completions and returned
structures then reveal M and the sub-goal order. Used by the shipped reference agents.

Checking a step is a look-up in the task's transition table (`mewa_bench.game.table`), found by the
bytes of the float32 observation; anything the table cannot answer exactly (an observation of no
reachable state, an action outside the palette) goes through the rules, with the same result.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from mewa_bench.design.suites import load_suite
from mewa_bench.game.palette import NUM_COLORS, OBS_SIZE
from mewa_bench.game.rules import (State, initial_state, is_terminal, observation, outcomes, state_from_observation,
                                   step_reward)
from mewa_bench.game.table import transition_table
from mewa_bench.game.task import Task
from mewa_bench.protocol.agent import Transition, state_vector

REWARD_TOLERANCE = 1e-6


class Explanation(NamedTuple):
    """How a task's rules produce an observed step: the mistake type at stake (-1: none), and if one happened."""

    mistake_type: int
    mistaken: bool


def starts_like(task: Task, obs: np.ndarray) -> bool:
    """True if `obs` is the first observation of an episode of `task`."""
    return bool(np.array_equal(observation(task, initial_state(task)), obs))


class StateLookup(NamedTuple):
    """A task's reachable states indexed by the bytes of their observations, with their table rows as lists."""

    by_obs: dict[bytes, int]  # observation bytes -> state index
    states: tuple[State, ...]
    next_ok: list[list[int]]  # [S][4]
    next_mistake: list[list[int]]
    mistake_type: list[list[int]]
    obs: np.ndarray  # float32 [S, 18]
    reward: list[float]
    terminal: list[bool]

    def find(self, obs: np.ndarray) -> int | None:
        """The index of the state whose observation is exactly `obs` (a float32[18]), or None."""
        if obs.dtype != np.float32 or obs.shape != (OBS_SIZE,):
            return None
        return self.by_obs.get(obs.tobytes())


def build_state_lookup(task: Task) -> StateLookup | None:
    """The task's state look-up, or None unless `state_from_observation` inverts every state's observation."""
    table = transition_table(task)
    if any(state_from_observation(task, row) != state for row, state in zip(table.obs, table.states)):
        return None  # then observations may not name states: leave every check to the rules
    by_obs = {row.tobytes(): index for index, row in enumerate(table.obs)}
    return StateLookup(by_obs, table.states, table.next_ok.tolist(), table.next_mistake.tolist(),
                       table.mistake_type.tolist(), table.obs, table.reward.tolist(), table.terminal.tolist())


_LOOKUPS: dict[tuple, StateLookup | None] = {}


def state_lookup(task: Task) -> StateLookup | None:
    """The (cached) state look-up of a task; tasks with the same rules share one."""
    key = task.key()
    if key not in _LOOKUPS:
        _LOOKUPS[key] = build_state_lookup(task)
    return _LOOKUPS[key]


def observed_state(task: Task, obs: np.ndarray) -> State:
    """`state_from_observation(task, obs)`, by look-up when `obs` is the observation of a reachable state."""
    lookup = state_lookup(task)
    index = None if lookup is None else lookup.find(obs)
    return state_from_observation(task, obs) if index is None else lookup.states[index]


def explain(task: Task, transition: Transition) -> Explanation | None:
    """How `task`'s rules produce `transition`, or None if they cannot (for any worker)."""
    obs = state_vector(transition.obs)
    next_obs = state_vector(transition.next_obs)
    lookup = state_lookup(task)
    index = None if lookup is None else lookup.find(obs)
    if index is None:
        return explain_by_rules(task, obs, next_obs, transition)
    if lookup.terminal[index]:
        return None
    action = int(transition.action)
    if not 0 <= action < NUM_COLORS:  # a no-op the table does not list
        return explain_by_rules(task, obs, next_obs, transition)
    return explain_by_table(lookup, index, action, next_obs, transition)


def explain_by_table(lookup: StateLookup, index: int, action: int, next_obs: np.ndarray,
                     transition: Transition) -> Explanation | None:
    """`explain` for a non-terminal reachable state `index` and a palette action, read off the table."""
    mistake_type = lookup.mistake_type[index][action]
    branches = [(lookup.next_ok[index][action], False)]
    if mistake_type >= 0:
        branches.append((lookup.next_mistake[index][action], True))
    next_index = lookup.find(next_obs)
    for reached, mistaken in branches:
        same_obs = (reached == next_index if next_index is not None
                    else np.array_equal(lookup.obs[reached], next_obs))
        if (same_obs and bool(transition.terminated) == lookup.terminal[reached]
                and abs(lookup.reward[reached] - float(transition.reward)) <= REWARD_TOLERANCE):
            return Explanation(mistake_type, mistaken)
    return None


def explain_by_rules(task: Task, obs: np.ndarray, next_obs: np.ndarray, transition: Transition) -> Explanation | None:
    """`explain` from the rules alone, given the transition's float32 observations."""
    state = state_from_observation(task, obs)
    if is_terminal(task, state) or not np.array_equal(observation(task, state), obs):
        return None
    result = outcomes(task, state, int(transition.action))
    branches = [(result.ok, False)] + ([(result.mistake, True)] if result.mistake is not None else [])
    for reached, mistaken in branches:
        if (np.array_equal(observation(task, reached), next_obs)
                and bool(transition.terminated) == is_terminal(task, reached)
                and abs(step_reward(task, reached) - float(transition.reward)) <= REWARD_TOLERANCE):
            return Explanation(result.mistake_type, mistaken)
    return None


def public_tasks(suites: str) -> list[Task]:
    """The tasks listed in the given suites (comma-separated names or paths), each task once."""
    tasks: dict[tuple, Task] = {}
    for name in suites.split(","):
        for task in load_suite(name.strip()).tasks:
            tasks.setdefault((task.key(), task.average_worker), task)
    return list(tasks.values())


class TaskBelief:
    """The known tasks still consistent with everything observed since `reset()`, in their given order."""

    def __init__(self, tasks: Sequence[Task]) -> None:
        self.tasks = tuple(tasks)
        self.candidates = list(self.tasks)

    def reset(self) -> None:
        """A new pair: every task is possible again."""
        self.candidates = list(self.tasks)

    def start_episode(self, obs: np.ndarray) -> None:
        """Keep the candidates whose episodes start with `obs`."""
        self.candidates = [task for task in self.candidates if starts_like(task, obs)]

    def update(self, transition: Transition) -> Explanation | None:
        """Drop the candidates that cannot produce `transition`; the explanation of the first one left."""
        explained = [(task, explain(task, transition)) for task in self.candidates]
        self.candidates = [task for task, why in explained if why is not None]
        return next((why for _, why in explained if why is not None), None)

    @property
    def task(self) -> Task | None:
        """The task acted for: the first candidate left (None if no known task explains what was seen)."""
        return self.candidates[0] if self.candidates else None
