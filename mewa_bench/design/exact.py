"""Exact expected returns of the baseline policies (SPEC section 4), batched over workers.

A policy together with its memory is a finite Markov chain over augmented states (game state,
memory); its only randomness is the worker's mistakes (and the policy's own coin flips), and
every transition probability is affine in one worker component. The engine

1. enumerates the augmented states reachable from the start, for all requested policies at once;
2. merges states with identical futures (a probabilistic bisimulation, across policies too);
3. collapses deterministic chains into delayed edges carrying their reward sums, so that only
   "core" states, where something random happens, remain (a few hundred for 19 policies);
4. runs backward induction over the T-step horizon on the core states, vectorised over workers:
   V_t(u) = sum_b p_b [(1 - w_x) (R_ok + V_{t-d_ok}(ok)) + w_x (R_bad + V_{t-d_bad}(bad))],
   keeping the last max(d) value vectors in a ring buffer and skipping states that cannot be
   reached early enough for t steps to remain.

Steps 1-3 depend on the rules and the policies, not on the rewards (rewards enter as sub-goal
indices until step 4), and are cached.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from mewa_bench.design.policies import Policy, as_policies, toptimal_family
from mewa_bench.game.normalise import normalised_return
from mewa_bench.game.table import TransitionTable, transition_table
from mewa_bench.game.task import Task

TERMINAL = -1  # target id of the absorbing terminal state (value 0 forever)
CHUNK = 128  # workers per block of the backward induction (keeps the working set in cache)


@dataclass(frozen=True)
class AugmentedChain:
    """Augmented states of several policies and their branches (one per action a policy may take).

    Branch b leaves state `node[b]` with probability `prob[b]`; it reaches `ok[b]` with probability
    1 - w[x[b]] and `bad[b]` with probability w[x[b]] (x = -1: always `ok`). Rewards are given as
    reward ids: the sub-goal index of the state reached, N for the terminal state.
    """

    roots: np.ndarray  # int64 [P]: start state of each policy
    depth: np.ndarray  # int64 [n]: earliest step at which each state can be reached
    node: np.ndarray  # int64 [B]
    prob: np.ndarray  # float64 [B]
    x: np.ndarray  # int64 [B]
    ok: np.ndarray  # int64 [B], TERMINAL allowed
    ok_reward: np.ndarray  # int64 [B]
    bad: np.ndarray  # int64 [B]
    bad_reward: np.ndarray  # int64 [B]
    action: np.ndarray  # int64 [B]: the colour handed over (for replays with coupled luck)
    state: np.ndarray  # int64 [n]: the game state (table row) of each node


@dataclass(frozen=True)
class Plan:
    """Core states in order of earliest arrival, their branches, and chain-collapsed edges.

    Edge e of a branch reaches core state `target` (or the zero row `n_core`) after `delay` steps,
    collecting the rewards whose ids are in row e of `reward_ids` (padded with N, reward 0).
    """

    horizon: int
    n_core: int
    root_rows: np.ndarray  # int64 [P]
    branch_start: np.ndarray  # int64 [n_core + 1]
    single_branch: bool  # every core state has one branch with probability 1
    prob: np.ndarray  # float64 [B]
    x: np.ndarray  # int64 [B]; -1: no mistake possible
    ok_target: np.ndarray  # int64 [B]
    ok_delay: np.ndarray  # int64 [B]
    ok_reward_ids: np.ndarray  # int64 [B, T]
    bad_target: np.ndarray
    bad_delay: np.ndarray
    bad_reward_ids: np.ndarray
    active_states: np.ndarray  # int64 [T + 1]: core states whose value is needed with t steps left
    ring: int  # value vectors kept (max delay + 1)


def structural_task(task: Task) -> Task:
    """The task with placeholder rewards: the chain's structure does not depend on the rewards."""
    return Task(colors=task.colors, order=task.order, K=task.K, M=task.M,
                rewards=tuple(float(i - task.N) for i in range(task.N)), worker_blocks=task.worker_blocks, T=task.T)


def augmented_chain(table: TransitionTable, policies: Sequence[Policy]) -> AugmentedChain:
    """Enumerate (policy, game state, memory) breadth-first from the start of every policy."""
    task = table.task
    next_ok, next_bad = table.next_ok.tolist(), table.next_mistake.tolist()
    mistake_type, terminal, progress = table.mistake_type.tolist(), table.terminal.tolist(), table.progress.tolist()
    index: dict[tuple, int] = {}
    keys: list[tuple] = []
    depth: list[int] = []

    def node(p: int, s: int, memory: object, d: int) -> int:
        if terminal[s]:
            return TERMINAL
        key = (p, s, memory)
        i = index.get(key)
        if i is None:
            i = index[key] = len(keys)
            keys.append(key)
            depth.append(d)
        return i

    roots = [node(p, 0, policy.initial_memory(), 0) for p, policy in enumerate(policies)]
    rows: list[tuple] = []
    i = 0
    while i < len(keys):  # `keys` grows while we walk it
        p, s, memory = keys[i]
        d = depth[i] + 1
        for prob, a, next_memory in policies[p].choices(task, table.states[s], memory):
            ok, bad = next_ok[s][a], next_bad[s][a]
            rows.append((i, prob, mistake_type[s][a], node(p, ok, next_memory, d), progress[ok],
                         node(p, bad, next_memory, d), progress[bad], a))
        i += 1
    cols = list(zip(*rows))
    ints = [np.array(c, dtype=np.int64) for c in cols]
    return AugmentedChain(np.array(roots, dtype=np.int64), np.array(depth, dtype=np.int64), ints[0],
                          np.array(cols[1], dtype=np.float64), ints[2], ints[3], ints[4], ints[5], ints[6], ints[7],
                          np.array([k[1] for k in keys], dtype=np.int64))


def _merged_branches(chain: AugmentedChain, cls: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Branches in class terms, identical ones of a state merged: (node, prob, key id, key rows)."""
    cls_ext = np.append(cls, TERMINAL)  # index TERMINAL (-1) picks the appended entry
    c_ok, c_bad = cls_ext[chain.ok], cls_ext[chain.bad]
    r_ok, r_bad = chain.ok_reward, chain.bad_reward
    sure = (chain.x < 0) | ((c_ok == c_bad) & (r_ok == r_bad))  # both outcomes equivalent: no branching
    keys = np.stack([np.where(sure, -1, chain.x), c_ok, r_ok, np.where(sure, c_ok, c_bad),
                     np.where(sure, r_ok, r_bad)], axis=1)
    key_rows, key_id = np.unique(keys, axis=0, return_inverse=True)
    pair, pair_id = np.unique(chain.node * len(key_rows) + key_id.reshape(-1), return_inverse=True)
    prob = np.bincount(pair_id.reshape(-1), weights=chain.prob, minlength=len(pair))
    return pair // len(key_rows), prob, pair % len(key_rows), key_rows


def bisimulation(chain: AugmentedChain) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """Coarsest partition of states with identical futures; returns (class per state, merged branches)."""
    n = len(chain.depth)
    cls = np.zeros(n, dtype=np.int64)
    n_classes = 1
    while True:
        node, prob, key, key_rows = _merged_branches(chain, cls)
        start = np.searchsorted(node, np.arange(n))
        rank = np.arange(len(node)) - start[node]
        width = int(rank.max()) + 1
        signature = np.full((n, 1 + 2 * width), -1.0)
        signature[:, 0] = cls
        signature[node, 1 + 2 * rank] = key
        signature[node, 2 + 2 * rank] = prob
        _, refined = np.unique(signature, axis=0, return_inverse=True)
        refined = refined.reshape(-1)
        if refined.max() + 1 == n_classes:  # refinement only splits classes: same count = stable
            return cls, (node, prob, key, key_rows)
        cls, n_classes = refined, int(refined.max()) + 1


def _plan(chain: AugmentedChain, horizon: int, n_reward_ids: int) -> Plan:
    """Quotient by bisimulation, collapse deterministic chains, order core states by depth."""
    cls, (node, prob, key, key_rows) = bisimulation(chain)
    n_classes = int(cls.max()) + 1
    class_depth = np.full(n_classes, np.iinfo(np.int64).max)
    np.minimum.at(class_depth, cls, chain.depth)
    _, representative = np.unique(cls, return_index=True)  # first member of each class
    keep = representative[cls[node]] == node
    order = np.argsort(cls[node[keep]], kind="stable")
    node, prob = cls[node[keep]][order], prob[keep][order]
    key = key_rows[key[keep][order]]  # columns: x, c_ok, r_ok, c_bad, r_bad
    root_classes = cls[chain.roots]
    counts = np.bincount(node, minlength=n_classes)
    first = np.searchsorted(node, np.arange(n_classes))
    chainable = (counts == 1) & (key[first, 0] < 0)
    chainable[root_classes] = False
    successor = key[first, 1].tolist()
    successor_reward = key[first, 2].tolist()
    chainable_list = chainable.tolist()

    def follow(target: int, reward: int) -> tuple[int, list[int]]:
        """End of the deterministic chain entered at `target`, and the reward ids collected."""
        rewards = [reward]
        while target != TERMINAL and chainable_list[target] and len(rewards) < horizon:
            target, reward = successor[target], successor_reward[target]
            rewards.append(reward)
        if len(rewards) >= horizon:
            target = TERMINAL  # reached at the horizon or later: its value is never read
        return target, rewards

    core = np.flatnonzero(~chainable)
    core = core[np.argsort(class_depth[core], kind="stable")]
    row_of = np.full(n_classes + 1, len(core))  # TERMINAL (-1) maps to the zero row
    row_of[core] = np.arange(len(core))
    is_core_branch = ~chainable[node]
    order = np.argsort(row_of[node[is_core_branch]], kind="stable")
    b_node, b_prob, b_key = node[is_core_branch][order], prob[is_core_branch][order], key[is_core_branch][order]
    edges = {}
    for side, (c_col, r_col) in (("ok", (1, 2)), ("bad", (3, 4))):
        ends = [follow(int(c), int(r)) for c, r in zip(b_key[:, c_col], b_key[:, r_col])]
        delay = np.array([len(rw) for _, rw in ends], dtype=np.int64)
        target = np.array([row_of[e] for e, _ in ends], dtype=np.int64)
        ids = np.full((len(ends), horizon), n_reward_ids - 1, dtype=np.int64)
        for j, (_, rw) in enumerate(ends):
            ids[j, : len(rw)] = rw
        edges[side] = (target, delay, ids)
    real = np.concatenate([edges[s][1][edges[s][0] < len(core)] for s in edges])
    sorted_depth = class_depth[core]
    active = np.searchsorted(sorted_depth, horizon - np.arange(horizon + 1), side="right")
    branch_start = np.searchsorted(row_of[b_node], np.arange(len(core) + 1))
    return Plan(horizon, len(core), row_of[root_classes], branch_start,
                bool(np.all(np.diff(branch_start) == 1) and np.all(b_prob == 1.0)), b_prob, b_key[:, 0],
                *edges["ok"], *edges["bad"], active, int(real.max(initial=0)) + 1)


@lru_cache(maxsize=64)
def _cached_plan(structure: Task, policies: tuple[Policy, ...]) -> Plan:
    chain = augmented_chain(transition_table(structure), policies)
    return _plan(chain, structure.T, structure.N + 1)


def plan_for(task: Task, policies: Sequence[Policy | str]) -> Plan:
    """The (cached) reward-independent plan of the exact engine for a task and policies."""
    objects = as_policies(policies)
    return _cached_plan(structural_task(task), objects)


def _edge_tables(plan: Plan, rewards: np.ndarray, target: np.ndarray, delay: np.ndarray,
                 ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per step t = 1..T: reward collected on each edge and flat row of the value it reads, [T+1, B]."""
    values = np.append(rewards, 0.0)[ids]
    cumulative = np.concatenate([np.zeros((len(ids), 1)), np.cumsum(values, axis=1)], axis=1)
    t = np.arange(plan.horizon + 1)[:, None]
    collected = np.ascontiguousarray(cumulative.T)  # cumulative[:, k] is constant for k >= delay
    rows = ((t - delay[None, :]) % plan.ring) * (plan.n_core + 1) + target[None, :]
    return collected, np.ascontiguousarray(rows)


def _values_block(plan: Plan, tables: tuple[np.ndarray, ...], workers: np.ndarray) -> np.ndarray:
    """V_T at the root rows for one block of workers [Wc, N] -> [P, Wc]."""
    ok_reward, ok_rows, bad_reward, bad_rows = tables
    n_workers = len(workers)
    w_ext = np.concatenate([workers.T, np.zeros((1, n_workers))])  # row N: "no mistake possible"
    w_branch = w_ext[np.where(plan.x < 0, workers.shape[1], plan.x)]
    stride = plan.n_core + 1
    history = np.zeros((plan.ring * stride, n_workers))
    n_branches = len(plan.x)
    g_ok = np.empty((n_branches, n_workers))
    g_bad = np.empty((n_branches, n_workers))
    prob = plan.prob[:, None]
    # Once t exceeds every delay the edge rewards stop changing: fold them into one offset.
    steady = int(max(plan.ok_delay.max(), plan.bad_delay.max()))
    offset = ok_reward[steady, :, None] + w_branch * (bad_reward[steady, :, None] - ok_reward[steady, :, None])
    for t in range(1, plan.horizon + 1):
        n_states = plan.active_states[t]
        nb = plan.branch_start[n_states]
        ok, bad = g_ok[:nb], g_bad[:nb]
        np.take(history, ok_rows[t, :nb], axis=0, out=ok, mode="clip")
        np.take(history, bad_rows[t, :nb], axis=0, out=bad, mode="clip")
        if t < steady:
            ok += ok_reward[t, :nb, None]
            bad += bad_reward[t, :nb, None]
        bad -= ok
        bad *= w_branch[:nb]
        if t >= steady:
            bad += offset[:nb]
        slot = (t % plan.ring) * stride
        if plan.single_branch:
            np.add(bad, ok, out=history[slot : slot + n_states])
        else:
            bad += ok
            bad *= prob[:nb]
            np.add.reduceat(bad, plan.branch_start[:n_states], axis=0, out=history[slot : slot + n_states])
    slot = (plan.horizon % plan.ring) * stride
    return history[slot + plan.root_rows]


def as_workers(workers: np.ndarray | Sequence, n: int) -> np.ndarray:
    """Workers as a float64 [W, N] array, checked."""
    arr = np.atleast_2d(np.asarray(workers, dtype=np.float64))
    if arr.ndim != 2 or arr.shape[1] != n:
        raise ValueError(f"workers must have shape [W, {n}], got {np.shape(workers)}")
    if not np.all((arr >= 0.0) & (arr <= 1.0)):
        raise ValueError("worker probabilities must lie in [0, 1]")
    return arr


def expected_returns(task: Task, policies: Sequence[Policy | str] | None, workers: np.ndarray | Sequence,
                     normalised: bool = True, chunk: int = CHUNK) -> np.ndarray:
    """Exact expected (normalised) return of each policy for each worker, [P, W].

    `policies` default to the t-optimal family of the task; `workers` is [W, N] (or one worker).
    """
    chosen = toptimal_family(task.N) if policies is None else as_policies(policies)
    arr = as_workers(workers, task.N)
    plan = plan_for(task, chosen)
    rewards = np.asarray(task.rewards, dtype=np.float64)
    tables = (*_edge_tables(plan, rewards, plan.ok_target, plan.ok_delay, plan.ok_reward_ids),
              *_edge_tables(plan, rewards, plan.bad_target, plan.bad_delay, plan.bad_reward_ids))
    raw = np.zeros((len(chosen), len(arr)))
    for start in range(0, len(arr), chunk):
        raw[:, start : start + chunk] = _values_block(plan, tables, arr[start : start + chunk])
    return normalised_return(task, raw) if normalised else raw


def best_toptimal(task: Task, worker: np.ndarray | Sequence[float]) -> tuple[Policy, float]:
    """The t-optimal policy with the highest exact expected normalised return for `worker`, and that return."""
    family = toptimal_family(task.N)
    values = expected_returns(task, family, as_workers([worker], task.N))[:, 0]
    best = int(np.argmax(values))  # ties: the first in canonical order
    return family[best], float(values[best])
