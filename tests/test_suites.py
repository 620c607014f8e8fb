"""Shipped suites: integrity, byte-for-byte regeneration, and the benchmark property."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import mewa_bench  # noqa: F401
from mewa_bench.design import exact
from mewa_bench.design.curate import ratios_to_best
from mewa_bench.design.generate import generate_suite
from mewa_bench.design.policies import policy_names
from mewa_bench.design.suites import SHIPPED_SUITES, SuiteError, content_hash, load_suite, shipped_path, suite_text
from mewa_bench.game.distributions import in_test_region, is_non_increasing, sample_train_workers


@pytest.mark.parametrize("name", SHIPPED_SUITES)
def test_shipped_suite_loads_and_matches_its_hash(name: str) -> None:
    suite = load_suite(name)
    assert suite.name == name
    assert suite.sha256 == content_hash(suite.content) == suite.content["sha256"]
    assert shipped_path(name).read_text() == suite_text(suite.content)


@pytest.mark.parametrize("kind", ["narrow", pytest.param("wide", marks=pytest.mark.slow)])  # wide: about 30 s
def test_generate_reproduces_the_shipped_file_byte_for_byte(kind: str) -> None:
    text = suite_text(generate_suite(kind))
    assert text == shipped_path(f"{kind}-v1").read_text()


def test_tampered_and_truncated_suites_are_rejected(tmp_path: Path) -> None:
    content = json.loads(shipped_path("narrow-v1").read_text())
    content["pairs"][0]["worker"][3] = 0.5
    tampered = tmp_path / "tampered.json"
    tampered.write_text(json.dumps(content))
    with pytest.raises(SuiteError, match=r"tampered\.json.*does not match its recorded hash"):
        load_suite(tampered)
    truncated = tmp_path / "truncated.json"
    truncated.write_text(shipped_path("narrow-v1").read_text()[:5000])
    with pytest.raises(SuiteError, match=r"truncated\.json.*not valid JSON"):
        load_suite(truncated)
    with pytest.raises(SuiteError, match="unknown suite"):
        load_suite("narrow-v9")


@pytest.mark.parametrize("name", SHIPPED_SUITES)
def test_benchmark_property_no_single_policy_is_enough(name: str) -> None:
    suite = load_suite(name)
    for t, task in enumerate(suite.tasks):
        values = np.array([p.data["toptimal"] for p in suite.pairs if p.task_index == t])
        ratio = ratios_to_best(values)
        assert ratio.min(axis=0).max() < 0.99, f"{task.name}: one policy is >= 0.99 on every worker"
    gap = suite.summary["non_adaptive_gap"]
    assert gap >= 0.005, f"{name}: non-adaptive gap {gap} is not clearly above 0"
    # The gap is what the pairs say it is.
    ratios = [p.data["best_fixed"] / p.max_expected for p in suite.pairs]
    assert gap == pytest.approx(1.0 - np.mean(ratios), abs=1e-11)


def test_canonical_design_quality() -> None:
    suite = load_suite("narrow-v1")
    task = suite.tasks[0]
    assert (task.order, task.K, task.M, task.worker_blocks) == ((3, 1, 2, 0), 5, 3, (2, 2, 4, 0))
    assert -1.0 <= task.rewards[0] < -0.1
    # MAD of the t-optimal returns at the average worker: paper 0.013.
    values = exact.expected_returns(task, policy_names(4, baselines=False), [task.average_worker])[:, 0]
    mad = np.abs(values - values.mean()).mean()
    assert mad <= 0.013
    assert suite.content["tasks"][0]["design"]["mad_at_average_worker"] == pytest.approx(mad, abs=1e-11)


@pytest.mark.parametrize("name", SHIPPED_SUITES)
def test_reference_values_are_consistent(name: str) -> None:
    suite = load_suite(name)
    for p in suite.pairs:
        d, task = p.data, suite.tasks[p.task_index]
        assert len(p.worker.w) == task.N and is_non_increasing(np.array(p.worker.w))
        assert d["baselines"]["max_expected"] == max(d["toptimal"])
        assert d["best_fixed"] in d["toptimal"]
        assert d["known_worker_optimum"] >= d["baselines"]["max_expected"] - 1e-12
        assert d["baselines"]["random"] < d["baselines"]["random_task_specific"] <= d["baselines"]["max_expected"]
    # Spot-check stored values against the engine.
    p = suite.pairs[0]
    task = suite.tasks[p.task_index]
    again = exact.expected_returns(task, policy_names(task.N, baselines=False), [p.worker.w])[:, 0]
    np.testing.assert_allclose(again, p.data["toptimal"], atol=1e-11)


@pytest.mark.parametrize("name", SHIPPED_SUITES)
def test_curated_workers_are_meta_test_and_never_sampled_for_training(name: str) -> None:
    suite = load_suite(name)
    rng = np.random.default_rng(0)
    for t, task in enumerate(suite.tasks):
        curated = np.array([p.worker.w for p in suite.pairs if p.task_index == t])
        assert in_test_region(task, curated).all()
        train = sample_train_workers(task, rng, 5000, include_centre=True)
        assert not in_test_region(task, train).any()
        # No train worker coincides with a curated one.
        assert not (np.abs(train[:, None, :] - curated[None, :, :]).max(axis=2) < 1e-12).any()


def test_default_env_plays_the_canonical_narrow_task() -> None:
    env = gym.make("mewa/MEWA-v0")
    env.reset(seed=0)
    assert env.unwrapped.task == load_suite("narrow-v1").tasks[0]
    assert not in_test_region(env.unwrapped.task, np.array(env.unwrapped.worker.w))


def test_design_report_is_generated_from_the_suites(tmp_path: Path) -> None:
    """The report of the two narrow suites: its figures, and each suite's section word for word as the shipped
    docs/suites.md has it (the whole report with the wide suites: the slow tier's test below)."""
    from matplotlib.image import imread

    from mewa_bench.reports.suite_report import policy_ratio_stats, write_report

    paths = write_report(tmp_path, ("narrow-v1", "narrow-v2"))
    text = (tmp_path / "suites.md").read_text()
    narrow = load_suite("narrow-v1")
    assert narrow.sha256 in text
    assert f"{narrow.summary['non_adaptive_gap']:.4f}" in text
    names, stats = policy_ratio_stats(narrow, 0)
    assert len(names) == 19 and (stats[:, 1] <= stats[:, 0]).all() and (stats[:, 0] <= stats[:, 2]).all()
    for png in paths[1:]:
        image = imread(png)
        assert image.ndim == 3 and image.shape[0] > 200 and image.shape[1] > 600
    shipped = (Path(__file__).resolve().parents[1] / "docs" / "suites.md").read_text()
    sections = text.split("\n## ")[1:]
    assert [section.split("\n")[0] for section in sections][-2:] == ["narrow-v1", "narrow-v2"]
    for section in sections[-2:]:
        assert "\n## " + section in shipped, section.split("\n")[0]


@pytest.mark.slow  # every suite's section and figure: about 45 s; the narrow suites' run by default (above)
def test_the_shipped_design_report_is_the_generated_one(tmp_path: Path) -> None:
    from mewa_bench.reports.suite_report import write_report

    write_report(tmp_path)
    shipped = Path(__file__).resolve().parents[1] / "docs" / "suites.md"
    assert shipped.read_text() == (tmp_path / "suites.md").read_text()


def test_generate_check_compares_without_writing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from typer.testing import CliRunner

    from mewa_bench.cli import app

    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["generate", "narrow", "--check"])
    assert result.exit_code == 0, result.output
    assert "byte-identical to the shipped narrow-v1.json: yes" in " ".join(result.output.split())
    assert list(tmp_path.iterdir()) == []  # --check alone writes nothing
