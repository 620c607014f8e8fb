"""The CLI at 80 columns: the evaluate summary keeps its labels whole, help pages stay short."""

from __future__ import annotations

import re

import pytest
from rich.console import Console
from typer.testing import CliRunner

from mewa_bench.cli import app
from mewa_bench.cli.results_tables import REFERENCE_LINES, results_table

REFERENCES = {"random": (0.3167, -0.5657), "random_task_specific": (0.5635, 0.0), "best_fixed": (0.5625, -0.0024),
              "max_expected": (1.0, 1.0), "known_worker_optimum": (1.0002, 1.0004)}


def ci(mean: float, low: float | None, high: float | None) -> dict[str, float | None]:
    return {"mean": mean, "low": low, "high": high}


def results(name: str, privileged: bool = False, intervals: bool = True) -> dict:
    """A finished run's results, as `evaluate` returns them (only the fields the summary reads)."""
    def interval(mean: float, half: float) -> dict[str, float | None]:
        return ci(mean, mean - half, mean + half) if intervals else ci(mean, None, None)

    return {"agent": {"name": name, "privileged": privileged}, "suite": {"name": "narrow-v2"},
            "units": [{}] * 4096, "protocol_version": 2, "complete": True,
            "scores": {"mean": interval(0.9508, 0.0011), "iqm": ci(0.9532, None, None),
                       "curve": [ci(0.5533 + 0.0496 * k, None, None) for k in range(10)],
                       "adaptability": interval(0.4467, 0.0107), "skill": ci(0.3883, None, None),
                       "verdicts": {"adapts": True, "beats_best_fixed": True},
                       "comparisons": {"best_fixed": {"difference": interval(0.3883, 0.0011)}}},
            "baselines": {"score": {k: v[0] for k, v in REFERENCES.items()},
                          "skill": {k: v[1] for k, v in REFERENCES.items()}}}


def rendered(data: dict, width: int = 80) -> str:
    console = Console(width=width, record=True, force_terminal=False, color_system=None)
    console.print(results_table(data))
    return console.export_text()


@pytest.mark.parametrize("name", ["bayes-explorer", "varibad-narrow-v2-seed1", "oracle-t-optimal"])
def test_the_summary_fits_80_columns_with_whole_labels(name: str) -> None:
    text = rendered(results(name, privileged=name.startswith("oracle")))
    lines = text.splitlines()
    assert "…" not in text and max(len(line) for line in lines) <= 80
    cells = {row[0]: row[1:] for row in (re.split(r"\s{2,}", line.strip()) for line in lines) if len(row) > 1}
    for key, label in REFERENCE_LINES:
        score, skill = REFERENCES[key]
        assert cells[label] == [f"{score:.4f}", f"{skill:.4f}"], label
    assert cells[name] == ["0.9508", "0.9532", "0.5533", f"{0.5533 + 0.0496 * 9:.4f}", "0.4467", "0.3883"]
    assert ("(privileged)" in text) == name.startswith("oracle")
    words = " ".join(text.split())
    assert "score [0.9497, 0.9519]" in words and "adapt. [0.4360, 0.4574]" in words
    assert "verdicts: adapts; beats the best fixed policy (paired difference 0.3883 [0.3872, 0.3894])" in words
    assert "4096 pair x seed units" in words


def test_the_summary_says_when_there_is_no_interval() -> None:
    words = " ".join(rendered(results("a", intervals=False)).split())
    assert "score [CI needs 2+ seeds per pair]" in words


def test_evaluate_help_is_short_at_80_columns() -> None:
    result = CliRunner().invoke(app, ["evaluate", "--help"], env={"COLUMNS": "80"})
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert max(len(line) for line in lines) <= 80
    assert len(lines) <= 85, len(lines)  # one line per flag plus its wrapped help, no --flag/--no-flag column
    assert all(f"--{flag}" in result.output for flag in ("log-pairs", "log-seeds", "privileged", "resume"))


COMMANDS = [["evaluate"], ["record"], ["view"], ["leaderboard"], ["generate"], ["train"], ["rollout"]]
NEGATIVE_FLAGS_IN_USE = {"--no-strict"}  # `leaderboard --no-strict` is documented and tested


@pytest.mark.parametrize("command", COMMANDS, ids=" ".join)
def test_boolean_flags_are_single_flags(command: list[str]) -> None:
    result = CliRunner().invoke(app, [*command, "--help"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert set(re.findall(r"--no-[a-z-]+", result.output)) <= NEGATIVE_FLAGS_IN_USE


def test_the_dataset_catalog_reads_at_80_columns() -> None:
    """Every dataset name whole, no header cut, at 80 columns; every column at 120."""
    from mewa_bench.datasets.catalog import load_catalog
    from mewa_bench.datasets.training_data import TRAINING_DATASETS

    content = load_catalog(None)
    names = [e["name"] for e in content["datasets"] + content["evaluation_recordings"]] + list(TRAINING_DATASETS)
    narrow = CliRunner().invoke(app, ["datasets", "list"], env={"COLUMNS": "80"})
    assert narrow.exit_code == 0, narrow.output
    assert max(map(len, narrow.output.splitlines())) <= 80
    assert all(re.search(rf"^\s*{re.escape(name)}\s", narrow.output, re.M) for name in names), narrow.output
    assert all(re.fullmatch(r"[0-9a-f]{10,}", cut) for cut in re.findall(r"(\S*)…", narrow.output))  # sha256s only
    assert "episodes" in narrow.output and "frames" in narrow.output
    wide = CliRunner().invoke(app, ["datasets", "list"], env={"COLUMNS": "200"})
    assert all(header in wide.output for header in ("suite", "tier", "policy", "source", "size"))
