"""Frames per second of `record` into a LeRobot dataset, against the same rollout without recording.

The random task-specific policy on narrow-v1, one seed (16 pairs x 10 episodes), in-process.

    .venv/bin/python benchmarks/record.py
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from mewa_bench.datasets import LeRobotSink
from mewa_bench.protocol import policy_agent
from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.runner import evaluate


def timed(record: bool) -> tuple[float, int]:
    with tempfile.TemporaryDirectory() as tmp:
        config = EvalConfig(agent_path=policy_agent.AGENT_FILE, out=Path(tmp) / "r.json", seeds=(0,),
                            agent_args={"policy": "random-task-specific"}, isolated=False, privileged=True)
        sinks = [LeRobotSink(Path(tmp) / "ds", "mewa/bench")] if record else []
        start = time.perf_counter()
        results, _ = evaluate(config, sinks=sinks)
        return time.perf_counter() - start, sum(sum(u["lengths"]) for u in results["units"])


def main() -> None:
    import lerobot.datasets.lerobot_dataset  # noqa: F401 - a one-off ~3 s import, not a per-frame cost

    base, frames = timed(record=False)
    rec, _ = timed(record=True)
    print(f"narrow-v1, 1 seed, random task-specific policy: {frames:,} frames")
    print(f"{'rollout only (baseline)':<28} {base:6.2f} s  {frames / base:10,.0f} frames/s  1.00x")
    print(f"{'rollout + LeRobot dataset':<28} {rec:6.2f} s  {frames / rec:10,.0f} frames/s  {rec / base:.2f}x")


if __name__ == "__main__":
    main()
