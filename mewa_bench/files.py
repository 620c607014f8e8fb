"""How the project writes files: canonical JSON text, and atomic replacement (never a half-written file).

Used by every layer that writes (suites, results, catalogs, datasets, leaderboards); imports nothing
of the package.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any


def json_text(content: Any) -> str:
    """The project's JSON files: sorted keys, one-space indent, no NaN, a final newline."""
    return json.dumps(content, sort_keys=True, indent=1, allow_nan=False) + "\n"


def write_atomic(path: Path, text: str) -> None:
    """Write a file via a temporary sibling and rename, so a good file is never half-overwritten."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; results and suites are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_json_atomic(path: Path, content: Any) -> None:
    """Write `json_text(content)` atomically."""
    write_atomic(path, json_text(content))
