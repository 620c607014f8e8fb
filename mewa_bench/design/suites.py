"""Versioned suite files: loading, content hash, verification, atomic writing (SPEC section 5).

A suite is a JSON object; its identity is the sha256 of its canonical JSON (sorted keys, no
whitespace) with the `sha256` field left out. The shipped files live in `mewa_bench/suites/`.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from mewa_bench.files import json_text
from mewa_bench.game.task import Task, Worker

SUITE_FORMAT_VERSION = 1
SHIPPED_SUITES = ("narrow-v1", "wide-v1")  # the paper's design: ranked on the leaderboards
V2_SUITES = ("narrow-v2", "wide-v2")  # + the overloaded worker family (docs/suites.md)
ALL_SUITES = SHIPPED_SUITES + V2_SUITES
# What the command line evaluates, trains and submits on when no suite is named: a v2 suite, because on v1
# no fixed policy is far from optimal (gap 0.019) and adaptation cannot be told from luck there.
DEFAULT_SUITE = "narrow-v2"
VALIDATION_SUITES = tuple(f"{name}-validation" for name in ALL_SUITES)  # for tuning, never ranked (design.validation)
_REQUIRED = ("format_version", "name", "suite", "version", "env_id", "generator", "tasks", "pairs", "summary")


class SuiteError(ValueError):
    """A suite file is missing, malformed, or does not match its recorded hash."""


@dataclass(frozen=True)
class Pair:
    """One curated (task, worker) pair with its exact reference values."""

    index: int
    task_index: int
    worker: Worker
    data: dict[str, Any]

    @property
    def max_expected(self) -> float:
        """The max-expected baseline: best t-optimal policy's expected normalised return."""
        return float(self.data["baselines"]["max_expected"])


@dataclass(frozen=True)
class Suite:
    """A loaded, verified suite."""

    name: str
    tasks: tuple[Task, ...]
    pairs: tuple[Pair, ...]
    sha256: str
    content: dict[str, Any]
    path: Path | None = None

    @property
    def summary(self) -> dict[str, Any]:
        """Suite-level reference values (baseline means, best fixed policy, non-adaptive gap)."""
        return self.content["summary"]


def canonical_json(content: dict[str, Any]) -> str:
    """Sorted keys, no whitespace: the text that is hashed."""
    return json.dumps(content, sort_keys=True, separators=(",", ":"), allow_nan=False)


def content_hash(content: dict[str, Any]) -> str:
    """sha256 of the canonical JSON of a suite without its `sha256` field."""
    body = {k: v for k, v in content.items() if k != "sha256"}
    return hashlib.sha256(canonical_json(body).encode()).hexdigest()


def suite_text(content: dict[str, Any]) -> str:
    """The exact bytes of a suite file: content plus its hash."""
    return json_text({**{k: v for k, v in content.items() if k != "sha256"}, "sha256": content_hash(content)})


def shipped_path(name: str) -> Path:
    """Path of a suite shipped inside the package."""
    return Path(str(resources.files("mewa_bench") / "suites" / f"{name}.json"))


def resolve(name_or_path: str | Path) -> Path:
    """A shipped suite's name, or a path to a suite file."""
    p = Path(name_or_path)
    if p.suffix == ".json" or p.exists():
        return p
    if str(name_or_path) in ALL_SUITES + VALIDATION_SUITES:
        return shipped_path(str(name_or_path))
    raise SuiteError(f"unknown suite {str(name_or_path)!r}: expected one of {', '.join(ALL_SUITES)}, a validation "
                     f"suite (<suite>-validation) or a .json path")


def parse_suite(content: Any, where: str) -> Suite:
    """Check a suite's structure and hash and build the `Suite` (errors name the file and the field)."""
    if not isinstance(content, dict):
        raise SuiteError(f"{where}: a suite must be a JSON object")
    missing = [k for k in (*_REQUIRED, "sha256") if k not in content]
    if missing:
        raise SuiteError(f"{where}: missing field(s) {', '.join(missing)}")
    if content["format_version"] != SUITE_FORMAT_VERSION:
        raise SuiteError(f"{where}: format_version {content['format_version']!r} is not supported "
                         f"(this mewa-bench reads {SUITE_FORMAT_VERSION})")
    actual = content_hash(content)
    if actual != content["sha256"]:
        raise SuiteError(f"{where}: content does not match its recorded hash (recorded sha256 "
                         f"{content['sha256']}, content hashes to {actual}); the file was modified or corrupted")
    try:
        tasks = tuple(Task.from_dict(t) for t in content["tasks"])
    except ValueError as e:
        raise SuiteError(f"{where}: bad task: {e}") from None
    pairs = []
    for i, p in enumerate(content["pairs"]):
        try:
            task = tasks[p["task"]]
            worker = Worker.of(p["worker"])
            worker.check_fits(task)
        except (KeyError, IndexError, TypeError, ValueError) as e:
            raise SuiteError(f"{where}: pair {i}: {e}") from None
        pairs.append(Pair(i, int(p["task"]), worker, p))
    return Suite(str(content["name"]), tasks, tuple(pairs), actual, content)


def load_suite(name_or_path: str | Path) -> Suite:
    """Load and verify a suite by shipped name (`narrow-v1`) or path."""
    path = resolve(name_or_path)
    try:
        text = path.read_text()
    except OSError as e:
        raise SuiteError(f"{path}: cannot read suite file: {e.strerror}") from None
    try:
        content = json.loads(text)
    except json.JSONDecodeError as e:
        raise SuiteError(f"{path}: not valid JSON (truncated or corrupted?): {e}") from None
    suite = parse_suite(content, str(path))
    return Suite(suite.name, suite.tasks, suite.pairs, suite.sha256, suite.content, path)
