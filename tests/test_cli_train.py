"""`mewa-bench train`: the env steps it trains are whole updates, said before training starts."""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from mewa_bench.agents.training_io import ALGORITHMS, METRICS, load_algorithm, whole_updates
from mewa_bench.cli import app


@pytest.mark.parametrize("algo", list(ALGORITHMS))
@pytest.mark.parametrize("asked", [1, 100_000, 4_000_000])
def test_steps_round_up_to_whole_updates(algo: str, asked: int) -> None:
    settings = load_algorithm(algo).settings_from({"total_steps": asked})
    per = settings.steps_per_update
    if "dataset" in vars(settings):  # offline: meta-episodes or windows per update
        assert per == settings.batch
    else:  # online: env steps of every env per update
        assert per == settings.num_envs * settings.num_steps
    rounded = whole_updates(settings)
    assert rounded.total_steps == math.ceil(asked / per) * per
    assert rounded.total_steps >= asked and rounded.total_steps - asked < per
    assert whole_updates(rounded).total_steps == rounded.total_steps  # whole already: unchanged
    assert {k: v for k, v in vars(rounded).items() if k != "total_steps"} == \
        {k: v for k, v in vars(settings).items() if k != "total_steps"}


def test_train_prints_the_steps_it_trains_and_trains_exactly_those(tmp_path: Path) -> None:
    pytest.importorskip("torch")
    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["train", "varibad", "--steps", "1000", "--out", str(out)],
                                env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert "training 8,192 env steps per run (1 update of 8,192; --steps 1,000 rounded up to whole updates)" in text
    assert text.index("training 8,192 env steps") < text.index("wrote ")  # said before training
    assert "meta-train normalised return" in text and "not a score" in text
    with (out / METRICS).open(newline="") as f:
        assert [int(r["env_steps"]) for r in csv.DictReader(f)] == [8192]
    readme = (out / "README.md").read_text()
    assert "--steps 8192 " in readme and "'total_steps': 8192" in readme  # the command that reproduces the run


def test_shipped_runs_state_the_env_steps_they_trained() -> None:
    root = Path(__file__).resolve().parents[1] / "submissions"
    runs = sorted(root.glob("*/metrics.csv"))
    assert len(runs) >= 4
    for metrics in runs:
        with metrics.open(newline="") as f:
            trained = int(list(csv.DictReader(f))[-1]["env_steps"])
        readme = metrics.with_name("README.md").read_text()
        asked = int(re.search(r"mewa-bench train .*--steps (\d+)", readme).group(1))
        assert asked == trained or f"trained {trained:,} env steps" in readme, metrics.parent.name


def test_train_set_changes_settings_under_an_algorithm_name_of_its_own(tmp_path: Path) -> None:
    pytest.importorskip("torch")
    from mewa_bench.design.suites import DEFAULT_SUITE
    from mewa_bench.protocol.run_info import read_run_info

    result = CliRunner().invoke(app, ["train", "varibad", "--steps", "1", "--set", "latent=3", "--set",
                                      "step_rewards=true", "--algorithm", "varibad-small", "--seed", "2", "--seed", "3",
                                      "--out", str(tmp_path)], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    for seed in (2, 3):
        folder = tmp_path / f"varibad-small-{DEFAULT_SUITE}-seed{seed}"  # the default suite
        info = read_run_info(folder)
        assert (info.algorithm, info.seed, info.settings) == ("varibad-small", seed, {"latent": 3, "step_rewards": True})
        readme = (folder / "README.md").read_text()
        assert readme.startswith(f"# varibad-small ({DEFAULT_SUITE}, seed {seed})\n")  # its name on the boards
        assert "Training data:" not in readme  # an online run learns from no dataset
        assert "'latent': 3" in readme and "'step_rewards': True" in readme  # what the run was trained with
        command = re.search(r"mewa-bench train .*", readme).group(0)
        assert "--algorithm varibad-small --set latent=3 --set step_rewards=true" in command


@pytest.mark.parametrize("item, message", [
    ("latent", "expected KEY=VALUE"), ("width=3", "not a Settings setting; known:"),
    ("latent=0.5", "latent is a int"), ("step_rewards=yes", "expected true or false"),
    ("seed=4", "set it with train's own option"), ("workers=1", "set it with train's own option"),
])
def test_train_set_names_what_is_wrong(item: str, message: str) -> None:
    result = CliRunner().invoke(app, ["train", "varibad", "--set", item], env={"COLUMNS": "200"})
    assert result.exit_code == 2 and message in " ".join(result.output.split()), result.output
