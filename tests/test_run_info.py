"""run.json: which algorithm a run belongs to; `train` writes it and names runs <algo>-<suite>-seed<s>."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mewa_bench.protocol.run_info import RunInfo, RunInfoError, read_run_info, run_name, write_run_info

SUBMISSIONS = Path(__file__).resolve().parents[1] / "submissions"


def test_absent_file_means_a_one_run_algorithm_named_after_the_folder(tmp_path: Path) -> None:
    folder = tmp_path / "my-agent"
    folder.mkdir()
    assert read_run_info(folder) == RunInfo(algorithm="my-agent")
    assert read_run_info(folder, "given").algorithm == "given"


def test_written_and_read_back(tmp_path: Path) -> None:
    info = RunInfo(algorithm="rl2", seed=4, suite="narrow-v2", steps=2_000_000, notes="lr 3e-4")
    path = write_run_info(tmp_path, info)
    assert path.name == "run.json" and read_run_info(tmp_path) == info
    assert json.loads(path.read_text()) == {"algorithm": "rl2", "seed": 4, "suite": "narrow-v2", "steps": 2_000_000,
                                            "notes": "lr 3e-4"}


@pytest.mark.parametrize("content, fragment", [
    ("[1]", "must be a JSON object"), ('{"seed": 1}', "`algorithm` must be a non-empty string"),
    ('{"algorithm": "a", "seed": "1"}', "`seed` must be an integer"), ('{"algorithm": "a", "steps": 0}', "positive"),
    ('{"algorithm": "a", "colour": 1}', "unknown field(s) ['colour']"), ("{oops", "cannot read it as JSON")])
def test_bad_files_are_refused_naming_the_file(tmp_path: Path, content: str, fragment: str) -> None:
    (tmp_path / "run.json").write_text(content)
    with pytest.raises(RunInfoError) as e:
        read_run_info(tmp_path)
    assert str(tmp_path / "run.json") in str(e.value) and fragment in str(e.value)


def test_every_shipped_learned_run_says_its_algorithm_seed_suite_and_budget() -> None:
    learned = sorted(p.parent for p in SUBMISSIONS.glob("*/checkpoint.pt"))
    assert learned
    for folder in learned:
        info = read_run_info(folder)
        assert run_name(info.algorithm, info.suite, info.seed) == folder.name
        assert f"--seed {info.seed} --steps {info.steps}" in (folder / "README.md").read_text()


def test_train_names_each_seeds_run_after_algorithm_suite_and_seed(tmp_path: Path) -> None:
    pytest.importorskip("torch")
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    result = CliRunner().invoke(app, ["train", "maml", "--suite", "narrow-v1", "--seed", "1", "--seed", "2",
                                      "--steps", "1", "--out", str(tmp_path)], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    for seed in (1, 2):
        folder = tmp_path / f"maml-narrow-v1-seed{seed}"
        info = read_run_info(folder)
        assert (info.algorithm, info.seed, info.suite) == ("maml", seed, "narrow-v1") and info.steps >= 1
        assert (folder / "agent.py").exists()
