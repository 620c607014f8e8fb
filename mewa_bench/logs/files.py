"""Which log files a run writes (`--log mcap,rerun --log-dir DIR`)."""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path
from typing import Any

LOG_KINDS = {"mcap": ".mcap", "rerun": ".rrd"}


def parse_log_kinds(text: str | None) -> tuple[str, ...]:
    """'mcap,rerun' -> ('mcap', 'rerun'); unknown kinds are a ValueError naming them."""
    if not text:
        return ()
    kinds = tuple(dict.fromkeys(k.strip().lower() for k in text.split(",") if k.strip()))
    unknown = [k for k in kinds if k not in LOG_KINDS]
    if unknown:
        raise ValueError(f"unknown log kind(s) {', '.join(unknown)}: expected {', '.join(LOG_KINDS)}")
    return kinds


def log_path(log_dir: Path, stem: str, kind: str) -> Path:
    """`DIR/<stem>.mcap`; when it exists (a resumed run), the next free `DIR/<stem>.part-N.mcap`.

    A resumed run logs only the units it plays, into a new file, so no earlier log is overwritten.
    """
    suffix = LOG_KINDS[kind]
    path = log_dir / f"{stem}{suffix}"
    n = 1
    while path.exists():
        n += 1
        path = log_dir / f"{stem}.part-{n}{suffix}"
    return path


def make_log_sinks(kinds: tuple[str, ...], log_dir: Path, stem: str, pairs: Collection[int] | None = None,
                   seeds: Collection[int] | None = None) -> list[Any]:
    """One sink per requested kind, writing into `log_dir`; with `pairs` or `seeds`, of those units only."""
    from mewa_bench.logs.mcap_log import McapSink
    from mewa_bench.logs.rerun_log import RerunSink
    from mewa_bench.logs.subset import UnitSubset

    makers = {"mcap": McapSink, "rerun": RerunSink}
    log_dir.mkdir(parents=True, exist_ok=True)
    sinks = [makers[k](log_path(log_dir, stem, k)) for k in kinds]
    if pairs is None and seeds is None:
        return sinks
    return [UnitSubset(sink, pairs, seeds) for sink in sinks]
