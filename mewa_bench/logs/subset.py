"""Log some units of a run only (`evaluate --log-pairs / --log-seeds`): a ranked run's full logs are large."""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import replace
from pathlib import Path
from typing import Any

from mewa_bench.protocol.trajectory import RunInfo, TrajectorySink, UnitRecord


class UnitSubset:
    """Passes on to `sink` only the units of the given pairs and seeds (None: every pair, every seed).

    The run is still played and scored in full; the log's run metadata lists what it holds
    (`logged_pairs`, `logged_seeds`).
    """

    def __init__(self, sink: TrajectorySink, pairs: Collection[int] | None = None,
                 seeds: Collection[int] | None = None) -> None:
        self.sink = sink
        self.pairs = None if pairs is None else frozenset(pairs)
        self.seeds = None if seeds is None else frozenset(seeds)

    @property
    def path(self) -> Path:
        """The wrapped sink's file."""
        return self.sink.path  # type: ignore[attr-defined]

    def wants(self, unit: UnitRecord) -> bool:
        """Whether `unit` is logged."""
        return (self.pairs is None or unit.pair in self.pairs) and (self.seeds is None or unit.seed in self.seeds)

    def start(self, run: RunInfo) -> None:
        """Start the wrapped sink, with the subset in the run's metadata."""
        extra: dict[str, Any] = dict(run.extra)
        if self.pairs is not None:
            extra["logged_pairs"] = sorted(self.pairs)
        if self.seeds is not None:
            extra["logged_seeds"] = sorted(self.seeds)
        self.sink.start(replace(run, extra=extra))

    def add_unit(self, unit: UnitRecord) -> None:
        """Log `unit` if it is in the subset."""
        if self.wants(unit):
            self.sink.add_unit(unit)

    def close(self) -> None:
        """Close the wrapped sink."""
        self.sink.close()
