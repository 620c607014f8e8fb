"""Transition table of a task: every reachable state enumerated once from `rules.outcomes`.

The state space of a task is small (about 4,000 states for the canonical task), so the envs and
the exact engine step by table look-up instead of re-running the rules. The table is built from
`rules.outcomes` and nothing else, so the rules have one definition.
"""

from __future__ import annotations

from dataclasses import dataclass
import numpy as np

from mewa_bench.game import rules
from mewa_bench.game.palette import NUM_COLORS, OBS_SIZE
from mewa_bench.game.rules import Event, State
from mewa_bench.game.task import Task


@dataclass(frozen=True)
class TransitionTable:
    """All reachable states of a task (index 0 is the initial state) and their transitions.

    For state s and action a: with probability 1 - w[mistake_type[s, a]] the next state is
    `next_ok[s, a]`, otherwise `next_mistake[s, a]`; `mistake_type[s, a] == -1` means no mistake
    is possible (then both next states are equal). Terminal states loop onto themselves.
    """

    task: Task
    states: tuple[State, ...]
    index: dict[State, int]
    next_ok: np.ndarray  # int32 [S, 4]
    next_mistake: np.ndarray  # int32 [S, 4]
    mistake_type: np.ndarray  # int8 [S, 4]
    events_ok: np.ndarray  # int32 [S, 4] -> row of `event_sets`
    events_mistake: np.ndarray  # int32 [S, 4]
    event_sets: tuple[tuple[Event, ...], ...]
    obs: np.ndarray  # float32 [S, 18], read-only
    reward: np.ndarray  # float64 [S]: reward on arriving in s
    terminal: np.ndarray  # bool [S]
    progress: np.ndarray  # int8 [S]

    @property
    def n_states(self) -> int:
        """Number of reachable states."""
        return len(self.states)


def _build(task: Task) -> TransitionTable:
    start = rules.initial_state(task)
    index: dict[State, int] = {start: 0}
    states: list[State] = [start]
    event_ids: dict[tuple[Event, ...], int] = {(): 0}
    rows_ok: list[list[int]] = []
    rows_bad: list[list[int]] = []
    rows_x: list[list[int]] = []
    rows_eok: list[list[int]] = []
    rows_ebad: list[list[int]] = []

    def intern(s: State) -> int:
        if s not in index:
            index[s] = len(states)
            states.append(s)
        return index[s]

    i = 0
    while i < len(states):  # breadth-first: `states` grows while we walk it
        s = states[i]
        if rules.is_terminal(task, s):
            rows_ok.append([i] * NUM_COLORS)
            rows_bad.append([i] * NUM_COLORS)
            rows_x.append([-1] * NUM_COLORS)
            rows_eok.append([0] * NUM_COLORS)
            rows_ebad.append([0] * NUM_COLORS)
        else:
            ok, bad, xs, eok, ebad = [], [], [], [], []
            for a in range(NUM_COLORS):
                out = rules.outcomes(task, s, a)
                ok.append(intern(out.ok))
                bad.append(intern(out.mistake) if out.mistake is not None else ok[-1])
                xs.append(out.mistake_type)
                eok.append(event_ids.setdefault(out.ok_events, len(event_ids)))
                ebad.append(event_ids.setdefault(out.mistake_events, len(event_ids)))
            rows_ok.append(ok)
            rows_bad.append(bad)
            rows_x.append(xs)
            rows_eok.append(eok)
            rows_ebad.append(ebad)
        i += 1

    obs = np.stack([rules.observation(task, s) for s in states]).astype(np.float32)
    obs.setflags(write=False)
    reward = np.array([rules.step_reward(task, s) for s in states], dtype=np.float64)
    terminal = np.array([rules.is_terminal(task, s) for s in states], dtype=bool)
    prog = np.array([rules.progress(s) for s in states], dtype=np.int8)
    event_sets = tuple(sorted(event_ids, key=event_ids.__getitem__))
    arrays = [np.array(r, dtype=np.int32) for r in (rows_ok, rows_bad)]
    for arr in (*arrays, reward, terminal, prog):
        arr.setflags(write=False)
    mtype = np.array(rows_x, dtype=np.int8)
    eok_arr = np.array(rows_eok, dtype=np.int32)
    ebad_arr = np.array(rows_ebad, dtype=np.int32)
    for arr in (mtype, eok_arr, ebad_arr):
        arr.setflags(write=False)
    assert obs.shape == (len(states), OBS_SIZE)
    return TransitionTable(task, tuple(states), index, arrays[0], arrays[1], mtype, eok_arr, ebad_arr,
                           event_sets, obs, reward, terminal, prog)


_CACHE: dict[tuple, TransitionTable] = {}


def transition_table(task: Task) -> TransitionTable:
    """The (cached) transition table of a task; tasks with the same rules share one table."""
    key = task.key()
    if key not in _CACHE:
        _CACHE[key] = _build(task)
    return _CACHE[key]
