"""`mewa-bench view FILE`: open a run's log in the Rerun viewer (native window, or web viewer on localhost)."""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

WEB_HOST = "127.0.0.1"


class ViewerError(RuntimeError):
    """The viewer cannot be started: a missing file, or rerun-sdk's `rerun` program not found."""


def rerun_executable() -> str:
    """The `rerun` program that rerun-sdk installs: beside this Python, in the rerun_cli package, or on PATH."""
    beside = Path(sys.executable).parent / "rerun"
    if beside.is_file():
        return str(beside)
    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin is not None:
        bundled = Path(spec.origin).parent / "rerun"
        if bundled.is_file():
            return str(bundled)
    found = shutil.which("rerun")
    if found is None:
        raise ViewerError("the Rerun viewer (`rerun`, installed by rerun-sdk) was not found: "
                          "pip install rerun-sdk==0.41.0")
    return found


def viewer_command(path: Path, web: bool = False, web_port: int | None = None) -> list[str]:
    """The command that opens `path` in the viewer; with `web`, a web viewer served on 127.0.0.1 only."""
    path = Path(path)
    if not path.is_file():
        raise ViewerError(f"{path}: no such file (expected a Rerun log, .rrd)" if not path.exists()
                          else f"{path} is not a file (expected a Rerun log, .rrd)")
    command = [rerun_executable()]
    if web:
        # Without --bind the viewer's servers listen on every interface (0.0.0.0).
        command += ["--web-viewer", "--bind", WEB_HOST]
        if web_port is not None:
            command += ["--web-viewer-port", str(web_port)]
    return [*command, str(path)]


def open_viewer(path: Path, web: bool = False, web_port: int | None = None) -> int:
    """Open the log in the Rerun viewer and wait until it is closed; returns the viewer's exit code."""
    command = viewer_command(path, web=web, web_port=web_port)
    try:
        return subprocess.call(command)
    except KeyboardInterrupt:
        return 130
