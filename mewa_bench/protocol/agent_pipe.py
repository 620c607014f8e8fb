"""The wire between the parent and the agent process: length-prefixed frames over a pipe, and the replies.

Requests are pickled by the parent (the agent process unpickles only what the parent sent);
replies are a few plain bytes, so the parent never unpickles anything the agent's process
produced: R (loaded and ready), K (a call done), A<action> (a step's action), B<token>,... (a
batch's replies), E<JSON> (an AgentError's kind, message and index in the batch).
"""

from __future__ import annotations

import json
import math
import os
import select
import struct
import time

from mewa_bench.protocol.agent_calls import ERROR_KINDS, AgentError

_HEADER = struct.Struct("<I")

_READY, _OK, _ACTION, _ERROR, _BATCHED = b"R", b"K", b"A", b"E", b"B"


class _FrameReader:
    """Reads length-prefixed frames from a pipe, waiting at most until a deadline."""

    def __init__(self, fd: int) -> None:
        self._fd = fd
        self._buffer = b""
        self._poller = select.poll()
        self._poller.register(fd, select.POLLIN)

    def read(self, deadline: float | None = None) -> bytes | None:
        """The next frame, or None at the end of the input; TimeoutError past `deadline` (monotonic)."""
        buffer = self._buffer
        while True:
            if len(buffer) >= _HEADER.size:
                end = _HEADER.size + _HEADER.unpack_from(buffer)[0]
                if len(buffer) >= end:
                    self._buffer = buffer[end:]
                    return buffer[_HEADER.size:end]
            if deadline is not None:
                milliseconds = math.ceil((deadline - time.monotonic()) * 1000)
                if milliseconds <= 0 or not self._poller.poll(milliseconds):
                    self._buffer = buffer
                    raise TimeoutError
            chunk = os.read(self._fd, 1 << 16)
            if not chunk:
                return None
            buffer += chunk


def _write_frame(fd: int, payload: bytes) -> None:
    """Write `payload` with its length in front."""
    data = memoryview(_HEADER.pack(len(payload)) + payload)
    while data:
        data = data[os.write(fd, data):]


def _decode_error(reply: bytes) -> tuple[str, str, int | None]:
    """The (kind, message, index in the batch) of an error reply; a malformed one counts as a crash."""
    try:
        error = json.loads(reply[1:])
        kind, message, index = error["kind"], error["message"], error.get("index")
    except (ValueError, KeyError, TypeError, AttributeError):
        return "crash", f"the agent process sent a malformed error reply {reply[:80]!r}", None
    index = index if isinstance(index, int) and not isinstance(index, bool) else None
    return (kind if kind in ERROR_KINDS else "crash"), str(message), index


def _reply_token(reply: int | None) -> bytes:
    """A call's reply on the wire: A<action> for a step, K for the other calls."""
    return _OK if reply is None else _ACTION + b"%d" % reply


def _error_reply(err: AgentError) -> bytes:
    return _ERROR + json.dumps({"kind": err.kind, "message": str(err), "index": err.index}).encode()
