"""Training tasks beyond a suite's own: tasks that a wide suite's generator samples from a dataset's seed.

A wide suite's ten tasks are ten draws of its generator (SPEC section 4). A model trained on those ten alone
learns to tell them apart, not to adapt to a task it has never seen, and a hidden twin of the suite draws
ten others (docs/baselines.md). A pool of tasks drawn the same way (N, colours, sub-goal order, K, M and
worker blocks by `design.generate.sample_wide_task`; Eq. 1's rewards and, on v2, the two worker families
by `design.generate.designed`) from the training dataset's own seed is data for that. Unlike the suite's
tasks, a pool's are not screened for adaptivity (that needs every candidate worker's exact values); a
learner still has to find the worker on each.

A pool drawn at random holds some structures (N, K, M, worker blocks) and not others, and its colours tell its
tasks apart where a new task's would not. `task_structures` is the generator's whole range up to renaming the
colours (`game.relabel`): every structure once, in colours 0..N-1 completed in that order, so a learner that
tells them apart must do it by playing, and a model trained on them under random renamings meets every task the
generator can draw.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from mewa_bench.design.generate import WORKER_BLOCK_TOTAL, designed, sample_wide_task
from mewa_bench.design.suites import Suite
from mewa_bench.game.task import Task


def generated_tasks(suite: Suite, count: int, rng: np.random.Generator) -> tuple[Task, ...]:
    """`count` tasks drawn by `suite`'s generator with `rng`, named `generated-<i>-n<N>-k<K>-m<M>`."""
    if suite.content.get("suite") != "wide":
        raise ValueError(f"{suite.name} has one task, not a task generator: generated tasks need a wide suite")
    families = int(suite.content["version"]) >= 2
    out = []
    for i in range(count):
        task, _ = designed(sample_wide_task(rng, i), families)
        out.append(Task.from_dict({**task.to_dict(), "name": f"generated-{i:03d}-n{task.N}-k{task.K}-m{task.M}"}))
    return tuple(out)


def task_structures(suite: Suite, ks: tuple[int, ...] = (3, 4, 5)) -> tuple[Task, ...]:
    """Every task structure of `suite`'s generator once (N in 3, 4; K in 3..5; M in 3..K; each composition of the
    worker blocks), colours 0..N-1 completed in that order, named `structure-<i>-n<N>-k<K>-m<M>`: 168 on the
    wide suites, each of the generator's tasks a renaming of one (`game.relabel.relabelled_task`). `ks`: only the
    structures with these K (Eq. 1's design of each (N, M) takes seconds)."""
    if suite.content.get("suite") != "wide":
        raise ValueError(f"{suite.name} has one task, not a task generator: task structures need a wide suite")
    families = int(suite.content["version"]) >= 2
    out = []
    every = [(n, k, m, cuts) for n, k in itertools.product((3, 4), (3, 4, 5))
             for m, cuts in itertools.product(range(3, k + 1), itertools.combinations(range(1, WORKER_BLOCK_TOTAL), n - 2))]
    for i, (n, k, m, cuts) in enumerate(every):
        if k not in ks:
            continue
        blocks = tuple(int(b) for b in np.diff((0, *cuts, WORKER_BLOCK_TOTAL))) + (0,)
        colours = tuple(range(n))
        task, _ = designed(Task(colors=colours, order=colours, K=k, M=m, rewards=tuple(-1.0 + 0.1 * j for j in range(n)),
                                worker_blocks=blocks, name=""), families)
        out.append(Task.from_dict({**task.to_dict(), "name": f"structure-{i:03d}-n{n}-k{k}-m{m}"}))
    return tuple(out)


def with_tasks(suite: Suite, tasks: tuple[Task, ...]) -> Suite:
    """`suite` (its name and hash: what the data is for) with another task list and no curated pairs."""
    return dataclasses.replace(suite, tasks=tuple(tasks), pairs=())
