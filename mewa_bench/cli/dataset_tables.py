"""Rich tables of the dataset catalog: training data, buildable training datasets, evaluation recordings."""

from __future__ import annotations

from typing import Any

from rich.table import Table


def _size(entry: dict[str, Any]) -> str:
    return f"{entry['size'] / 1e6:.1f} MB" if "size" in entry else ""


def _source(entry: dict[str, Any]) -> str:
    return entry.get("hf_repo_id") or entry["url"].rsplit("/", 1)[-1]


def training_table(content: dict[str, Any]) -> Table:
    """The catalog's training data (meta-train workers only)."""
    table = Table("name", "version", "suite", "tier", "policy", "episodes", "frames", "size", "source",
                  title="Training data (meta-train workers only; safe to train on)")
    for e in content["datasets"]:
        table.add_row(e["name"], e["version"], e["suite"], e.get("tier", "?"), e["policy"], f"{e['episodes']:,}",
                      f"{e['frames']:,}", _size(e), _source(e))
    return table


def buildable_table(specs: dict[str, Any], content: dict[str, Any]) -> Table:
    """The named training datasets `datasets build` makes, with the sha256 the catalog records for a build."""
    builds = {(b["name"], b["version"]): b for b in content.get("builds", [])}
    table = Table("name", "version", "suite", "tier", "frames (at least)", "recorded sha256",
                  title="Training datasets built on demand: mewa-bench datasets build NAME")
    for name, spec in sorted(specs.items()):
        record = builds.get((name, spec.version))
        table.add_row(name, spec.version, spec.suite, spec.tier, f"{spec.frames:,}",
                      record["sha256"][:16] + "…" if record else "")
    return table


def evaluation_table(content: dict[str, Any]) -> Table:
    """The catalog's recordings of the curated test pairs (viewing only)."""
    table = Table("name", "version", "suite", "policy", "episodes", "frames", "size", "source",
                  title="Evaluation recordings (curated TEST pairs, protocol seeds): "
                        "for viewing only, never train on these")
    for e in content.get("evaluation_recordings", []):
        table.add_row(e["name"], e["version"], e["suite"], e["policy"], f"{e['episodes']:,}", f"{e['frames']:,}",
                      _size(e), _source(e))
    return table
