"""Pack a recorded dataset into a reproducible .tar.gz and describe it for the catalog.

The archive holds the dataset under one top-level folder `<name>/`, members sorted, with fixed
mtime/owner/permissions and a gzip header without name or time, so the same dataset always gives
the same bytes and sha256.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import os
import tarfile
from pathlib import Path
from typing import Any

from mewa_bench.datasets.catalog import NAME_RE, DatasetError, add_to_catalog, validate_entry
from mewa_bench.datasets.lerobot_recorder import MEWA_META_FILE

__all__ = ["add_to_catalog", "archive_name", "pack_dataset", "sha256_file", "write_archive"]

SKIP_DIRS = {".cache"}  # huggingface_hub bookkeeping in downloaded copies


def archive_name(name: str, version: str) -> str:
    """`mewa-narrow-rts` + `1.0` -> `mewa-narrow-rts-1.0.tar.gz`."""
    return f"{name}-{version}.tar.gz"


def sha256_file(path: Path) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def _tar_info(arcname: str, is_dir: bool, size: int = 0) -> tarfile.TarInfo:
    """A member header with nothing that depends on the machine or the time."""
    info = tarfile.TarInfo(arcname)
    info.type = tarfile.DIRTYPE if is_dir else tarfile.REGTYPE
    info.mode = 0o755 if is_dir else 0o644
    info.size = size
    info.mtime = 0
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    return info


def _members(dataset_dir: Path) -> list[Path]:
    """Every directory and file under `dataset_dir`, sorted; links are refused."""
    out: list[Path] = []
    for dirpath, dirnames, filenames in os.walk(dataset_dir):
        dirnames[:] = sorted(d for d in dirnames if d not in SKIP_DIRS)
        for name in dirnames + sorted(filenames):
            path = Path(dirpath) / name
            if path.is_symlink():
                raise DatasetError(f"{path}: links cannot be packed into a dataset archive")
            out.append(path)
    return sorted(out, key=lambda p: p.relative_to(dataset_dir).as_posix())


def write_archive(dataset_dir: Path, out: Path, top: str) -> None:
    """Write the deterministic .tar.gz of `dataset_dir` under folder `top` (via a temp file, atomically)."""
    tmp = out.with_name(f".{out.name}.tmp")
    try:
        with open(tmp, "wb") as raw, gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0) as gz, \
                tarfile.open(fileobj=gz, mode="w", format=tarfile.PAX_FORMAT) as tar:
            tar.addfile(_tar_info(top, is_dir=True))
            for path in _members(dataset_dir):
                arcname = f"{top}/{path.relative_to(dataset_dir).as_posix()}"
                if path.is_dir():
                    tar.addfile(_tar_info(arcname, is_dir=True))
                else:
                    with open(path, "rb") as f:
                        tar.addfile(_tar_info(arcname, False, path.stat().st_size), f)
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)


def read_info(dataset_dir: Path) -> dict[str, Any]:
    """The dataset's meta/info.json."""
    path = dataset_dir / "meta" / "info.json"
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise DatasetError(f"{dataset_dir} is not a LeRobot dataset: cannot read {path}: {e}") from None


TRAINING_FIELDS = ("dataset_id", "tier", "ref_min_score", "ref_max_score", "ref_known_worker_optimum", "ref_scale",
                   "total_meta_episodes", "build_command", "mewa_bench_version")


def _provenance(dataset_dir: Path) -> dict[str, Any]:
    """Kind, suite and policy hashes (and a training dataset's Minari-style fields) from meta/mewa.json.

    Only a training dataset's own metadata makes an entry `kind: training`; a `record`ed dataset plays the
    curated test pairs, so it is an evaluation recording."""
    from mewa_bench.datasets.catalog import EVALUATION_RECORDING, EVALUATION_WARNING, TRAINING

    path = dataset_dir / MEWA_META_FILE
    if not path.is_file():
        return {"kind": EVALUATION_RECORDING, "warning": EVALUATION_WARNING}
    meta = json.loads(path.read_text())
    if meta.get("kind") == TRAINING:
        return {"kind": TRAINING, "suite_sha256": meta["suite"]["sha256"], "policy_sha256": meta["behaviour"]["sha256"],
                "eval_suite": meta["eval_env_spec"]["suite"], **{k: meta[k] for k in TRAINING_FIELDS}}
    return {"kind": EVALUATION_RECORDING, "warning": EVALUATION_WARNING, "suite_sha256": meta["suite"]["sha256"],
            "policy_sha256": meta["policy"]["sha256"], "mewa_bench_version": meta["mewa_bench_version"]}


def pack_dataset(dataset_dir: Path | str, out_dir: Path | str, name: str, version: str, suite: str, policy: str,
                 url_base: str | None = None, catalog_dir: Path | str | None = None) -> dict[str, Any]:
    """Archive a dataset deterministically; returns its catalog entry.

    Its URL: under `url_base` if given; else the archive's name when it sits in `catalog_dir` (the
    catalog's folder: shipped datasets travel with their catalog); else a file URL.
    """
    dataset_dir, out_dir = Path(dataset_dir), Path(out_dir)
    if not NAME_RE.match(name):
        raise DatasetError(f"dataset name {name!r} must be letters, digits, '.', '_' or '-'")
    info = read_info(dataset_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    archive = out_dir / archive_name(name, version)
    write_archive(dataset_dir, archive, name)
    if url_base:
        url = f"{url_base.rstrip('/')}/{archive.name}"
    elif catalog_dir is not None and archive.resolve().parent == Path(catalog_dir).resolve():
        url = archive.name
    else:
        url = archive.resolve().as_uri()
    entry = {"name": name, "version": version, "suite": suite, "policy": policy,
             "episodes": int(info["total_episodes"]), "frames": int(info["total_frames"]),
             "size": archive.stat().st_size, "sha256": sha256_file(archive), "url": url,
             "format": f"lerobot-{info.get('codebase_version', '?')}", **_provenance(dataset_dir)}
    return validate_entry(entry)

