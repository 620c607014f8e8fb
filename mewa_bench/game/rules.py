"""The MEWA rules, one step at a time (SPEC section 2). The single definition of the game.

A game state is a plain tuple of 17 ints, so that it can be hashed and enumerated:
`(agent[4], structure[4], mistake[4], completed[4], progress)`, indexed by palette colour.
Everything faster (the transition table, the batched env, the exact engine) is built from
`outcomes()` below.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from mewa_bench.game.palette import (NUM_COLORS, OBS_AGENT_BLOCKS, OBS_COMPLETED, OBS_MISTAKE_FLAGS, OBS_SIZE,
                                      OBS_STRUCTURE_BLOCKS, OBS_WORKER_LEFT, OBS_WORKER_PLACED)
from mewa_bench.game.task import Task

State = tuple[int, ...]

AGENT = 0  # offsets of the four per-colour groups inside a State
STRUCT = NUM_COLORS
FLAG = 2 * NUM_COLORS
DONE = 3 * NUM_COLORS
PROGRESS = 4 * NUM_COLORS
STATE_SIZE = PROGRESS + 1


class Event(NamedTuple):
    """Something that happened during a step, reported in the env's `info["events"]`.

    kind: "mistake" (value = mistake type x), "structure_completed", "structure_returned"
    (value = blocks given back), or "subgoal_reached" (value = sub-goal index; `color` is its colour).
    """

    kind: str
    color: int
    value: int

    def to_dict(self) -> dict[str, int | str]:
        """JSON-ready form."""
        return {"kind": self.kind, "color": self.color, "value": self.value}


class Outcomes(NamedTuple):
    """What one action can lead to: `ok` always; `mistake` with probability w[mistake_type].

    When the action cannot cause a mistake, `mistake_type` is -1 and `mistake` is None.
    """

    ok: State
    ok_events: tuple[Event, ...]
    mistake_type: int
    mistake: State | None
    mistake_events: tuple[Event, ...]


def initial_state(task: Task) -> State:
    """The state at reset: K blocks of each used colour, everything else empty."""
    s = [0] * STATE_SIZE
    for c in task.colors:
        s[AGENT + c] = task.K
    return tuple(s)


def progress(state: State) -> int:
    """Number of sub-goals reached so far."""
    return state[PROGRESS]


def is_terminal(task: Task, state: State) -> bool:
    """True once every sub-goal is reached."""
    return state[PROGRESS] == task.N


def step_reward(task: Task, state: State) -> float:
    """Reward received on arriving in `state`: 0 when done, else the current sub-goal's reward."""
    p = state[PROGRESS]
    return 0.0 if p == task.N else task.rewards[p]


def _finish_structure(task: Task, s: list[int], a: int, events: list[Event]) -> None:
    """Apply rule 4 to structure `a`, which has just reached M blocks."""
    mistaken = s[FLAG + a] == 1
    s[STRUCT + a] = 0
    s[FLAG + a] = 0
    if mistaken:
        s[AGENT + a] += task.M
        events.append(Event("structure_returned", a, task.M))
        return
    s[DONE + a] = 1
    events.append(Event("structure_completed", a, 0))
    while s[PROGRESS] < task.N and s[DONE + task.order[s[PROGRESS]]] == 1:
        events.append(Event("subgoal_reached", task.order[s[PROGRESS]], s[PROGRESS]))
        s[PROGRESS] += 1


def outcomes(task: Task, state: State, action: int) -> Outcomes:
    """Both possible results of taking `action` in `state` (rules 1-4 of SPEC section 2)."""
    a = int(action)
    if state[PROGRESS] == task.N:
        raise ValueError("the episode is over: no action can be taken in a terminal state")
    if not 0 <= a < NUM_COLORS or a not in task.colors or state[AGENT + a] == 0:
        return Outcomes(state, (), -1, None, ())  # rule 1: a no-op that still costs a step
    s = list(state)
    s[AGENT + a] -= 1
    s[STRUCT + a] += 1
    x = -1
    if s[STRUCT + a] == 2:  # rule 3: the worker may make a mistake of type x
        x = sum(1 for c in range(NUM_COLORS) if s[STRUCT + c] >= 1) - 1
    branches = []
    for mistake in ((False, True) if x >= 0 else (False,)):
        b = list(s)
        events: list[Event] = []
        if mistake:
            b[FLAG + a] = 1
            events.append(Event("mistake", a, x))
        if b[STRUCT + a] == task.M:
            _finish_structure(task, b, a, events)
        branches.append((tuple(b), tuple(events)))
    if x < 0:
        return Outcomes(branches[0][0], branches[0][1], -1, None, ())
    return Outcomes(branches[0][0], branches[0][1], x, branches[1][0], branches[1][1])


def observation(task: Task, state: State) -> np.ndarray:
    """The float32[18] observation of a state."""
    obs = np.zeros(OBS_SIZE, dtype=np.float32)
    obs[OBS_AGENT_BLOCKS] = state[AGENT : AGENT + NUM_COLORS]
    obs[OBS_STRUCTURE_BLOCKS] = state[STRUCT : STRUCT + NUM_COLORS]
    obs[OBS_MISTAKE_FLAGS] = state[FLAG : FLAG + NUM_COLORS]
    obs[OBS_COMPLETED] = state[DONE : DONE + NUM_COLORS]
    placed = sum(task.worker_blocks[: state[PROGRESS]])
    obs[OBS_WORKER_LEFT] = sum(task.worker_blocks) - placed
    obs[OBS_WORKER_PLACED] = placed
    return obs


def state_from_observation(task: Task, obs: np.ndarray) -> State:
    """Invert `observation` (progress is recovered from the worker's placed blocks and completions)."""
    o = [int(round(float(v))) for v in obs]
    s = [0] * STATE_SIZE
    s[AGENT : AGENT + NUM_COLORS] = o[OBS_AGENT_BLOCKS]
    s[STRUCT : STRUCT + NUM_COLORS] = o[OBS_STRUCTURE_BLOCKS]
    s[FLAG : FLAG + NUM_COLORS] = o[OBS_MISTAKE_FLAGS]
    completed = o[OBS_COMPLETED]
    s[DONE : DONE + NUM_COLORS] = completed
    p = 0
    while p < task.N and completed[task.order[p]] == 1:
        p += 1
    s[PROGRESS] = p
    return tuple(s)
