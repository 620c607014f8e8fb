"""The results file of an evaluation run (JSON, schema-versioned; SPEC section 6).

Layout (schema 3, protocol 2; schema-2 files of protocol 2 read the same, schema-1 files of protocol 1 still
load and are shown as such):
- `schema_version`, `protocol_version`, `complete` (false while the run is in progress);
- `agent`: name, file, sha256, privileged, agent_args, checkpoint;
- `suite`: name, version, sha256; `env`: id, version, mode; `package_version`;
- `seeds`, `episodes_per_pair`, `isolation` (isolated, time_limit, memory_limit);
- `units`: one per (pair, seed), sorted: pair, seed, task, env_seeds (= the episodes' luck keys),
  returns, normalised_returns, lengths, scores (raw: normalised return / the pair's max-expected);
  schema 3 stores them as compressed typed columns (`protocol.unit_columns`), schema 2 as a JSON list;
  `read_results` and `validate_structure` give the list of unit dicts either way;
- `scores` (when complete; `protocol.scoring`): curve s_1..s_K, mean, iqm, adaptability, skill
  (control-variate adjusted, with 95% stratified-bootstrap CIs, null when not estimable),
  verdicts, comparisons with the reference lines, the raw (unadjusted) estimates, control-variate
  and bootstrap settings; `baselines`: the suite's reference lines on the score scale and skill;
- `timing` (started, finished, wall_time, per-unit seconds), `machine` and `execution` (jobs,
  lanes): the only fields that differ between two runs of the same agent with the same seeds.
"""

from __future__ import annotations

import json
import os
import platform
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from mewa_bench.design.references import summarise
from mewa_bench.design.suites import Suite
from mewa_bench.envs.mewa_env import ENV_VERSION
from mewa_bench.files import json_text, write_atomic
from mewa_bench.protocol.agent import agent_sha256
from mewa_bench.protocol.config import EvalConfig, agent_name
from mewa_bench.protocol.scoring import score_units
from mewa_bench.protocol.unit_columns import ColumnError, decode_units, encode_units

SCHEMA_VERSION = 3
PROTOCOL_VERSION = 2
SUPPORTED = {1: 1, 2: 2, 3: 2}  # schema version -> its protocol version
COLUMNAR = 3  # the first schema whose units are columns
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
    write_atomic(path, results_text(results, str(path)))


def results_text(results: dict[str, Any], where: str = "results") -> str:
    """The text of a results file (units sorted; schema 3: as columns): the same results give the same bytes."""
    units = sorted(results["units"], key=unit_key)
    if results.get("schema_version") == COLUMNAR:
        try:
            units = encode_units(units, results["episodes_per_pair"], results["suite"], where)
        except ColumnError as e:
            raise ResultsError(str(e)) from None
    return json_text({**results, "units": units})


def read_results(path: Path) -> dict[str, Any]:
    """Read and structurally validate a results file; errors name the file and the field."""
    try:
        results = json.loads(Path(path).read_text())
    except OSError as e:
        raise ResultsError(f"{path}: cannot read results file: {e.strerror}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ResultsError(f"{path}: not valid JSON: {e}") from None
    return validate_structure(results, str(path))


def validate_structure(results: Any, where: str) -> dict[str, Any]:
    """Check the schema of a results dict (not its agreement with a suite); returns it with its units as
    the list of unit dicts (a schema-3 file's columns decoded: a new dict, the given one is left as it was)."""
    try:
        return _validate(results, where)
    except (TypeError, KeyError, AttributeError) as e:  # a field of the wrong type
        raise ResultsError(f"{where}: malformed results ({type(e).__name__}: {e})") from None


def _validate(results: Any, where: str) -> dict[str, Any]:
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
    if schema == COLUMNAR:
        results = {**results, "units": _decoded_units(results, where)}
    elif not isinstance(results["units"], list):
        raise ResultsError(f"{where}: units must be a list in schema {schema}")
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
    return results


def _decoded_units(results: dict[str, Any], where: str) -> list[dict[str, Any]]:
    """A schema-3 file's unit dicts, from its columns (env seeds derived from its suite hash where not stored)."""
    k, suite_hash = results["episodes_per_pair"], results["suite"]["sha256"]
    if not isinstance(k, int) or isinstance(k, bool) or not 1 <= k <= 1000:
        raise ResultsError(f"{where}: episodes_per_pair must be a whole number in 1..1000, got {k!r}")
    if not isinstance(suite_hash, str):
        raise ResultsError(f"{where}: suite.sha256 must be a string, got {suite_hash!r}")
    try:
        return decode_units(results["units"], k, suite_hash, where)
    except ColumnError as e:
        raise ResultsError(str(e)) from None


def stable_view(results: dict[str, Any]) -> dict[str, Any]:
    """The results without the fields that legitimately differ between identical runs."""
    return {k: v for k, v in results.items() if k not in VOLATILE_FIELDS}


def available_cpus() -> int:
    """CPUs this process may run on (the affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def machine_info() -> dict[str, Any]:
    """Where the run happened (the results file's `machine`)."""
    return {"platform": platform.platform(), "python": platform.python_version(), "cpus": available_cpus(),
            "processor": platform.machine()}


def new_results(config: EvalConfig, suite: Suite) -> dict[str, Any]:
    """The header of a results file, before any unit."""
    from mewa_bench import __version__

    return {
        "schema_version": SCHEMA_VERSION, "protocol_version": PROTOCOL_VERSION, "complete": False,
        "agent": {"name": config.name or agent_name(config.agent_path), "file": str(config.agent_path),
                  "sha256": agent_sha256(config.agent_path), "privileged": config.privileged,
                  "agent_args": dict(sorted(config.agent_args.items())), "checkpoint": config.checkpoint},
        "suite": {"name": suite.name, "version": suite.content["version"], "sha256": suite.sha256},
        "env": {"id": suite.content["env_id"], "version": ENV_VERSION, "mode": config.mode,
                **({"image_size": list(config.image_size)} if config.mode == "sapien" else {})},
        "package_version": __version__, "seeds": list(config.seeds), "episodes_per_pair": config.episodes,
        "pairs": list(config.pairs) if config.pairs is not None else None,
        "isolation": {"isolated": config.isolated, "time_limit": config.time_limit, "memory_limit": config.memory_limit},
        "execution": {"jobs": config.jobs, "lanes": config.lanes, "ray": config.ray},
        "units": [],
        "timing": {"started": datetime.now(timezone.utc).isoformat(timespec="seconds"), "units": {}},
        "machine": machine_info(),
    }


def resume_from(path: Path, fresh: dict[str, Any]) -> dict[str, Any]:
    """Continue an earlier run of the same agent, suite and settings."""
    old = read_results(path)
    before, now = old.get("agent", {}), fresh["agent"]
    if before.get("sha256") != now["sha256"]:
        raise ResultsError(f"{path}: cannot resume: the agent file changed since this run started (sha256 "
                           f"{str(before.get('sha256'))[:12]}… then, {now['sha256'][:12]}… now); results of two "
                           f"different agents cannot be mixed: start a new run (--out FILE, or --overwrite)")
    for key in ("agent", "suite", "seeds", "episodes_per_pair", "pairs", "env"):
        if old.get(key) != fresh.get(key):
            raise ResultsError(f"{path}: cannot resume: {key} differs from this run "
                               f"({old.get(key)!r} in the file, {fresh.get(key)!r} now)")
    if old["protocol_version"] == PROTOCOL_VERSION:
        old["schema_version"] = SCHEMA_VERSION  # a run of this protocol goes on in the current layout
    return old


def finish(results: dict[str, Any], suite: Suite) -> dict[str, Any]:
    """Add scores and baselines to a results dict whose units are all done.

    A partial run (--pairs) is compared with the references over its own pairs, never the whole suite's.
    """
    units = results["units"] = sorted(results["units"], key=unit_key)
    partial = results.get("pairs") is not None
    if partial:
        played = [suite.pairs[i].data for i in results["pairs"]]
        baselines = {**summarise(played), "pairs": list(results["pairs"])}
    else:
        baselines = {"score": suite.summary["score"], "skill": suite.summary["skill"],
                     "non_adaptive_gap": suite.summary["non_adaptive_gap"]}
    scores = score_units(suite, units, baselines["score"]["random_task_specific"])
    results["scores"] = scores.to_dict()
    results["baselines"] = baselines
    results["complete"] = not partial
    return results
