"""The isolated runner's parent side: starting the agent process, talking to it, stopping it.

`IsolatedAgent` starts a fresh Python interpreter running `agent_child._child_main` (or a sandbox's
entry, through a `Launcher`) with two pipes, sends it the agent file's path and spaces, then one
pickled request per call or batch, and reads each reply (`agent_pipe`) within a deadline. Any
failure kills and reaps the child; the error is remembered (`_FailureTracking`).
"""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import time
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from gymnasium import spaces

from mewa_bench.protocol.agent import Transition
from mewa_bench.protocol.agent_calls import (_BATCH, _END_EPISODE, _OBSERVE, _RESET_TASK, _STEP, AgentError, Call,
                                             _columns, _num_actions)
from mewa_bench.protocol.agent_in_process import _FailureTracking
from mewa_bench.protocol.agent_pipe import (_ACTION, _BATCHED, _ERROR, _OK, _READY, _decode_error, _FrameReader,
                                            _write_frame)

DEFAULT_TIME_LIMIT = 10.0
DEFAULT_LOAD_TIME_LIMIT = 60.0
DEFAULT_MEMORY_LIMIT = 4 << 30

_CLOSE_GRACE_SECONDS = 2.0
_EXIT_WAIT_SECONDS = 5.0
_CHILD_COMMAND = "from mewa_bench.protocol.agent_child import _child_main; _child_main()"
_PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])


@dataclass(frozen=True)
class Launcher:
    """How a sandbox starts the agent process: `prefix` + [python, *`flags`, "-c", `entry`, pipe fds, memory limit].

    `entry` is the code the child runs (it must end by calling `agent_child._child_main()`), `environment`
    the whole environment it gets, `flags` the interpreter's options (e.g. -I), `output` a file
    descriptor that takes the process's stdout and stderr (None: this process's own). Exit codes
    above 128 count as deaths by signal (code - 128), the convention of bwrap and shells, which
    stand between the parent and the agent process.
    """

    prefix: tuple[str, ...]
    entry: str
    environment: tuple[tuple[str, str], ...]
    python: str = sys.executable
    flags: tuple[str, ...] = ()
    output: int | None = None


class IsolatedAgent(_FailureTracking):
    """Runs the agent file at `path` in a child process with a per-call time limit and a memory limit.

    The child is a fresh Python interpreter that gets only the file's path, the two spaces and the
    agent args; it loads the agent (AgentError of kind "load" if that fails, with AgentLoadError's
    message). Each call must return within `time_limit` seconds; loading and the first call after it
    get `load_time_limit` each (None: no limit). The child's address space is capped at `memory_limit`
    bytes (RLIMIT_AS; None for no cap). A failing call kills and reaps the child and raises AgentError;
    the runner is then closed. A `launcher` starts the child inside a sandbox.
    """

    def __init__(self, path: str | Path, observation_space: Any, action_space: spaces.Discrete,
                 agent_args: dict[str, str] | None = None, checkpoint: str | None = None, *,
                 time_limit: float | None = DEFAULT_TIME_LIMIT, load_time_limit: float | None = DEFAULT_LOAD_TIME_LIMIT,
                 memory_limit: int | None = DEFAULT_MEMORY_LIMIT, lanes: int = 1,
                 launcher: Launcher | None = None) -> None:
        if lanes < 1:
            raise ValueError(f"lanes must be >= 1, got {lanes}")
        self.name = Path(path).name
        self.lanes = lanes
        self._num_actions = _num_actions(action_space)
        self._time_limit = time_limit
        self._next_time_limit = load_time_limit
        self._memory_limit = memory_limit
        self._launcher = launcher
        prefix, python, entry = ((), sys.executable, _CHILD_COMMAND) if launcher is None else \
            (launcher.prefix, launcher.python, launcher.entry)
        environment = _child_environment() if launcher is None else dict(launcher.environment)
        parent_read, child_write = os.pipe()
        child_read, parent_write = os.pipe()
        try:
            self._process = subprocess.Popen(
                [*prefix, python, *(launcher.flags if launcher else ()), "-c", entry, str(child_read), str(child_write),
                 str(memory_limit or 0)], pass_fds=(child_read, child_write), stdin=subprocess.DEVNULL, env=environment,
                stdout=launcher.output if launcher else None,
                stderr=subprocess.STDOUT if launcher and launcher.output is not None else None)
        except BaseException:
            for fd in (parent_read, child_write, child_read, parent_write):
                os.close(fd)
            raise
        os.close(child_read)
        os.close(child_write)
        self.pid = self._process.pid
        self._write_fd = parent_write
        self._reader = _FrameReader(parent_read)
        self._finalizer = weakref.finalize(self, _stop_process, self._process, (parent_write, parent_read))
        spec = (str(path), observation_space, action_space, agent_args, checkpoint, lanes)
        self._request_ok(pickle.dumps(spec, pickle.HIGHEST_PROTOCOL), "loading", expected=_READY)
        self._next_time_limit = load_time_limit
        self._first_batch = True

    def batch(self, calls: Sequence[Call]) -> list[int | None]:
        """Carry out one call per lane in one round trip; actions for steps, None for the other calls.

        Each call has the per-call time limit (enforced in the child); an AgentError's `index` says
        which call of the batch failed.
        """
        per_call = self._next_time_limit if self._first_batch else self._time_limit
        request = pickle.dumps((_BATCH, *_columns(calls), per_call), pickle.HIGHEST_PROTOCOL)
        backstop = None if per_call is None else per_call * len(calls) + _CLOSE_GRACE_SECONDS
        self._next_time_limit = backstop
        reply = self._request(request, f"a batch of {len(calls)} calls")
        self._first_batch = False
        if reply[:1] != _BATCHED:
            raise self._fail("crash", f"agent {self.name}: the agent process sent a malformed reply {reply[:40]!r}")
        tokens = reply[1:].split(b",") if len(reply) > 1 else []
        if len(tokens) != len(calls):
            raise self._fail("crash", f"agent {self.name}: the agent process answered {len(tokens)} of "
                                      f"{len(calls)} calls")
        out: list[int | None] = []
        for token in tokens:
            if token == _OK:
                out.append(None)
            elif token[:1] == _ACTION and token[1:].isdigit() and int(token[1:]) < self._num_actions:
                out.append(int(token[1:]))
            else:
                raise self._fail("crash", f"agent {self.name}: the agent process sent a malformed reply {token[:40]!r}")
        return out

    def step(self, transition: Transition | None, observation: Any) -> int:
        """Observe the previous step's `transition` (None on an episode's first step), then act."""
        request = pickle.dumps((_STEP, transition, observation), pickle.HIGHEST_PROTOCOL)
        reply = self._request(request, "act()" if transition is None else "observe()/act()")
        if reply[:1] == _ACTION and reply[1:].isdigit():
            action = int(reply[1:])
            if action < self._num_actions:
                return action
        raise self._fail("crash", f"agent {self.name}: the agent process sent a malformed reply {reply[:40]!r}")

    def act(self, observation: Any) -> int:
        """The agent's action for `observation`."""
        return self.step(None, observation)

    def reset_task(self, hidden: dict | None = None, seed: int | None = None) -> None:
        """A new hidden task-worker pair begins (`hidden` reveals it: privileged runs only)."""
        self._request_ok(pickle.dumps((_RESET_TASK, hidden, seed)), "reset_task()")

    def observe(self, transition: Transition) -> None:
        """Report one step's outcome to the agent."""
        self._request_ok(pickle.dumps((_OBSERVE, transition), pickle.HIGHEST_PROTOCOL), "observe()")

    def end_episode(self, final_transition: Transition | None = None) -> None:
        """Observe the episode's last `final_transition` (unless None), then end the episode."""
        self._request_ok(pickle.dumps((_END_EPISODE, final_transition), pickle.HIGHEST_PROTOCOL), "end_episode()")

    def close(self) -> None:
        """Let the child exit (it stops at the end of its input), killing it if it does not; idempotent."""
        self._closed = True
        self._finalizer()

    def _request_ok(self, request: bytes, call: str, expected: bytes = _OK) -> None:
        """A request whose reply is just an acknowledgement."""
        reply = self._request(request, call)
        if reply != expected:
            raise self._fail("crash", f"agent {self.name}: the agent process sent a malformed reply {reply[:40]!r}")

    def _request(self, request: bytes, call: str) -> bytes:
        """Send one request and wait for its reply within the time limit; raise AgentError on failure."""
        self._check_usable()
        time_limit = self._next_time_limit
        try:
            _write_frame(self._write_fd, request)
            reply = self._reader.read(None if time_limit is None else time.monotonic() + time_limit)
        except TimeoutError:
            raise self._fail("timeout", f"agent {self.name}: {call} did not finish within the time limit "
                                        f"of {time_limit:g} s; the agent process was killed") from None
        except BrokenPipeError:
            reply = None
        except BaseException:  # e.g. Ctrl-C mid-call: a late reply would put the pipe out of step, so end the child
            self._process.kill()
            self.close()
            raise
        if reply is None:
            raise self._fail("crash", f"agent {self.name}: the agent process died during {call} "
                                      f"({self._exit_description()})")
        if reply[:1] == _ERROR:
            kind, message, index = _decode_error(reply)
            error = self._fail(kind, message)
            error.index = index
            raise error
        self._next_time_limit = self._time_limit
        return reply

    def _fail(self, kind: str, message: str) -> AgentError:
        """Kill and reap the child, remember the error and return it."""
        self._process.kill()
        self.close()
        self._failure = AgentError(kind, message)
        return self._failure

    def _exit_description(self) -> str:
        """How the child ended, waiting briefly for it to finish exiting."""
        try:
            code = self._process.wait(_EXIT_WAIT_SECONDS)
        except subprocess.TimeoutExpired:
            return "it closed its pipe but kept running"
        if self._launcher is not None and code > 128:
            code = 128 - code  # the sandbox's wrapper reports the agent process's death by signal N as 128 + N
        if code >= 0:
            return f"exit code {code}"
        name = signal.Signals(-code).name if -code in signal.valid_signals() else str(-code)
        hint = ", perhaps by the system's out-of-memory killer" if -code == signal.SIGKILL else ""
        return f"killed by signal {name}{hint}"


def _stop_process(process: subprocess.Popen, fds: tuple[int, ...]) -> None:
    """Close our ends of the pipes, which makes an idle child exit; kill it if it has not after a grace period."""
    for fd in fds:
        try:
            os.close(fd)
        except OSError:
            pass
    try:
        process.wait(_CLOSE_GRACE_SECONDS)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


AGENT_THREADS = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


def with_agent_threads(environment: dict[str, str]) -> dict[str, str]:
    """`environment` with one compute thread for the agent's torch/OpenMP/BLAS unless the user set a number:
    the runner already runs one agent process per core (--jobs), and on a busy machine a library's
    default of one thread per core made a 64-lane forward pass about 10x slower."""
    return {**AGENT_THREADS, **environment}


def _child_environment() -> dict[str, str]:
    """The parent's environment, with this copy of mewa_bench first on the child's import path."""
    environment = with_agent_threads(dict(os.environ))
    environment["PYTHONPATH"] = os.pathsep.join(filter(None, [_PACKAGE_ROOT, environment.get("PYTHONPATH")]))
    return environment
