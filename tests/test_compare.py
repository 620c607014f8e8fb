"""`mewa-bench compare`: runs grouped by algorithm, refused runs named, the table and the PNG."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from mewa_bench.design.suites import Suite, load_suite
from mewa_bench.game.normalise import return_bounds
from mewa_bench.leaderboard.compare import CompareError, compare
from mewa_bench.protocol.config import env_seed
from mewa_bench.protocol.results import PROTOCOL_VERSION, SCHEMA_VERSION, write_results
from mewa_bench.protocol.scoring import score_units

K = 10
SEEDS = [0, 1, 2]


def results(suite: Suite, name: str, level: float, rng: np.random.Generator, seeds: list[int] = SEEDS,
            pairs: list[int] | None = None) -> dict:
    """A complete results dict of a synthetic agent scoring about `level` on every pair."""
    units = []
    for pair in suite.pairs:
        if pairs is not None and pair.index not in pairs:
            continue
        lo, hi = return_bounds(suite.tasks[pair.task_index])
        for s in seeds:
            normalised = ((level + rng.normal(0.0, 0.02, K)) * pair.max_expected).tolist()
            units.append({"pair": pair.index, "seed": s, "task": pair.task_index,
                          "env_seeds": [env_seed(suite.sha256, pair.index, s, k) for k in range(K)],
                          "returns": [lo + v * (hi - lo) for v in normalised], "normalised_returns": normalised,
                          "lengths": [20] * K, "scores": [v / pair.max_expected for v in normalised]})
    scores = score_units(suite, units, suite.summary["score"]["random_task_specific"], samples=50)
    return {"schema_version": SCHEMA_VERSION, "protocol_version": PROTOCOL_VERSION, "complete": pairs is None,
            "agent": {"name": name, "file": "agent.py", "sha256": hashlib.sha256(name.encode()).hexdigest(),
                      "privileged": False, "agent_args": {}, "checkpoint": None},
            "suite": {"name": suite.name, "version": suite.content["version"], "sha256": suite.sha256},
            "env": {"id": suite.content["env_id"], "version": "v0", "mode": "vector"}, "package_version": "0.1.0",
            "seeds": seeds, "episodes_per_pair": K, "pairs": pairs, "units": units, "scores": scores.to_dict(),
            "baselines": {"score": suite.summary["score"], "skill": suite.summary["skill"]}}


def run_folder(root: Path, algorithm: str, seed: int, suite: Suite, level: float, **kw) -> Path:
    """runs/<algo>-<suite>-seed<s>/ with run.json and its results file."""
    folder = root / f"{algorithm}-{suite.name}-seed{seed}"
    folder.mkdir(parents=True)
    (folder / "run.json").write_text(json.dumps({"algorithm": algorithm, "seed": seed, "suite": suite.name}))
    write_results(folder / f"results-{suite.name}.json",
                  results(suite, folder.name, level, np.random.default_rng(seed + 100 * len(algorithm)), **kw))
    return folder


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    narrow = load_suite("narrow-v1")
    root = tmp_path_factory.mktemp("runs")
    for s in range(3):
        run_folder(root, "good", s, narrow, 0.95 + 0.01 * s)
        run_folder(root, "weak", s, narrow, 0.70 + 0.02 * s)
    run_folder(root, "single", 0, narrow, 0.8)
    return root


def test_runs_are_grouped_by_algorithm_and_compared(runs: Path) -> None:
    compared = compare([str(runs / "good-*"), str(runs / "weak-narrow-v1-seed*"), str(runs / "single-narrow-v1-seed0")])
    by = {a.algorithm: a for a in compared.comparison.algorithms}
    assert set(by) == {"good", "weak", "single"}
    assert len(by["good"].runs) == 3 and by["good"].note == "" and "cannot include" in by["single"].note
    p = compared.comparison.improvement[("good", "weak")]
    assert p.mean == 1.0 and p.low is not None and p.low > 0.5


def test_a_run_listed_twice_is_refused(runs: Path) -> None:
    folder = runs / "good-narrow-v1-seed0"
    with pytest.raises(CompareError, match="listed twice") as e:
        compare([str(folder), str(folder / "results-narrow-v1.json")])
    assert "good-narrow-v1-seed0" in str(e.value)


def test_runs_of_another_suite_partial_runs_and_other_seeds_are_refused(runs: Path, tmp_path: Path) -> None:
    v2 = load_suite("narrow-v2")
    other = run_folder(tmp_path, "good", 7, v2, 0.9)
    with pytest.raises(CompareError, match=r"a run on narrow-v2, not narrow-v1") as e:
        compare([str(runs / "good-narrow-v1-seed0"), str(other)])
    assert str(other) in str(e.value)
    with pytest.raises(CompareError, match="a run on narrow-v2, not narrow-v1"):
        compare([str(other / "results-narrow-v2.json")], suite="narrow-v1")
    partial = run_folder(tmp_path, "part", 1, load_suite("narrow-v1"), 0.9, pairs=[0, 1])
    with pytest.raises(CompareError, match="unranked partial run") as e:
        compare([str(runs / "good-narrow-v1-seed0"), str(partial)])
    assert str(partial) in str(e.value)
    seeds = run_folder(tmp_path, "seeds", 1, load_suite("narrow-v1"), 0.9, seeds=[0, 1])
    with pytest.raises(CompareError, match="seeds") as e:
        compare([str(runs / "good-narrow-v1-seed0"), str(seeds)])
    assert str(seeds) in str(e.value)


def test_the_compare_command_prints_verdicts_and_writes_the_png(runs: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    png = tmp_path / "cmp.png"
    result = CliRunner().invoke(app, ["compare", str(runs / "good-*"), str(runs / "weak-*"), "--out", str(png)],
                                env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "good vs weak on narrow-v1: probability of improvement 1.0000" in result.output
    assert "good better" in result.output and png.stat().st_size > 0
    twice = CliRunner().invoke(app, ["compare", str(runs / "good-*"), str(runs / "good-narrow-v1-seed1")])
    assert twice.exit_code == 1 and "listed twice" in twice.output


def test_a_run_of_another_protocol_is_refused_naming_the_file(runs: Path, tmp_path: Path) -> None:
    old = tmp_path / "old-narrow-v1-seed0"
    shutil.copytree(runs / "good-narrow-v1-seed0", old)
    path = old / "results-narrow-v1.json"
    content = json.loads(path.read_text())
    content["protocol_version"] = 1
    path.write_text(json.dumps(content))
    with pytest.raises(CompareError, match="protocol") as e:
        compare([str(runs / "good-narrow-v1-seed1"), str(old)])
    assert str(path) in str(e.value)
