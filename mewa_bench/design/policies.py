"""The paper's baseline policies (SPEC section 4): the t-optimal family and the two random baselines.

Each policy is defined once, by `choices(task, state, memory)`: the distribution over
(action, next memory) in a game state, given the policy's memory (its counters). `PolicyAgent`
samples from it to play episodes; the exact engine (`design.exact`) enumerates it.

Semantics of the t-optimal policy (rho1, rho2, q), as reproduced from the authors' traces:

- The deadline is `order[progress]`. Critical state 1: the deadline structure holds 1 block.
  Critical state 2: it holds 2 blocks and a later sub-goal's structure holds exactly 1.
- Safe action (critical 1): the first later sub-goal colour, in sub-goal order, whose structure
  is empty; with q = 1, if there is none, the first completed colour, in sub-goal order, with an
  empty structure and leftover blocks. Risky action: the deadline colour.
- Postpone action (critical 2): the first later sub-goal colour, in sub-goal order, whose structure
  holds 1 block (leftover structures of completed colours never count). Complete: the deadline.
- Counters count consecutive critical-1 (critical-2) states, including the one acted in, and reset
  only when a state of another kind is reached: a critical-2 run goes on across a completed
  deadline when the next deadline is critical 2 at once. The first rho1 states of a critical-1
  run take a safe action (risky when none exists), the first rho2 of a critical-2 run postpone.
  Counters saturate at rho, which changes no decision and keeps the memory finite.
- Anywhere else: the deadline colour. The agent always holds a block of it (the blocks of an
  uncompleted colour are either in the agent's hand or in its open structure).
"""

from __future__ import annotations

import re
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np

from mewa_bench.game.palette import NUM_COLORS
from mewa_bench.game.rules import AGENT, PROGRESS, STRUCT, State, state_from_observation
from mewa_bench.game.task import Task

Memory = Hashable

NOT_CRITICAL, CRITICAL_1, CRITICAL_2 = 0, 1, 2
RANDOM_TASK_SPECIFIC = "random-task-specific"
RANDOM = "random"
_TOPTIMAL_NAME = re.compile(r"toptimal\(rho1=(\d+),rho2=(\d+),q=([01])\)")


class Choice(NamedTuple):
    """One outcome of a policy's decision: take `action` with probability `prob`, then hold `memory`."""

    prob: float
    action: int
    memory: Memory


class Policy(Protocol):
    """A policy as a function of (game state, memory); the only definition a policy has."""

    @property
    def name(self) -> str: ...

    @property
    def deterministic(self) -> bool: ...

    def initial_memory(self) -> Memory: ...

    def choices(self, task: Task, state: State, memory: Memory) -> tuple[Choice, ...]: ...


def deadline(task: Task, state: State) -> int:
    """Colour of the current sub-goal."""
    if state[PROGRESS] >= task.N:
        raise ValueError("the episode is over: a terminal state has no deadline")
    return task.order[state[PROGRESS]]


def safe_actions(task: Task, state: State, leftovers: bool) -> list[int]:
    """Colours a safe action may start, in the order the policies prefer them."""
    p = state[PROGRESS]
    colors = task.order[p + 1 :] + (task.order[:p] if leftovers else ())
    return [c for c in colors if state[STRUCT + c] == 0 and state[AGENT + c] > 0]


def postpone_actions(task: Task, state: State) -> list[int]:
    """Later sub-goal colours whose structure holds exactly one block, in sub-goal order."""
    return [c for c in task.order[state[PROGRESS] + 1 :] if state[STRUCT + c] == 1]


def critical_kind(task: Task, state: State) -> int:
    """NOT_CRITICAL, CRITICAL_1 or CRITICAL_2 (SPEC section 4)."""
    held = state[STRUCT + deadline(task, state)]
    if held == 1:
        return CRITICAL_1
    if held == 2 and postpone_actions(task, state):
        return CRITICAL_2
    return NOT_CRITICAL


@dataclass(frozen=True)
class TOptimal:
    """The t-optimal policy (rho1, rho2, q); its memory is the pair of run counters (c1, c2)."""

    rho1: int
    rho2: int
    q: int

    @property
    def name(self) -> str:
        """Canonical name, as in the reference traces."""
        return f"toptimal(rho1={self.rho1},rho2={self.rho2},q={self.q})"

    @property
    def deterministic(self) -> bool:
        """A t-optimal policy never flips a coin."""
        return True

    def initial_memory(self) -> tuple[int, int]:
        """No critical state seen yet."""
        return (0, 0)

    def choices(self, task: Task, state: State, memory: Memory) -> tuple[Choice, ...]:
        """The single action and the updated counters."""
        run1, run2 = memory  # type: ignore[misc]
        kind = critical_kind(task, state)
        if kind == CRITICAL_1:
            safe = safe_actions(task, state, leftovers=self.q == 1)
            action = safe[0] if run1 < self.rho1 and safe else deadline(task, state)
            return (Choice(1.0, action, (min(run1 + 1, self.rho1), 0)),)
        if kind == CRITICAL_2:
            action = postpone_actions(task, state)[0] if run2 < self.rho2 else deadline(task, state)
            return (Choice(1.0, action, (0, min(run2 + 1, self.rho2))),)
        return (Choice(1.0, deadline(task, state), (0, 0)),)


@dataclass(frozen=True)
class RandomTaskSpecific:
    """Critical 1: leftovers allowed with prob 1/2, then safe (if any) or risky with prob 1/2 each.

    Critical 2: postpone or complete with prob 1/2 each. Otherwise the deadline colour.
    """

    @property
    def name(self) -> str:
        """Canonical name."""
        return RANDOM_TASK_SPECIFIC

    @property
    def deterministic(self) -> bool:
        """It flips coins in critical states."""
        return False

    def initial_memory(self) -> tuple[()]:
        """Memoryless."""
        return ()

    def choices(self, task: Task, state: State, memory: Memory) -> tuple[Choice, ...]:
        """Distribution over actions (identical actions merged)."""
        target = deadline(task, state)
        kind = critical_kind(task, state)
        weights: dict[int, float] = {}
        if kind == CRITICAL_1:
            for leftovers in (False, True):
                safe = safe_actions(task, state, leftovers)
                if safe:
                    weights[safe[0]] = weights.get(safe[0], 0.0) + 0.25
                    weights[target] = weights.get(target, 0.0) + 0.25
                else:
                    weights[target] = weights.get(target, 0.0) + 0.5
        elif kind == CRITICAL_2:
            weights = {postpone_actions(task, state)[0]: 0.5, target: 0.5}
        else:
            weights = {target: 1.0}
        return tuple(Choice(p, a, ()) for a, p in weights.items())


@dataclass(frozen=True)
class UniformRandom:
    """Uniform over the 4 palette actions (actions outside the task's colours are no-ops)."""

    @property
    def name(self) -> str:
        """Canonical name."""
        return RANDOM

    @property
    def deterministic(self) -> bool:
        """Every step is a coin flip."""
        return False

    def initial_memory(self) -> tuple[()]:
        """Memoryless."""
        return ()

    def choices(self, task: Task, state: State, memory: Memory) -> tuple[Choice, ...]:
        """Each palette action with probability 1/4."""
        return tuple(Choice(1.0 / NUM_COLORS, a, ()) for a in range(NUM_COLORS))


def toptimal_family(n: int) -> tuple[TOptimal, ...]:
    """The t-optimal policies of an N-colour task, in canonical order (19 for N = 4, 11 for N = 3)."""
    return tuple(TOptimal(rho1, rho2, q) for q in (0, 1) for rho1 in range(n) for rho2 in range(rho1 + 1)
                 if not (rho1 == 0 and q == 1))


def policy_names(n: int, baselines: bool = True) -> tuple[str, ...]:
    """Names of the t-optimal family (canonical order), then the two random baselines."""
    names = tuple(p.name for p in toptimal_family(n))
    return names + (RANDOM_TASK_SPECIFIC, RANDOM) if baselines else names


def policy_from_name(name: str) -> Policy:
    """Parse "toptimal(rho1=2,rho2=1,q=0)", "random-task-specific" or "random"."""
    compact = name.replace(" ", "")
    if compact == RANDOM_TASK_SPECIFIC:
        return RandomTaskSpecific()
    if compact == RANDOM:
        return UniformRandom()
    match = _TOPTIMAL_NAME.fullmatch(compact)
    if match is None:
        raise ValueError(f"unknown policy {name!r}; expected 'toptimal(rho1=R1,rho2=R2,q=Q)', "
                         f"{RANDOM_TASK_SPECIFIC!r} or {RANDOM!r}")
    rho1, rho2, q = (int(g) for g in match.groups())
    if rho2 > rho1 or (rho1 == 0 and q == 1):
        raise ValueError(f"{name!r} is not in the t-optimal family (rho2 <= rho1, no rho1 = 0 with q = 1)")
    return TOptimal(rho1, rho2, q)


def as_policies(policies: Sequence[Policy | str]) -> tuple[Policy, ...]:
    """Policies given as objects or names, as objects."""
    return tuple(policy_from_name(p) if isinstance(p, str) else p for p in policies)


class PolicyAgent:
    """Plays a policy in an env: `reset()` at every episode start, then `act(state)` each step."""

    def __init__(self, policy: Policy | str, task: Task, rng: np.random.Generator | None = None) -> None:
        self.policy = policy_from_name(policy) if isinstance(policy, str) else policy
        if not self.policy.deterministic and rng is None:
            raise ValueError(f"policy {self.policy.name!r} is random: pass an np.random.Generator")
        self.task = task
        self.rng = rng
        self.memory: Memory = self.policy.initial_memory()

    def reset(self) -> None:
        """Forget the previous episode (counters back to zero)."""
        self.memory = self.policy.initial_memory()

    def act(self, state: State) -> int:
        """The action for a game state (the 17-int tuple of `mewa_bench.game.rules`)."""
        options = self.policy.choices(self.task, state, self.memory)
        pick = options[0]
        if len(options) > 1:
            u = self.rng.random()  # type: ignore[union-attr]
            for pick in options:
                u -= pick.prob
                if u < 0:
                    break
        self.memory = pick.memory
        return pick.action

    def act_observation(self, obs: np.ndarray) -> int:
        """The action for an 18-float observation (decoded back into the game state)."""
        return self.act(state_from_observation(self.task, obs))
