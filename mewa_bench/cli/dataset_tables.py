"""Rich tables of the dataset catalog: training data, buildable training datasets, evaluation recordings.

Below WIDE columns a table keeps the name whole and leaves out what the name already says (suite, tier)
or what `datasets info NAME` shows (policy, size, source), so that it reads at 80 columns."""

from __future__ import annotations

from typing import Any, Sequence

from rich import box
from rich.table import Table

WIDE = 120  # terminal columns from which every column is shown


def _size(entry: dict[str, Any]) -> str:
    return f"{entry['size'] / 1e6:.1f} MB" if "size" in entry else ""


def _source(entry: dict[str, Any]) -> str:
    return entry.get("hf_repo_id") or entry["url"].rsplit("/", 1)[-1]


def _table(title: str, columns: Sequence[tuple[str, bool]], rows: Sequence[Sequence[str]], width: int) -> Table:
    """A table of `rows` under `columns` ((header, shown only when wide)); the name column (the first) never wraps."""
    wide = width >= WIDE
    keep = [i for i, (_, wide_only) in enumerate(columns) if wide or not wide_only]
    table = Table(title=title, **({} if wide else {"box": box.SIMPLE_HEAD, "pad_edge": False}))
    for i in keep:
        table.add_column(columns[i][0], no_wrap=i == 0)
    for row in rows:
        table.add_row(*(row[i] for i in keep))
    return table


def training_table(content: dict[str, Any], width: int = WIDE) -> Table:
    """The catalog's training data (meta-train workers only)."""
    columns = [("name", False), ("version", False), ("suite", True), ("tier", True), ("policy", True),
               ("episodes", False), ("frames", False), ("size", True), ("source", True)]
    rows = [(e["name"], e["version"], e["suite"], e.get("tier", "?"), e["policy"], f"{e['episodes']:,}",
             f"{e['frames']:,}", _size(e), _source(e)) for e in content["datasets"]]
    return _table("Training data (meta-train workers only; safe to train on)", columns, rows, width)


def buildable_table(specs: dict[str, Any], content: dict[str, Any], width: int = WIDE) -> Table:
    """The named training datasets `datasets build` makes, with the sha256 the catalog records for a build."""
    builds = {(b["name"], b["version"]): b for b in content.get("builds", [])}
    columns = [("name", False), ("version", False), ("suite", True), ("tier", True), ("frames (at least)", False),
               ("recorded sha256", False)]
    rows = []
    for name, spec in sorted(specs.items()):
        record = builds.get((name, spec.version))
        rows.append((name, spec.version, spec.suite, spec.tier, f"{spec.frames:,}",
                     (record["sha256"][:16] if width >= WIDE else record["sha256"][:12]) + "…" if record else ""))
    return _table("Training datasets built on demand: mewa-bench datasets build NAME", columns, rows, width)


def evaluation_table(content: dict[str, Any], width: int = WIDE) -> Table:
    """The catalog's recordings of the curated test pairs (viewing only)."""
    columns = [("name", False), ("version", False), ("suite", True), ("policy", True), ("episodes", False),
               ("frames", False), ("size", True), ("source", True)]
    rows = [(e["name"], e["version"], e["suite"], e["policy"], f"{e['episodes']:,}", f"{e['frames']:,}", _size(e),
             _source(e)) for e in content.get("evaluation_recordings", [])]
    return _table("Evaluation recordings (curated TEST pairs, protocol seeds): for viewing only, never train on these",
                  columns, rows, width)
