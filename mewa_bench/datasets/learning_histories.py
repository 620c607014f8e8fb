"""Learning histories for Algorithm Distillation: posterior (Thompson) sampling over the t-optimal family.

The learner faces one (task, worker) for many episodes. It holds an exact posterior over the
worker on the 0.05 grid of the task's families' monotone workers, starting uniform (it knows the
rules and the policy family, not the meta-train distribution, so its first episodes are poor and
its improvement is visible). Before each episode it samples a grid worker from the posterior and
plays the t-optimal policy whose exact expected return (`design.exact`) is highest for it; every
second block it hands over is a Bernoulli(w_x) trial that updates the posterior after the episode.
The behaviour of every episode is one fixed t-optimal policy, so its exact expected return at the
true worker is known and stored with the frames. All histories of a batch run side by side, one
episode index at a time.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from mewa_bench.datasets.chain_rollout import Played, concat_played, play_chain
from mewa_bench.design.exact import expected_returns
from mewa_bench.design.policies import toptimal_family
from mewa_bench.design.replay import replay_chain
from mewa_bench.game.distributions import worker_families, worker_grid
from mewa_bench.game.task import Task

GRID_STEP = 0.05
TINY = 1e-300  # stands in for 0 under log


@dataclass(frozen=True)
class LearnerModel:
    """A task's grid, log-likelihood columns and the best t-optimal policy of each grid worker."""

    grid: np.ndarray  # float64 [G, N]
    log_w: np.ndarray  # [G, N]
    log_not_w: np.ndarray  # [G, N]
    best_policy: np.ndarray  # int64 [G]: index into the t-optimal family


@lru_cache(maxsize=16)
def learner_model(task: Task) -> LearnerModel:
    """The learner's model of a task (exact values of the t-optimal family on the grid)."""
    orders = sorted({f.monotone for f in worker_families(task)})
    grid = np.unique(np.concatenate([worker_grid(task.N, GRID_STEP, m) for m in orders]), axis=0)
    values = expected_returns(task, toptimal_family(task.N), grid)  # [P, G]
    return LearnerModel(grid, np.log(np.maximum(grid, TINY)), np.log(np.maximum(1.0 - grid, TINY)),
                        np.argmax(values, axis=0).astype(np.int64))


def sample_posterior(log_post: np.ndarray, u: np.ndarray) -> np.ndarray:
    """One grid index per row of an unnormalised log posterior [L, G], by inverse CDF with uniforms u [L]."""
    weight = np.exp(log_post - log_post.max(axis=1, keepdims=True))
    cdf = np.cumsum(weight, axis=1)
    return np.minimum(np.sum(cdf < (u * cdf[:, -1])[:, None], axis=1), log_post.shape[1] - 1)


def play_histories(task: Task, workers: np.ndarray, keys: np.ndarray,
                   rng: np.random.Generator) -> tuple[Played, np.ndarray]:
    """Histories of len(keys[0]) episodes, one per worker; keys [L, H]. Returns the frames (history-major,
    then episode order) and the t-optimal policy index each episode played, int64 [L, H]."""
    model = learner_model(task)
    family = toptimal_family(task.N)
    chain = replay_chain(task, family)
    n_hist, n_ep = keys.shape
    mistakes = np.zeros((n_hist, task.N))
    trials = np.zeros((n_hist, task.N))
    chosen = np.zeros((n_hist, n_ep), dtype=np.int64)
    episodes = []
    for e in range(n_ep):
        log_post = mistakes @ model.log_w.T + (trials - mistakes) @ model.log_not_w.T  # [L, G], uniform prior
        chosen[:, e] = model.best_policy[sample_posterior(log_post, rng.random(n_hist))]
        played = play_chain(task, chain, chain.roots[chosen[:, e]], workers, keys[:, e])
        mistakes += played.mistakes[:, : task.N]
        trials += played.trials[:, : task.N]
        episodes.append(played)
    order = np.arange(n_hist * n_ep).reshape(n_ep, n_hist).T.ravel()  # history-major
    return reorder_episodes(concat_played(episodes), order), chosen


def reorder_episodes(played: Played, order: np.ndarray) -> Played:
    """The same episodes in another order (`order[k]` = old index of the new k-th episode)."""
    new_of_old = np.empty_like(order)
    new_of_old[order] = np.arange(len(order))
    new_episode = new_of_old[played.episode]
    frames = np.argsort(new_episode, kind="stable")
    per_frame = ("t", "state", "action", "next_state", "reward", "terminated", "done")
    return Played(new_episode[frames], *(getattr(played, f)[frames] for f in per_frame),
                  *(getattr(played, f)[order] for f in ("mistakes", "trials", "lengths", "returns")))
