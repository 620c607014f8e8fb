"""The four-colour palette shared by every MEWA task, and the observation layout."""

from __future__ import annotations

COLOR_NAMES: tuple[str, ...] = ("orange", "blue", "green", "red")
NUM_COLORS = len(COLOR_NAMES)
ORANGE, BLUE, GREEN, RED = range(NUM_COLORS)

# Observation layout (float32[18]); see SPEC section 2.
OBS_SIZE = 18
OBS_AGENT_BLOCKS = slice(0, 4)
OBS_STRUCTURE_BLOCKS = slice(4, 12, 2)  # per colour, interleaved with the flags: blocks in its open structure
OBS_MISTAKE_FLAGS = slice(5, 12, 2)  # per colour: 1 if its open structure holds a mistake
OBS_COMPLETED = slice(12, 16)
OBS_WORKER_LEFT = 16
OBS_WORKER_PLACED = 17

