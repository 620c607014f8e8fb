"""Task structures: every task a wide suite's generator can draw is one renaming of the colours of exactly one
structure, and a training dataset on them lists and plays those structures."""

from __future__ import annotations

import itertools
import json
from dataclasses import replace

import numpy as np
import pytest

from mewa_bench.datasets.generated_tasks import generated_tasks, task_structures
from mewa_bench.design.suites import load_suite
from mewa_bench.game.relabel import relabelled_task
from mewa_bench.game.task import Task


def game_of(task: Task) -> str:
    """What the game plays of a task (no name, no record of its design)."""
    fields = task.to_dict()
    for key in ("name", "design", "curation"):
        fields.pop(key, None)
    return json.dumps(fields, sort_keys=True)


@pytest.mark.parametrize("name", ["wide-v1", "wide-v2"])
def test_every_task_the_generator_draws_is_a_renaming_of_exactly_one_structure(name: str) -> None:
    suite = load_suite(name)
    structures = task_structures(suite)
    assert len(structures) == 2 * (7 + 21) * 3  # N 3 or 4; 8 blocks in 2 or 3 positive parts; (K, M) with M <= K
    renamed: dict[str, set[int]] = {}
    for i, structure in enumerate(structures):
        assert structure.colors == structure.order == tuple(range(structure.N))
        for p in itertools.permutations(range(4)):
            renamed.setdefault(game_of(relabelled_task(structure, p)), set()).add(i)
    assert len(renamed) == 24 * len(structures)  # no two structures are renamings of each other
    drawn = generated_tasks(suite, 400, np.random.default_rng(11)) + suite.tasks
    found = [renamed.get(game_of(task)) for task in drawn]
    assert all(f is not None and len(f) == 1 for f in found), [t.name for t, f in zip(drawn, found) if not f]
    assert len({next(iter(f)) for f in found}) > 100  # the draws spread over the structures
    assert task_structures(suite, ks=(3, 5)) == tuple(t for t in structures if t.K in (3, 5))  # the same, named alike


def test_a_narrow_suite_has_no_structures() -> None:
    with pytest.raises(ValueError, match="narrow-v2 has one task"):
        task_structures(load_suite("narrow-v2"))


@pytest.mark.slow  # about 40 s: the learner's model of each of the 168 candidate tasks
@pytest.mark.usefixtures("offline_hub")
def test_a_task_structures_dataset_lists_and_plays_the_structures(tmp_path) -> None:
    import pyarrow.parquet as pq

    from mewa_bench.datasets import build_training_dataset, check_training_dataset, training_spec
    from mewa_bench.datasets.lookup import buildable_description
    from mewa_bench.datasets.training_data import dataset_suite

    spec = replace(training_spec("wide-v2-train-task-structures", 1), meta_batch=2, history_episodes=2)
    meta = build_training_dataset(spec, tmp_path / "ds", jobs=1)
    structures = task_structures(load_suite("wide-v2"))
    assert meta["spec"]["task_structures"] is True and "generated_tasks" not in meta["spec"]
    assert dataset_suite(meta, tmp_path / "ds").tasks == structures
    assert check_training_dataset(tmp_path / "ds") == meta  # every worker in its structure's meta-train support
    played = {m["task"] for m in meta["meta_episodes"]}
    index = np.concatenate([pq.read_table(p).column("suite_task_index").to_numpy()
                            for p in sorted((tmp_path / "ds" / "data").rglob("*.parquet"))])
    assert set(index.tolist()) == played and played <= set(range(len(structures)))
    assert meta["behaviour"]["source"] == "mewa_bench/datasets/generator_histories.py"  # it knows every renaming
    assert "every structure" in meta["columns"]["suite_task_index"]
    assert "task structures" in meta["worker_distribution"]["task_choice"]
    assert "every structure" in buildable_description("wide-v2-train-task-structures", None)["tasks"]


def test_a_spec_with_generated_tasks_and_structures_is_a_clear_error() -> None:
    from mewa_bench.datasets import training_spec
    from mewa_bench.datasets.training_keys import TrainingDataError

    with pytest.raises(TrainingDataError, match="wide-v2-train-task-structures: a training dataset plays generated"):
        replace(training_spec("wide-v2-train-task-structures"), generated_tasks=200)
