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
    for order in ([str(runs / "good-*"), str(seeds)], [str(seeds), str(runs / "good-*")]):  # whatever the order
        with pytest.raises(CompareError, match="seeds") as e:
            compare(order)
        assert str(e.value).startswith(str(seeds / "results-narrow-v1.json"))
        assert "evaluated with 2 seeds (0..1), the other runs with 3 seeds (0..2)" in str(e.value)
        assert "re-evaluate it with --seeds 3" in str(e.value)


def test_the_compare_command_prints_verdicts_and_writes_the_png(runs: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    png = tmp_path / "cmp.png"
    result = CliRunner().invoke(app, ["compare", str(runs / "good-*"), str(runs / "weak-*"), "--out", str(png)],
                                env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "good vs weak: P(X > Y) 1.0000" in result.output
    assert "good better" in result.output and png.stat().st_size > 0
    assert (tmp_path / "cmp-gap-won.png").stat().st_size > 0
    for term in ("gap won:", "IQM:", "P(X > Y): probability of improvement", "verdicts: one-sided tests"):
        assert term in result.output  # a line defining each statistic
    assert f"good <- {runs / 'good-narrow-v1-seed0' / 'results-narrow-v1.json'} (by run.json)" in result.output
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


def test_a_seed_mismatch_with_the_protocols_seeds_says_omit_seeds() -> None:
    from mewa_bench.leaderboard.compare import common_seeds
    from mewa_bench.protocol.config import default_seeds

    default = list(default_seeds("narrow-v1"))
    runs = [(Path(f"run{i}.json"), {"suite": {"name": "narrow-v1"}, "seeds": seeds})
            for i, seeds in enumerate([[0, 1, 2], default, default])]
    for order in (runs, runs[::-1]):
        with pytest.raises(CompareError) as e:
            common_seeds(order)
        message = str(e.value)
        assert message.startswith("run0.json: evaluated with 3 seeds (0..2), the other runs with 256 seeds (0..255)")
        assert "(omit --seeds)" in message and "0,1,2,3" not in message


def loose_file(folder: Path, name: str, level: float, seed: int) -> Path:
    """A results file alone in a folder (no run.json, no agent.py): grouped by the agent name inside it."""
    folder.mkdir(parents=True)
    path = folder / "results-narrow-v1.json"
    write_results(path, results(load_suite("narrow-v1"), name, level, np.random.default_rng(seed)))
    return path


def test_algorithm_options_name_the_runs_as_asked_and_say_how_each_was_grouped(runs: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from mewa_bench.cli import app
    from mewa_bench.leaderboard.compare import BY_AGENT, BY_OPTION, BY_RUN_JSON

    long = "my_agent_with_a_rather_long_descriptive_name_that_a_narrow_terminal_would_cut"
    for seed in range(3):  # three training runs of one agent file: the same agent name in every results file
        loose_file(tmp_path / "mine" / f"seed{seed}", long, 0.85 + 0.01 * seed, seed)
    loose_file(tmp_path / "other" / "a", long, 0.6, 7)  # another algorithm's run, under the same agent name
    alone = compare([str(tmp_path / "mine" / "*"), str(tmp_path / "other" / "a")])
    assert [(len(a.runs), a.algorithm) for a in alone.comparison.algorithms] == [(4, long)]  # grouped by name...
    assert {g.by for g in alone.groupings} == {BY_AGENT}  # ...and it says so
    asked = compare([str(runs / "good-*")], algorithms=[f"{long}-tuned=" + str(tmp_path / "mine" / "*"),
                                                        f"{long}-other=" + str(tmp_path / "other" / "a")])
    assert [(a.algorithm, len(a.runs)) for a in asked.comparison.algorithms] == [
        (f"{long}-tuned", 3), (f"{long}-other", 1), ("good", 3)]  # in the order given: --algorithm ones first
    assert [g.by for g in asked.groupings] == [BY_OPTION] * 4 + [BY_RUN_JSON] * 3
    result = CliRunner().invoke(app, ["compare", str(runs / "good-*"), "--algorithm", f"{long}-tuned={tmp_path}/mine/*",
                                      "--algorithm", f"{long}-other={tmp_path}/other/a",
                                      "--out", str(tmp_path / "c.png")], env={"COLUMNS": "80"})
    assert result.exit_code == 0, result.output
    assert "…" not in result.output  # no name is cut: two long names never print as one label
    assert f"{long}-tuned <- {tmp_path}/mine/seed0/results-narrow-v1.json (by --algorithm)" in result.output
    with pytest.raises(CompareError, match="expected NAME=GLOB"):
        compare([], algorithms=["no-pattern"])
