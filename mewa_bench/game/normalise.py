"""Normalised return of an episode (SPEC section 2): 0 = worst possible, 1 = perfect episode."""

from __future__ import annotations

from mewa_bench.game.task import Task


def return_bounds(task: Task) -> tuple[float, float]:
    """(R_min, R_max): T steps at r_0, and the mistake-free episode (M-1) r_0 + M (r_1 + ... + r_{N-1})."""
    r = task.rewards
    r_min = task.T * r[0]
    r_max = (task.M - 1) * r[0] + task.M * sum(r[1:])
    return r_min, r_max


def normalised_return(task: Task, episode_return: float) -> float:
    """(R - R_min) / (R_max - R_min)."""
    r_min, r_max = return_bounds(task)
    return (episode_return - r_min) / (r_max - r_min)
