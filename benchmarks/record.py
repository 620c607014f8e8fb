"""Frames per second of `record` into a LeRobot dataset and of `datasets build`, against the bare rollout.

1. `record`: the random task-specific policy on narrow-v1, one seed (16 pairs x 10 episodes), in-process,
   through lerobot's own per-episode writer, against the same rollout without recording.
2. `datasets build`: the 1,000,000-frame random task-specific training dataset of narrow-v2 (exact
   optimal label on every frame, exact values, LeRobot v3.0 written in bulk), phase by phase, against
   the bare rollout's speed from 1.

    .venv/bin/python benchmarks/record.py [--frames N] [--jobs N]
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from pathlib import Path

from mewa_bench.datasets import LeRobotSink, build_training_dataset, training_spec
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


def cpu_seconds() -> float:
    """CPU time of this process and its finished children (the build's worker processes)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def build_timed(frames: int, jobs: int) -> tuple[float, float, int, dict[str, float]]:
    """Wall and CPU seconds, frames and per-phase seconds of building the narrow-v2 random task-specific
    training dataset."""
    phases: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        start, cpu = time.perf_counter(), cpu_seconds()
        meta = build_training_dataset(training_spec("narrow-v2-train-random-task-specific", frames),
                                      Path(tmp) / "ds", jobs=jobs, timings=phases)
        return time.perf_counter() - start, cpu_seconds() - cpu, meta["total_steps"], phases


def main() -> None:
    import lerobot.datasets.lerobot_dataset  # noqa: F401 - a one-off ~3 s import, not a per-frame cost

    parser = argparse.ArgumentParser()
    parser.add_argument("--frames", type=int, default=1_000_000)
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    base, frames = timed(record=False)
    rec, _ = timed(record=True)
    rate = frames / base
    print(f"narrow-v1, 1 seed, random task-specific policy: {frames:,} frames")
    print(f"{'rollout only (baseline)':<34} {base:7.2f} s  {rate:10,.0f} frames/s  1.00x")
    print(f"{'rollout + LeRobot dataset (record)':<34} {rec:7.2f} s  {frames / rec:10,.0f} frames/s  {rec / base:.2f}x")
    load = os.getloadavg()[0]
    total, cpu, built, phases = build_timed(args.frames, args.jobs)
    bare = built / rate
    print(f"\nnarrow-v2 training dataset, random task-specific tier, {built:,} frames, exact optimal labels, "
          f"{args.jobs} processes (load average before: {load:.1f}):")
    print(f"{'bare rollout at the baseline speed':<34} {bare:7.2f} s  {rate:10,.0f} frames/s  1.00x")
    for phase, label in (("play", "play (vectorised, luck keys)"), ("exact", "exact labels and values"),
                         ("write", "write LeRobot v3.0 in bulk")):
        print(f"{'  ' + label:<34} {phases[phase]:7.2f} s")
    print(f"{'datasets build (total)':<34} {total:7.2f} s  {built / total:10,.0f} frames/s  {total / bare:.2f}x")
    print(f"{'  CPU time, all processes':<34} {cpu:7.2f} s")


if __name__ == "__main__":
    main()
