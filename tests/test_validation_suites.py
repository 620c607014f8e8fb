"""Validation suites: byte-for-byte reproducible, drawn from the meta-train distribution, never a test worker."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mewa_bench.design.suites import ALL_SUITES, load_suite, shipped_path, suite_text
from mewa_bench.design.validation import validation_suite_content
from mewa_bench.game.distributions import in_test_region


@pytest.mark.parametrize("name", ALL_SUITES)
def test_a_validation_suite_is_regenerated_byte_for_byte_and_holds_no_test_worker(name: str) -> None:
    validation = load_suite(f"{name}-validation")  # by name, its hash checked
    assert suite_text(validation_suite_content(name)) == shipped_path(f"{name}-validation").read_text()
    suite = load_suite(name)
    without_curation = lambda t: {k: v for k, v in t.to_dict().items() if k != "curation"}  # noqa: E731
    assert [without_curation(t) for t in validation.tasks] == [without_curation(t) for t in suite.tasks]
    for task in validation.tasks:  # its own curation's figures, not the test pairs'
        assert task.extra["curation"]["candidates"] == validation.content["generator"]["pool"]
    assert validation.content["generator"]["suite_sha256"] == suite.sha256
    tested = {tuple(p.worker.w) for other in ALL_SUITES for p in load_suite(other).pairs}
    for pair in validation.pairs:
        task = validation.tasks[pair.task_index]
        w = np.asarray(pair.worker.w)
        assert tuple(pair.worker.w) not in tested
        if name.endswith("-v1"):  # v1 meta-train draws lie inside the paper's box, never in the test region
            assert not in_test_region(task, w), (name, pair.index, w)
        else:  # v2 ones may lie anywhere (the cover sampler) but 0.01 clear of the 0.05 grid of test candidates
            assert np.max(np.abs(w - 0.05 * np.round(w / 0.05))) >= 0.01 - 1e-9, (name, pair.index, w)
    per_task = np.bincount([p.task_index for p in validation.pairs])
    assert per_task.min() == per_task.max() == validation.content["generator"]["cap"]


def test_v2_validation_pairs_leave_room_to_adapt() -> None:
    """Curated like the suite, the v2 validation pairs are ones where no fixed policy does well everywhere."""
    for name in ("narrow-v2", "wide-v2"):
        score = load_suite(f"{name}-validation").content["summary"]["score"]
        assert score["best_fixed"] < 0.85 and score["known_worker_optimum"] >= 1.0, (name, score)


def test_a_run_on_a_validation_suite_is_scored_but_never_ranked(tmp_path) -> None:
    from mewa_bench.leaderboard.validate import InvalidResults, SuiteCache, load_entry
    from mewa_bench.protocol.config import EvalConfig
    from mewa_bench.protocol.runner import evaluate

    random_agent = Path(__file__).resolve().parents[1] / "submissions" / "random" / "agent.py"
    results, _ = evaluate(EvalConfig(agent_path=random_agent, suite="narrow-v2-validation", seeds=(0, 1, 2, 3),
                                     out=tmp_path / "results.json", isolated=False))
    exact = load_suite("narrow-v2-validation").content["summary"]["score"]["random"]
    mean = results["scores"]["mean"]
    assert mean["low"] <= exact <= mean["high"], (mean, exact)
    with pytest.raises(InvalidResults, match="'narrow-v2-validation' is a validation suite .*never ranked"):
        load_entry(tmp_path / "results.json", SuiteCache())
