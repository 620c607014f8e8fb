"""Agent steps/s of `evaluate` (a trivial random agent, narrow-v1), against the env's own steps/s.

Baseline measured in the same run: the unwrapped `MewaEnv` stepped with random actions in this
process. Then `evaluate` isolated with one lane (one pipe round trip per step, the protocol-1
design), isolated with the default lanes (one round trip per step of all lanes), and in-process.
Agent steps/s count the play only; the scoring (reference replays + bootstrap) is timed apart.
Targets (SPEC and the planners): isolated >= 100,000 agent steps/s; bayes-adaptive on narrow-v1 with the
default protocol in under 60 s (`--bayes`).

`--neural`: a small torch GRU (64 units, the README's batched example) against the same network
written as a one-lane agent (`benchmarks/agents/gru_one_lane.py`: one object and one forward pass per
lane and step), isolated, default lanes, on narrow-v2. Targets: batched >= 20x the one-lane agent
steps/s, and >= 50,000 agent steps/s with --jobs 2. Its last line (alone: `--parts`) times the parts no
runner can avoid and the ratio they allow.
`--learned`: a ranked wide-v2 run (96 seeds, 7,680 units) of each shipped learned baseline with
--jobs 2, against the random agent's in the same run, and whether its units are those of the submission's
committed results file. Targets: each within 3 minutes, and the transformer agents' (DPT, AD) within 3x the
random agent's. `--repeat N` times each learned run N times, each right after a run of the random agent of its
own (a paired ratio: a busy moment of the shared machine slows both), and adds each run's median ratio. An
untimed random-agent run comes first: the first run in a process pays for the reference replays its scoring needs
(about 5 s, cached for the later runs), so every timed run scores alike.

    .venv/bin/python benchmarks/evaluate.py [--seeds N] [--bayes] [--neural] [--learned [--only A,B] [--repeat N]] [--parts]
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from mewa_bench.design.suites import load_suite
from mewa_bench.envs.mewa_env import MewaEnv
from mewa_bench.protocol import runner
from mewa_bench.protocol.config import DEFAULT_LANES, EvalConfig, default_seeds
from mewa_bench.protocol.results import read_results
from mewa_bench.protocol.runner import evaluate

REPO = Path(__file__).resolve().parents[1]
AGENT = REPO / "tests" / "agents" / "delayed_fault_agent.py"


def env_steps_per_second(seconds: float = 1.0) -> float:
    """Random-action steps/s of the unwrapped scalar env on the canonical narrow-v1 pair 0."""
    suite = load_suite("narrow-v1")
    env = MewaEnv(task=suite.tasks[0], worker=suite.pairs[0].worker.w)
    actions = np.random.default_rng(0).integers(0, 4, size=1 << 16).tolist()
    env.reset(seed=0)
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        for a in actions[:4096]:
            _, _, term, trunc, _ = env.step(a)
            if term or trunc:
                env.reset()
        steps += 4096
    return steps / (time.perf_counter() - start)


def timed(agent: Path, seeds: tuple[int, ...], **kw) -> tuple[float, float, int]:
    """(total seconds, scoring seconds, agent steps) of one evaluate run."""
    total, scoring, steps, _ = timed_results(agent, seeds, **kw)
    return total, scoring, steps


def timed_results(agent: Path, seeds: tuple[int, ...], **kw) -> tuple[float, float, int, dict]:
    """(total seconds, scoring seconds, agent steps, results) of one evaluate run."""
    scoring = [0.0]
    finish = runner.finish

    def timed_finish(results, suite):
        start = time.perf_counter()
        try:
            return finish(results, suite)
        finally:
            scoring[0] += time.perf_counter() - start

    runner.finish = timed_finish
    try:
        with tempfile.TemporaryDirectory() as tmp:
            config = EvalConfig(agent_path=agent, out=Path(tmp) / "r.json", seeds=seeds, **kw)
            start = time.perf_counter()
            results, _ = evaluate(config)
            total = time.perf_counter() - start
    finally:
        runner.finish = finish
    return total, scoring[0], sum(sum(u["lengths"]) for u in results["units"]), results


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=50, help="seeds of the random-agent runs (bayes-adaptive: the default 256)")
    parser.add_argument("--bayes", action="store_true", help="also time bayes-adaptive with the default protocol")
    parser.add_argument("--neural", action="store_true", help="also time a torch GRU agent, one-lane vs batched")
    parser.add_argument("--learned", action="store_true", help="also time ranked wide-v2 runs of the learned baselines")
    parser.add_argument("--only", default="", help="with --learned: a comma-separated list of submission folders (the "
                                                   "random agent, the baseline, always runs first)")
    parser.add_argument("--repeat", type=int, default=1, help="with --learned: time each run this many times, each "
                                                              "paired with a random-agent run just before it")
    parser.add_argument("--parts", action="store_true", help="only the --neural section's last line: the GRU's act() "
                                                               "one-lane and batched, the env's step, and their ceiling")
    args = parser.parse_args()
    if args.parts:
        with tempfile.TemporaryDirectory() as tmp:
            parts(readme_gru_agent(Path(tmp)), REPO / "benchmarks/agents/gru_one_lane.py")
        return
    if args.neural:
        neural(seeds=tuple(range(min(args.seeds, 64))))
    if args.learned:
        learned([name for name in args.only.split(",") if name], args.repeat)
    if args.neural or args.learned:
        return
    seeds = tuple(range(args.seeds))
    env_rate = env_steps_per_second()
    print(f"narrow-v1, {len(seeds)} seeds, random agent")
    print(f"{'configuration':<40} {'agent steps/s':>14} {'x env':>7} {'play s':>7} {'scoring s':>9}")
    print(f"{'MewaEnv unwrapped (baseline)':<40} {env_rate:>14,.0f} {1.0:>7.3f}")
    runs = [("isolated, 1 lane (protocol 1 design)", dict(lanes=1)),
            (f"isolated, {DEFAULT_LANES} lanes (default)", {}),
            (f"isolated, {DEFAULT_LANES} lanes, --jobs 2", dict(jobs=2)),
            (f"in-process, {DEFAULT_LANES} lanes", dict(isolated=False))]
    for label, kw in runs:
        total, scoring, steps = timed(AGENT, seeds, agent_args={"fault": "none"}, **kw)
        rate = steps / (total - scoring)
        print(f"{label:<40} {rate:>14,.0f} {rate / env_rate:>7.3f} {total - scoring:>7.2f} {scoring:>9.2f}")
    if args.bayes:
        agent = REPO / "submissions" / "bayes-adaptive" / "agent.py"
        for label, kw in (("bayes-adaptive, default protocol", {}), ("bayes-adaptive, --jobs 2", dict(jobs=2))):  # 256 seeds
            total, scoring, steps = timed(agent, default_seeds("narrow-v1"), **kw)
            print(f"{label:<40} {steps / (total - scoring):>14,.0f}   total {total:.1f} s (target < 60 s)")


def readme_gru_agent(folder: Path) -> Path:
    """The README's batched GRU example, written to a file in `folder`."""
    blocks = re.findall(r"```python\n(.*?)```", (REPO / "README.md").read_text(), re.S)
    path = folder / "gru_batched.py"
    path.write_text(next(b for b in blocks if "class VectorAgent" in b and "import torch" in b))
    return path


def neural(seeds: tuple[int, ...]) -> None:
    """One-lane vs batched torch GRU agent steps/s under isolated evaluate (narrow-v2). The first row is the
    one-lane agent with torch's default thread count (one per core: what a user's agent got before agent
    processes were given one compute thread), the second with the runner's one thread."""
    print(f"narrow-v2, {len(seeds)} seeds, torch GRU (64 units)")
    print(f"{'configuration':<44} {'agent steps/s':>14} {'x 1-lane':>8} {'play s':>7}")
    one_lane = REPO / "benchmarks/agents/gru_one_lane.py"
    with tempfile.TemporaryDirectory() as tmp:
        batched = readme_gru_agent(Path(tmp))
        base = None
        for label, agent, kw, threads in (
                ("one-lane objects, torch's default threads", one_lane, {}, str(os.cpu_count())),
                ("one-lane objects, one thread (the default)", one_lane, {}, None),
                ("batched, default lanes", batched, {}, None),
                ("batched, default lanes, --jobs 2", batched, dict(jobs=2), None),
                ("runner's ceiling: random agent, --jobs 2", AGENT, dict(jobs=2, agent_args={"fault": "none"}), None)):
            saved = os.environ.get("OMP_NUM_THREADS")
            if threads is not None:
                os.environ["OMP_NUM_THREADS"] = threads
            try:
                total, scoring, steps = timed(agent, seeds, suite="narrow-v2", **kw)
            finally:
                os.environ.pop("OMP_NUM_THREADS", None)
                if saved is not None:
                    os.environ["OMP_NUM_THREADS"] = saved
            rate = steps / (total - scoring)
            base = base or rate
            print(f"{label:<44} {rate:>14,.0f} {rate / base:>8.1f} {total - scoring:>7.1f}")
        parts(batched, one_lane)


def _per_call(call: Callable[[], object], repeats: int = 2000) -> float:
    """Seconds per call of `call` (best of three rounds)."""
    best = np.inf
    for _ in range(3):
        start = time.perf_counter()
        for _ in range(repeats):
            call()
        best = min(best, (time.perf_counter() - start) / repeats)
    return best


def parts(batched: Path, one_lane: Path, lanes: int = 64) -> None:
    """The parts of an agent step that no runner can avoid, in this process on one thread: the one-lane GRU's act()
    per step, the batched GRU's act() per lane, the batched env's step per lane; and the ratio a runner costing
    nothing else would reach, (one-lane act + env) / (batched act + env) per lane."""
    import torch

    from mewa_bench.envs import MewaVectorEnv
    from mewa_bench.protocol.agent import load_agent, load_lanes

    torch.set_num_threads(1)
    suite = load_suite("narrow-v2")
    env = MewaVectorEnv(num_envs=lanes, tasks=suite.tasks)
    obs, _ = env.reset(seed=0)
    obs = obs.astype(np.float32)
    space, actions = env.single_observation_space, env.single_action_space
    one = load_agent(one_lane, space, actions)
    vector = load_lanes(batched, space, actions, lanes)
    all_lanes = np.arange(lanes, dtype=np.int64)
    rng = np.random.default_rng(0)
    one_act = _per_call(lambda: one.act(obs[0]))
    batched_act = _per_call(lambda: vector.act(all_lanes, obs), 500) / lanes
    env_step = _per_call(lambda: env.step(rng.integers(0, 4, lanes)), 500) / lanes
    print(f"parts, one thread: one-lane act() {one_act * 1e6:.1f} us per step; batched act() {batched_act * 1e6:.2f} "
          f"us and the batched env's step {env_step * 1e6:.2f} us per lane ({lanes} lanes); a runner costing nothing "
          f"else would reach {(one_act + env_step) / (batched_act + env_step):.1f}x")


LEARNED = ("rl2-wide-v2-seed1", "varibad-wide-v2-seed1", "pearl-wide-v2-seed1", "maml-wide-v2-seed1",
           "dpt-wide-v2-seed1", "imitation-wide-v2-seed1", "ad-wide-v2-seed1", "ad-mqa-wide-v2-seed1",
           "ad-task-structures-wide-v2-seed1")


def learned(only: list[str], repeat: int = 1) -> None:
    """Ranked wide-v2 runs (default seeds) with --jobs 2: random, then each learned baseline's wide-v2 run; with
    `repeat` > 1, each learned run `repeat` times, each after a random-agent run of its own, and the median ratio."""
    unknown = sorted(name for name in only if not (REPO / "submissions" / name / "checkpoint.pt").exists())
    if unknown:
        raise SystemExit(f"--only: {', '.join(unknown)}: no submission folder with a checkpoint (the default runs: "
                         f"{', '.join(LEARNED)})")
    if repeat < 1:
        raise SystemExit(f"--repeat {repeat}: expected at least 1")
    seeds = default_seeds("wide-v2")
    print(f"wide-v2, {len(seeds)} seeds (ranked run), --jobs 2" + (f", each run {repeat} times" if repeat > 1 else ""))
    print(f"{'agent':<34} {'play s':>7} {'scoring s':>9} {'total s':>8} {'x random':>9}  units as committed")

    def timed_row(name: str, base: float | None) -> float:
        folder = REPO / "submissions" / name
        total, scoring, _, results = timed_results(folder / "agent.py", seeds, suite="wide-v2", jobs=2)
        print(f"{name:<34} {total - scoring:>7.1f} {scoring:>9.1f} {total:>8.1f} {total / (base or total):>9.2f}  "
              f"{as_committed(results, folder / 'results-wide-v2.json')}", flush=True)
        return total

    # the first run in a process replays the suite's reference policies for scoring (cached for the later ones): an
    # untimed run pays for it, so that every timed run scores alike
    timed_results(REPO / "submissions" / "random" / "agent.py", seeds, suite="wide-v2", jobs=2)
    base = timed_row("random", None) if repeat == 1 else None
    for name in only or LEARNED:
        ratios = []
        for _ in range(repeat):
            paired = base if repeat == 1 else timed_row("random", None)
            ratios.append(timed_row(name, paired) / paired)
        if repeat > 1:
            print(f"{name:<34} median of {repeat} paired ratios: {statistics.median(ratios):.2f}x "
                  f"(each: {', '.join(f'{r:.2f}' for r in ratios)})", flush=True)


def as_committed(results: dict, committed: Path) -> str:
    """Whether a run's units (returns and lengths of every pair and seed) are those of the committed results file."""
    if not committed.exists():
        return "(none committed)"
    before = {(u["pair"], u["seed"]): (u["returns"], u["lengths"]) for u in read_results(committed)["units"]}
    differ = sum(before.get((u["pair"], u["seed"])) != (u["returns"], u["lengths"]) for u in results["units"])
    return "yes" if differ == 0 and len(before) == len(results["units"]) else f"no: {differ} of {len(before)} differ"


if __name__ == "__main__":
    main()
