"""Overhead of `--log mcap,rerun` on an evaluate run, as a ratio to the same run without logs.

A random agent on narrow-v1 with 3 seeds, isolated (the default), measured in the same run with
and without each sink. SPEC target: logging <= 2x.

    .venv/bin/python benchmarks/logging_overhead.py
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from mewa_bench.logs import McapSink, RerunSink
from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.runner import evaluate

AGENT = Path(__file__).resolve().parents[1] / "tests" / "agents" / "delayed_fault_agent.py"


def timed(sinks: list[str], isolated: bool = True) -> tuple[float, int]:
    with tempfile.TemporaryDirectory() as tmp:
        made = [{"mcap": McapSink, "rerun": RerunSink}[k](Path(tmp) / f"run.{k}") for k in sinks]
        config = EvalConfig(agent_path=AGENT, out=Path(tmp) / "r.json", agent_args={"fault": "none"}, seeds=(0, 1, 2),
                            isolated=isolated)
        start = time.perf_counter()
        results, _ = evaluate(config, sinks=made)
        return time.perf_counter() - start, sum(sum(u["lengths"]) for u in results["units"])


def main() -> None:
    import rerun  # noqa: F401 - import once up front: its ~1 s import is not a per-run cost

    base, steps = timed([])
    print(f"narrow-v1, 3 seeds, random agent (isolated): {steps:,} env steps")
    print(f"{'no logs (baseline)':<22} {base:7.2f} s  1.00x")
    for kinds in (["mcap"], ["rerun"], ["mcap", "rerun"]):
        t, _ = timed(kinds)
        print(f"{'--log ' + ','.join(kinds):<22} {t:7.2f} s  {t / base:.2f}x   (SPEC: <= 2x)   "
              f"{(t - base) / steps * 1e6:.1f} us/step")


if __name__ == "__main__":
    main()
