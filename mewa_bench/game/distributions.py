"""Worker distributions of a task (SPEC section 3): worker families, meta-train sampling, the meta-test region.

A worker family is a centre (average worker), widths `sigma` and a monotone order. Every task has
the paper's family: its `average_worker` and `sigma`, non-increasing workers (more structures
open, fewer mistakes). A v2 task also lists an *overloaded* family (non-decreasing workers: more
structures open, more mistakes) in its `worker_distribution` field, and a meta-train mixture.

- Meta-test region: grid workers outside the 2-sigma box of every family of the task (at least
  one component with |w_x - avg_x| >= 2 sigma_x for each family), rounded to 12 decimals.
- v1 meta-train sampler (`sample_train_workers`): the paper's bands inside the box, never in the
  test region. v2 meta-train sampler (`sample_meta_train_workers`): a mixture, per family, of
  that box sampler and a *cover* sampler (uniform over the family's monotone workers in [0, 1]^N),
  every draw kept at L-inf distance >= `grid_clearance` from every point of the 0.05 grid, so from
  every possible meta-test worker.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from mewa_bench.game.task import Task

ROUND = 12  # decimals for region comparisons (keeps grid points like 0.05 k exact)
_MAX_TRIES = 10_000
NON_INCREASING, NON_DECREASING = "non-increasing", "non-decreasing"
PAPER, OVERLOADED = "paper", "overloaded"


@dataclass(frozen=True)
class WorkerFamily:
    """A family of workers: centre, widths and the monotone order its workers keep."""

    name: str
    centre: tuple[float, ...]
    sigma: tuple[float, ...]
    monotone: str  # NON_INCREASING or NON_DECREASING

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record (as stored in a v2 task's `worker_distribution`)."""
        return {"name": self.name, "average_worker": list(self.centre), "sigma": list(self.sigma), "monotone": self.monotone}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "WorkerFamily":
        """Inverse of `to_dict`."""
        if d["monotone"] not in (NON_INCREASING, NON_DECREASING):
            raise ValueError(f"unknown monotone order {d['monotone']!r}")
        return cls(str(d["name"]), tuple(float(v) for v in d["average_worker"]), tuple(float(v) for v in d["sigma"]),
                   str(d["monotone"]))


def _distribution(task: Task) -> tuple[np.ndarray, np.ndarray]:
    if task.average_worker is None or task.sigma is None:
        raise ValueError(f"task {task.name or task.order!r} has no worker distribution (average_worker, sigma)")
    return np.asarray(task.average_worker, dtype=np.float64), np.asarray(task.sigma, dtype=np.float64)


def paper_family(task: Task) -> WorkerFamily:
    """The paper's family: the task's average worker and sigma, non-increasing workers."""
    avg, sigma = _distribution(task)
    return WorkerFamily(PAPER, tuple(avg.tolist()), tuple(sigma.tolist()), NON_INCREASING)


def overloaded_family(task: Task) -> WorkerFamily:
    """The overloaded family: the paper's centre and widths mirrored (w_x <-> w_{N-1-x}), non-decreasing."""
    paper = paper_family(task)
    return WorkerFamily(OVERLOADED, paper.centre[::-1], paper.sigma[::-1], NON_DECREASING)


def worker_families(task: Task) -> tuple[WorkerFamily, ...]:
    """The task's worker families: those of its `worker_distribution` field, else the paper's alone."""
    spec = task.extra.get("worker_distribution")
    if spec is None:
        return (paper_family(task),)
    return tuple(WorkerFamily.from_dict(f) for f in spec["families"])


def meta_train_spec(task: Task) -> dict[str, Any] | None:
    """The task's v2 meta-train mixture parameters, or None for a v1 task."""
    spec = task.extra.get("worker_distribution")
    return None if spec is None else spec["meta_train"]


def in_box(family: WorkerFamily, w: np.ndarray) -> np.ndarray:
    """True where every component satisfies |w_x - avg_x| < 2 sigma_x (rows of an [n, N] array)."""
    dev = np.round(np.abs(np.asarray(w, dtype=np.float64) - np.asarray(family.centre)), ROUND)
    return (dev < np.round(2.0 * np.asarray(family.sigma), ROUND)).all(axis=-1)


def in_test_region(task: Task, w: Sequence[float] | np.ndarray) -> np.ndarray | bool:
    """True where a worker (or each row of an [n, N] array) lies outside the 2-sigma box of every family."""
    arr = np.asarray(w, dtype=np.float64)
    out = np.ones(arr.shape[:-1], dtype=bool)
    for family in worker_families(task):
        out &= ~in_box(family, arr)
    return bool(out) if out.ndim == 0 else out


def is_non_increasing(w: np.ndarray) -> np.ndarray | bool:
    """True where w_0 >= w_1 >= ... (for a worker or each row of an array)."""
    arr = np.asarray(w, dtype=np.float64)
    out = (np.diff(arr, axis=-1) <= 0).all(axis=-1)
    return bool(out) if out.ndim == 0 else out


def is_monotone(w: np.ndarray, monotone: str) -> np.ndarray | bool:
    """True where a worker (or each row) keeps the given monotone order."""
    arr = np.asarray(w, dtype=np.float64)
    return is_non_increasing(arr if monotone == NON_INCREASING else arr[..., ::-1])


def family_names(task: Task, w: Sequence[float]) -> list[str]:
    """Names of the task's families whose monotone order a worker keeps."""
    return [f.name for f in worker_families(task) if is_monotone(np.asarray(w), f.monotone)]


def sample_box_workers(task: Task, family: WorkerFamily, rng: np.random.Generator, n: int,
                       include_centre: bool = False, clearance: float = 0.0, step: float = 0.05) -> np.ndarray:
    """n workers of `family` from the paper's bands inside its 2-sigma box, float64 [n, N].

    Each component is drawn uniformly from (avg - 2 sigma, avg - 0.5 sigma) or
    (avg + 0.5 sigma, avg + 2 sigma), picked with equal probability (with `include_centre`, the centre
    band (avg - 0.5 sigma, avg + 0.5 sigma) is a third equally likely choice), then clipped to [0, 1].
    Draws that break the family's order, that clipping pushed onto the task's test region, or (with
    `clearance` > 0) that lie within `clearance` of the `step` grid are redrawn.
    """
    avg, sigma = np.asarray(family.centre), np.asarray(family.sigma)
    bands = np.array([[-2.0, -0.5], [0.5, 2.0]] + ([[-0.5, 0.5]] if include_centre else []))

    def draw(m: int) -> np.ndarray:
        pick = rng.integers(0, len(bands), size=(m, task.N))
        u = rng.random((m, task.N))
        lo, hi = bands[pick, 0], bands[pick, 1]
        w = np.clip(avg + sigma * (lo + (hi - lo) * u), 0.0, 1.0)
        return w[is_monotone(w, family.monotone) & ~in_test_region(task, w) & clear_of_grid(w, clearance, step)]

    return _rejection(draw, n, f"{family.name} meta-train workers for task {task.name!r} "
                      f"(average {family.centre}, sigma {family.sigma})")


def sample_cover_workers(family: WorkerFamily, rng: np.random.Generator, n: int, clearance: float,
                         step: float = 0.05) -> np.ndarray:
    """n workers uniform over the family's monotone workers in [0, 1]^N, kept `clearance` off the grid."""
    def draw(m: int) -> np.ndarray:
        w = np.sort(rng.random((m, len(family.centre))), axis=1)
        w = w[:, ::-1] if family.monotone == NON_INCREASING else w
        return w[clear_of_grid(w, clearance, step)]

    return _rejection(draw, n, f"{family.name} cover workers")


def _rejection(draw: Any, n: int, what: str) -> np.ndarray:
    """Fill n rows from a `draw(m) -> accepted rows` function, in draw order.

    Each draw is sized by the acceptance rate seen so far, so a low rate costs few calls."""
    parts, filled, tried, accepted = [], 0, 0, 0
    for _ in range(_MAX_TRIES):
        if filled == n:
            break
        rate = max(accepted / tried, 0.01) if tried else 0.5
        m = max(int(1.2 * (n - filled) / rate), 16)
        got = draw(m)
        tried, accepted = tried + m, accepted + len(got)
        good = got[: n - filled]
        parts.append(good)
        filled += len(good)
    if filled < n:
        raise ValueError(f"could not sample {what}")
    return np.concatenate(parts) if parts else np.empty((0, 0))


def clear_of_grid(w: np.ndarray, clearance: float, step: float = 0.05) -> np.ndarray:
    """True where a worker lies at L-inf distance >= `clearance` from every point of the `step` grid."""
    arr = np.asarray(w, dtype=np.float64)
    if clearance <= 0.0:
        return np.ones(arr.shape[:-1], dtype=bool)
    off = np.abs(arr / step - np.round(arr / step)) * step  # distance of each component to its nearest grid value
    return (np.round(off, ROUND) >= clearance).any(axis=-1)


def sample_train_workers(task: Task, rng: np.random.Generator, n: int, include_centre: bool = False) -> np.ndarray:
    """n meta-train workers of the paper's family inside its box (SPEC section 3), float64 [n, N]."""
    if n == 0:
        return np.empty((0, task.N))
    return sample_box_workers(task, paper_family(task), rng, n, include_centre)


def sample_meta_train_workers(task: Task, rng: np.random.Generator, n: int, include_centre: bool = False) -> np.ndarray:
    """n meta-train workers from the task's own distribution: v2 mixture if it has one, else v1's, [n, N]."""
    spec = meta_train_spec(task)
    if spec is None:
        return sample_train_workers(task, rng, n, include_centre)
    families = worker_families(task)
    family = rng.choice(len(families), size=n, p=np.asarray(spec["family_weights"], dtype=np.float64))
    cover = rng.random(n) < spec["cover_weight"]
    clearance, step = float(spec["grid_clearance"]), float(spec["grid_step"])
    out = np.empty((n, task.N))
    for f, fam in enumerate(families):
        rows = np.flatnonzero((family == f) & cover)
        if len(rows):
            out[rows] = sample_cover_workers(fam, rng, len(rows), clearance, step)
        rows = np.flatnonzero((family == f) & ~cover)
        if len(rows):
            out[rows] = sample_box_workers(task, fam, rng, len(rows), include_centre, clearance, step)
    return out


def worker_grid(n: int, step: float = 0.05, monotone: str = NON_INCREASING) -> np.ndarray:
    """All workers of one monotone order on the `step` grid over [0, 1]^n, lexicographically sorted, [m, n]."""
    k = int(round(1.0 / step))
    axes = np.meshgrid(*([np.arange(k + 1)] * n), indexing="ij")
    pts = np.stack([a.ravel() for a in axes], axis=1)  # lexicographic order
    pts = pts[is_monotone(pts, monotone)]
    return np.round(pts * step, ROUND)


def meta_test_candidates(task: Task, step: float = 0.05) -> np.ndarray:
    """Grid workers of any of the task's families in its meta-test region (SPEC section 4), lexicographic order."""
    orders = sorted({f.monotone for f in worker_families(task)}, key=(NON_INCREASING, NON_DECREASING).index)
    grid = worker_grid(task.N, step, orders[0])
    if len(orders) > 1:
        grid = np.unique(np.concatenate([worker_grid(task.N, step, m) for m in orders]), axis=0)
    return grid[in_test_region(task, grid)]
