"""Wall time of `evaluate` with a random agent on narrow-v1 (3 seeds): isolated vs in-process.

The in-process run is the same-run baseline; the difference per env step is the cost of running
the agent in its own process. SPEC target: isolated < 30 s.

    .venv/bin/python benchmarks/evaluate.py
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from mewa_bench.protocol.runner import EvalConfig, evaluate

AGENT = Path(__file__).resolve().parents[1] / "tests" / "agents" / "delayed_fault_agent.py"


def timed(isolated: bool, jobs: int = 1) -> tuple[float, int]:
    with tempfile.TemporaryDirectory() as tmp:
        config = EvalConfig(agent_path=AGENT, out=Path(tmp) / "r.json", agent_args={"fault": "none"},
                            isolated=isolated, jobs=jobs)
        start = time.perf_counter()
        results, _ = evaluate(config)
        return time.perf_counter() - start, sum(sum(u["lengths"]) for u in results["units"])


def main() -> None:
    base, steps = timed(isolated=False)
    iso, _ = timed(isolated=True)
    par, _ = timed(isolated=True, jobs=2)
    print(f"narrow-v1, 3 seeds, random agent: {steps:,} env steps")
    print(f"{'in-process (baseline)':<34} {base:7.2f} s   1.00x")
    print(f"{'isolated':<34} {iso:7.2f} s   {iso / base:.2f}x   (SPEC: < 30 s)")
    print(f"{'isolated, --jobs 2':<34} {par:7.2f} s   {par / base:.2f}x")
    print(f"isolation overhead per env step: {(iso - base) / steps * 1e6:.1f} us")


if __name__ == "__main__":
    main()
