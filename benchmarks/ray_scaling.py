"""Units/s of `evaluate` on Ray (1 and 2 workers of a local Ray instance) against `--jobs 1` and
`--jobs 2` local processes, measured in the same run, and Ray's overhead per unit.

A trivial random agent on narrow-v1, 20 seeds (320 units) in batches of 16 units (one Ray task or
one pool job per batch). The Ray rows include starting nothing: the local Ray instance is started
before the clock and joined by `evaluate`. Machines are shared and noisy: compare the ratios.

    .venv/bin/python benchmarks/ray_scaling.py
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.ray_backend import LOCAL
from mewa_bench.protocol.runner import evaluate

REPO = Path(__file__).resolve().parents[1]
AGENT = REPO / "submissions" / "random" / "agent.py"
SEEDS = tuple(range(20))
LANES = 16


def units_per_second(**kw) -> float:
    """Units/s of one evaluate run (play and scoring)."""
    with tempfile.TemporaryDirectory() as tmp:
        config = EvalConfig(agent_path=AGENT, out=Path(tmp) / "r.json", seeds=SEEDS, lanes=LANES, **kw)
        start = time.perf_counter()
        results, _ = evaluate(config)
        return len(results["units"]) / (time.perf_counter() - start)


def on_ray(workers: int) -> float:
    """Units/s on a local Ray instance with `workers` CPUs."""
    import ray

    ray.init(address="local", num_cpus=workers, _node_ip_address="127.0.0.1", include_dashboard=False,
             log_to_driver=False)
    try:
        units_per_second(ray=LOCAL)  # warm the workers up (imports, agent process), as a pool's first jobs do
        return units_per_second(ray=LOCAL)
    finally:
        ray.shutdown()


def main() -> None:
    rows = [("--jobs 1 (baseline)", units_per_second(jobs=1)), ("--jobs 2", units_per_second(jobs=2)),
            ("Ray, 1 worker", on_ray(1)), ("Ray, 2 workers", on_ray(2))]
    base = rows[0][1]
    print(f"narrow-v1, {len(SEEDS)} seeds ({16 * len(SEEDS)} units), batches of {LANES} units, random agent")
    print(f"{'configuration':<24} {'units/s':>9} {'x --jobs 1':>11}")
    for name, rate in rows:
        print(f"{name:<24} {rate:>9.1f} {rate / base:>10.2f}x")
    overhead = 1.0 / rows[2][1] - 1.0 / rows[0][1]
    print(f"Ray overhead per unit (1 worker vs --jobs 1): {overhead * 1e3:+.1f} ms")


if __name__ == "__main__":
    main()
