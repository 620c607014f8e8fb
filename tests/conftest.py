"""Shared fixtures: the reference traces and a canonical task."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from mewa_bench.game import Task

# A COLUMNS inherited by pytest-xdist's workers would fix the width of the CLI's rich console when it is
# created at import; without it the console reads COLUMNS at each print, as the CLI tests set it.
os.environ.pop("COLUMNS", None)

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "tests" / "data"
# A copy of shared/reference/traces-canonical.json ships here, so a fresh clone tests without shared/;
# MEWA_SHARED points the tests at another shared/ folder (its copy must then be the same file).
SHARED = Path(os.environ["MEWA_SHARED"]) if "MEWA_SHARED" in os.environ else None
TRACES = SHARED / "reference" / "traces-canonical.json" if SHARED else DATA / "traces-canonical.json"


def load_traces() -> list[dict]:
    """The reference traces recorded from the authors' original code."""
    if not TRACES.exists():
        pytest.fail(f"reference traces not found at {TRACES} (unset MEWA_SHARED to use tests/data/)")
    return json.loads(TRACES.read_text())["traces"]


@pytest.fixture(scope="session", autouse=True)
def sb3_logs_in_pytest_tmp(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Stable-Baselines3 makes a logger folder per `learn()` (<tmp>/SB3-<time> unless SB3_LOGDIR names one): keep
    them under pytest's own temporary folders, which pytest prunes, rather than in the machine's /tmp."""
    os.environ.setdefault("SB3_LOGDIR", str(tmp_path_factory.mktemp("sb3-logs")))


@pytest.fixture(scope="session")
def traces() -> list[dict]:
    return load_traces()


@pytest.fixture(scope="session")
def canonical_task() -> Task:
    """The canonical task with the traces' rewards and an illustrative worker distribution."""
    return Task(colors=(0, 1, 2, 3), order=(3, 1, 2, 0), K=5, M=3, rewards=(-0.4, -0.3, -0.2, -0.1),
                worker_blocks=(2, 2, 4, 0), name="canonical").with_distribution((0.6, 0.4, 0.25, 0.1))


@pytest.fixture(scope="session")
def small_task() -> Task:
    """An N = 3 task with M = K = 4 and a non-trivial order."""
    return Task(colors=(0, 2, 3), order=(2, 0, 3), K=4, M=4, rewards=(-1.0, -0.5, -0.2),
                worker_blocks=(3, 5, 0), name="n3").with_distribution((0.5, 0.3, 0.15))


@pytest.fixture(scope="module")
def offline_hub(tmp_path_factory):
    """Keep lerobot / huggingface_hub caches in a temp dir and forbid Hub access (for the module)."""
    home = tmp_path_factory.mktemp("hf_home")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HF_HOME", str(home))
        mp.setenv("HF_LEROBOT_HOME", str(home / "lerobot"))
        mp.setenv("HF_HUB_OFFLINE", "1")
        mp.setenv("HF_DATASETS_OFFLINE", "1")
        yield


# The longest test files first (measured with `--durations=0`; the rest keep their order): under `-n 3 --dist
# loadfile` each worker takes whole files in this order, so the workers finish together instead of one of them
# starting a long file when the others are done.
LONGEST_FIRST = ("test_service_jobs.py", "test_leaderboard.py", "test_ray.py", "test_service.py",
                 "test_service_hostile.py", "test_service_faults.py", "test_vector_agents.py", "test_evaluate.py",
                 "test_training_data.py", "test_service_sandbox.py", "test_imitation.py", "test_varibad.py",
                 "test_service_browser.py")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Run the longest files first."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
