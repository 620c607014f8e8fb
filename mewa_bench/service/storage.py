"""The data dir's disk: free space, the reserve kept on it, and what the API answers when it is full.

An upload is refused with a 507 before anything of it is written when the data dir's free space,
less the upload's size, would fall below the reserve (`Settings.reserve_bytes`); a write that runs
out of space anyway (another process filled the disk, files run out of inodes, a checkpoint
unpacks larger than it said) is a 507 too, its partial files removed by the code that wrote them.
Reads need no space, so the boards and statuses keep being served. The log says "storage full"
once when the disk becomes full and "storage available again" once an upload is written whole again,
however many requests are refused in between.
"""

from __future__ import annotations

import errno
import logging
import os
import threading
from pathlib import Path

from mewa_bench.service.errors import ApiError

log = logging.getLogger("mewa_bench.service")
FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)


def free_bytes(path: Path) -> int:
    """Bytes an unprivileged process may still write on the file system holding `path`."""
    stats = os.statvfs(path)
    return stats.f_bavail * stats.f_frsize


def is_disk_full(error: BaseException) -> bool:
    """Whether an error (or one it was raised from) is the disk or a quota being full, in a file or in SQLite."""
    seen: set[int] = set()
    current: BaseException | None = error
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if isinstance(current, OSError) and current.errno in FULL_ERRNOS:
            return True
        if type(current).__name__ == "OperationalError" and "disk is full" in str(current):  # sqlite3's
            return True
        current = current.__cause__ or current.__context__
    return False


def storage_full(free: int, reserve: int, needed: int | None = None) -> ApiError:
    """The 507 answer: what is free, what the server keeps in reserve, and what the upload needed."""
    wanted = "" if needed is None else f"; this upload needs {needed:,}"
    return ApiError(507, "storage_full", f"the server is out of storage: {free:,} bytes free on its data dir's disk, "
                                         f"{reserve:,} kept in reserve{wanted}; nothing was stored, try again later")


class StorageGuard:
    """Checks room before uploads are written and logs each episode of fullness once (shared by the API's threads)."""

    def __init__(self, data_dir: Path, reserve: int) -> None:
        self.data_dir, self.reserve = data_dir, reserve
        self.full = False
        self._lock = threading.Lock()

    def free(self) -> int:
        """Free bytes on the data dir's disk now."""
        return free_bytes(self.data_dir)

    def ensure_room(self, size: int) -> None:
        """A 507 unless `size` bytes fit above the reserve (a refusal is noted for the log)."""
        free = self.free()
        if free - size < self.reserve:
            self.note(True, free)
            raise storage_full(free, self.reserve, size)

    def stored(self) -> None:
        """An upload was written whole: the disk is not full (noted for the log)."""
        if self.full:
            self.note(False, self.free())

    def refused(self) -> ApiError:
        """The 507 of a write that ran out of space midway (its partial files are gone already)."""
        free = self.free()
        self.note(True, free)
        return storage_full(free, self.reserve)

    def note(self, full: bool, free: int) -> None:
        """Log a change between full and not full (only a change: one line per episode)."""
        with self._lock:
            changed, self.full = full != self.full, full
        if changed and full:
            log.error("storage full: %s bytes free on the data dir's disk (%s), %s kept in reserve; uploads are "
                      "refused with 507 until space is freed", f"{free:,}", self.data_dir, f"{self.reserve:,}")
        elif changed:
            log.warning("storage available again: %s bytes free on the data dir's disk; uploads are accepted",
                        f"{free:,}")
