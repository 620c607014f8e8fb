"""Pure MEWA game: palette, tasks and workers, the one-step rules, normalisation (numpy only)."""

from mewa_bench.game.normalise import normalised_return, return_bounds
from mewa_bench.game.palette import COLOR_NAMES, NUM_COLORS, OBS_SIZE
from mewa_bench.game.rules import Event, Outcomes, State, initial_state, observation, outcomes
from mewa_bench.game.table import TransitionTable, transition_table
from mewa_bench.game.task import Task, Worker, default_sigma

__all__ = [
    "COLOR_NAMES", "NUM_COLORS", "OBS_SIZE", "Event", "Outcomes", "State", "Task", "TransitionTable",
    "Worker", "default_sigma", "initial_state", "normalised_return", "observation", "outcomes",
    "return_bounds", "transition_table",
]
