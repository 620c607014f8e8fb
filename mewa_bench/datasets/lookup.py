"""What a dataset name is: a published catalog entry, a training dataset built on demand, or unknown.

`datasets info` and `datasets download` ask here, so that a name `datasets list` shows is never "unknown"
to them: a buildable training dataset is described with its build command (it is built, not downloaded).
"""

from __future__ import annotations

from typing import Any

from mewa_bench.datasets.catalog import (EVALUATION_WARNING, TRAINING, DatasetError, catalog_entries, dataset_info,
                                         entry_kind, recorded_build)
from mewa_bench.datasets.training_data import TRAINING_DATASETS


def buildable_description(name: str, catalog: dict[str, Any] | None) -> dict[str, Any] | None:
    """The fields of the training dataset `datasets build NAME` makes (None if NAME is not one)."""
    base, _, version = name.partition("@")
    spec = TRAINING_DATASETS.get(base)
    if spec is None or (version and version != spec.version):
        return None
    record = recorded_build(catalog, spec.name, spec.version) if catalog is not None else None
    return {"name": spec.name, "version": spec.version, "kind": TRAINING, "suite": spec.suite, "tier": spec.tier,
            "frames (at least)": f"{spec.frames:,}", "behaviour": _behaviour(spec.tier, spec.expert_agent),
            "tasks": ("every structure of the suite's generator, colours 0..N-1 (not the suite's)" if spec.task_structures
                      else f"{spec.generated_tasks} that the suite's generator draws (not the suite's)" if spec.generated_tasks
                      else "the suite's"),
            "dataset id": spec.dataset_id, "recorded sha256": record["sha256"] if record else "none recorded yet",
            "how to get it": f"{spec.build_command()} (built locally and deterministically; not downloaded)"}


def _behaviour(tier: str, expert: str) -> str:
    """The policy that plays a tier's meta-episodes."""
    return expert if tier == "expert" else tier


def describe(catalog: dict[str, Any] | None, name: str) -> tuple[dict[str, Any], str | None]:
    """A dataset's fields and the warning to show first (for a recording of the test pairs), whatever it is."""
    if catalog is not None and any(e["name"] == name.partition("@")[0] for e in catalog_entries(catalog)):
        entry = dataset_info(catalog, name)
        return entry, (None if entry_kind(entry) == TRAINING else EVALUATION_WARNING)
    built = buildable_description(name, catalog)
    if built is not None:
        return built, None
    known = sorted({e["name"] for e in catalog_entries(catalog)} if catalog is not None else set())
    raise DatasetError(f"dataset {name!r} is neither in the catalog ({', '.join(known) or 'none'}) nor a training "
                       f"dataset `datasets build` makes ({', '.join(sorted(TRAINING_DATASETS))})")


def download_warning(catalog: dict[str, Any] | None, source: str) -> str | None:
    """The warning to show before downloading `source`, or an error if it is built rather than downloaded."""
    if catalog is None or "/" in source or ":" in source:
        return None
    if not any(e["name"] == source.partition("@")[0] for e in catalog_entries(catalog)):
        built = buildable_description(source, catalog)
        if built is not None:
            raise DatasetError(f"{source!r} is a training dataset built on demand, not published for download: "
                               f"{built['how to get it']}")
        return None
    return None if entry_kind(dataset_info(catalog, source)) == TRAINING else EVALUATION_WARNING
