"""The dataset catalog and its archives: size, sha256 and HTTP Range, so an interrupted download resumes.

The catalog served is the server's (`settings.catalog`, else `<data dir>/datasets/index.json`, else
the one mewa-bench ships) with each local archive's URL pointing at this server, so
`mewa-bench datasets download NAME --server URL` works against it. Only archives the catalog
lists are served, found by name and version, never by a path from the request.
"""

from __future__ import annotations

import urllib.parse
import urllib.request
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse

from mewa_bench.service.errors import ApiError, not_found
from mewa_bench.service.routes.context import settings_of
from mewa_bench.service.settings import Settings

router = APIRouter(prefix="/api/datasets", tags=["datasets"])


def catalog_path(settings: Settings) -> Path:
    """Which catalog this server serves."""
    from mewa_bench.datasets.catalog import default_catalog_path

    if settings.catalog is not None:
        return settings.catalog
    own = settings.data_dir / "datasets" / "index.json"
    return own if own.exists() else default_catalog_path()


def _catalog(settings: Settings) -> dict[str, Any]:
    """The server's catalog, or a 503 saying why it cannot be read."""
    from mewa_bench.datasets.catalog import DatasetError, load_catalog

    try:
        return load_catalog(catalog_path(settings))
    except DatasetError as e:
        raise ApiError(503, "catalog_unavailable", f"the server's dataset catalog cannot be read: {e}") from None


def local_archive(entry: dict[str, Any]) -> Path | None:
    """The file behind a catalog entry whose archive is on this machine (a file:// URL), else None."""
    url = entry.get("url", "")
    if not url.startswith("file://"):
        return None
    path = Path(urllib.request.url2pathname(urllib.parse.urlparse(url).path))
    return path if path.is_file() else None


def archive_url(request: Request, entry: dict[str, Any]) -> str:
    """Where this server serves an entry's archive."""
    return str(request.url_for("download_archive", name=entry["name"], version=entry["version"]))


@router.get("", summary="The dataset catalog")
def catalog(request: Request) -> dict[str, Any]:
    """The catalog (format as `datasets/index.json`), local archives' URLs pointing at this server."""
    from mewa_bench.datasets.catalog import catalog_entries

    content = _catalog(settings_of(request))
    for entry in catalog_entries(content):  # training data and evaluation recordings
        if local_archive(entry) is not None:
            entry["url"] = archive_url(request, entry)
    return content


def _entry(settings: Settings, name: str, version: str | None) -> dict[str, Any]:
    """A catalog entry by name and version, or a 404 naming the known ones."""
    from mewa_bench.datasets.catalog import DatasetError, dataset_info

    try:
        return dataset_info(_catalog(settings), name if version is None else f"{name}@{version}")
    except DatasetError as e:
        raise ApiError(404, "unknown_dataset", str(e)) from None


@router.get("/{name}", summary="One dataset's entry")
def dataset(name: str, request: Request) -> dict[str, Any]:
    """The newest version's entry (`name@version` for another)."""
    base, _, version = name.partition("@")
    entry = _entry(settings_of(request), base, version or None)
    if local_archive(entry) is not None:
        entry["url"] = archive_url(request, entry)
    return entry


@router.get("/{name}/{version}/archive", summary="Download a dataset archive (HTTP Range supported)",
            response_class=FileResponse)
def download_archive(name: str, version: str, request: Request) -> FileResponse:
    """The .tar.gz with Content-Length, its sha256 in X-Content-SHA256, and Range requests (206, 416)."""
    entry = _entry(settings_of(request), name, version)
    path = local_archive(entry)
    if path is None:
        raise not_found(f"an archive of {name}@{version} on this server (the catalog points elsewhere: "
                        f"{entry.get('url') or entry.get('hf_repo_id')})")
    return FileResponse(path, media_type="application/gzip", filename=path.name,
                        headers={"X-Content-SHA256": entry.get("sha256", "")})
