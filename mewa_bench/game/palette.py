"""The four-colour palette shared by every MEWA task, and the observation layout."""

from __future__ import annotations

COLOR_NAMES: tuple[str, ...] = ("orange", "blue", "green", "red")
NUM_COLORS = len(COLOR_NAMES)
ORANGE, BLUE, GREEN, RED = range(NUM_COLORS)

# Observation layout (float32[18]); see SPEC section 2.
OBS_SIZE = 18
OBS_AGENT_BLOCKS = slice(0, 4)
OBS_STRUCTURES = slice(4, 12)  # per colour: (blocks in open structure, mistake flag)
OBS_COMPLETED = slice(12, 16)
OBS_WORKER_LEFT = 16
OBS_WORKER_PLACED = 17


def color_index(color: int | str) -> int:
    """Return the palette index of a colour given by index or name."""
    if isinstance(color, str):
        try:
            return COLOR_NAMES.index(color.lower())
        except ValueError:
            raise ValueError(f"unknown colour {color!r}; the palette is {', '.join(COLOR_NAMES)}") from None
    if not 0 <= int(color) < NUM_COLORS:
        raise ValueError(f"colour index {color} is outside the palette 0..{NUM_COLORS - 1}")
    return int(color)
