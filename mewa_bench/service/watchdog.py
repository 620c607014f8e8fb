"""A sandbox's watchdog: a thread that stops the sandbox mid-call when a limit of the whole run is broken.

It polls the run's wall-clock deadline, the scratch directory's size (with the files the agent removed
from it but keeps open, which still take their space), the sandbox group's out-of-memory kills and the caller's `cancel` (e.g. the worker lost its job's lease), and on the
first of them records why and kills every process of the sandbox. The evaluation then sees the
agent process die, and the caller reports the watchdog's reason instead of the crash.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

POLL_SECONDS = 0.25
SCRATCH_EVERY = 4  # polls between two walks of the scratch directory
MAX_SCRATCH_ENTRIES = 200_000  # files and directories in the scratch directory


@dataclass(frozen=True)
class Stop:
    """Why the watchdog stopped the sandbox: a sandbox rule (wall_time, scratch_size, memory) or `cancelled`."""

    rule: str
    message: str


def scratch_usage(scratch: Path, stop_above: int) -> tuple[int, int]:
    """(bytes on disk, entries) under `scratch`, counting stopped once past `stop_above` bytes or too many entries."""
    used, entries, pending = 0, 0, [str(scratch)]
    while pending and used <= stop_above and entries <= MAX_SCRATCH_ENTRIES:
        try:
            with os.scandir(pending.pop()) as listing:
                for entry in listing:
                    entries += 1
                    try:
                        info = entry.stat(follow_symlinks=False)
                    except OSError:
                        continue
                    used += info.st_blocks * 512
                    if entry.is_dir(follow_symlinks=False):
                        pending.append(entry.path)
        except OSError:
            continue
    return used, entries


def unlinked_open_bytes(pids: set[int], device: int) -> int:
    """Bytes on `device` held by files that the processes `pids` keep open or mapped after removing them from
    their directory."""
    counted: dict[int, int] = {}
    for pid in pids:
        for kind in ("fd", "map_files"):  # open descriptors, and memory mappings that outlive theirs
            links = f"/proc/{pid}/{kind}"
            try:
                names = os.listdir(links)
            except OSError:
                continue  # gone meanwhile (or, for map_files, not readable here)
            for name in names:
                try:
                    if not os.readlink(f"{links}/{name}").endswith(" (deleted)"):
                        continue
                    info = os.stat(f"{links}/{name}")
                except OSError:
                    continue
                if info.st_dev == device and info.st_nlink == 0:
                    counted[info.st_ino] = info.st_blocks * 512
    return sum(counted.values())


class Watchdog:
    """Watches one sandboxed run; `stop` is None until it stopped the sandbox, then says why."""

    def __init__(self, kill: Callable[[], None], *, wall_seconds: float | None, scratch: Path, scratch_bytes: int,
                 memory_bytes: int, oom_kills: Callable[[], int] | None = None,
                 cancel: Callable[[], str | None] | None = None, pids: Callable[[], set[int]] = set,
                 poll_seconds: float = POLL_SECONDS) -> None:
        self._kill, self._scratch, self._scratch_bytes, self._pids = kill, scratch, scratch_bytes, pids
        self._wall, self._memory, self._oom_kills, self._cancel = wall_seconds, memory_bytes, oom_kills, cancel
        self._poll = poll_seconds
        self._started = time.monotonic()
        self._polls = 0
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sandbox-watchdog", daemon=True)
        self.stop: Stop | None = None

    def __enter__(self) -> Watchdog:
        """Start watching."""
        self._started = time.monotonic()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        """Stop watching (the run ended)."""
        self._done.set()
        self._thread.join()

    def check(self) -> Stop | None:
        """The first limit broken now, if any."""
        if self._cancel is not None and (why := self._cancel()) is not None:
            return Stop("cancelled", why)
        elapsed = time.monotonic() - self._started
        if self._wall is not None and elapsed > self._wall:
            return Stop("wall_time", f"the evaluation ran past its wall-clock limit of {self._wall:g} s; the sandbox "
                                     f"was stopped mid-call after {elapsed:.1f} s")
        if (stop := self.check_memory()) is not None:
            return stop
        self._polls += 1
        if self._polls % SCRATCH_EVERY:
            return None
        used, entries = scratch_usage(self._scratch, self._scratch_bytes)
        if used <= self._scratch_bytes:
            used += unlinked_open_bytes(self._pids(), os.stat(self._scratch).st_dev)
        if used > self._scratch_bytes:
            return Stop("scratch_size", f"the agent's scratch directory grew past its limit of {self._scratch_bytes:,} "
                                        f"bytes; the sandbox was stopped")
        if entries > MAX_SCRATCH_ENTRIES:
            return Stop("scratch_size", f"the agent's scratch directory holds more than {MAX_SCRATCH_ENTRIES:,} files "
                                        f"and directories; the sandbox was stopped")
        return None

    def check_memory(self) -> Stop | None:
        """A memory Stop if the kernel's out-of-memory killer stopped a process of the sandbox's group."""
        if self._oom_kills is None or self._oom_kills() == 0:
            return None
        return Stop("memory", f"the sandbox's processes together reached its memory limit of "
                              f"{self._memory / (1 << 30):.3g} GiB; the kernel stopped one of them and the sandbox "
                              f"was stopped")

    def _run(self) -> None:
        """Poll until the run ends or a limit is broken; then kill the sandbox."""
        while not self._done.wait(self._poll):
            stop = self.check()
            if stop is not None:
                self.stop = stop
                self._kill()
                return
