"""Known-worker optimum (SPEC section 4): the best expected return when the worker is known.

Finite-horizon backward induction over every reachable game state and every action, batched over
workers: U_t(s) = r(s) + max_a [(1 - w_x) U_{t-1}(ok(s, a)) + w_x U_{t-1}(bad(s, a))], where r(s)
is the reward on arriving in s. Time-dependent Markov policies are optimal for a finite horizon,
so no history-dependent policy (a t-optimal policy with its counters, say) can do better.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from mewa_bench.design.exact import as_workers, structural_task
from mewa_bench.game.normalise import normalised_return
from mewa_bench.game.palette import NUM_COLORS
from mewa_bench.game.table import TransitionTable, transition_table
from mewa_bench.game.task import Task

CHUNK = 64  # workers per block: the [S * 4, W] action values of a block stay a few MB


def state_depths(table: TransitionTable) -> np.ndarray:
    """Fewest steps from the initial state to each state (breadth-first over all actions)."""
    depth = np.full(table.n_states, -1, dtype=np.int64)
    depth[0] = 0
    frontier = np.array([0])
    while len(frontier):
        reached = np.unique(np.concatenate([table.next_ok[frontier].ravel(), table.next_mistake[frontier].ravel()]))
        reached = reached[depth[reached] < 0]
        depth[reached] = depth[frontier[0]] + 1
        frontier = reached
    return depth


class _Layout(NamedTuple):
    """The table's state-action pairs as rows s * 4 + a, states sorted by depth."""

    ok: np.ndarray  # int64 [S * 4]: row of the state reached without a mistake
    bad: np.ndarray  # int64 [S * 4]: with a mistake
    branching: np.ndarray  # int64: rows where a mistake is possible
    mistake_type: np.ndarray  # int64: per branching row
    progress: np.ndarray  # int64 [S]: reward id of each state (N when terminal)
    active: np.ndarray  # int64 [T + 1]: states that can still be reached with t steps left


def _layout(table: TransitionTable, horizon: int) -> _Layout:
    """Reorder the table by depth so that the states needed at each step form a prefix."""
    depth = state_depths(table)
    order = np.argsort(depth, kind="stable")
    position = np.empty(table.n_states, dtype=np.int64)
    position[order] = np.arange(table.n_states)
    kind = table.mistake_type[order].ravel().astype(np.int64)
    branching = np.flatnonzero(kind >= 0)
    active = np.searchsorted(depth[order], horizon - np.arange(horizon + 1), side="right")
    return _Layout(position[table.next_ok[order]].ravel(), position[table.next_mistake[order]].ravel(),
                   branching, kind[branching], table.progress[order].astype(np.int64), active)


def _optimal_block(task: Task, layout: _Layout, workers: np.ndarray, actions: np.ndarray | None = None,
                   queries: tuple["_Queries", np.ndarray] | None = None) -> np.ndarray:
    """Optimal raw return from the initial state for a block of workers [Wc, N] -> [Wc].

    With `actions` ([T + 1, S] in layout order, one worker), also the optimal action of every
    state that can be reached with t steps left, in row t. With `queries` (points, out), the optimal
    action at each point (worker column, steps left, state) is written to `out`.
    """
    w_branch = workers.T[layout.mistake_type]
    arrival = np.append(np.asarray(task.rewards, dtype=np.float64), 0.0)[layout.progress][:, None]
    after = np.repeat(arrival, len(workers), axis=1)  # arrival reward + V_t, here t = 0
    value = np.zeros_like(after)
    for t in range(1, task.T + 1):
        n_active = layout.active[t]
        rows = n_active * NUM_COLORS
        nb = np.searchsorted(layout.branching, rows)
        branching = layout.branching[:nb]
        q = after[layout.ok[:rows]]
        gap = after[layout.bad[branching]] - q[branching]
        gap *= w_branch[:nb]
        q[branching] += gap
        if actions is not None:
            actions[t, :n_active] = np.argmax(q.reshape(n_active, NUM_COLORS), axis=1)
        if queries is not None and queries[0].bounds[t] < queries[0].bounds[t + 1]:
            points, out = queries
            here = slice(points.bounds[t], points.bounds[t + 1])
            chosen = q.reshape(n_active, NUM_COLORS, -1)[points.position[here], :, points.worker[here]]  # [n, 4]
            out[points.order[here]] = np.argmax(chosen, axis=1)  # ties: the lowest action
        np.max(q.reshape(n_active, NUM_COLORS, -1), axis=1, out=value[:n_active])
        np.add(value[:n_active], arrival[:n_active], out=after[:n_active])
    return value[0]  # the initial state is the only state at depth 0


def optimal_actions(task: Task, worker: np.ndarray | Sequence[float]) -> np.ndarray:
    """The known-worker optimal policy: action [T + 1, S] by steps left and table state (ties: lowest action)."""
    arr = as_workers([worker], task.N)
    table = transition_table(structural_task(task))
    layout = _layout(table, task.T)
    by_position = np.zeros((task.T + 1, table.n_states), dtype=np.int8)
    _optimal_block(task, layout, arr, by_position)
    order = np.argsort(state_depths(table), kind="stable")  # layout position -> table state
    out = np.empty_like(by_position)
    out[:, order] = by_position
    return out


def optimal_actions_at(task: Task, workers: np.ndarray | Sequence, owner: np.ndarray, steps_left: np.ndarray,
                       state: np.ndarray, chunk: int = CHUNK) -> tuple[np.ndarray, np.ndarray]:
    """The known-worker optimal action at many (worker, steps left, table state) points, vectorised over
    workers: `owner[i]` is the worker row of point i. Returns (actions int64 [Q], ties: the lowest action;
    optimal raw returns float64 [W]). Each point must be reachable with its steps left (at most
    T - steps_left steps from the start), as every state an episode visits is."""
    arr = as_workers(workers, task.N)
    table = transition_table(structural_task(task))
    layout = _layout(table, task.T)
    position = np.empty(table.n_states, dtype=np.int64)
    position[np.argsort(state_depths(table), kind="stable")] = np.arange(table.n_states)
    owner, steps_left = np.asarray(owner, dtype=np.int64), np.asarray(steps_left, dtype=np.int64)
    if len(owner) and (steps_left.min() < 1 or steps_left.max() > task.T):
        raise ValueError(f"steps left must lie in 1..{task.T}")
    out = np.zeros(len(owner), dtype=np.int64)
    raw = np.zeros(len(arr))
    by_owner = np.argsort(owner, kind="stable")
    edges = np.searchsorted(owner[by_owner], np.arange(0, len(arr) + chunk, chunk))
    for b, start in enumerate(range(0, len(arr), chunk)):
        points = by_owner[edges[b] : edges[b + 1]]
        order = points[np.argsort(steps_left[points], kind="stable")]
        bounds = np.searchsorted(steps_left[order], np.arange(task.T + 2))
        queries = _Queries(order, bounds, position[np.asarray(state)[order]], owner[order] - start)
        raw[start : start + chunk] = _optimal_block(task, layout, arr[start : start + chunk], queries=(queries, out))
    return out, raw


class _Queries(NamedTuple):
    """Points (sorted by steps left) at which `_optimal_block` reports the optimal action."""

    order: np.ndarray  # point index of each sorted entry
    bounds: np.ndarray  # [T + 2]: entries with t steps left are bounds[t]:bounds[t + 1]
    position: np.ndarray  # layout position of each sorted entry's state
    worker: np.ndarray  # worker column of each sorted entry


def _plan_block(task: Task, layout: _Layout, workers: np.ndarray, plan: np.ndarray) -> np.ndarray:
    """Raw expected return of following `plan` ([T + 1, S] in layout order) for a block of workers -> [Wc]."""
    kind = np.full(len(layout.ok), -1, dtype=np.int64)
    kind[layout.branching] = layout.mistake_type
    w_rows = np.vstack([workers.T, np.zeros((1, len(workers)))])  # row -1: no mistake possible
    arrival = np.append(np.asarray(task.rewards, dtype=np.float64), 0.0)[layout.progress][:, None]
    after = np.repeat(arrival, len(workers), axis=1)
    value = np.zeros(len(workers))
    for t in range(1, task.T + 1):
        n_active = layout.active[t]
        rows = np.arange(n_active) * NUM_COLORS + plan[t, :n_active]
        q = after[layout.ok[rows]]
        q += w_rows[kind[rows]] * (after[layout.bad[rows]] - q)
        value = q[0]
        after[:n_active] = q + arrival[:n_active]
    return value


def plan_returns(task: Task, plan: np.ndarray, workers: np.ndarray | Sequence, normalised: bool = True,
                 chunk: int = CHUNK) -> np.ndarray:
    """Expected (normalised) return of following a step-level plan (an action [T + 1, S] by steps left and
    table state, as `optimal_actions` gives) for each worker, [W]."""
    arr = as_workers(workers, task.N)
    table = transition_table(structural_task(task))
    if plan.shape != (task.T + 1, table.n_states):
        raise ValueError(f"plan has shape {plan.shape}, expected {(task.T + 1, table.n_states)} (steps left, states)")
    layout = _layout(table, task.T)
    by_position = plan[:, np.argsort(state_depths(table), kind="stable")].astype(np.int64)
    raw = np.zeros(len(arr))
    for start in range(0, len(arr), chunk):
        raw[start : start + chunk] = _plan_block(task, layout, arr[start : start + chunk], by_position)
    return normalised_return(task, raw) if normalised else raw


def known_worker_optimum(task: Task, workers: np.ndarray | Sequence, normalised: bool = True,
                    chunk: int = CHUNK) -> np.ndarray:
    """Optimal expected (normalised) return for each worker when the worker is known, [W]."""
    arr = as_workers(workers, task.N)
    layout = _layout(transition_table(structural_task(task)), task.T)
    raw = np.zeros(len(arr))
    for start in range(0, len(arr), chunk):
        raw[start : start + chunk] = _optimal_block(task, layout, arr[start : start + chunk])
    return normalised_return(task, raw) if normalised else raw
