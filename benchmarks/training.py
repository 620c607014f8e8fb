"""End-to-end training speed of the learned baselines (`mewa-bench train ALGO`), against the bare env.

For each algorithm: a short run on narrow-v1 with its default settings (those of the shipped runs),
env steps/s end to end (rollouts, updates, metrics, checkpoints), and the share of that time the
env alone would take: the bare batched meta-episode env, stepped with random actions at the
algorithm's batch size, is measured in the same run. Extrapolates the time of a 4 M-step run (the
SPEC budget: 30 minutes on 2 cores). The machines are shared and noisy: compare the ratios.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/training.py [--steps 200000] [--algos rl2,varibad]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from mewa_bench.agents.training_io import available_algorithms, load_algorithm, make_meta_env

FULL_RUN = 4_000_000


def bare_env_steps_per_second(num_envs: int, steps: int, suite: str = "narrow-v1") -> float:
    """Random-action env steps/s of the batched meta-episode env with `num_envs` pairs."""
    env = make_meta_env(suite, num_envs, 10)
    env.reset(seed=0)
    actions = np.random.default_rng(0).integers(0, 4, size=(1024, num_envs))
    start, done = time.perf_counter(), 0
    while done < steps:
        env.step(actions[(done // num_envs) % 1024])
        done += num_envs
    return done / (time.perf_counter() - start)


def training_steps_per_second(name: str, steps: int) -> tuple[float, int, int]:
    """(env steps/s end to end, env steps done, batch size) of a short narrow-v1 run of `name`."""
    module = load_algorithm(name)
    settings = module.settings_from({"suite": "narrow-v1", "seed": 1, "total_steps": steps})
    reported: list[int] = []
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        module.train_run(settings, Path(tmp) / name, False, f"benchmark {name}",
                         progress=lambda done, total, row: reported.append(done))
        seconds = time.perf_counter() - start
    done = reported[-1] if reported else 0
    return done / seconds, done, getattr(settings, "num_envs", 64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=200_000, help="env steps per algorithm")
    parser.add_argument("--algos", default=",".join(available_algorithms()))
    args = parser.parse_args()
    print(f"{'algorithm':<10} {'env steps':>10} {'steps/s':>10} {'bare env steps/s':>17} {'env share':>10} "
          f"{'4 M steps':>10}")
    for name in args.algos.split(","):
        rate, done, num_envs = training_steps_per_second(name, args.steps)
        bare = bare_env_steps_per_second(num_envs, max(done, 100_000))
        print(f"{name:<10} {done:>10,} {rate:>10,.0f} {bare:>17,.0f} {rate / bare:>9.1%} "
              f"{FULL_RUN / rate / 60:>8.1f} min")


if __name__ == "__main__":
    main()
