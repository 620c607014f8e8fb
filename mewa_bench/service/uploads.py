"""Uploads: schema checks of results files and agent files, and how they are kept in the data dir.

Everything that needs no scoring is checked here, before anything is stored, and answered with a
4xx naming what was wrong: not JSON, the results schema (`protocol.results.validate_structure`), the
leaderboard's run checks (`leaderboard.validate.check_run`: complete, a public suite with its exact
hash, this protocol, the board's seeds, every unit once), an agent file that is not Python or has
no agent, an unsafe or oversized checkpoint archive. Re-scoring (`scoring`) is the workers' job.

Files are written under a fresh name, fsynced and renamed into place before the database row that
points at them is committed; `sweep_orphans` removes the files of uploads whose row never came
(a server killed in between). It runs when an API process starts (`server.prepare`), and the rule
for what is certainly orphaned is the data dir's API lock (`hold_api_lock`): every running API
process holds `<data dir>/api.lock` shared. One that starts and gets it exclusively is the only API
process on the data dir, and one that has just started has no upload in flight, so every file
without a row is an orphan, whatever its age. One that starts beside others (the lock is held
shared) removes only files older than ORPHAN_AGE: a younger one may be another process's upload
between its file and its commit. Only API processes write uploads (workers never do). The lock is
flock(2), seen by every process of one machine; API processes on several machines sharing the data
dir over storage without shared locks must keep to one API process per data dir (see the README).
"""

from __future__ import annotations

import ast
import errno
import fcntl
import hashlib
import json
import os
import re
import shutil
import tarfile
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Iterable

from mewa_bench.design.suites import ALL_SUITES, canonical_json
from mewa_bench.service.errors import ApiError, bad_request, unprocessable
from mewa_bench.service.settings import Settings

CHUNK = 1 << 20
AGENT_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
AGENT_ARG_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")
MAX_AGENT_ARGS = 32
MAX_ARCHIVE_MEMBERS = 10_000
ORPHAN_AGE = 60.0  # seconds: younger files may belong to an upload still being committed
API_LOCK = "api.lock"  # in the data dir: held shared by every running API process


@dataclass(frozen=True)
class CheckedResults:
    """A results upload that passed the checks: what its row and job need."""

    results: dict[str, Any]
    suite: str
    seeds: tuple[int, ...]
    agent_name: str
    agent_sha256: str
    digest: str


@dataclass(frozen=True)
class CheckedAgent:
    """An agent upload that passed the checks."""

    source: bytes
    name: str
    suite: str
    agent_args: dict[str, str]
    agent_sha256: str
    checkpoint_sha256: str | None
    digest: str


def _no_constants(name: str) -> float:
    """Refuse NaN and Infinity, which JSON does not have."""
    raise ValueError(f"{name} is not a JSON number (non-finite values are not allowed)")


MAX_DEPTH = 32  # nesting of arrays and objects (a results file needs 6)
MAX_INTEGER = 2**63 - 1  # integers beyond a database's and numpy's range are refused before they are used
_BRACKETS = re.compile(rb'[\[\]{}"\\]')


def nesting_depth(data: bytes, stop_above: int = MAX_DEPTH) -> int:
    """How deeply arrays and objects nest in JSON text (outside strings); counting stops past `stop_above`."""
    depth = deepest = 0
    in_string = False
    escaped_at = -1  # the position a backslash escapes
    for match in _BRACKETS.finditer(data):
        char, at = match.group(), match.start()
        if in_string:
            if at == escaped_at:
                continue
            if char == b"\\":
                escaped_at = at + 1
            elif char == b'"':
                in_string = False
            continue
        if char == b'"':
            in_string = True
        elif char in (b"[", b"{"):
            depth += 1
            deepest = max(deepest, depth)
            if deepest > stop_above:
                return deepest
        elif char in (b"]", b"}"):
            depth -= 1
    return deepest


def _bounded_int(text: str) -> int:
    """An integer literal within MAX_INTEGER, else a ValueError naming it."""
    if len(text.lstrip("-")) > 19 or abs(value := int(text)) > MAX_INTEGER:
        raise ValueError(f"the integer {text[:30]}{'...' if len(text) > 30 else ''} is out of range "
                         f"(at most {MAX_INTEGER} in magnitude)")
    return value


def parse_results(data: bytes) -> Any:
    """The uploaded bytes as JSON, or a 400 saying where the syntax breaks (nesting and integers are bounded)."""
    if (depth := nesting_depth(data)) > MAX_DEPTH:
        raise bad_request("invalid_json", f"the results file nests arrays and objects more than {MAX_DEPTH} deep "
                                          f"(at least {depth})")
    try:
        return json.loads(data.decode("utf-8"), parse_constant=_no_constants, parse_int=_bounded_int)
    except UnicodeDecodeError as e:
        raise bad_request("invalid_json", f"the results file is not UTF-8 text (byte {e.start})") from None
    except json.JSONDecodeError as e:
        raise bad_request("invalid_json", f"the results file is not valid JSON: {e}") from None
    except ValueError as e:
        raise bad_request("invalid_json", f"the results file is not valid JSON: {e}") from None


# What a run is: the suite, seeds and env it was played on and the episodes it played (their env
# seeds, which `check_run` holds to the protocol's, and returns, to which the normalised returns and
# scores must agree). Who claims it, how it was isolated, the episode lengths (not scored) and the
# aggregates derived from the episodes are not part of it, so the same episodes under a new agent
# name, with other lengths or with retouched aggregates are a replay (one run cannot fill a board).
# Returns that differ make another run: a results upload cannot prove it was played (the server's
# own evaluation of agent files can). A rejected or failed submission gives its digest up
# (`jobs.free_digest`).
RUN_FIELDS = ("suite", "seeds", "episodes_per_pair", "env", "protocol_version")
UNIT_FIELDS = ("pair", "seed", "task", "env_seeds", "returns")


def results_digest(results: dict[str, Any], units: list[dict[str, Any]] | None = None) -> str:
    """What makes two results uploads the same run: where it was played and its episodes (`units`: its units as
    dicts, default `results["units"]`), whoever claims it."""
    run = {field: results[field] for field in RUN_FIELDS}
    run["units"] = sorted(({field: u[field] for field in UNIT_FIELDS} for u in (results["units"] if units is None
                                                                                else units)),
                          key=lambda u: (u["pair"], u["seed"]))
    return hashlib.sha256(b"results\0" + canonical_json(run).encode()).hexdigest()


def check_results(data: bytes, settings: Settings, suites: Any,
                  privileged_agents: set[str] | frozenset[str] = frozenset()) -> CheckedResults:
    """Every check of a results upload that needs no scoring; 4xx ApiErrors say what failed. A file that says a
    run of one of `privileged_agents` (sha256s) was not privileged is refused first."""
    from mewa_bench.leaderboard.validate import InvalidResults, check_run
    from mewa_bench.protocol.results import ResultsError, validate_structure
    from mewa_bench.service.privileged import refuse_unprivileged_claim

    results = parse_results(data)
    agent = results.get("agent") if isinstance(results, dict) else None
    if isinstance(agent, dict):
        refuse_unprivileged_claim(privileged_agents, agent.get("sha256"), agent.get("privileged") is True)
    try:
        results = validate_structure(results, "results file")  # schema 3: its unit columns decoded
        name = results["suite"]["name"]
        if name not in ALL_SUITES:
            raise unprocessable("unknown_suite", f"results file: suite {name!r} is not a public suite of this server "
                                                 f"({', '.join(ALL_SUITES)})")
        suite, seeds, _ = check_run(results, suites, settings.seeds_for(name))
        _check_stored_scores(results["scores"])
        agent = results["agent"]
        agent_name, agent_sha256 = agent.get("name"), agent.get("sha256")
    except ResultsError as e:
        raise unprocessable("invalid_results", str(e)) from None
    except InvalidResults as e:
        raise unprocessable("invalid_results", f"results file: {e}") from None
    except (AttributeError, KeyError, IndexError, TypeError, ValueError) as e:
        raise unprocessable("invalid_results", f"results file: malformed results ({type(e).__name__}: {e})") from None
    if not isinstance(agent_name, str) or not 0 < len(agent_name) <= 100:
        raise unprocessable("invalid_results", f"results file: agent.name must be a string of 1-100 characters, got {agent_name!r}")
    if not isinstance(agent_sha256, str) or not re.fullmatch(r"[0-9a-f]{64}", agent_sha256):
        raise unprocessable("invalid_results", f"results file: agent.sha256 must be 64 hex digits, got {agent_sha256!r}")
    return CheckedResults(results, suite.name, seeds, agent_name, agent_sha256, results_digest(results))


def _check_stored_scores(scores: Any) -> None:
    """The aggregates the workers compare with their recomputation are present and numbers."""
    where = [("raw", "mean", "mean"), ("mean", "mean"), ("adaptability", "mean")]
    for path in where:
        value: Any = scores
        for key in path:
            if not isinstance(value, dict) or key not in value:
                raise unprocessable("invalid_results", f"results file: scores.{'.'.join(path)} is missing")
            value = value[key]
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise unprocessable("invalid_results", f"results file: scores.{'.'.join(path)} must be a number, got {value!r}")
    curve = scores.get("curve")
    if not isinstance(curve, list) or not all(isinstance(p, dict) and isinstance(p.get("mean"), (int, float))
                                              for p in curve):
        raise unprocessable("invalid_results", "results file: scores.curve must be a list of {\"mean\": number, ...}")


def check_agent(source: bytes, filename: str, name: str | None, suite: str, agent_args: Iterable[str],
                checkpoint_sha256: str | None) -> CheckedAgent:
    """An agent file must be UTF-8 Python defining make_agent or class Agent; the suite public; args key=value."""
    if suite not in ALL_SUITES:
        raise unprocessable("unknown_suite", f"suite {suite!r} is not a public suite of this server ({', '.join(ALL_SUITES)})")
    try:
        text = source.decode("utf-8")
    except UnicodeDecodeError as e:
        raise unprocessable("invalid_agent", f"agent file {filename}: not UTF-8 text (byte {e.start})") from None
    try:
        tree = ast.parse(text, filename=filename)
    except SyntaxError as e:
        raise unprocessable("invalid_agent", f"agent file {filename}, line {e.lineno}: {e.msg}") from None
    defined = {node.name for node in tree.body if isinstance(node, (ast.FunctionDef, ast.ClassDef))}
    if not defined & {"make_agent", "Agent"}:
        raise unprocessable("invalid_agent", f"agent file {filename}: defines neither make_agent(observation_space, "
                                             f"action_space) nor class Agent at its top level")
    stem = Path(filename).stem
    name = name or (stem if stem != "agent" else None)
    if name is None or not AGENT_NAME_RE.match(name):
        raise unprocessable("invalid_agent", f"agent name {name!r}: give a name of 1-64 letters, digits, '.', '_' or "
                                             f"'-' (form field name; a file called agent.py has no name of its own)")
    args = parse_agent_args(agent_args)
    agent_sha256 = hashlib.sha256(source).hexdigest()
    basis = json.dumps({"agent": agent_sha256, "checkpoint": checkpoint_sha256, "suite": suite, "args": args},
                       sort_keys=True)
    digest = hashlib.sha256(b"agent\0" + basis.encode()).hexdigest()
    return CheckedAgent(source, name, suite, args, agent_sha256, checkpoint_sha256, digest)


def check_algorithm(name: str | None) -> str | None:
    """A submission's algorithm name (agent-name rules), None when not given, or a 422."""
    if name is None or name == "":
        return None
    if not AGENT_NAME_RE.match(name):
        raise unprocessable("invalid_algorithm", f"algorithm name {name!r}: give a name of 1-64 letters, digits, "
                                                 f"'.', '_' or '-', starting with a letter or digit")
    return name


def parse_agent_args(items: Iterable[str]) -> dict[str, str]:
    """`key=value` strings as a dict; a 422 for anything else."""
    args: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not AGENT_ARG_RE.match(key):
            raise unprocessable("invalid_agent_args", f"agent arg {item!r}: expected key=value with a Python identifier as key")
        if key in args:
            raise unprocessable("invalid_agent_args", f"agent arg {key!r} is given twice")
        if len(value) > 1000:
            raise unprocessable("invalid_agent_args", f"agent arg {key!r}: values are limited to 1000 characters")
        args[key] = value
    if len(args) > MAX_AGENT_ARGS:
        raise unprocessable("invalid_agent_args", f"{len(args)} agent args; at most {MAX_AGENT_ARGS}")
    return args


# -- storage ---------------------------------------------------------------------------------------
def write_bytes_atomic(path: Path, data: bytes, mode: int = 0o644) -> None:
    """Write via a temporary sibling, fsync and rename: the file is whole or absent."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def store_results(settings: Settings, data: bytes) -> Path:
    """Keep an uploaded results file as it was sent; returns its path relative to the data dir."""
    relative = Path("uploads") / "results" / f"{uuid.uuid4().hex}.json"
    write_bytes_atomic(settings.data_dir / relative, data)
    return relative


def copy_limited(source: IO[bytes], out: Path, limit: int, what: str) -> str:
    """Copy a spooled upload to `out` (at most `limit` bytes, else 413); returns its sha256."""
    h, size = hashlib.sha256(), 0
    with open(out, "wb") as f:
        while chunk := source.read(CHUNK):
            size += len(chunk)
            if size > limit:
                raise ApiError(413, "too_large", f"{what} is larger than the limit of {limit:,} bytes")
            h.update(chunk)
            f.write(chunk)
        f.flush()
        os.fsync(f.fileno())
    return h.hexdigest()


def staging_path(settings: Settings, suffix: str) -> Path:
    """A fresh file name in the data dir's staging area (swept if it outlives its request)."""
    staging = settings.uploads_dir / "staging"
    staging.mkdir(parents=True, exist_ok=True)
    return staging / f"{uuid.uuid4().hex}{suffix}"


def check_archive(archive: Path, unpacked_limit: int) -> int:
    """A checkpoint archive: a readable tar(.gz) within the member and unpacked-size limits, without an agent.py
    (member safety, no links or paths out of it, is checked as it is unpacked: `store_agent`); returns its unpacked
    size."""
    try:
        with tarfile.open(archive, "r:*") as tar:
            members = tar.getmembers()
    except (tarfile.TarError, EOFError, OSError) as e:
        raise unprocessable("invalid_checkpoint", f"checkpoint archive: not a readable .tar or .tar.gz ({e})") from None
    if len(members) > MAX_ARCHIVE_MEMBERS:
        raise unprocessable("invalid_checkpoint", f"checkpoint archive: {len(members)} members; at most {MAX_ARCHIVE_MEMBERS}")
    total = 0
    for m in members:
        if Path(m.name).parts[:1] == ("agent.py",):
            raise unprocessable("invalid_checkpoint", "checkpoint archive: a member named agent.py would replace the agent file")
        total += m.size
    if total > unpacked_limit:
        raise ApiError(413, "too_large", f"checkpoint archive: unpacks to {total:,} bytes; the limit is {unpacked_limit:,}")
    return total


def store_agent(settings: Settings, agent: CheckedAgent, archive: Path | None) -> Path:
    """Lay out `uploads/agents/<uuid>/<name>/agent.py`, the checkpoint unpacked beside it (where agents find
    their files); everything world-readable for the sandbox user. Returns agent.py relative to the data dir."""
    from mewa_bench.datasets.catalog import DatasetError
    from mewa_bench.datasets.downloader import extract_archive
    from mewa_bench.service.storage import is_disk_full

    base = Path("uploads") / "agents" / uuid.uuid4().hex
    staging = staging_path(settings, ".agent")
    folder = staging / agent.name
    staging.mkdir()
    try:
        if archive is not None:
            try:
                extract_archive(archive, folder, "checkpoint archive")
            except DatasetError as e:  # an unsafe member (absolute path, '..', a link) or a broken stream
                if is_disk_full(e):  # the server's fault, not the archive's: a 507
                    raise OSError(errno.ENOSPC, "no space left unpacking the checkpoint archive") from e
                raise unprocessable("invalid_checkpoint", str(e)) from None
        folder.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(folder / "agent.py", agent.source)
        for path in [staging, *staging.rglob("*")]:
            os.chmod(path, 0o755 if path.is_dir() else 0o644)
        target = settings.data_dir / base
        target.parent.mkdir(parents=True, exist_ok=True)
        os.chmod(target.parent, 0o755)
        os.rename(staging, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return base / agent.name / "agent.py"


def remove_upload(settings: Settings, relative: Path) -> None:
    """Remove the files of an upload whose row was not committed."""
    path = settings.data_dir / relative
    if path.parent.parent.parent.name == "agents":  # uploads/agents/<uuid>/<name>/agent.py
        shutil.rmtree(path.parent.parent, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def hold_api_lock(settings: Settings) -> tuple[IO[str], bool]:
    """Take the data dir's API lock exclusively if no other API process holds it (True: alone), else shared; the
    caller sweeps, then `share_api_lock`, and keeps the file open while it serves."""
    lock = open(settings.data_dir / API_LOCK, "a")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return lock, True
    except BlockingIOError:
        fcntl.flock(lock, fcntl.LOCK_SH)  # waits only while another process starting alone sweeps
        return lock, False


def share_api_lock(lock: IO[str]) -> None:
    """Turn an exclusive API lock into the shared one every running API process holds."""
    fcntl.flock(lock, fcntl.LOCK_SH)


def sweep_orphans(settings: Settings, referenced: set[str], now: float | None = None,
                  min_age: float = ORPHAN_AGE) -> list[Path]:
    """Remove upload files no submission row points at, if at least `min_age` seconds old (0: any age, only when no
    upload can be in flight); returns what was removed."""
    now = time.time() if now is None else now
    removed: list[Path] = []
    uploads = settings.uploads_dir
    candidates = [*(uploads / "results").glob("*.json"), *(uploads / "agents").glob("*"), *(uploads / "staging").glob("*")]
    candidates += [p for p in (uploads / "results").glob(".*.tmp")]
    for path in candidates:
        try:
            age = now - path.lstat().st_mtime
        except FileNotFoundError:
            continue
        if age < min_age:
            continue
        relative = path.relative_to(settings.data_dir)
        if path.parent.name == "agents":
            if any(r.startswith(f"{relative.as_posix()}/") for r in referenced):
                continue
        elif relative.as_posix() in referenced:
            continue
        shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)
        removed.append(relative)
    return removed
