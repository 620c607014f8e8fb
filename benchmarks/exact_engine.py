"""Exact engine vs Monte Carlo (SPEC section 11), as a ratio measured in one run.

Times the exact expected returns of all t-optimal policies over the narrow candidate grid
(10,626 non-increasing workers on the 0.05 grid x 19 policies; SPEC target <= 10 s, aim 2 s),
then measures a vectorised, table-driven Monte Carlo simulator of the same policies and
estimates what Monte Carlo would need to reach the same accuracy: a standard error of `--se`
(normalised) on every (policy, worker) pair. The machines are shared and noisy: compare ratios.

    .venv/bin/python benchmarks/exact_engine.py [--se 1e-4] [--pairs 200] [--episodes 2000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mewa_bench.design.exact import TERMINAL, augmented_chain, expected_returns, plan_for, structural_task
from mewa_bench.design.policies import toptimal_family
from mewa_bench.game import Task, transition_table
from mewa_bench.game.distributions import worker_grid
from mewa_bench.game.normalise import return_bounds

TASK = Task(colors=(0, 1, 2, 3), order=(3, 1, 2, 0), K=5, M=3, rewards=(-0.4, -0.3, -0.2, -0.1),
            worker_blocks=(2, 2, 4, 0))


class ChainSimulator:
    """Plays the deterministic t-optimal policies by table look-up over their augmented states."""

    def __init__(self, task: Task) -> None:
        chain = augmented_chain(transition_table(structural_task(task)), toptimal_family(task.N))
        n = len(chain.depth)
        assert np.array_equal(chain.node, np.arange(n)), "one branch per state expected (deterministic policies)"
        absorbing = n  # the terminal state, appended
        self.roots = chain.roots
        self.x = np.append(np.where(chain.x < 0, task.N, chain.x), task.N)
        self.ok = np.append(np.where(chain.ok == TERMINAL, absorbing, chain.ok), absorbing)
        self.bad = np.append(np.where(chain.bad == TERMINAL, absorbing, chain.bad), absorbing)
        values = np.append(np.asarray(task.rewards, dtype=np.float64), 0.0)
        self.ok_reward = np.append(values[chain.ok_reward], 0.0)
        self.bad_reward = np.append(values[chain.bad_reward], 0.0)
        self.task = task

    def play(self, policies: np.ndarray, workers: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Normalised returns of one episode per (policy index, worker row) pair."""
        n = len(policies)
        w_ext = np.concatenate([workers, np.zeros((n, 1))], axis=1)
        rows = np.arange(n)
        node = self.roots[policies]
        total = np.zeros(n)
        for _ in range(self.task.T):
            mistake = rng.random(n) < w_ext[rows, self.x[node]]
            total += np.where(mistake, self.bad_reward[node], self.ok_reward[node])
            node = np.where(mistake, self.bad[node], self.ok[node])
        r_min, r_max = return_bounds(self.task)
        return (total - r_min) / (r_max - r_min)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--se", type=float, default=1e-4, help="target standard error per pair (normalised)")
    parser.add_argument("--pairs", type=int, default=200, help="(policy, worker) pairs sampled for Monte Carlo")
    parser.add_argument("--episodes", type=int, default=2000, help="episodes per sampled pair")
    args = parser.parse_args()
    grid = worker_grid(TASK.N)
    n_policies = len(toptimal_family(TASK.N))

    start = time.perf_counter()
    plan_for(TASK, toptimal_family(TASK.N))
    plan_seconds = time.perf_counter() - start
    start = time.perf_counter()
    exact = expected_returns(TASK, None, grid)
    exact_seconds = time.perf_counter() - start

    rng = np.random.default_rng(0)
    simulator = ChainSimulator(TASK)
    pair_policy = rng.integers(0, n_policies, size=args.pairs)
    pair_worker = rng.integers(0, len(grid), size=args.pairs)
    policies = np.repeat(pair_policy, args.episodes)
    workers = grid[np.repeat(pair_worker, args.episodes)]
    start = time.perf_counter()
    returns = simulator.play(policies, workers, rng).reshape(args.pairs, args.episodes)
    mc_seconds = time.perf_counter() - start
    episodes_per_second = returns.size / mc_seconds
    variance = returns.var(axis=1, ddof=1)
    needed = variance.mean() / args.se**2 * n_policies * len(grid)
    error = np.abs(returns.mean(axis=1) - exact[pair_policy, pair_worker])
    within = np.mean(error <= 3 * np.sqrt(variance / args.episodes) + 1e-12)

    print(f"{'exact engine: plan (augmented chain, bisimulation, chains)':62s} {plan_seconds:9.3f} s")
    print(f"{f'exact engine: {n_policies} policies x {len(grid):,} workers':62s} {exact_seconds:9.3f} s"
          "   (SPEC: <= 10 s, aim 2 s)")
    print(f"{'Monte Carlo: vectorised table-driven simulator':62s} {episodes_per_second:12,.0f} episodes/s")
    print(f"{'Monte Carlo: mean variance of a normalised return':62s} {variance.mean():12.5f}")
    print(f"{f'Monte Carlo: episodes for SE {args.se:g} on every pair':62s} {needed:12.3e}")
    print(f"{'Monte Carlo: estimated time':62s} {needed / episodes_per_second:12,.0f} s")
    print(f"{'ratio Monte Carlo / exact':62s} {needed / episodes_per_second / exact_seconds:12,.0f}x")
    print(f"{'cross-check: sampled pairs within 3 SE of the exact value':62s} {within:12.1%}")


if __name__ == "__main__":
    main()
