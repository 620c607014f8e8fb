"""Writing matplotlib figures as stable PNG files (shared by the design report and the leaderboards)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any


def save_png(fig: Any, path: Path, tight: bool = True) -> None:
    """Save a figure as PNG via a temporary sibling and rename, without timestamps or versions."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".png", dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, format="png", metadata={"Software": None}, **({"bbox_inches": "tight"} if tight else {}))
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
