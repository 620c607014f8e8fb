"""Task and Worker validation and JSON round trips."""

from __future__ import annotations

import json

import pytest

from mewa_bench.game import Task, Worker

GOOD = dict(colors=[0, 1, 2, 3], order=[3, 1, 2, 0], K=5, M=3, rewards=[-0.4, -0.3, -0.2, -0.1],
            worker_blocks=[2, 2, 4, 0])


@pytest.mark.parametrize("change, field", [
    ({"M": 6}, "'M'"),
    ({"M": 1}, "'M'"),
    ({"order": [3, 1, 2, 2]}, "'order'"),
    ({"order": [3, 1, 2]}, "'order'"),
    ({"colors": [0, 1, 2, 3, 4]}, "'colors'"),
    ({"colors": [0, 0, 2, 3]}, "'colors'"),
    ({"colors": [0]}, "'colors'"),
    ({"rewards": [-0.4, -0.3, -0.3, -0.1]}, "'rewards'"),
    ({"rewards": [-0.4, -0.3, -0.2, 0.1]}, "'rewards'"),
    ({"rewards": [-0.4, -0.3, -0.2]}, "'rewards'"),
    ({"worker_blocks": [2, 2, 4]}, "'worker_blocks'"),
    ({"worker_blocks": [2, -2, 4, 0]}, "'worker_blocks'"),
    ({"worker_blocks": [2, 2.5, 4, 0]}, "'worker_blocks'"),
    ({"average_worker": [0.5, 0.4, 1.2, 0.1]}, "'average_worker'"),
    ({"average_worker": [0.5, 0.4]}, "'average_worker'"),
    ({"sigma": [0.1, 0.1, 0.1, -0.1], "average_worker": [0.5, 0.4, 0.3, 0.1]}, "'sigma'"),
    ({"T": 0}, "'T'"),
])
def test_invalid_task_names_the_field(change: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        Task.from_dict({**GOOD, **change})


def test_missing_field_is_named() -> None:
    d = dict(GOOD)
    del d["worker_blocks"]
    with pytest.raises(ValueError, match="worker_blocks"):
        Task.from_dict(d)


def test_task_json_round_trip(canonical_task: Task) -> None:
    text = json.dumps(canonical_task.to_dict())
    again = Task.from_dict(json.loads(text))
    assert again == canonical_task
    assert again.to_dict() == canonical_task.to_dict()


def test_worker_validation() -> None:
    assert Worker.of([0.5, 0.25, 0.0]).to_list() == [0.5, 0.25, 0.0]
    with pytest.raises(ValueError, match="outside"):
        Worker((0.5, 1.5))
    with pytest.raises(ValueError, match="N = 4"):
        Worker((0.5, 0.5, 0.1)).check_fits(Task.from_dict(GOOD))
