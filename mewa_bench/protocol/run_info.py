"""`run.json`: what a submission folder's run is a run of (algorithm, training seed, suite, budget).

Runs of one algorithm are compared as a group (`protocol.aggregate`): the file names the algorithm
and the training run. `mewa-bench train` writes it; a user's own submission may carry one. Without
it a folder is a one-run algorithm named after the agent (the folder's name for submissions/<name>/).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mewa_bench.files import write_atomic

RUN_FILE = "run.json"
_FIELDS = {"algorithm": str, "seed": int, "suite": str, "steps": int, "notes": str, "settings": dict}


class RunInfoError(ValueError):
    """A run.json that cannot be read; the message names the file and the field."""


@dataclass(frozen=True)
class RunInfo:
    """A training run: its algorithm, training seed, training suite, budget (env steps; an offline algorithm's
    own unit, e.g. DPT's meta-episodes), free notes and the settings it changed from the algorithm's defaults
    (`train --set`, and an offline run's `dataset`)."""

    algorithm: str
    seed: int | None = None
    suite: str | None = None
    steps: int | None = None
    notes: str = ""
    settings: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (absent fields left out)."""
        out = {"algorithm": self.algorithm, "seed": self.seed, "suite": self.suite, "steps": self.steps,
               "notes": self.notes, "settings": self.settings}
        return {k: v for k, v in out.items() if v not in (None, "", {})}


def read_run_info(folder: Path, default_name: str | None = None) -> RunInfo:
    """The folder's run.json, or a one-run algorithm named `default_name` (default: the folder's name)."""
    path = Path(folder) / RUN_FILE
    if not path.exists():
        return RunInfo(algorithm=default_name or Path(folder).resolve().name)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise RunInfoError(f"{path}: cannot read it as JSON ({e})") from None
    return parse_run_info(data, str(path))


def parse_run_info(data: Any, where: str) -> RunInfo:
    """A RunInfo from run.json's content; RunInfoError naming `where` and the field otherwise."""
    if not isinstance(data, dict):
        raise RunInfoError(f"{where}: run.json must be a JSON object")
    unknown = sorted(set(data) - set(_FIELDS))
    if unknown:
        raise RunInfoError(f"{where}: unknown field(s) {unknown}; known: {sorted(_FIELDS)}")
    for key, kind in _FIELDS.items():
        value = data.get(key)
        if value is not None and (not isinstance(value, kind) or isinstance(value, bool)):
            what = {int: "n integer", str: " string", dict: "n object"}[kind]
            raise RunInfoError(f"{where}: `{key}` must be a{what}, got {value!r}")
    algorithm = data.get("algorithm")
    if not isinstance(algorithm, str) or not algorithm.strip():
        raise RunInfoError(f"{where}: `algorithm` must be a non-empty string")
    steps = data.get("steps")
    if steps is not None and steps < 1:
        raise RunInfoError(f"{where}: `steps` must be a positive number of env steps, got {steps}")
    return RunInfo(algorithm=algorithm.strip(), seed=data.get("seed"), suite=data.get("suite"), steps=steps,
                   notes=data.get("notes") or "", settings=data.get("settings") or {})


def write_run_info(folder: Path, info: RunInfo) -> Path:
    """Write the folder's run.json atomically; the path written."""
    path = Path(folder) / RUN_FILE
    write_atomic(path, json.dumps(info.to_dict(), indent=2) + "\n")
    return path


def run_name(algorithm: str, suite: str, seed: int) -> str:
    """`<algorithm>-<suite>-seed<seed>`: the folder and agent name of a training run (unique across algorithms)."""
    return f"{algorithm}-{suite}-seed{seed}"
