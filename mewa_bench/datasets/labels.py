"""Per-frame exact labels: the known-worker optimal action for the frame's state and steps left.

The finite-horizon optimum of `mewa_bench.design.optimum` (time-dependent: with t steps taken,
T - t steps are left), computed for blocks of workers at once and reported only at the points the
frames visit. Ties go to the lowest action.
"""

from __future__ import annotations

import numpy as np

from mewa_bench.design.optimum import optimal_actions_at
from mewa_bench.game.task import Task


def optimal_labels(task: Task, workers: np.ndarray, owner: np.ndarray, t: np.ndarray,
                   state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Optimal action of each frame (worker row `owner[f]`, step `t[f]`, table state `state[f]`), int64 [F],
    and each worker's known-worker optimal raw return, float64 [W]."""
    return optimal_actions_at(task, np.asarray(workers)[:, : task.N], owner, task.T - np.asarray(t), state)
