"""Rewriting a schema-2 results file as schema 3 (`mewa-bench results convert`), after checking it.

A file is converted only if it is a run of its shipped suite as the runner writes one: every unit's
task is its pair's, its env seeds are the protocol's, its scores are its normalised returns over the
pair's max-expected baseline (bit for bit), the units decoded from the new columns are the old ones
bit for bit, the scores recomputed from them are the stored ones exactly, and every other field is
unchanged. The new file replaces the old one atomically; nothing is written if a check fails.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mewa_bench.design.suites import ALL_SUITES, Suite, load_suite
from mewa_bench.files import json_text, write_atomic
from mewa_bench.game.normalise import episode_score
from mewa_bench.protocol.results import (COLUMNAR, SCHEMA_VERSION, ResultsError, finish, read_results, results_text,
                                         unit_key, validate_structure)
from mewa_bench.protocol.unit_columns import protocol_env_seeds, same_units


@dataclass(frozen=True)
class Conversion:
    """What converting one file did: its size before and after (the same when it was schema 3 already)."""

    path: Path
    schema_before: int
    bytes_before: int
    bytes_after: int
    rescored: tuple[str, ...] = ()  # the score fields that re-scoring changed (empty: none, or not re-scored)
    largest_change: float = 0.0  # the largest absolute change of a number among them (fields added or removed aside)


def convert_results(path: Path, rescore: bool = False) -> Conversion:
    """Rewrite a schema-2 results file as schema 3 after the checks above; a schema-3 file is left as it is.

    With `rescore`, the scores are recomputed from the (checked) units instead of checked against the stored ones.
    """
    path = Path(path)
    size = path.stat().st_size if path.exists() else 0
    results = read_results(path)
    schema = results["schema_version"]
    if schema == COLUMNAR:
        return Conversion(path, schema, size, size)
    if schema != 2:
        raise ResultsError(f"{path}: schema {schema} (protocol {results['protocol_version']}) results cannot become "
                           f"schema {COLUMNAR}: only schema-2 files (protocol 2) convert; re-run the evaluation")
    suite = _suite(results, path)
    units = sorted(results["units"], key=unit_key)
    _check_units(units, suite, results["episodes_per_pair"], path)
    text = results_text({**results, "schema_version": SCHEMA_VERSION}, str(path))
    back = validate_structure(json.loads(text), str(path))
    differ = same_units(units, back["units"])
    if differ is not None:
        raise ResultsError(f"{path}: the columns do not give back the units exactly ({differ}); nothing was written")
    others = json_text({**back, "schema_version": schema, "units": units})
    if others != json_text({**results, "units": units}):
        raise ResultsError(f"{path}: a field other than the units changed in conversion; nothing was written")
    if rescore:
        again = finish({**back, "units": list(back["units"])}, suite)
        moved = _differences(again, results)
        text = results_text({**again, "schema_version": SCHEMA_VERSION}, str(path))
        write_atomic(path, text)
        finite = [v for v in moved.values() if v != float("inf")]
        return Conversion(path, schema, size, len(text.encode()), tuple(moved), max(finite, default=0.0))
    if "scores" in results:
        _check_scores(back, results, suite, path)
    write_atomic(path, text)
    return Conversion(path, schema, size, len(text.encode()))


def _suite(results: dict[str, Any], path: Path) -> Suite:
    """The shipped suite the file was played on, with the file's hash."""
    name = results["suite"]["name"]
    if name not in ALL_SUITES:
        raise ResultsError(f"{path}: suite {name!r} is not a shipped suite ({', '.join(ALL_SUITES)}): conversion "
                           f"checks a file against its suite")
    suite = load_suite(name)
    if results["suite"]["sha256"] != suite.sha256:
        raise ResultsError(f"{path}: suite sha256 {results['suite']['sha256']} is not the shipped {name}'s "
                           f"{suite.sha256}: the run used another version of the suite")
    return suite


def _check_units(units: list[dict[str, Any]], suite: Suite, episodes: int, path: Path) -> None:
    """Each unit's task, env seeds and scores are those the runner gives it."""
    for unit in units:
        pair, seed = unit_key(unit)
        where = f"{path}: unit (pair {pair}, seed {seed})"
        if not 0 <= pair < len(suite.pairs) or unit["task"] != suite.pairs[pair].task_index:
            raise ResultsError(f"{where}: task {unit['task']!r} is not the pair's task in {suite.name}")
        if unit["env_seeds"] != list(protocol_env_seeds(suite.sha256, pair, seed, episodes)):
            raise ResultsError(f"{where}: env seeds are not the protocol's (derived from the suite hash, pair, seed "
                               f"and episode)")
        expected = [float(v) for v in episode_score(np.array(unit["normalised_returns"], dtype=np.float64),
                                                    suite.pairs[pair].max_expected)]
        if same_units([{"scores": unit["scores"]}], [{"scores": expected}]) is not None:
            raise ResultsError(f"{where}: scores {unit['scores']} are not its normalised returns over the pair's "
                               f"max-expected baseline {suite.pairs[pair].max_expected!r}")


LATER_SCORE_FIELDS = ("pair_means",)  # score fields newer than some valid files


def _check_scores(back: dict[str, Any], results: dict[str, Any], suite: Suite, path: Path) -> None:
    """The scores, baselines and completeness recomputed from the decoded units are the stored ones exactly."""
    again = finish({**back, "units": list(back["units"])}, suite)
    stored = results.get("scores")
    if isinstance(stored, dict) and isinstance(again.get("scores"), dict):
        for added in LATER_SCORE_FIELDS:  # a file scored before a field existed checks out without it
            if added not in stored:
                again["scores"].pop(added, None)
    for key in ("scores", "baselines", "complete"):
        where = _first_difference(again.get(key), results.get(key), key)
        if where is not None:
            raise ResultsError(f"{path}: {where} recomputed from the units differs from the stored one (scored by "
                               f"another version of mewa-bench?): re-score the run before converting it; nothing "
                               f"was written")


def _differences(again: dict[str, Any], results: dict[str, Any]) -> dict[str, float]:
    """Each leaf of scores/baselines/complete that differs after re-scoring, with its absolute change (inf if
    not numeric)."""
    moved: dict[str, float] = {}

    def walk(a: Any, b: Any, at: str) -> None:
        if isinstance(a, dict) and isinstance(b, dict):
            for key in sorted(set(a) | set(b)):
                if key in a and key in b:
                    walk(a[key], b[key], f"{at}.{key}")
                else:  # a field today's scoring adds (or no longer writes)
                    moved[f"{at}.{key}"] = float("inf")
        elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
            for i, (x, y) in enumerate(zip(a, b)):
                walk(x, y, f"{at}[{i}]")
        elif json_text(a) != json_text(b):
            numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (a, b))
            moved[at] = abs(float(a) - float(b)) if numeric else float("inf")

    for key in ("scores", "baselines", "complete"):
        walk(again.get(key), results.get(key), key)
    return moved


def _first_difference(a: Any, b: Any, at: str) -> str | None:
    """The first field (dotted path) where two JSON values differ, None if they are the same JSON."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            if key not in a or key not in b:
                return f"{at}.{key}"
            found = _first_difference(a[key], b[key], f"{at}.{key}")
            if found is not None:
                return found
        return None
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return next((d for i, (x, y) in enumerate(zip(a, b)) if (d := _first_difference(x, y, f"{at}[{i}]"))), None)
    return None if json_text(a) == json_text(b) else at
