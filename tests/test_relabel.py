"""The colour symmetry: a renamed task plays as the original, state for state, and the renamed observation moves
exactly the per-colour entries."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from mewa_bench.game.relabel import observation_gather, relabelled_task, renamings
from mewa_bench.game.table import transition_table
from mewa_bench.game.task import Task


def renamed_by_hand(obs: np.ndarray, p: tuple[int, ...]) -> np.ndarray:
    """SPEC section 2's layout, colour by colour: colour c's entries go to colour p[c]'s places."""
    out = obs.copy()
    for c in range(4):
        out[p[c]] = obs[c]  # agent's blocks
        out[4 + 2 * p[c]], out[5 + 2 * p[c]] = obs[4 + 2 * c], obs[5 + 2 * c]  # open structure, mistake flag
        out[12 + p[c]] = obs[12 + c]  # completed
    return out


@pytest.mark.parametrize("p", list(itertools.permutations(range(4)))[1::5])
def test_a_renamed_task_moves_as_the_original_on_every_state(small_task: Task, p: tuple[int, ...]) -> None:
    original, renamed = transition_table(small_task), transition_table(relabelled_task(small_task, p))
    assert renamed.n_states == original.n_states
    gather = observation_gather(p)
    at = {renamed.obs[s].tobytes(): s for s in range(renamed.n_states)}
    image = np.array([at[renamed_by_hand(o, p).tobytes()] for o in original.obs])  # state s -> its renaming
    assert (original.obs[:, gather] == renamed.obs[image]).all()
    assert (original.reward == renamed.reward[image]).all() and (original.terminal == renamed.terminal[image]).all()
    for a in range(4):
        assert (image[original.next_ok[:, a]] == renamed.next_ok[image, p[a]]).all()
        assert (image[original.next_mistake[:, a]] == renamed.next_mistake[image, p[a]]).all()
        assert (original.mistake_type[:, a] == renamed.mistake_type[image, p[a]]).all()


def test_a_renamed_task_keeps_everything_but_its_colour_names() -> None:
    task = Task(colors=(0, 1, 3), order=(3, 0, 1), K=5, M=3, rewards=(-1.0, -0.5, -0.2), worker_blocks=(2, 6, 0),
                name="t").with_distribution((0.5, 0.3, 0.15))
    renamed = relabelled_task(task, (2, 0, 3, 1))
    assert renamed.colors == (0, 1, 2) and renamed.order == (1, 2, 0)
    same = ("K", "M", "rewards", "worker_blocks", "average_worker", "sigma", "T", "name")
    assert all(getattr(renamed, f) == getattr(task, f) for f in same)
    with pytest.raises(ValueError, match="permutation of 0..3"):
        relabelled_task(task, (0, 0, 1, 2))


def test_renamings_are_uniform_permutations_from_the_generator() -> None:
    drawn = renamings(np.random.default_rng(7), 24_000)
    assert (np.sort(drawn, axis=1) == np.arange(4)).all()
    counts = np.unique(drawn @ (4 ** np.arange(4)), return_counts=True)[1]
    assert len(counts) == 24 and abs(counts - 1000).max() < 5 * np.sqrt(1000)  # 5 sigma
    assert (renamings(np.random.default_rng(7), 10) == drawn[:10]).all()
