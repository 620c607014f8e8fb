"""Shipped learned agents (a checkpoint in their submission folder) reproduce their committed results."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.results import read_results
from mewa_bench.protocol.runner import evaluate

SUBMISSIONS = Path(__file__).resolve().parents[1] / "submissions"
CHECKPOINTED = sorted(p for p in SUBMISSIONS.glob("*/results-*.json") if (p.parent / "checkpoint.pt").exists())
SAMPLE_PAIRS, SAMPLE_SEEDS = (0, 1), (0, 1)  # the whole file would take minutes per checkpoint


def algorithm_of(results_path: Path) -> str:
    """The algorithm a shipped run belongs to (its run.json, else the folder name up to the suite)."""
    run = results_path.parent / "run.json"
    if run.exists():
        return json.loads(run.read_text())["algorithm"]
    return results_path.parent.name.split("-narrow-")[0].split("-wide-")[0]


def one_per_algorithm(paths: list[Path]) -> set[Path]:
    """The first shipped run of each algorithm: their replays run by default, every other one in the slow tier."""
    firsts: dict[str, Path] = {}
    for path in paths:
        firsts.setdefault(algorithm_of(path), path)
    return set(firsts.values())


DEFAULT_TIER = one_per_algorithm(CHECKPOINTED)


@pytest.mark.skipif(not CHECKPOINTED, reason="no learned submissions shipped")
@pytest.mark.parametrize("results_path", [p if p in DEFAULT_TIER else pytest.param(p, marks=pytest.mark.slow)
                                          for p in CHECKPOINTED], ids=lambda p: f"{p.parent.name}/{p.name}")
def test_a_shipped_checkpoint_replays_its_committed_units(results_path: Path, tmp_path: Path) -> None:
    committed = read_results(results_path)
    config = EvalConfig(agent_path=results_path.parent / "agent.py", suite=committed["suite"]["name"],
                        seeds=SAMPLE_SEEDS, pairs=SAMPLE_PAIRS, agent_args=committed["agent"]["agent_args"],
                        isolated=False, out=tmp_path / "again.json")
    again, _ = evaluate(config)
    assert again["agent"]["sha256"] == committed["agent"]["sha256"]
    by_key = {(u["pair"], u["seed"]): u for u in committed["units"]}
    for unit in again["units"]:
        old = by_key[(unit["pair"], unit["seed"])]
        for field in ("env_seeds", "returns", "normalised_returns", "lengths"):
            assert unit[field] == old[field], (results_path.name, unit["pair"], unit["seed"], field)


OFFLINE_RUNS = sorted(p for p in SUBMISSIONS.glob("*/run.json")
                      if json.loads(p.read_text()).get("settings", {}).get("dataset"))


@pytest.mark.skipif(not OFFLINE_RUNS, reason="no offline runs shipped")
def test_every_offline_run_names_the_recorded_archive_it_learnt_from() -> None:
    """An offline run's run.json names its dataset and that build's archive sha256, as the catalog records it."""
    from mewa_bench.datasets.catalog import load_catalog

    catalog = load_catalog(SUBMISSIONS.parent / "datasets" / "index.json")
    builds = {(b["name"], b["sha256"]) for b in catalog.get("builds", [])}
    for path in OFFLINE_RUNS:
        info = json.loads(path.read_text())
        name = Path(info["settings"]["dataset"]).name
        found = re.search(rf"trained on {re.escape(name)}[ (].*?archive sha256 ([0-9a-f]{{64}})", info.get("notes", ""))
        assert found, f"{path}: notes do not name {name}'s archive sha256"
        assert (name, found.group(1)) in builds, f"{path}: {name} {found.group(1)} is not a recorded build"
