"""SAPIEN-mode rendering speed (SPEC section 11: >= 100 frames/s at 128x128 on 2 CPU cores).

Renders random reachable states of the canonical task, and measures, in the same run, a baseline:
the numpy-only encoding of the same states as vector observations (what vector mode pays per
step). Also reports the one-off costs: SAPIEN import and Vulkan start-up, scene build, and the
latency of the first frame after a scene is built (target < 1 s). Compare ratios across machines.

    .venv/bin/python benchmarks/render.py [--seconds 2]
"""

from __future__ import annotations

import argparse
import os
import time
from typing import Callable

import numpy as np

from mewa_bench.game import Task
from mewa_bench.game.rules import State, observation
from mewa_bench.game.table import transition_table
from mewa_bench.render import find_render_device, require_render_device

TASK = Task(colors=(0, 1, 2, 3), order=(3, 1, 2, 0), K=5, M=3, rewards=(-1, -0.6, -0.4, -0.2),
            worker_blocks=(2, 2, 4, 0))
SIZES = ((128, 128), (256, 256))


def random_states(n: int, seed: int = 0) -> list[State]:
    """n reachable states of the canonical task, drawn uniformly with replacement."""
    states = transition_table(TASK).states
    rng = np.random.default_rng(seed)
    return [states[i] for i in rng.integers(0, len(states), n)]


def per_second(work: Callable[[State], object], states: list[State], seconds: float) -> float:
    """Calls of `work` per second, cycling through `states` for about `seconds`."""
    done, start = 0, time.perf_counter()
    while True:
        for s in states:
            work(s)
        done += len(states)
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return done / elapsed


def timed(make: Callable[[], object]) -> tuple[object, float]:
    """(result, seconds) of one call."""
    start = time.perf_counter()
    out = make()
    return out, time.perf_counter() - start


def row(label: str, value: str, note: str = "") -> None:
    print(f"{label:<52}{value:>14}   {note}".rstrip())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=2.0, help="time per throughput measurement")
    args = parser.parse_args()

    _, detect = timed(find_render_device)
    device = require_render_device()
    print(f"device: {device.name}, {device.driver} [{device.kind}], ICD {device.icd}; {os.cpu_count()} CPUs")
    row("device detection (ICD files)", f"{detect * 1e3:.2f} ms")

    from mewa_bench.render import SceneRenderer  # noqa: F401 - sapien itself is imported at first build

    states = random_states(512)
    baseline = per_second(lambda s: observation(TASK, s), states, args.seconds)
    row("baseline: numpy state encoding (rules.observation)", f"{baseline:,.0f}/s", "1.0x")

    _, imported = timed(lambda: __import__("sapien"))
    row("import sapien", f"{imported:.3f} s")
    first, startup = timed(lambda: SceneRenderer(*SIZES[0]))
    _, latency = timed(lambda: first.render(TASK, states[0]))
    row("first renderer in the process: Vulkan start + scene", f"{startup:.3f} s")
    row("first renderer: first frame (compiles the shaders)", f"{latency:.3f} s", "(target < 1 s)")
    first.close()
    for width, height in SIZES:
        renderer, build = timed(lambda: SceneRenderer(width, height))
        _, latency = timed(lambda: renderer.render(TASK, states[0]))
        fps = per_second(lambda s: renderer.render(TASK, s), states, args.seconds)
        row(f"{width}x{height}: scene build (another renderer)", f"{build:.3f} s")
        row(f"{width}x{height}: first frame after build", f"{latency:.3f} s", "(target < 1 s)")
        target = "(target >= 100/s)" if (width, height) == (128, 128) else ""
        row(f"{width}x{height}: random reachable states", f"{fps:,.0f} frames/s",
            f"{fps / baseline:.4f}x baseline = 1/{baseline / fps:,.0f}; {1e3 / fps:.2f} ms/frame {target}")
        renderer.close()


if __name__ == "__main__":
    main()
