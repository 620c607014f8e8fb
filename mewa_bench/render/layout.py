"""Where every block of a game state goes on the table: pure Python, no renderer.

Top view, with the camera in front of the table looking along +x (so +y is the image's left):

    x = 0.32   worker area: the worker's placed blocks, grey, in rows of 8
    x = 0.12   goal area:   a completed structure, a tower of M blocks, per colour
    x = -0.08  build area:  the worker's open structure, a tower, per colour
    x = -0.26  supply:      the agent's blocks, rows of 3 slots, per colour

Each palette colour has its own lane (orange left ... red right), so a block's place and colour
both say what it is. Odd levels of a tower are a darker shade so that stacked blocks can be
counted. A structure with a mistake is built wrongly: from its second block on it
leans, shifted sideways and tilted, like the worker building the wrong shape.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from mewa_bench.game.palette import NUM_COLORS
from mewa_bench.game.rules import AGENT, DONE, FLAG, PROGRESS, STATE_SIZE, STRUCT, State
from mewa_bench.game.task import Task

BLOCK = 0.05  # edge of a block (m)
PITCH = 0.062  # distance between neighbouring blocks in a row
LANE = 0.22  # distance between colour lanes
SUPPLY_PER_ROW = 3
WORKER_PER_ROW = 8
X_SUPPLY, X_BUILD, X_GOAL, X_WORKER = -0.26, -0.08, 0.12, 0.32
MISTAKE_SHIFT = 0.45 * BLOCK  # sideways shift of a mistaken structure's second block
MISTAKE_TILT = math.radians(28.0)  # and its lean about the lane axis
GREY = NUM_COLORS  # material index of the worker's blocks (after the palette colours)


class Block(NamedTuple):
    """One block to draw: material (palette colour, or GREY), shade (0, 1 darker), centre (m), lean (rad)."""

    material: int
    shade: int
    x: float
    y: float
    z: float
    tilt: float = 0.0


def lane_y(color: int) -> float:
    """The y of a colour's lane (orange leftmost in the image)."""
    return ((NUM_COLORS - 1) / 2 - color) * LANE


def supply_blocks(color: int, count: int) -> list[Block]:
    """The agent's blocks of one colour: slots filled left to right, next rows towards the camera."""
    y0 = lane_y(color)
    out = []
    for j in range(count):
        row, slot = divmod(j, SUPPLY_PER_ROW)
        y = y0 + ((SUPPLY_PER_ROW - 1) / 2 - slot) * PITCH
        out.append(Block(color, 0, X_SUPPLY - row * PITCH, y, BLOCK / 2))
    return out


def tower(color: int, x: float, count: int, mistaken: bool = False) -> list[Block]:
    """A stack of `count` blocks at (x, lane); if mistaken, it leans from the second block on."""
    y0 = lane_y(color)
    out = [Block(color, 0, x, y0, BLOCK / 2)] if count else []
    if count < 2:
        return out
    if not mistaken:
        return out + [Block(color, i % 2, x, y0, BLOCK / 2 + i * BLOCK) for i in range(1, count)]
    # The misplaced block sits half off its base; the rest follow the tilted column above it.
    base_y, base_z = y0 - MISTAKE_SHIFT, BLOCK * 1.5
    dy, dz = -math.sin(MISTAKE_TILT) * BLOCK, math.cos(MISTAKE_TILT) * BLOCK
    for i in range(count - 1):
        out.append(Block(color, (i + 1) % 2, x, base_y + i * dy, base_z + i * dz, MISTAKE_TILT))
    return out


def worker_blocks(placed: int) -> list[Block]:
    """The worker's placed blocks: grey rows centred behind the lanes, extra rows further back."""
    out = []
    for j in range(placed):
        row, slot = divmod(j, WORKER_PER_ROW)
        in_row = min(WORKER_PER_ROW, placed - row * WORKER_PER_ROW)
        y = ((in_row - 1) / 2 - slot) * PITCH
        out.append(Block(GREY, 0, X_WORKER + row * PITCH, y, BLOCK / 2))
    return out


def check_state(state: State) -> tuple[int, ...]:
    """The state as a tuple of STATE_SIZE non-negative ints, or ValueError."""
    s = tuple(int(v) for v in state)
    if len(s) != STATE_SIZE or min(s) < 0:
        raise ValueError(f"a game state is {STATE_SIZE} non-negative ints, got {tuple(state)!r}")
    return s


def layout(task: Task, state: State) -> list[Block]:
    """Every block of `state` (supply, open structures, completed ones, worker's) in a fixed order."""
    s = check_state(state)
    blocks: list[Block] = []
    for c in range(NUM_COLORS):
        blocks += supply_blocks(c, s[AGENT + c])
        blocks += tower(c, X_BUILD, s[STRUCT + c], mistaken=s[FLAG + c] == 1)
        blocks += tower(c, X_GOAL, task.M if s[DONE + c] else 0)
    blocks += worker_blocks(sum(task.worker_blocks[: s[PROGRESS]]))
    return blocks
