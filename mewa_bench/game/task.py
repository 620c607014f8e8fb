"""Task and Worker: the parameters of one MEWA game (SPEC section 2), validated and JSON-ready."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

from mewa_bench.game.palette import NUM_COLORS

DEFAULT_HORIZON = 100
# Default worker-distribution widths for N = 4; N = 3 uses the last three (SPEC section 3).
DEFAULT_SIGMA_N4: tuple[float, ...] = (0.12, 0.12, 0.10, 0.08)


def default_sigma(n: int) -> tuple[float, ...]:
    """Default sigma of the worker distribution for a task with n colours."""
    if not 1 <= n <= len(DEFAULT_SIGMA_N4):
        raise ValueError(f"no default sigma for N = {n}")
    return DEFAULT_SIGMA_N4[len(DEFAULT_SIGMA_N4) - n :]


def _ints(name: str, values: Any) -> tuple[int, ...]:
    try:
        out = tuple(int(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(f"task field {name!r} must be a list of integers, got {values!r}") from None
    if any(float(v) != o for v, o in zip(values, out)):
        raise ValueError(f"task field {name!r} must hold integers, got {list(values)!r}")
    return out


def _floats(name: str, values: Any) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(f"field {name!r} must be a list of numbers, got {values!r}") from None
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"field {name!r} must hold finite numbers, got {list(out)!r}")
    return out


def _probabilities(name: str, values: Any, n: int) -> tuple[float, ...]:
    out = _floats(name, values)
    if len(out) != n:
        raise ValueError(f"field {name!r} must have N = {n} entries, got {len(out)}")
    bad = [v for v in out if not 0.0 <= v <= 1.0]
    if bad:
        raise ValueError(f"field {name!r} holds probabilities outside [0, 1]: {bad}")
    return out


@dataclass(frozen=True)
class Task:
    """One MEWA task: colours, sub-goal order, block counts, rewards and worker distribution.

    `average_worker` and `sigma` describe the task's worker distribution (SPEC section 3); they are
    optional for playing a task with an explicit worker, required for sampling workers.
    """

    colors: tuple[int, ...]
    order: tuple[int, ...]
    K: int
    M: int
    rewards: tuple[float, ...]
    worker_blocks: tuple[int, ...]
    T: int = DEFAULT_HORIZON
    average_worker: tuple[float, ...] | None = None
    sigma: tuple[float, ...] | None = None
    name: str = ""
    extra: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)

    def __post_init__(self) -> None:
        set_ = object.__setattr__  # frozen dataclass: normalise fields once, here
        colors = _ints("colors", self.colors)
        if not 2 <= len(colors) <= NUM_COLORS:
            raise ValueError(f"task field 'colors' must hold 2..{NUM_COLORS} colours, got {list(colors)}")
        if any(not 0 <= c < NUM_COLORS for c in colors):
            raise ValueError(f"task field 'colors' holds a colour outside the palette 0..{NUM_COLORS - 1}: {list(colors)}")
        if len(set(colors)) != len(colors):
            raise ValueError(f"task field 'colors' repeats a colour: {list(colors)}")
        n = len(colors)
        order = _ints("order", self.order)
        if sorted(order) != sorted(colors):
            raise ValueError(f"task field 'order' must be a permutation of colors {list(colors)}, got {list(order)}")
        k, m, t = int(self.K), int(self.M), int(self.T)
        if m < 2:
            raise ValueError(f"task field 'M' must be >= 2, got {m}")
        if m > k:
            raise ValueError(f"task field 'M' ({m}) must not exceed 'K' ({k})")
        if t < 1:
            raise ValueError(f"task field 'T' must be >= 1, got {t}")
        rewards = _floats("rewards", self.rewards)
        if len(rewards) != n:
            raise ValueError(f"task field 'rewards' must have N = {n} entries, got {len(rewards)}")
        if any(r >= 0 for r in rewards):
            raise ValueError(f"task field 'rewards' must be negative, got {list(rewards)}")
        if any(a >= b for a, b in zip(rewards, rewards[1:])):
            raise ValueError(f"task field 'rewards' must be strictly increasing, got {list(rewards)}")
        blocks = _ints("worker_blocks", self.worker_blocks)
        if len(blocks) != n:
            raise ValueError(f"task field 'worker_blocks' must have N = {n} entries, got {len(blocks)}")
        if any(b < 0 for b in blocks):
            raise ValueError(f"task field 'worker_blocks' must be non-negative, got {list(blocks)}")
        set_(self, "colors", colors)
        set_(self, "order", order)
        set_(self, "K", k)
        set_(self, "M", m)
        set_(self, "T", t)
        set_(self, "rewards", rewards)
        set_(self, "worker_blocks", blocks)
        if self.average_worker is not None:
            set_(self, "average_worker", _probabilities("average_worker", self.average_worker, n))
        if self.sigma is not None:
            sigma = _floats("sigma", self.sigma)
            if len(sigma) != n or any(s <= 0 for s in sigma):
                raise ValueError(f"task field 'sigma' must hold N = {n} positive widths, got {list(sigma)}")
            set_(self, "sigma", sigma)

    @property
    def N(self) -> int:  # noqa: N802 - the paper's symbol
        """Number of colours (= sub-goals) in the task."""
        return len(self.colors)

    def with_distribution(self, average_worker: Sequence[float], sigma: Sequence[float] | None = None) -> "Task":
        """Copy of this task with the given worker distribution (default sigma if none given)."""
        return Task(**{**self._fields(), "average_worker": tuple(average_worker),
                       "sigma": tuple(sigma) if sigma is not None else default_sigma(self.N)})

    def with_rewards(self, rewards: Sequence[float]) -> "Task":
        """Copy of this task with other step rewards."""
        return Task(**{**self._fields(), "rewards": tuple(rewards)})

    def _fields(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (the inverse of `Task.from_dict`)."""
        d: dict[str, Any] = {
            "name": self.name,
            "colors": list(self.colors),
            "order": list(self.order),
            "K": self.K,
            "M": self.M,
            "rewards": list(self.rewards),
            "worker_blocks": list(self.worker_blocks),
            "T": self.T,
        }
        if self.average_worker is not None:
            d["average_worker"] = list(self.average_worker)
        if self.sigma is not None:
            d["sigma"] = list(self.sigma)
        d.update(self.extra)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Task":
        """Build a task from a dict as written by `to_dict` (unknown keys are kept in `extra`)."""
        if not isinstance(d, dict):
            raise ValueError(f"a task must be a JSON object, got {type(d).__name__}")
        required = ("colors", "order", "K", "M", "rewards", "worker_blocks")
        missing = [k for k in required if k not in d]
        if missing:
            raise ValueError(f"task is missing field(s) {', '.join(map(repr, missing))}")
        known = set(required) | {"T", "average_worker", "sigma", "name"}
        return cls(
            colors=d["colors"], order=d["order"], K=d["K"], M=d["M"], rewards=d["rewards"],
            worker_blocks=d["worker_blocks"], T=d.get("T", DEFAULT_HORIZON),
            average_worker=d.get("average_worker"), sigma=d.get("sigma"), name=d.get("name", ""),
            extra={k: v for k, v in d.items() if k not in known},
        )

    def key(self) -> tuple:
        """Hashable identity of the game rules (what the transition table depends on)."""
        return (self.colors, self.order, self.K, self.M, self.rewards, self.worker_blocks, self.T)


@dataclass(frozen=True)
class Worker:
    """A worker: w[x] is the probability of a mistake of type x (x + 1 structures open at once)."""

    w: tuple[float, ...]

    def __post_init__(self) -> None:
        w = _floats("worker", self.w)
        if not 2 <= len(w) <= NUM_COLORS:
            raise ValueError(f"a worker must have 2..{NUM_COLORS} probabilities, got {len(w)}")
        bad = [v for v in w if not 0.0 <= v <= 1.0]
        if bad:
            raise ValueError(f"worker holds probabilities outside [0, 1]: {bad}")
        object.__setattr__(self, "w", w)

    @classmethod
    def of(cls, value: "Worker | Sequence[float]") -> "Worker":
        """Coerce a sequence of probabilities (or a Worker) to a Worker."""
        return value if isinstance(value, Worker) else cls(tuple(value))

    def check_fits(self, task: Task) -> None:
        """Raise ValueError if this worker's length does not match the task's N."""
        if len(self.w) != task.N:
            raise ValueError(f"worker has {len(self.w)} probabilities but task {task.name or ''} has N = {task.N}".replace("  ", " "))

    def to_list(self) -> list[float]:
        """JSON-ready list of probabilities."""
        return list(self.w)

    def __len__(self) -> int:
        return len(self.w)
