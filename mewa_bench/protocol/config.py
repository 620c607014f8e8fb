"""What an evaluation run is: its configuration, and the seeds every unit and episode derives from.

The seeds depend only on (suite hash, pair, seed, episode), never on run order, lanes or jobs, so
the same agent file and seeds give the same results file however the run is executed.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mewa_bench.design.suites import Suite
from mewa_bench.envs.mewa_env import DEFAULT_IMAGE_SIZE
from mewa_bench.protocol.isolation import DEFAULT_MEMORY_LIMIT, DEFAULT_TIME_LIMIT, Launcher

EPISODES_PER_PAIR = 10
DEFAULT_LANES = 64
# protocol 2: seeds 0..n-1 per suite family, set by the power analysis in docs/protocol.md (section 4)
DEFAULT_SEED_COUNTS = {"narrow": 256, "wide": 96}
OTHER_SUITES_SEED_COUNT = 50  # suites of your own: no power analysis behind this one


def default_seeds_text() -> str:
    """The default seed counts in words, for help texts: "256 on narrow-*, 96 on wide-*, 50 on suites of your own"."""
    counts = ", ".join(f"{n} on {family}-*" for family, n in DEFAULT_SEED_COUNTS.items())
    return f"{counts}, {OTHER_SUITES_SEED_COUNT} on suites of your own"


def suite_family(suite_name: str) -> str:
    """'narrow-v2' -> 'narrow': the name without its version suffix (a hidden suite's too: 'narrow-v2-hidden')."""
    return re.sub(r"-v\d+(-hidden)?$", "", suite_name)


def default_seeds(suite_name: str) -> tuple[int, ...]:
    """The protocol's seeds for a suite (ranked runs use exactly these)."""
    return tuple(range(DEFAULT_SEED_COUNTS.get(suite_family(suite_name), OTHER_SUITES_SEED_COUNT)))


@dataclass(frozen=True)
class EvalConfig:
    """What to evaluate and how."""

    agent_path: Path
    suite: str = "narrow-v1"
    seeds: tuple[int, ...] | None = None  # None: the suite's default_seeds
    episodes: int = EPISODES_PER_PAIR
    out: Path | None = None
    name: str | None = None
    agent_args: dict[str, str] = field(default_factory=dict)
    checkpoint: str | None = None
    isolated: bool = True
    time_limit: float | None = DEFAULT_TIME_LIMIT
    memory_limit: int | None = DEFAULT_MEMORY_LIMIT
    privileged: bool = False
    jobs: int = 1
    resume: bool = False
    overwrite: bool = False  # replace an existing results file (it is replaced when the first unit is written)
    pairs: tuple[int, ...] | None = None  # a subset of pairs, for quick checks (the run is then partial)
    lanes: int = DEFAULT_LANES  # agent objects played side by side per process (one IPC round trip per step for all)
    mode: str = "vector"  # or "sapien": agents observe {"state": float32[18], "image": uint8[H, W, 3]}
    image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE
    ray: str | None = None  # run units as Ray tasks: "local" (a Ray instance on this machine) or a cluster address
    launcher: Launcher | None = None  # start the agent process in a sandbox (service.sandbox); None: a plain child


def rollout_config(policy: str, agent_args: dict[str, str] | None = None, privileged: bool = False,
                   **fields: Any) -> EvalConfig:
    """The run of `policy`: an agent .py file (isolated), or a baseline policy name (`policy_agent`, in-process).

    A baseline is told the task (privileged), as the reference lines are; raises ValueError for an unknown name.
    """
    from mewa_bench.protocol import policy_agent

    agent_args = dict(agent_args or {})
    if policy.endswith(".py"):
        return EvalConfig(agent_path=Path(policy), agent_args=agent_args, isolated=True, privileged=privileged, **fields)
    policy_agent.check_policy_name(policy)
    return EvalConfig(agent_path=policy_agent.AGENT_FILE, name=policy, agent_args={"policy": policy, **agent_args},
                      isolated=False, privileged=True, **fields)


def agent_name(path: Path) -> str:
    """`submissions/foo/agent.py` -> "foo"; `my_agent.py` -> "my_agent"."""
    return path.parent.name if path.stem == "agent" else path.stem


def default_results_path(config: EvalConfig, suite: Suite) -> Path:
    """`results/<agent>-<suite>.json` in the working directory (`...-partial.json` for a --pairs run)."""
    partial = "-partial" if config.pairs is not None else ""
    return Path("results") / f"{config.name or agent_name(config.agent_path)}-{suite.name}{partial}.json"


def env_seed(suite_hash: str, pair: int, seed: int, episode: int) -> int:
    """Deterministic env seed of one episode, independent of run order and parallelism."""
    digest = hashlib.sha256(f"{suite_hash}/{pair}/{seed}/{episode}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def hidden_pair(suite: Suite, pair: int) -> dict[str, Any]:
    """What a privileged agent is told at reset_task: the pair's task and worker."""
    p = suite.pairs[pair]
    return {"task": suite.tasks[p.task_index].to_dict(), "worker": list(p.worker.w)}


def unit_seed(suite_hash: str, pair: int, seed: int) -> int:
    """The seed an agent gets with reset_task(seed=...) for one unit (independent of order, lanes and jobs)."""
    digest = hashlib.sha256(f"{suite_hash}/{pair}/{seed}/agent".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1
