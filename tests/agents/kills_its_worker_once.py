"""Test agent: random play; the first time any copy of it acts, it kills the process that runs its
agent process (a Ray worker in the Ray tests), leaving a marker file so that the retried task plays
normally. Reseeded per unit, so every run gives the same units."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np


class Agent:
    def __init__(self, observation_space, action_space, marker: str = "", seed: str = "0") -> None:
        self.marker = Path(marker) if marker else None
        self.seed = int(seed)
        self.rng = np.random.default_rng(self.seed)

    def reset_task(self, seed: int | None = None) -> None:
        if seed is not None:
            self.rng = np.random.default_rng([self.seed, seed])

    def act(self, observation: np.ndarray) -> int:
        if self.marker is not None and not self.marker.exists():
            self.marker.write_text("killed once")
            os.kill(os.getppid(), signal.SIGKILL)  # the runner process this agent process belongs to
        return int(self.rng.integers(0, 4))
