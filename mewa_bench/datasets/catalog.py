"""The dataset catalog (SPEC section 8): a JSON file listing published datasets with URL, size and sha256.

Format: `{"format_version": 1, "datasets": [entry, ...], "evaluation_recordings": [entry, ...],
"builds": [build, ...]}`. `datasets` lists training data only (`kind` "training": meta-train workers,
never a test pair); `evaluation_recordings` lists recordings of the curated test pairs, for viewing
only (training on them is training on the test set); `builds` records the sha256 of training
datasets built locally with `mewa-bench datasets build` (too large to ship). An entry has `name`, `version`, `suite`,
`policy`, `episodes`, `frames`, `size` (bytes of the archive), `sha256` (of the archive) and either
`url` (http(s) or file URL of a .tar.gz) or `hf_repo_id` (a Hugging Face Hub dataset repo, optionally
pinned by `hf_revision`; `size` and `sha256` are then optional, the Hub checks its own files). Other
fields (`format`, `suite_sha256`, `policy_sha256`, `mewa_bench_version`, ...) are kept as they are.
"""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path
from typing import Any

from mewa_bench.files import write_json_atomic

CATALOG_FORMAT_VERSION = 1
CATALOG_ENV = "MEWA_DATASETS_CATALOG"
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")  # a dataset name becomes a directory name
SHA256_RE = re.compile(r"^[0-9a-f]{64}$")
URL_SCHEMES = ("http://", "https://", "file://")
REQUIRED = {"name": str, "version": str, "suite": str, "policy": str, "episodes": int, "frames": int}
TRAINING, EVALUATION_RECORDING = "training", "evaluation-recording"
SECTIONS = {TRAINING: "datasets", EVALUATION_RECORDING: "evaluation_recordings"}  # kind -> catalog section
EVALUATION_WARNING = ("an evaluation recording of the curated TEST pairs with the ranked protocol's seeds: for "
                      "viewing only. Training on it is training on the test set; train on `kind: training` data "
                      "(meta-train workers only), e.g. `mewa-bench datasets build narrow-v2-train-expert`.")


class DatasetError(RuntimeError):
    """A catalog, download or archive problem, with a message saying what and where."""


INSTALLED_DATASETS = Path("share") / "mewa-bench" / "datasets"  # where a wheel puts the shipped catalog (pyproject)


CHECKOUT_CATALOG = Path(__file__).resolve().parents[2] / "datasets" / "index.json"


def default_catalog_path(checkout: Path = CHECKOUT_CATALOG, prefix: Path | None = None) -> Path:
    """`$MEWA_DATASETS_CATALOG`; else `datasets/index.json` of the checkout; else the copy a wheel installs
    under `<prefix>/share/mewa-bench/datasets/` (with its archives, so relative URLs still resolve)."""
    env = os.environ.get(CATALOG_ENV)
    if env:
        return Path(env)
    installed = Path(sys.prefix if prefix is None else prefix) / INSTALLED_DATASETS / "index.json"
    return installed if not checkout.exists() and installed.exists() else checkout


def empty_catalog() -> dict[str, Any]:
    """A catalog without datasets."""
    return {"format_version": CATALOG_FORMAT_VERSION, "datasets": [], "evaluation_recordings": []}


def entry_kind(entry: dict[str, Any]) -> str:
    """"training" only for an entry that says so; anything else is treated as an evaluation recording."""
    return TRAINING if entry.get("kind") == TRAINING else EVALUATION_RECORDING


def catalog_entries(content: dict[str, Any]) -> list[dict[str, Any]]:
    """Every downloadable entry: training data, then evaluation recordings."""
    return list(content.get("datasets", [])) + list(content.get("evaluation_recordings", []))


def _check_type(where: str, key: str, value: Any, kind: type) -> None:
    # bool is an int subclass; a count of True episodes is a typo, not a number
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise DatasetError(f"{where}: field {key!r} must be {kind.__name__}, got {value!r}")


def is_relative_path(url: str) -> bool:
    """A catalog-relative archive path such as `narrow-v1-rts-1.0.0.tar.gz` (no scheme, not absolute)."""
    return "://" not in url and not url.startswith("/") and bool(url)


def resolve_relative_urls(content: dict[str, Any], base: Path) -> dict[str, Any]:
    """Entries whose url is relative to the catalog file get an absolute file:// URL."""
    for entry in catalog_entries(content):
        if "url" in entry and is_relative_path(entry["url"]):
            entry["url"] = (base / entry["url"]).resolve().as_uri()
    return content


def validate_entry(entry: Any, where: str = "catalog entry") -> dict[str, Any]:
    """Check one entry's fields; returns it unchanged."""
    if not isinstance(entry, dict):
        raise DatasetError(f"{where}: an entry must be a JSON object, got {entry!r}")
    where = f"{where} {entry.get('name', '?')!r}"
    for key, kind in REQUIRED.items():
        if key not in entry:
            raise DatasetError(f"{where}: missing field {key!r}")
        _check_type(where, key, entry[key], kind)
    if not NAME_RE.match(entry["name"]):
        raise DatasetError(f"{where}: name must be letters, digits, '.', '_' or '-' (it becomes a directory name)")
    if ("url" in entry) == ("hf_repo_id" in entry):
        raise DatasetError(f"{where}: needs exactly one of 'url' or 'hf_repo_id'")
    if "url" in entry:
        _check_type(where, "url", entry["url"], str)
        if not (entry["url"].startswith(URL_SCHEMES) or is_relative_path(entry["url"])):
            raise DatasetError(f"{where}: url must start with one of {', '.join(URL_SCHEMES)} or be a path "
                               f"relative to the catalog, got {entry['url']!r}")
        for key in ("size", "sha256"):
            if key not in entry:
                raise DatasetError(f"{where}: an archive URL needs field {key!r} to verify the download")
    else:
        _check_type(where, "hf_repo_id", entry["hf_repo_id"], str)
    if "size" in entry:
        _check_type(where, "size", entry["size"], int)
    if "sha256" in entry and not (isinstance(entry["sha256"], str) and SHA256_RE.match(entry["sha256"])):
        raise DatasetError(f"{where}: sha256 must be 64 lowercase hex digits, got {entry['sha256']!r}")
    return entry


def validate_catalog(content: Any, where: str) -> dict[str, Any]:
    """Check a catalog's structure and every entry; names+versions must be unique."""
    if not isinstance(content, dict) or not isinstance(content.get("datasets"), list):
        raise DatasetError(f"{where}: a catalog is a JSON object with a 'datasets' list")
    for section in ("evaluation_recordings", "builds"):
        if not isinstance(content.get(section, []), list):
            raise DatasetError(f"{where}: {section!r} must be a list")
    if content.get("format_version") != CATALOG_FORMAT_VERSION:
        raise DatasetError(f"{where}: unsupported catalog format_version {content.get('format_version')!r} "
                           f"(this mewa-bench reads {CATALOG_FORMAT_VERSION})")
    seen: set[tuple[str, str]] = set()
    for section in ("datasets", "evaluation_recordings"):
        for i, entry in enumerate(content.get(section, [])):
            validate_entry(entry, f"{where}: {section} #{i}")
            wrong = EVALUATION_RECORDING if section == "datasets" else TRAINING
            if entry.get("kind") == wrong:  # an entry without a kind (an older catalog) counts as not training
                raise DatasetError(f"{where}: {section} #{i} {entry['name']!r} has kind {wrong!r}; 'datasets' holds "
                                   "training data, 'evaluation_recordings' the recordings of test pairs")
    for entry in catalog_entries(content):
        key = (entry["name"], entry["version"])
        if key in seen:
            raise DatasetError(f"{where}: {entry['name']} version {entry['version']} is listed twice")
        seen.add(key)
    return content


def load_catalog(path: Path | str | None = None, resolve: bool = True) -> dict[str, Any]:
    """Read and validate a catalog file (default: `default_catalog_path()`).

    With `resolve`, archive paths relative to the catalog become absolute file:// URLs (for
    downloading); without, entries are as written (for editing the catalog).
    """
    path = Path(path) if path is not None else default_catalog_path()
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DatasetError(f"dataset catalog {path} does not exist") from None
    except OSError as e:
        raise DatasetError(f"cannot read dataset catalog {path}: {e.strerror}") from None
    try:
        content = json.loads(text)
    except json.JSONDecodeError as e:
        raise DatasetError(f"dataset catalog {path} is not valid JSON: {e}") from None
    content = validate_catalog(content, str(path))
    return resolve_relative_urls(content, path.parent) if resolve else content


def version_key(version: str) -> tuple:
    """Sort key for versions: numeric parts compare as numbers ("1.10" > "1.9")."""
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in re.split(r"[.\-+]", version))


def dataset_info(catalog: dict[str, Any], name: str) -> dict[str, Any]:
    """The entry named `name` (its newest version), or `name@version`."""
    base, _, version = name.partition("@")
    entries = catalog_entries(catalog)
    matches = [e for e in entries if e["name"] == base and (not version or e["version"] == version)]
    if not matches:
        known = sorted({f"{e['name']}@{e['version']}" for e in entries})
        raise DatasetError(f"dataset {name!r} is not in the catalog; known: {', '.join(known) or 'none'}")
    return max(matches, key=lambda e: version_key(e["version"]))


def add_to_catalog(catalog_path: Path | str, entry: dict[str, Any]) -> dict[str, Any]:
    """Add `entry` to its section of a catalog file (created if missing), replacing the same name+version; atomic."""
    catalog_path = Path(catalog_path)
    validate_entry(entry)
    catalog = load_catalog(catalog_path, resolve=False) if catalog_path.exists() else empty_catalog()
    same = lambda e: (e["name"], e["version"]) == (entry["name"], entry["version"])  # noqa: E731
    for section in SECTIONS.values():  # an entry may change kind: drop it from the other section
        keep = section == SECTIONS[entry_kind(entry)]
        catalog[section] = [e for e in catalog.get(section, []) if keep or not same(e)]
    datasets = catalog[SECTIONS[entry_kind(entry)]]
    index = next((i for i, e in enumerate(datasets) if same(e)), None)
    if index is None:
        datasets.append(dict(entry))
    else:
        datasets[index] = dict(entry)
    write_json_atomic(catalog_path, catalog)
    return catalog


def recorded_build(catalog: dict[str, Any], name: str, version: str) -> dict[str, Any] | None:
    """The catalog's record of a local training build (name, version, sha256, ...), if it has one."""
    return next((b for b in catalog.get("builds", []) if (b.get("name"), b.get("version")) == (name, version)), None)
