"""Fetch, verify and unpack datasets (SPEC section 8); a bad download never replaces a good copy.

A source is a catalog name (`name` or `name@version`), an archive URL (http(s) or file, .tar.gz) or a
Hugging Face Hub dataset repo id (`user/repo`). Archives are streamed to a temp file beside the
destination, checked against the expected size and sha256, unpacked into a temp directory (members
with absolute paths, `..` or links are refused), checked to be a LeRobot dataset and only then
renamed to `dest_dir/<name>`.

An archive with a known sha256 served over http(s) by a server that accepts byte ranges (a
mewa-bench server does) resumes where it stopped: after a dropped connection in the same call, and
in a later call, from the partial file kept in the download cache (`partial_path`).
"""

from __future__ import annotations

import hashlib
import http.client
import json
import os
import shutil
import tarfile
import tempfile
import urllib.error
import urllib.parse
import urllib.request
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any, Callable, Iterator

from mewa_bench.datasets.catalog import NAME_RE, SHA256_RE, URL_SCHEMES, DatasetError, dataset_info
from mewa_bench.extras import MissingExtra, require

Progress = Callable[[int, int | None], None]  # (bytes done, total bytes or None when unknown)
CHUNK = 1 << 20
TIMEOUT = 60.0
RESUMES = 3  # Range requests after a dropped connection, in one call
CACHE_ENV = "MEWA_CACHE_DIR"
INFO_FILE = Path("meta") / "info.json"


@dataclass(frozen=True)
class Downloaded:
    """Where a dataset landed and how it was checked."""

    name: str
    path: Path
    source: str
    size: int | None
    sha256: str | None
    verified: bool  # size and sha256 matched known values (False: nothing to compare against)


@dataclass(frozen=True)
class Source:
    """What to fetch: an archive URL or a Hub repo, with the values to verify it against."""

    name: str
    url: str | None = None
    hf_repo_id: str | None = None
    revision: str | None = None
    size: int | None = None
    sha256: str | None = None
    episodes: int | None = None
    frames: int | None = None
    kind: str | None = None  # the catalog's kind ("training" or "evaluation-recording")


def is_url(text: str) -> bool:
    """An http(s) or file URL."""
    return text.startswith(URL_SCHEMES)


def is_repo_id(text: str) -> bool:
    """Looks like a Hugging Face Hub repo id (`owner/name`)."""
    parts = text.split("/")
    return len(parts) == 2 and all(NAME_RE.match(p) for p in parts)


def name_from_url(url: str) -> str:
    """`https://host/path/mewa-narrow-1.tar.gz` -> `mewa-narrow-1`."""
    base = PurePosixPath(urllib.parse.urlparse(url).path).name
    for suffix in (".tar.gz", ".tgz", ".tar"):
        if base.endswith(suffix):
            return base[: -len(suffix)]
    return base


def resolve_source(source: str, catalog: dict[str, Any] | None, sha256: str | None = None,
                   name: str | None = None) -> Source:
    """Turn a catalog name, URL or Hub repo id into a `Source`."""
    if sha256 is not None and not SHA256_RE.match(sha256.lower()):
        raise DatasetError(f"--sha256 must be 64 hex digits, got {sha256!r}")
    if is_url(source):
        src = Source(name or name_from_url(source), url=source, sha256=sha256.lower() if sha256 else None)
    elif catalog is not None and "/" not in source:
        e = dataset_info(catalog, source)
        src = Source(name or e["name"], url=e.get("url"), hf_repo_id=e.get("hf_repo_id"),
                     revision=e.get("hf_revision"), size=e.get("size"), sha256=e.get("sha256"),
                     episodes=e.get("episodes"), frames=e.get("frames"), kind=e.get("kind"))
    elif is_repo_id(source):
        src = Source(name or source.split("/")[1], hf_repo_id=source)
    else:
        hint = "" if catalog is not None else " (no catalog given)"
        raise DatasetError(f"{source!r} is not a catalog dataset{hint}, an http(s)/file URL or a Hub repo id")
    if not NAME_RE.match(src.name):
        raise DatasetError(f"dataset name {src.name!r} is not a valid directory name; pass name=...")
    return src


def download(source: str, catalog: dict[str, Any] | None, dest_dir: Path | str, progress: Progress | None = None,
             sha256: str | None = None, name: str | None = None) -> Downloaded:
    """Fetch a dataset into `dest_dir/<name>`, replacing an existing copy only once the new one is verified."""
    src = resolve_source(source, catalog, sha256, name)
    dest_dir = Path(dest_dir)
    dest_dir.mkdir(parents=True, exist_ok=True)
    if src.url is not None:
        return _download_archive(src, dest_dir, progress)
    return _download_hub(src, dest_dir)


@contextmanager
def _temp_dir(dest_dir: Path, name: str, kind: str) -> Iterator[Path]:
    """A hidden temp directory beside the destination, removed on exit whatever happens."""
    path = Path(tempfile.mkdtemp(dir=dest_dir, prefix=f".{name}.", suffix=f".{kind}"))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


def _download_archive(src: Source, dest_dir: Path, progress: Progress | None) -> Downloaded:
    """Archive URL: stream, verify, unpack, check, install."""
    assert src.url is not None
    resumable = src.sha256 is not None and src.url.startswith(("http://", "https://"))
    with _temp_dir(dest_dir, src.name, "download") as work:
        archive = partial_path(src.sha256) if resumable else work / "archive.tar.gz"
        size, digest = fetch(src.url, archive, progress, resume=resumable)  # a resumable partial stays on failure
        try:
            if src.size is not None and size != src.size:
                raise DatasetError(f"{src.url}: downloaded {size} bytes, the catalog says {src.size} "
                                   "(truncated or changed archive)")
            if src.sha256 is not None and digest != src.sha256:
                raise DatasetError(f"{src.url}: sha256 mismatch: got {digest}, expected {src.sha256} "
                                   "(corrupted or changed archive)")
        except DatasetError:
            archive.unlink()  # complete but wrong: the next call starts again
            raise
        unpacked = work / "unpacked"
        try:
            extract_archive(archive, unpacked, src.url)
        finally:
            archive.unlink()
        root = dataset_root(unpacked, src.url)
        check_dataset(root, src, src.url)
        check_training_content(root, src, src.url)
        path = install(root, dest_dir / src.name)
    return Downloaded(src.name, path, src.url, size, digest, verified=src.sha256 is not None)


def partial_path(sha256: str) -> Path:
    """Where a resumable download of the archive with this sha256 is kept while it is incomplete."""
    cache = os.environ.get(CACHE_ENV) or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "mewa-bench"
    folder = Path(cache) / "downloads"
    folder.mkdir(parents=True, exist_ok=True)
    return folder / f"{sha256}.part"


class _Interrupted(Exception):
    """A transfer that stopped part-way; `ranges`: the server accepts Range requests, so it can resume."""

    def __init__(self, message: str, ranges: bool) -> None:
        super().__init__(message)
        self.ranges = ranges


def fetch(url: str, out: Path, progress: Progress | None = None, resume: bool = False) -> tuple[int, str]:
    """Stream `url` to `out`; returns (bytes, sha256). A short or failed transfer raises `DatasetError`.

    With `resume`, bytes already in `out` are kept and the rest is asked for with an HTTP Range
    request, also after a dropped connection (RESUMES times); a partial `out` is left for a later
    call only if the server accepts ranges.
    """
    out = Path(out)
    for attempt in range(RESUMES + 1):
        try:
            return _fetch_once(url, out, progress, resume and out.exists())
        except _Interrupted as e:
            if not (resume and e.ranges) or attempt == RESUMES:
                if resume and not e.ranges:
                    out.unlink(missing_ok=True)
                raise DatasetError(str(e)) from None
    raise AssertionError("unreachable")


def _fetch_once(url: str, out: Path, progress: Progress | None, continued: bool) -> tuple[int, str]:
    """One HTTP(S) or file request: all of `url`, or with `continued` the bytes after those in `out`."""
    h, start = hashlib.sha256(), out.stat().st_size if continued else 0
    if start:
        with open(out, "rb") as f:
            while chunk := f.read(CHUNK):
                h.update(chunk)
    request = urllib.request.Request(url, headers={"Range": f"bytes={start}-"} if start else {})
    done, total, ranges = start, None, False
    try:
        with urllib.request.urlopen(request, timeout=TIMEOUT) as response:
            ranges = response.headers.get("Accept-Ranges", "").lower() == "bytes" or response.status == 206
            if start and not _continues_at(response, start):
                start = done = 0  # the server sent the whole file: start again
                h = hashlib.sha256()
            length = response.headers.get("Content-Length")
            total = start + int(length) if length is not None and length.isdigit() else None
            if progress:
                progress(done, total)
            with open(out, "ab" if start else "wb") as f:
                while chunk := response.read(CHUNK):
                    f.write(chunk)
                    h.update(chunk)
                    done += len(chunk)
                    if progress:
                        progress(done, total)
    except urllib.error.HTTPError as e:
        if e.code == 416 and start:  # nothing after the bytes we have: the size and sha256 checks judge them
            return start, h.hexdigest()
        raise DatasetError(f"{url}: server answered HTTP {e.code} {e.reason}") from None
    except urllib.error.URLError as e:
        raise DatasetError(f"{url}: cannot connect: {e.reason}") from None
    except (OSError, ValueError, http.client.HTTPException) as e:  # timeouts, resets, IncompleteRead
        raise _Interrupted(f"{url}: transfer failed after {done} bytes: {e!r}", ranges) from None
    # http.client returns a short body without error when the server closes early: check ourselves
    if total is not None and done != total:
        raise _Interrupted(f"{url}: transfer ended after {done} of {total} bytes (connection closed early)", ranges)
    return done, h.hexdigest()


def _continues_at(response: Any, start: int) -> bool:
    """A 206 whose Content-Range starts where our bytes end."""
    content_range = response.headers.get("Content-Range", "")
    return response.status == 206 and content_range.startswith(f"bytes {start}-")


def _member_problem(member: tarfile.TarInfo) -> str | None:
    """Why an archive member may not be extracted, or None."""
    path = PurePosixPath(member.name)
    if path.is_absolute() or member.name.startswith(("/", "\\")):
        return "has an absolute path"
    if ".." in path.parts:
        return "leaves the archive directory ('..')"
    if member.issym() or member.islnk():
        return "is a link"
    if not (member.isfile() or member.isdir()):
        return "is not a regular file or directory"
    return None


def extract_archive(archive: Path, out: Path, where: str) -> None:
    """Unpack a .tar(.gz) into `out`, refusing unsafe members (path traversal, links, devices)."""
    try:
        with tarfile.open(archive, "r:*") as tar:
            members = tar.getmembers()
            for m in members:
                problem = _member_problem(m)
                if problem:
                    raise DatasetError(f"{where}: unsafe archive member {m.name!r} {problem}; refusing to unpack")
            out.mkdir()
            tar.extractall(out, members=members, filter="data")  # the "data" filter is a second guard
    except (tarfile.TarError, EOFError, OSError) as e:
        raise DatasetError(f"{where}: cannot unpack archive: {e}") from None


def dataset_root(unpacked: Path, where: str) -> Path:
    """The dataset directory inside an unpacked archive: its top level or its single top-level folder."""
    if (unpacked / INFO_FILE).is_file():
        return unpacked
    entries = list(unpacked.iterdir())
    if len(entries) == 1 and entries[0].is_dir() and (entries[0] / INFO_FILE).is_file():
        return entries[0]
    raise DatasetError(f"{where}: the archive holds no LeRobot dataset ({INFO_FILE} not found)")


def check_dataset(root: Path, src: Source, where: str) -> None:
    """The unpacked dataset's episode and frame counts match the catalog's."""
    try:
        info = json.loads((root / INFO_FILE).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise DatasetError(f"{where}: unreadable {INFO_FILE}: {e}") from None
    for key, expected in (("total_episodes", src.episodes), ("total_frames", src.frames)):
        if expected is not None and info.get(key) != expected:
            raise DatasetError(f"{where}: {INFO_FILE} has {key} = {info.get(key)!r}, the catalog says {expected}")


def check_training_content(root: Path, src: Source, where: str) -> None:
    """A training dataset (by its metadata or its catalog entry) is re-checked frame by frame before it is
    installed: one curated worker or protocol luck key and it is refused (the previous copy stays)."""
    from mewa_bench.datasets.catalog import TRAINING
    from mewa_bench.datasets.training_data import MEWA_META_FILE, check_training_dataset
    from mewa_bench.datasets.training_keys import TrainingDataError

    try:
        says_training = json.loads((root / MEWA_META_FILE).read_text()).get("kind") == TRAINING
    except (OSError, json.JSONDecodeError):
        says_training = False
    if not (says_training or src.kind == TRAINING):
        return
    try:
        check_training_dataset(root)
    except TrainingDataError as e:
        raise DatasetError(f"{where}: refused: {e}") from None


def install(new: Path, target: Path) -> Path:
    """Move a verified dataset to `target`, replacing an existing copy; the old one is kept if the move fails."""
    old = None
    if target.exists() or target.is_symlink():
        old = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}.", suffix=".old"))
        old.rmdir()
        os.rename(target, old)
    try:
        os.rename(new, target)
    except BaseException:
        if old is not None:
            os.rename(old, target)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return target


def hub_snapshot(repo_id: str, local_dir: Path, revision: str | None = None) -> None:
    """Download a Hub dataset repo into `local_dir` (the only function that talks to the Hub)."""
    hub = require("huggingface_hub", "datasets",
                  "downloading from the Hugging Face Hub (`mewa-bench datasets download`)")
    hub.snapshot_download(repo_id, repo_type="dataset", local_dir=local_dir, revision=revision)


def _download_hub(src: Source, dest_dir: Path) -> Downloaded:
    """Hub repo: snapshot into a temp dir, check, install."""
    assert src.hf_repo_id is not None
    where = f"Hugging Face Hub dataset {src.hf_repo_id}"
    with _temp_dir(dest_dir, src.name, "hub") as work:
        local = work / src.name
        try:
            hub_snapshot(src.hf_repo_id, local, src.revision)
        except MissingExtra:
            raise  # not a download failure: the message says what to install
        except Exception as e:  # the hub raises many types (HTTP, offline mode, missing repo)
            raise DatasetError(f"{where}: download failed: {type(e).__name__}: {e}") from None
        shutil.rmtree(local / ".cache", ignore_errors=True)  # huggingface_hub's own bookkeeping
        if not (local / INFO_FILE).is_file():
            raise DatasetError(f"{where}: not a LeRobot dataset ({INFO_FILE} not found)")
        check_dataset(local, src, where)
        check_training_content(local, src, where)
        path = install(local, dest_dir / src.name)
    return Downloaded(src.name, path, src.hf_repo_id, None, None, verified=False)
