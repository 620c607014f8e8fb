"""`mewa-bench view FILE`: open a run's log in the Rerun viewer (native window, or web viewer on localhost)."""

from __future__ import annotations

import importlib.util
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import FrameType

WEB_HOST = "127.0.0.1"
DEFAULT_WEB_PORT = 9090  # rerun's --web-viewer-port default
DEFAULT_SERVER_PORT = 9876  # rerun's gRPC server (--port) default
STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)


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
                          "pip install 'mewa-bench[logs]'")
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
        command += ["--web-viewer", "--bind", WEB_HOST, "--web-viewer-port", str(web_port or DEFAULT_WEB_PORT),
                    "--port", "auto"]  # the gRPC server takes a free port: only the web port is the user's choice
    return [*command, str(path)]


def port_in_use(port: int, host: str = WEB_HOST) -> bool:
    """Whether something already listens on host:port (a bind attempt fails)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((host, port))
        except OSError:
            return True
    return False


def check_web_port(port: int) -> None:
    """Fail with a hint before starting a web viewer on a port that is taken."""
    if port_in_use(port):
        raise ViewerError(f"port {port} on {WEB_HOST} is already in use (another viewer still running?): "
                          f"stop it or pass --port N for another port")


class _Stopped(Exception):
    """SIGTERM or SIGHUP arrived while the viewer was running."""


def _raise_stopped(signum: int, frame: FrameType | None) -> None:
    raise _Stopped(signum)


def has_display() -> bool:
    """Whether a native window can open here (an X11 or Wayland display is set)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def open_viewer(path: Path, web: bool = False, web_port: int | None = None) -> int:
    """Open the log in the Rerun viewer and wait until it is closed; returns the viewer's exit code.

    Without a display the native viewer is refused before anything starts (it would open a server and fail);
    Ctrl-C, SIGTERM and SIGHUP stop the viewer too (a web viewer left running would hold its port).
    """
    command = viewer_command(path, web=web, web_port=web_port)
    if not web and not has_display():
        raise ViewerError("no display found (DISPLAY and WAYLAND_DISPLAY are unset): the native viewer needs one; "
                          "use --web to serve the web viewer on 127.0.0.1 and open it in a browser")
    if web:
        check_web_port(web_port or DEFAULT_WEB_PORT)
    previous = {sig: signal.signal(sig, _raise_stopped) for sig in STOP_SIGNALS}
    viewer = subprocess.Popen(command, start_new_session=True)  # its own process group: see _stop
    try:
        return viewer.wait()
    except KeyboardInterrupt:
        return 130
    except _Stopped as stop:
        return 128 + int(stop.args[0])
    finally:
        _stop(viewer)
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _stop(viewer: subprocess.Popen) -> None:
    """Stop the viewer's whole process group (rerun-sdk's `rerun` script runs the viewer binary as a
    child): SIGTERM, then SIGKILL if anything of it is left after 5 s."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        if not _group_alive(viewer):
            return
        try:
            os.killpg(viewer.pid, sig)
        except ProcessLookupError:
            return
        deadline = time.monotonic() + 5.0
        while _group_alive(viewer) and time.monotonic() < deadline:
            time.sleep(0.05)


def _group_alive(viewer: subprocess.Popen) -> bool:
    """Whether any process of the viewer's group is left (the leader is reaped first, so a zombie does not count)."""
    viewer.poll()
    try:
        os.killpg(viewer.pid, 0)
    except PermissionError:
        return True
    except OSError:  # ProcessLookupError: no process left in the group
        return False
    return True
