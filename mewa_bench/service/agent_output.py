"""An agent's stdout and stderr, kept in a log of its own and capped.

The sandbox's processes write into a pipe; a thread copies at most `limit` bytes into the log file
(then one line saying the rest was dropped) and keeps draining the pipe, so an agent that prints
without end neither blocks nor fills the disk. Nothing of it reaches the server's own log.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

TRUNCATED = b"\n[mewa-bench: the agent's output was cut here, at its limit of %d bytes]\n"


class OutputCapture:
    """A pipe whose write end (`fd`) is given to the agent process; what comes through goes to `log`."""

    def __init__(self, log: Path, limit: int) -> None:
        self.log, self.limit = log, limit
        log.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(log, "ab")
        self.written = self._file.tell()  # an attempt that goes on after a restart appends: the cap is the file's
        self.dropped = 0
        self._marked = self.written >= limit  # the file was cut at its limit already
        read_fd, self.fd = os.pipe()
        os.chmod(log, 0o600)
        self._thread = threading.Thread(target=self._drain, args=(read_fd,), name="agent-output", daemon=True)
        self._thread.start()

    def _drain(self, read_fd: int) -> None:
        """Copy up to the limit, drop the rest, until every write end is closed."""
        try:
            while chunk := os.read(read_fd, 1 << 16):
                room = self.limit - self.written
                if room > 0:
                    self._file.write(chunk[:room])
                    self._file.flush()
                    self.written += min(room, len(chunk))
                if len(chunk) > room:
                    if not self._marked:
                        self._file.write(TRUNCATED % self.limit)
                        self._file.flush()
                        self._marked = True
                    self.dropped += len(chunk) - max(room, 0)
        finally:
            os.close(read_fd)

    def close(self, timeout: float = 10.0) -> None:
        """Close our write end and wait for the sandbox's to be closed (its processes gone)."""
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
        self._thread.join(timeout)
        if not self._thread.is_alive():
            self._file.close()
