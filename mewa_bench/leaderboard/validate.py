"""Finding results files in `submissions/*/` and checking them against the shipped suites (SPEC section 7).

A results file goes on a leaderboard only if it is well-formed, complete, made on a shipped suite
with that suite's exact hash, under this protocol, covers every (pair, seed) unit, and its stored
scores agree with its units. The scores shown are recomputed from the units, never copied.
"""

from __future__ import annotations

import hashlib

import json
import re
from collections import Counter
from dataclasses import dataclass
from itertools import zip_longest
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from mewa_bench.design.suites import ALL_SUITES, VALIDATION_SUITES, Suite, SuiteError, load_suite
from mewa_bench.game.normalise import normalised_return
from mewa_bench.protocol.results import PROTOCOL_VERSION, ResultsError, read_results
from mewa_bench.protocol.config import EPISODES_PER_PAIR, default_seeds, env_seed
from mewa_bench.protocol.run_info import RunInfoError, read_run_info
from mewa_bench.protocol.scoring import Scores, episode_scores, score_units

TOLERANCE = 1e-9
_SHOWN = 5  # how many missing or unexpected units a reason lists


class InvalidResults(Exception):
    """A results file that cannot go on a leaderboard; the message says why."""


@dataclass(frozen=True)
class Entry:
    """One valid results file: an agent's row on a suite's leaderboard, scores recomputed from its units."""

    suite: str
    agent: str
    path: Path
    privileged: bool
    scores: Scores
    seeds: tuple[int, ...]
    date: str
    package_version: str
    agent_sha256: str
    algorithm: str = ""  # run.json's algorithm, or the folder's name (a one-run algorithm)


def find_results_files(submissions_dir: Path) -> Iterator[Path]:
    """Candidate results files directly inside each `submissions/<name>/`, in sorted order."""
    folders = sorted(p for p in submissions_dir.iterdir() if p.is_dir() and not p.name.startswith("."))
    for folder in folders:
        for path in sorted(folder.glob("*.json")):
            if not path.name.startswith(".") and (path.name.startswith("results-") or _looks_like_results(path)):
                yield path


def _looks_like_results(path: Path) -> bool:
    """A JSON file with `schema_version`, or one that does not parse (a truncated results file is reported)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return True
    return isinstance(data, dict) and "schema_version" in data


class SuiteCache:
    """Shipped suites, each loaded and verified once."""

    def __init__(self) -> None:
        self._suites: dict[str, Suite] = {}

    def get(self, name: Any) -> Suite:
        """The shipped suite `name`; only shipped names, never a path taken from a results file."""
        if isinstance(name, str) and name in VALIDATION_SUITES:
            raise InvalidResults(f"suite {name!r} is a validation suite (held-out meta-train workers, for tuning): "
                                 f"its runs are never ranked")
        if not isinstance(name, str) or name not in ALL_SUITES:
            raise InvalidResults(f"suite {name!r} is not a shipped suite ({', '.join(ALL_SUITES)})")
        if name not in self._suites:
            try:
                self._suites[name] = load_suite(name)
            except SuiteError as e:
                raise InvalidResults(f"the shipped suite {name} cannot be loaded: {e}") from None
        return self._suites[name]


def load_entry(path: Path, suites: SuiteCache) -> Entry:
    """Read and check one results file; raises InvalidResults with the reason."""
    try:
        return _check(path, read_results(path), suites)
    except ResultsError as e:
        raise InvalidResults(_without_prefix(str(e), path)) from None
    except (AttributeError, KeyError, IndexError, TypeError, ValueError) as e:
        # read_results checks which fields exist, not their types: a wrong type surfaces here
        raise InvalidResults(f"malformed results ({type(e).__name__}: {e})") from None


def _without_prefix(message: str, path: Path) -> str:
    """ResultsError messages start with the file name, which the report already gives."""
    prefix = f"{path}: "
    return message[len(prefix):] if message.startswith(prefix) else message


def _check(path: Path, results: dict[str, Any], suites: SuiteCache) -> Entry:
    """All leaderboard checks of a structurally valid results dict, then the entry."""
    suite, seeds, units = check_run(results, suites)
    agent = results["agent"]
    _check_agent_file(path, agent)  # before the scores: a stale file is refused without a bootstrap
    scores = verified_scores(units, suite, results["scores"])
    try:
        algorithm = read_run_info(path.parent).algorithm
    except RunInfoError as e:
        raise InvalidResults(str(e)) from None
    return Entry(suite=suite.name, agent=str(agent["name"]), path=path, privileged=agent.get("privileged") is True,
                 scores=scores, seeds=seeds, date=finished_date(results),
                 package_version=str(results["package_version"]), agent_sha256=str(agent.get("sha256") or ""),
                 algorithm=algorithm)


def check_run(results: dict[str, Any], suites: SuiteCache, expected_seeds: tuple[int, ...] | None = None
              ) -> tuple[Suite, tuple[int, ...], list[dict[str, Any]]]:
    """The checks that need no scoring: complete, a shipped suite with its exact hash, this protocol, the
    expected seeds (default: the protocol's), every unit exactly once; returns the suite, seeds and sorted units."""
    if results["complete"] is not True:
        raise InvalidResults("the run is incomplete (`complete` is not true)")
    suite = suites.get(results["suite"]["name"])
    if results["suite"]["sha256"] != suite.sha256:
        raise InvalidResults(f"suite sha256 {results['suite']['sha256']} is not the shipped {suite.name}'s "
                             f"{suite.sha256}: the run used a different or modified suite")
    if results["protocol_version"] != PROTOCOL_VERSION:
        raise InvalidResults(f"protocol {results['protocol_version']!r} results are not ranked beside protocol "
                             f"{PROTOCOL_VERSION} ones: re-run the evaluation with this version of mewa-bench")
    if results["episodes_per_pair"] != EPISODES_PER_PAIR:
        raise InvalidResults(f"episodes_per_pair is {results['episodes_per_pair']!r}; the protocol plays "
                             f"{EPISODES_PER_PAIR} per pair")
    seeds = _seeds(results["seeds"])
    expected = default_seeds(suite.name) if expected_seeds is None else tuple(expected_seeds)
    if seeds != expected and expected_seeds is None:
        raise InvalidResults(f"ranked runs on {suite.name} use the protocol's default seeds 0..{len(expected) - 1}; this run used "
                             f"{len(seeds)} seed(s) {_short(seeds)}: re-run without --seeds")
    if seeds != expected:
        raise InvalidResults(f"runs on {suite.name} are ranked here with the seeds {_short(expected)}; this run used "
                             f"{len(seeds)} seed(s) {_short(seeds)}: re-run with --seeds {','.join(map(str, expected))}")
    return suite, seeds, _covering_units(results["units"], suite, seeds)


SUBMISSION_FILES = ("agent.py", "README.md")  # besides its results files


def _check_agent_file(path: Path, agent: dict[str, Any]) -> None:
    """The submission folder holds its agent.py and README.md, and agent.py is the file these results came from."""
    missing = [name for name in SUBMISSION_FILES if not (path.parent / name).is_file()]
    if missing:
        raise InvalidResults(f"the submission folder {path.parent} has no {' and no '.join(missing)}: a submission "
                             f"holds {', '.join(SUBMISSION_FILES)} and its results files")
    agent_file = path.parent / "agent.py"
    actual = hashlib.sha256(agent_file.read_bytes()).hexdigest()
    if actual != agent.get("sha256"):
        raise InvalidResults(f"{agent_file} (sha256 {actual[:12]}…) is not the agent these results were produced "
                             f"by (sha256 {str(agent.get('sha256'))[:12]}…): re-run the evaluation")


def _seeds(seeds: Any) -> tuple[int, ...]:
    """The run's seeds: a non-empty list of distinct integers."""
    if not isinstance(seeds, list) or not seeds:
        raise InvalidResults("`seeds` must be a non-empty list")
    if not all(isinstance(s, int) and not isinstance(s, bool) for s in seeds):
        raise InvalidResults(f"`seeds` must be integers, got {seeds!r}")
    if len(set(seeds)) != len(seeds):
        raise InvalidResults(f"`seeds` has repeats: {seeds!r}")
    return tuple(seeds)


def _short(values: tuple[int, ...]) -> str:
    """A seed list, abbreviated when long."""
    return str(list(values)) if len(values) <= _SHOWN else f"[{', '.join(map(str, values[:_SHOWN]))}, ...]"


def _covering_units(units: list[dict[str, Any]], suite: Suite, seeds: tuple[int, ...]) -> list[dict[str, Any]]:
    """The units sorted by (pair, seed), if they are exactly every pair of the suite times every seed."""
    keys = [_key(u) for u in units]
    repeated = sorted(k for k, n in Counter(keys).items() if n > 1)
    if repeated:
        raise InvalidResults(f"repeated units (pair, seed): {_listing(repeated)}")
    expected = {(p, s) for p in range(len(suite.pairs)) for s in seeds}
    missing = sorted(expected - set(keys))
    if missing:
        raise InvalidResults(f"missing {len(missing)} of {len(expected)} units (pair, seed): {_listing(missing)}")
    unexpected = sorted(set(keys) - expected)
    if unexpected:
        raise InvalidResults(f"units (pair, seed) not in {suite.name} x seeds {list(seeds)}: {_listing(unexpected)}")
    for key, unit in zip(keys, units):
        if unit["task"] != suite.pairs[key[0]].task_index:
            raise InvalidResults(f"unit (pair {key[0]}, seed {key[1]}) names task {unit['task']!r}, the pair's task "
                                 f"is {suite.pairs[key[0]].task_index}")
        _check_episodes(unit, suite, key)
    return [u for _, u in sorted(zip(keys, units), key=lambda ku: ku[0])]


def _check_episodes(unit: dict[str, Any], suite: Suite, key: tuple[int, int]) -> None:
    """A unit's episodes were played where the protocol says (its env seeds are those derived from the suite
    hash, pair, seed and episode: a run cannot pick its own luck), each lasted 1..T steps, and each normalised
    return is its return normalised by the task's bounds (SPEC section 2)."""
    pair, seed = key
    where = f"unit (pair {pair}, seed {seed})"
    task = suite.tasks[suite.pairs[pair].task_index]
    expected = [env_seed(suite.sha256, pair, seed, k) for k in range(EPISODES_PER_PAIR)]
    for k, (got, want) in enumerate(zip_longest(unit["env_seeds"], expected, fillvalue="none")):
        if got != want:
            raise InvalidResults(f"{where}, episode {k}: env seed {got} is not the protocol's {want} (derived from the "
                                 f"suite hash, pair, seed and episode)")
    for k, length in enumerate(unit["lengths"]):
        if not isinstance(length, int) or isinstance(length, bool) or not 1 <= length <= task.T:
            raise InvalidResults(f"{where}, episode {k}: length {length!r} is not a step count in 1..{task.T}")
    returns = np.asarray(unit["returns"], dtype=np.float64)
    stored = np.asarray(unit["normalised_returns"], dtype=np.float64)
    off = np.flatnonzero(~(np.abs(normalised_return(task, returns) - stored) <= TOLERANCE))
    if len(off):
        k = int(off[0])
        raise InvalidResults(f"{where}, episode {k}: normalised return {float(stored[k])!r} is not that of its return "
                             f"{float(returns[k])!r} on the pair's task ({normalised_return(task, float(returns[k]))!r}): "
                             f"the file was edited after the run")


def _key(unit: dict[str, Any]) -> tuple[int, int]:
    """(pair, seed) of a unit, insisting on integers (int() would accept 1.5 or "1")."""
    pair, seed = unit["pair"], unit["seed"]
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in (pair, seed)):
        raise InvalidResults(f"unit pair and seed must be integers, got pair {pair!r}, seed {seed!r}")
    return pair, seed


def _listing(keys: list[tuple[int, int]]) -> str:
    """The first few (pair, seed) keys, and how many more."""
    shown = ", ".join(f"({p}, {s})" for p, s in keys[:_SHOWN])
    return shown + (f", ... ({len(keys)} in all)" if len(keys) > _SHOWN else "")


def verified_scores(units: list[dict[str, Any]], suite: Suite, stored: dict[str, Any]) -> Scores:
    """Recompute the scores from the units and reject files whose stored numbers disagree."""
    normalised = np.array([u["normalised_returns"] for u in units], dtype=np.float64)
    unit_scores = np.array([u["scores"] for u in units], dtype=np.float64)
    best = np.array([suite.pairs[u["pair"]].max_expected for u in units])
    if not (np.isfinite(normalised).all() and np.isfinite(unit_scores).all()):
        raise InvalidResults("units contain non-finite returns or scores")
    off = np.argwhere(np.abs(unit_scores - episode_scores(normalised, best)) > TOLERANCE)
    if len(off):
        u, k = off[0]
        raise InvalidResults(f"unit (pair {units[u]['pair']}, seed {units[u]['seed']}) episode {k}: score is not "
                             f"normalised return / the pair's max-expected baseline")
    _agree("raw mean score", stored["raw"]["mean"]["mean"], float(unit_scores.mean()))
    scores = score_units(suite, units, suite.summary["score"]["random_task_specific"])
    curve = stored["curve"]
    if len(curve) != len(scores.curve):
        raise InvalidResults(f"stored curve has {len(curve)} points, expected {len(scores.curve)}")
    for k, (point, estimate) in enumerate(zip(curve, scores.curve)):
        _agree(f"s_{k + 1}", point["mean"], estimate.mean)
    _agree("mean score", stored["mean"]["mean"], scores.mean.mean)
    _agree("adaptability", stored["adaptability"]["mean"], scores.adaptability.mean)
    return scores


def _agree(what: str, stored: Any, recomputed: float) -> None:
    """A stored point estimate must match its recomputation from the units (tampering check)."""
    if not isinstance(stored, (int, float)) or isinstance(stored, bool) or not abs(stored - recomputed) <= TOLERANCE:
        raise InvalidResults(f"stored {what} {stored!r} disagrees with {recomputed!r} recomputed from the units: "
                             f"the file was edited after the run")


def finished_date(results: dict[str, Any]) -> str:
    """The date part (YYYY-MM-DD) of `timing.finished`, or "" when absent."""
    timing = results.get("timing")
    finished = timing.get("finished") if isinstance(timing, dict) else None
    match = re.match(r"\d{4}-\d{2}-\d{2}", finished) if isinstance(finished, str) else None
    return match.group(0) if match else ""
