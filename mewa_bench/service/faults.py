"""Crash points for the fault tests: with MEWA_TEST_CRASH_AT=<point> in its environment, a server process kills
itself (SIGKILL: no clean-up, no answer, as a power cut would) when it reaches <point>. Without it they do nothing.

Points: `results-stored` and `agent-stored`, right after an upload's files are in the data dir and before
the transaction that adds its row commits (the window `uploads.sweep_orphans` is for); `results-committed` and
`agent-committed`, right after that transaction and before the answer (the window `Idempotency-Key` is for).
"""

from __future__ import annotations

import os
import signal

CRASH_VARIABLE = "MEWA_TEST_CRASH_AT"


def crash_point(name: str) -> None:
    """Die here if the environment asks for a crash at `name`."""
    if os.environ.get(CRASH_VARIABLE) == name:
        os.kill(os.getpid(), signal.SIGKILL)
