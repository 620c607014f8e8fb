"""Replaying reference policies on given luck keys (protocol v2), vectorised over episodes.

The evaluation runner plays, for every agent episode, the t-optimal family and the two random
baselines on the same luck key (`mewa_bench.game.luck`), so that their realised returns can serve
as control variates. Each policy walks the augmented chain the exact engine enumerates (one node
per (game state, policy memory)), so replays and exact values come from one definition of every
policy. The random baselines' own coin flips use draws of the key that the worker never uses
(colour slot `COIN_SLOT`, counter = step), so a replay is a pure function of (task, worker, key).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from mewa_bench.design.exact import TERMINAL, augmented_chain, structural_task
from mewa_bench.design.policies import Policy, as_policies
from mewa_bench.game import luck
from mewa_bench.game.palette import NUM_COLORS
from mewa_bench.game.table import transition_table
from mewa_bench.game.task import Task

COIN_SLOT = 7  # `luck.uniforms(key, COIN_SLOT, step)`: the policies' coins, never a worker's draw


@dataclass(frozen=True)
class ReplayChain:
    """Branches of the augmented chain grouped by node; `cum` holds each node's cumulative probabilities."""

    roots: np.ndarray  # int64 [P]
    first: np.ndarray  # int64 [n]: first branch of each node
    count: np.ndarray  # int64 [n]: branches of each node
    cum: np.ndarray  # float64 [B]
    action: np.ndarray  # int64 [B]
    x: np.ndarray  # int64 [B]: mistake type, -1 if none is possible
    ok: np.ndarray  # int64 [B]: next node, TERMINAL allowed
    ok_reward: np.ndarray  # int64 [B]: reward id (sub-goal index; N = terminal, reward 0)
    bad: np.ndarray  # int64 [B]
    bad_reward: np.ndarray  # int64 [B]
    state: np.ndarray  # int64 [n]: the game state (table row of the rules' table) of each node


@lru_cache(maxsize=64)
def _cached_chain(structure: Task, policies: tuple[Policy, ...]) -> ReplayChain:
    chain = augmented_chain(transition_table(structure), policies)
    n = len(chain.depth)
    count = np.bincount(chain.node, minlength=n)
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    cum = np.cumsum(chain.prob) - np.repeat(np.cumsum(chain.prob)[first] - chain.prob[first], count)
    return ReplayChain(chain.roots, first, count, cum, chain.action, chain.x, chain.ok, chain.ok_reward,
                       chain.bad, chain.bad_reward, chain.state)


def replay_chain(task: Task, policies: Sequence[Policy | str]) -> ReplayChain:
    """The (cached) replay chain of a task's rules and the given policies."""
    return _cached_chain(structural_task(task), as_policies(policies))


def replay_returns(task: Task, policies: Sequence[Policy | str], worker: Sequence[float],
                   keys: Sequence[int] | np.ndarray) -> np.ndarray:
    """Episode returns of each policy on each luck key with one worker, float64 [len(keys), P]."""
    chain = replay_chain(task, policies)
    keys_arr = np.asarray(keys, dtype=np.uint64)
    n_keys, n_pol = len(keys_arr), len(chain.roots)
    w = np.append(np.asarray(worker, dtype=np.float64)[: task.N], 0.0)  # index -1: no mistake possible
    rewards = np.append(np.asarray(task.rewards, dtype=np.float64), 0.0)  # reward id N: terminal
    key = np.repeat(keys_arr, n_pol)
    node = np.tile(chain.roots, n_keys)
    draws = np.zeros((len(node), NUM_COLORS), dtype=np.int64)
    total = np.zeros(len(node))
    live = np.flatnonzero(node != TERMINAL)
    for step in range(task.T):
        if live.size == 0:
            break
        here = node[live]
        branch = chain.first[here]
        several = np.flatnonzero(chain.count[here] > 1)
        if several.size:  # a random baseline flips its coin
            coin = luck.uniforms(key[live[several]], COIN_SLOT, step)
            b, n_b = branch[several], chain.count[here[several]]
            branch[several] = b + _passed(chain.cum, b, n_b, coin)
        x = chain.x[branch]
        mistake = np.zeros(live.size, dtype=bool)
        draw = np.flatnonzero(x >= 0)
        if draw.size:
            rows, colour = live[draw], chain.action[branch[draw]]
            j = draws[rows, colour]
            draws[rows, colour] = j + 1
            mistake[draw] = luck.uniforms(key[rows], colour, j) < w[x[draw]]
        nxt = np.where(mistake, chain.bad[branch], chain.ok[branch])
        total[live] += rewards[np.where(mistake, chain.bad_reward[branch], chain.ok_reward[branch])]
        node[live] = nxt
        live = live[nxt != TERMINAL]
    return total.reshape(n_keys, n_pol)


def _passed(cum: np.ndarray, start: np.ndarray, count: np.ndarray, coin: np.ndarray) -> np.ndarray:
    """How many of a node's cumulative probabilities (all but the last, which is 1) the coin passes."""
    width = int(count.max()) - 1
    i = np.arange(width)[None, :]
    inside = i < (count - 1)[:, None]
    bounds = cum[np.where(inside, start[:, None] + i, 0)]
    return np.sum(inside & (coin[:, None] >= bounds), axis=1)
