"""The results file of an evaluation run (JSON, schema-versioned; SPEC section 6).

Layout (schema 2, protocol 2; schema-1 files of protocol 1 still load and are shown as such):
- `schema_version`, `protocol_version`, `complete` (false while the run is in progress);
- `agent`: name, file, sha256, privileged, agent_args, checkpoint;
- `suite`: name, version, sha256; `env`: id, version, mode; `package_version`;
- `seeds`, `episodes_per_pair`, `isolation` (isolated, time_limit, memory_limit);
- `units`: one per (pair, seed), sorted: pair, seed, task, env_seeds (= the episodes' luck keys),
  returns, normalised_returns, lengths, scores (raw: normalised return / the pair's max-expected);
- `scores` (when complete; `protocol.scoring`): curve s_1..s_K, mean, iqm, adaptability, skill
  (control-variate adjusted, with 95% stratified-bootstrap CIs, null when not estimable),
  verdicts, comparisons with the reference lines, the raw (unadjusted) estimates, control-variate
  and bootstrap settings; `baselines`: the suite's reference lines on the score scale and skill;
- `timing` (started, finished, wall_time, per-unit seconds), `machine` and `execution` (jobs,
  lanes): the only fields that differ between two runs of the same agent with the same seeds.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from mewa_bench.design.suites import write_json_atomic

SCHEMA_VERSION = 2
PROTOCOL_VERSION = 2
SUPPORTED = {1: 1, 2: 2}  # schema version -> its protocol version
VOLATILE_FIELDS = ("timing", "machine", "execution")
_REQUIRED = ("schema_version", "protocol_version", "complete", "agent", "suite", "env", "package_version",
             "seeds", "episodes_per_pair", "units")
_UNIT_FIELDS = ("pair", "seed", "task", "env_seeds", "returns", "normalised_returns", "lengths", "scores")


class ResultsError(ValueError):
    """A results file is malformed or does not fit the suite or protocol it claims."""


def unit_key(unit: dict[str, Any]) -> tuple[int, int]:
    """(pair, seed): the identity and sort order of a unit."""
    return int(unit["pair"]), int(unit["seed"])


def write_results(path: Path, results: dict[str, Any]) -> None:
    """Write a results file atomically (units sorted), so a good file is never half-written."""
    results = {**results, "units": sorted(results["units"], key=unit_key)}
    write_json_atomic(path, results)


def read_results(path: Path) -> dict[str, Any]:
    """Read and structurally validate a results file; errors name the file and the field."""
    try:
        results = json.loads(Path(path).read_text())
    except OSError as e:
        raise ResultsError(f"{path}: cannot read results file: {e.strerror}") from None
    except json.JSONDecodeError as e:
        raise ResultsError(f"{path}: not valid JSON: {e}") from None
    validate_structure(results, str(path))
    return results


def validate_structure(results: Any, where: str) -> None:
    """Check the schema of a results dict (not its agreement with a suite)."""
    try:
        _validate(results, where)
    except (TypeError, KeyError, AttributeError) as e:  # a field of the wrong type
        raise ResultsError(f"{where}: malformed results ({type(e).__name__}: {e})") from None


def _validate(results: Any, where: str) -> None:
    if not isinstance(results, dict):
        raise ResultsError(f"{where}: a results file must be a JSON object")
    missing = [k for k in _REQUIRED if k not in results]
    if missing:
        raise ResultsError(f"{where}: missing field(s) {', '.join(missing)}")
    schema = results["schema_version"]
    if schema not in SUPPORTED or isinstance(schema, bool):
        raise ResultsError(f"{where}: schema_version {schema!r} is not supported (expected one of {sorted(SUPPORTED)})")
    if results["protocol_version"] != SUPPORTED[schema]:
        raise ResultsError(f"{where}: protocol_version {results['protocol_version']!r} does not match schema_version "
                           f"{schema} (protocol {SUPPORTED[schema]})")
    for key in ("name", "sha256"):
        if key not in results["suite"]:
            raise ResultsError(f"{where}: suite.{key} is missing")
    k = results["episodes_per_pair"]
    for i, unit in enumerate(results["units"]):
        absent = [f for f in _UNIT_FIELDS if f not in unit]
        if absent:
            raise ResultsError(f"{where}: units[{i}] is missing {', '.join(absent)}")
        for f in ("env_seeds", "returns", "normalised_returns", "lengths", "scores"):
            if len(unit[f]) != k:
                raise ResultsError(f"{where}: units[{i}] (pair {unit['pair']}, seed {unit['seed']}): {f} has "
                                   f"{len(unit[f])} entries, expected {k}")
    if results["complete"] and "scores" not in results:
        raise ResultsError(f"{where}: a complete results file must have scores")


def stable_view(results: dict[str, Any]) -> dict[str, Any]:
    """The results without the fields that legitimately differ between identical runs."""
    return {k: v for k, v in results.items() if k not in VOLATILE_FIELDS}
