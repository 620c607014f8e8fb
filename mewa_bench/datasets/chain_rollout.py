"""Many episodes of the baseline policies at once, vectorised over episodes, with coupled worker luck.

Each policy walks the augmented chain of the exact engine (`mewa_bench.design.replay`: one node per
(game state, policy memory), built from the policy's one definition); the worker's mistakes come
from each episode's luck key exactly as in the envs (`mewa_bench.game.luck`), and a random policy's
coins from the key's `COIN_SLOT` draws, as in the protocol's replays. An episode is therefore a pure
function of (task, worker, policy, luck key), and `MewaEnv` fed the same key and actions replays it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mewa_bench.design.exact import TERMINAL, structural_task
from mewa_bench.design.replay import COIN_SLOT, ReplayChain
from mewa_bench.game import luck
from mewa_bench.game.palette import NUM_COLORS
from mewa_bench.game.table import transition_table
from mewa_bench.game.task import Task


@dataclass(frozen=True)
class Played:
    """Frames of several episodes, episode-major (episode 0's frames in time order, then episode 1's...)."""

    episode: np.ndarray  # int64 [F]: which of the played episodes
    t: np.ndarray  # int64 [F]: step within the episode (LeRobot's frame_index)
    state: np.ndarray  # int64 [F]: table state the action was chosen in
    action: np.ndarray  # int64 [F]
    next_state: np.ndarray  # int64 [F]
    reward: np.ndarray  # float64 [F]
    terminated: np.ndarray  # bool [F]
    done: np.ndarray  # bool [F]: terminated or truncated
    mistakes: np.ndarray  # float64 [E, 4]: mistakes seen per type, per episode
    trials: np.ndarray  # float64 [E, 4]: second blocks (trials) per type, per episode
    lengths: np.ndarray  # int64 [E]
    returns: np.ndarray  # float64 [E]: raw episode returns


def _choose_branch(chain: ReplayChain, here: np.ndarray, keys: np.ndarray, step: int) -> np.ndarray:
    """The branch each node takes: its only one, or the one its coin (the key's COIN_SLOT draw) picks."""
    branch = chain.first[here].copy()
    several = np.flatnonzero(chain.count[here] > 1)
    if several.size:
        coin = luck.uniforms(keys[several], COIN_SLOT, step)
        start, count = branch[several], chain.count[here[several]]
        width = int(count.max()) - 1
        i = np.arange(width)[None, :]
        inside = i < (count - 1)[:, None]
        bounds = chain.cum[np.where(inside, start[:, None] + i, 0)]
        branch[several] = start + np.sum(inside & (coin[:, None] >= bounds), axis=1)
    return branch


def play_chain(task: Task, chain: ReplayChain, roots: np.ndarray, workers: np.ndarray, keys: np.ndarray) -> Played:
    """Play episode i from chain node `roots[i]` with worker `workers[i]` and luck key `keys[i]`, all at once."""
    table = transition_table(structural_task(task))
    n = len(roots)
    next_ok, next_bad = table.next_ok.astype(np.int64), table.next_mistake.astype(np.int64)
    arrival = np.append(np.asarray(task.rewards, dtype=np.float64), 0.0)[table.progress.astype(np.int64)]
    w = np.concatenate([np.asarray(workers, dtype=np.float64)[:, : task.N], np.zeros((n, 1))], axis=1)  # -1: none
    keys = np.asarray(keys, dtype=np.uint64)
    node = np.asarray(roots, dtype=np.int64).copy()
    draws = np.zeros((n, NUM_COLORS), dtype=np.int64)
    mistakes = np.zeros((n, NUM_COLORS))
    trials = np.zeros((n, NUM_COLORS))
    live = np.arange(n)
    parts: list[tuple[np.ndarray, ...]] = []
    for step in range(task.T):
        if live.size == 0:
            break
        here = node[live]
        branch = _choose_branch(chain, here, keys[live], step)
        state, action, x = chain.state[here], chain.action[branch], chain.x[branch]
        mistake = np.zeros(live.size, dtype=bool)
        draw = np.flatnonzero(x >= 0)
        if draw.size:
            rows, colour = live[draw], action[draw]
            j = draws[rows, colour]
            draws[rows, colour] = j + 1
            mistake[draw] = luck.uniforms(keys[rows], colour, j) < w[rows, x[draw]]
            np.add.at(trials, (rows, x[draw]), 1.0)
            np.add.at(mistakes, (rows, x[draw]), mistake[draw].astype(np.float64))
        nxt_state = np.where(mistake, next_bad[state, action], next_ok[state, action])
        nxt_node = np.where(mistake, chain.bad[branch], chain.ok[branch])
        terminated = nxt_node == TERMINAL
        done = terminated | (step + 1 == task.T)
        parts.append((live, np.full(live.size, step), state, action, nxt_state, terminated, done))
        node[live] = nxt_node
        live = live[~terminated]
    cols = [np.concatenate(c) for c in zip(*parts)]
    order = np.argsort(cols[0], kind="stable")  # episode-major; time order kept within an episode
    episode, t, state, action, nxt_state, terminated, done = (c[order] for c in cols)
    reward = arrival[nxt_state]
    lengths = np.bincount(episode, minlength=n).astype(np.int64)
    returns = np.bincount(episode, weights=reward, minlength=n)
    return Played(episode, t.astype(np.int64), state, action, nxt_state, reward, terminated, done, mistakes, trials,
                  lengths, returns)


def concat_played(parts: list[Played]) -> Played:
    """Several `Played` one after the other (episode numbers shifted)."""
    offsets = np.cumsum([0] + [len(p.lengths) for p in parts[:-1]])
    return Played(np.concatenate([p.episode + o for p, o in zip(parts, offsets)]),
                  *(np.concatenate([getattr(p, f) for p in parts]) for f in
                    ("t", "state", "action", "next_state", "reward", "terminated", "done", "mistakes", "trials",
                     "lengths", "returns")))
