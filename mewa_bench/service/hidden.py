"""Hidden test suites: made on the server from a private seed, played by its workers, never served.

Each public suite `X` (narrow-v1, wide-v1, narrow-v2, wide-v2) has a hidden twin `X-hidden` made by
the same generator (`design.generate`: Eq. 1 design, curation by MAD and Mann-Whitney, the same
phase 2) with three differences that make its curated workers the server's secret: its seed is
derived from the private seed (wide suites sample other tasks); curation chooses only among grid
workers that no public suite of the family uses; and only among a random half of those, drawn
from that seed and the task. The private seed is drawn once with `secrets` into
`<data dir>/hidden/seed.json`; the suites are cached beside it (generating all four takes about a
minute), and the same seed always gives the same bytes.
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import json
import os
import secrets
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterable, Iterator

from mewa_bench.design.generate import SPECS, SuiteSpec, generate_suite
from mewa_bench.design.suites import ALL_SUITES, SuiteError, load_suite, suite_text
from mewa_bench.files import write_atomic
from mewa_bench.protocol.config import suite_family

HIDDEN_SUITES = {f"{name}-hidden": name for name in ALL_SUITES}  # hidden suite -> its public twin
CANDIDATE_FRACTION = 0.5
HIDDEN_DIR = "hidden"  # in the data dir: the seed, the suites and a lock file, readable by the server only
SEED_FILE = "seed.json"
_KIND_OF = {spec.name: kind for kind, spec in SPECS.items()}  # public suite name -> its generator kind


def hidden_suites(data_dir: Path, names: Iterable[str] | None = None,
                  progress: Callable[[str], None] = lambda msg: None) -> dict[str, Path]:
    """The hidden suites' files (all of HIDDEN_SUITES, or `names`), generated into `data_dir` the first time.

    A cached file is checked (its hash, and that it came from this data dir's seed) on every call; a
    damaged one is generated again, to the same bytes. Safe to call from several processes at once.
    """
    names = list(HIDDEN_SUITES if names is None else names)
    unknown = [n for n in names if n not in HIDDEN_SUITES]
    if unknown:
        raise ValueError(f"unknown hidden suite(s) {unknown}: expected some of {', '.join(HIDDEN_SUITES)}")
    directory = Path(data_dir) / HIDDEN_DIR
    directory.mkdir(parents=True, exist_ok=True)
    os.chmod(directory, 0o700)
    paths = {}
    with _locked(directory / ".lock"):
        seed = _private_seed(directory)
        for name in names:
            path = directory / f"{name}.json"
            if not _cached(path, name, seed):
                progress(f"generating hidden suite {name}")
                write_atomic(path, suite_text(hidden_suite_content(name, seed, progress)))
            paths[name] = path
    return paths


def hidden_suite_content(name: str, private_seed: int, progress: Callable[[str], None] = lambda msg: None) -> dict:
    """The content (without its hash) of hidden suite `name` for a private seed."""
    spec = hidden_spec(name, private_seed)
    content = generate_suite(spec, progress)
    public = HIDDEN_SUITES[name]
    content["generator"]["command"] = "mewa_bench.service.hidden.hidden_suites (from the server's private seed)"
    content["generator"]["hidden"] = {"public_twin": public, "candidate_fraction": spec.candidate_fraction,
                                      "excluded_public_workers": len(spec.excluded_workers)}
    content["description"] += f"; hidden twin of {public} (workers drawn from a private seed)"
    return content


def hidden_spec(name: str, private_seed: int) -> SuiteSpec:
    """What hidden suite `name` is generated from: its public twin's spec, with the changes above."""
    public = HIDDEN_SUITES[name]
    family = suite_family(public)
    excluded = sorted({tuple(pair.worker.w) for other in ALL_SUITES if suite_family(other) == family
                       for pair in load_suite(other).pairs})
    return dataclasses.replace(SPECS[_KIND_OF[public]], name=name, seed=suite_seed(private_seed, name),
                               excluded_workers=tuple(excluded), candidate_fraction=CANDIDATE_FRACTION)


def suite_seed(private_seed: int, name: str) -> int:
    """The generator seed of one hidden suite (63 bits of sha256 of the private seed and the name)."""
    digest = hashlib.sha256(f"{private_seed:x}/{name}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def _private_seed(directory: Path) -> int:
    """The data dir's private seed, drawn (128 bits, `secrets`) and written the first time."""
    path = directory / SEED_FILE
    if path.exists():
        try:
            return int(json.loads(path.read_text())["seed"], 16)
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise SuiteError(f"{path}: unreadable private seed of the hidden suites ({e}); restore it from a backup "
                             f"(a new seed would make new hidden suites, not comparable with the results so far)") from None
    existing = sorted(p.name for p in directory.glob("*-hidden.json"))
    if existing:
        raise SuiteError(f"{path} is missing but hidden suites exist ({', '.join(existing)}): restore the seed file "
                         f"from a backup, or remove the hidden suites to start new ones from a new seed")
    seed = secrets.randbits(128)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(json.dumps({"seed": f"{seed:032x}"}) + "\n")
        f.flush()
        os.fsync(f.fileno())
    return seed


def _cached(path: Path, name: str, private_seed: int) -> bool:
    """True if `path` holds hidden suite `name` of this private seed, intact; False if it must be (re)generated."""
    if not path.exists():
        return False
    try:
        suite = load_suite(path)
    except SuiteError:
        return False  # damaged: generated again (the same bytes)
    if suite.name != name or suite.content["generator"].get("seed") != suite_seed(private_seed, name):
        raise SuiteError(f"{path}: not hidden suite {name} of this data dir's private seed ({path.parent / SEED_FILE}); "
                         f"was the seed file replaced?")
    return True


@contextmanager
def _locked(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on `path` (created if missing) while the block runs."""
    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
