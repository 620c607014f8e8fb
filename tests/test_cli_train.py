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
    per = settings.num_envs * settings.num_steps
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
