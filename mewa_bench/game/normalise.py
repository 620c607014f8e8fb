"""Normalised return of an episode (SPEC section 2): 0 = worst possible, 1 = perfect episode; and the
protocol's two ratios built on it, score and skill (their only definitions)."""

from __future__ import annotations

import numpy as np

from mewa_bench.game.task import Task


def return_bounds(task: Task) -> tuple[float, float]:
    """(R_min, R_max): T steps at r_0, and the mistake-free episode (M-1) r_0 + M (r_1 + ... + r_{N-1})."""
    r = task.rewards
    r_min = task.T * r[0]
    r_max = (task.M - 1) * r[0] + task.M * sum(r[1:])
    return r_min, r_max


def normalised_return(task: Task, episode_return: np.ndarray | float) -> np.ndarray | float:
    """(R - R_min) / (R_max - R_min), for one return or an array of them."""
    r_min, r_max = return_bounds(task)
    return (episode_return - r_min) / (r_max - r_min)


def episode_score(normalised: np.ndarray | float, max_expected: np.ndarray | float) -> np.ndarray | float:
    """The protocol's score of an episode: s = normalised return / the pair's max-expected baseline."""
    return np.divide(normalised, max_expected)


def skill_of(score: np.ndarray | float, rts_score: float) -> np.ndarray | float:
    """skill = (S - S_rts) / (1 - S_rts): 0 = random task-specific, 1 = best t-optimal per worker."""
    return (score - rts_score) / (1.0 - rts_score)
