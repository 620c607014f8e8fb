"""Running an agent in a separate process with time and memory limits, or in-process for debugging.

Both runners give the agent's calls one interface (`AgentRunner`) and report every failure as an
`AgentError`. The isolated runner is a child Python process that loads the agent file itself and
never gets the env, so the agent cannot reach the hidden worker. Parent and child talk over two
pipes: requests are pickled, replies are a few plain bytes (an action, "ok" or a JSON error), so the
parent never unpickles anything the agent's process produced.

Per env step there is one round trip: `step(previous_transition, observation)` calls the agent's
`observe(previous_transition)` (unless None), then `act(observation)`; the episode's last
transition goes with `end_episode(final_transition)`.

Lanes (the fast path of the evaluation runner): a runner may hold several independent agent
objects, `lanes` of them, each built from the file as the agent would be alone. `batch(calls)`
sends one call per lane in one round trip, so the per-step cost of crossing the process boundary
is shared by as many units as there are lanes. In the child every call has its own time limit
(an interval timer), the parent waiting for the whole batch only as a backstop.

Sandboxes (`mewa_bench.service.sandbox`): a `Launcher` starts the agent process inside one (a
command prefix such as bwrap, its own environment, code run before the agent loads); a rule the
sandbox sees the agent break (`report_violation`) fails the call under way with kind "sandbox",
even if the agent catches the error it got.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import pickle
import resource
import select
import signal
import struct
import subprocess
import sys
import time
import functools
import inspect
import traceback
import weakref
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Callable, Iterator, Protocol, Self, Sequence

import numpy as np
from gymnasium import spaces

from mewa_bench.protocol.agent import (OPTIONAL_METHODS, AgentLoadError, InvalidActions, Transition, check_action,
                                       check_actions, is_vector_agent, load_lanes, stack_observations,
                                       stack_transitions)

DEFAULT_TIME_LIMIT = 10.0
DEFAULT_LOAD_TIME_LIMIT = 60.0
DEFAULT_MEMORY_LIMIT = 4 << 30
ERROR_KINDS = ("load", "exception", "invalid_action", "timeout", "memory", "crash", "sandbox")

_TRACEBACK_FRAMES = 3
_MAX_EXCEPTION_TEXT = 2000
_CLOSE_GRACE_SECONDS = 2.0
_EXIT_WAIT_SECONDS = 5.0
_HEADER = struct.Struct("<I")
_CHILD_COMMAND = "from mewa_bench.protocol.isolation import _child_main; _child_main()"
_PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])

_STEP, _RESET_TASK, _OBSERVE, _END_EPISODE, _BATCH, _STEP_ROW = range(6)
_READY, _OK, _ACTION, _ERROR, _BATCHED = b"R", b"K", b"A", b"E", b"B"
CALL_NAMES = {_STEP: "observe()/act()", _RESET_TASK: "reset_task()", _OBSERVE: "observe()",
              _END_EPISODE: "end_episode()"}
RESET_TASK, STEP, END_EPISODE = _RESET_TASK, _STEP, _END_EPISODE  # the calls a batch may carry


class AgentError(RuntimeError):
    """The agent failed; `kind` is one of ERROR_KINDS and the message says what happened."""

    def __init__(self, kind: str, message: str, index: int | None = None) -> None:
        super().__init__(message)
        self.kind = kind
        self.index = index  # in a batch: the position of the call that failed


class _CallTimeout(BaseException):
    """Raised in the agent process by the interval timer when one call overruns its time limit."""


Call = tuple[int, int, tuple]  # (lane, operation, arguments) of one call in a batch


@dataclass(frozen=True)
class Launcher:
    """How a sandbox starts the agent process: `prefix` + [python, *`flags`, "-c", `entry`, pipe fds, memory limit].

    `entry` is the code the child runs (it must end by calling `_child_main()`), `environment` the
    whole environment it gets, `flags` the interpreter's options (e.g. -I), `output` a file
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


class AgentRunner(Protocol):
    """The evaluator's handle on an agent: its calls, plus `step` (observe, then act) and `close`.

    After an AgentError the runner is closed and every later call raises the same error again.
    """

    name: str
    lanes: int

    def reset_task(self, hidden: dict | None = None, seed: int | None = None) -> None:
        """A new hidden task-worker pair begins (`hidden` reveals it: privileged runs only; `seed` for agents that take one)."""

    def batch(self, calls: Sequence[Call]) -> list[int | None]:
        """One call per lane (lane, RESET_TASK|STEP|END_EPISODE, args); actions for steps, None otherwise."""
        ...

    def step(self, transition: Transition | None, observation: Any) -> int:
        """Observe the previous step's `transition` (None on an episode's first step), then act."""
        ...

    def act(self, observation: Any) -> int:
        """The agent's action for `observation`."""
        ...

    def observe(self, transition: Transition) -> None:
        """Report one step's outcome to the agent."""

    def end_episode(self, final_transition: Transition | None = None) -> None:
        """Observe the episode's last `final_transition` (unless None), then end the episode."""

    def close(self) -> None:
        """Release the agent (stop its process); idempotent."""

    def __enter__(self) -> Self:
        """The runner itself; leaving the block closes it."""
        ...

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        """Close the runner."""


def make_agent_runner(path: str | Path, observation_space: Any, action_space: spaces.Discrete,
                      agent_args: dict[str, str] | None = None, checkpoint: str | None = None, *,
                      isolated: bool = True, time_limit: float | None = DEFAULT_TIME_LIMIT,
                      load_time_limit: float | None = DEFAULT_LOAD_TIME_LIMIT,
                      memory_limit: int | None = DEFAULT_MEMORY_LIMIT, lanes: int = 1,
                      launcher: Launcher | None = None) -> AgentRunner:
    """Load the agent file at `path` into an IsolatedAgent, or an InProcessAgent if not `isolated`.

    `lanes` independent agent objects are built (see `batch`). A file that does not load raises
    AgentError of kind "load" with AgentLoadError's message. The limits and the `launcher` (a
    sandbox) apply to the isolated runner only.
    """
    if isolated:
        return IsolatedAgent(path, observation_space, action_space, agent_args, checkpoint, time_limit=time_limit,
                             load_time_limit=load_time_limit, memory_limit=memory_limit, lanes=lanes,
                             launcher=launcher)
    if launcher is not None:
        raise ValueError("a sandboxed agent (launcher) must run isolated, not in-process")
    try:
        agent = _load_lanes(path, observation_space, action_space, agent_args, checkpoint, lanes, None)
    except AgentLoadError as exc:
        raise AgentError("load", str(exc)) from exc
    return InProcessAgent(agent, lanes, name=Path(path).name)


class _AgentCalls:
    """Calls an agent's methods, a missing optional one being a no-op, and turns failures into AgentErrors."""

    def __init__(self, agent: object, num_actions: int, name: str, memory_limit: int | None) -> None:
        self.name = name
        self._num_actions = num_actions
        self._memory_limit = memory_limit
        self._act: Callable[[Any], object] = agent.act  # type: ignore[attr-defined]
        self._reset_task, self._observe, self._end_episode = (getattr(agent, method, None) or _no_op
                                                              for method in OPTIONAL_METHODS)
        self._takes_seed = _accepts_keyword(self._reset_task, "seed")

    def step(self, transition: Transition | None, observation: Any) -> int:
        """observe(transition) unless None, then act(observation), checked."""
        method = "observe"
        try:
            if transition is not None:
                self._observe(transition)
            method = "act"
            action = self._act(observation)
        except (Exception, SystemExit) as exc:
            raise self._failure(method, exc) from None
        if type(action) is int and 0 <= action < self._num_actions:
            return action
        try:
            return check_action(action, self._num_actions)
        except ValueError as exc:
            raise AgentError("invalid_action", f"agent {self.name}: {exc}") from None

    def reset_task(self, hidden: dict | None = None, seed: int | None = None) -> None:
        """The agent's reset_task(), reset_task(hidden) in a privileged run, with seed=... if it takes one."""
        args = () if hidden is None else (hidden,)
        if seed is not None and self._takes_seed:
            self._call("reset_task", functools.partial(self._reset_task, seed=seed), *args)
        else:
            self._call("reset_task", self._reset_task, *args)

    def answer(self, operation: int, args: tuple) -> int | None:
        """Carry out one call of a batch; the action for a step, None otherwise."""
        if operation == _STEP:
            return self.step(*args)
        if operation == _RESET_TASK:
            self.reset_task(*args)
        elif operation == _END_EPISODE:
            self.end_episode(*args)
        elif operation == _OBSERVE:
            self.observe(*args)
        else:
            raise AgentError("crash", f"unknown request {operation!r}")
        return None

    def observe(self, transition: Transition) -> None:
        """The agent's observe(transition)."""
        self._call("observe", self._observe, transition)

    def end_episode(self, final_transition: Transition | None) -> None:
        """observe(final_transition) unless None, then end_episode()."""
        if final_transition is not None:
            self._call("observe", self._observe, final_transition)
        self._call("end_episode", self._end_episode)

    def _call(self, method: str, function: Callable[..., object], *args: Any) -> None:
        try:
            function(*args)
        except (Exception, SystemExit) as exc:
            raise self._failure(method, exc) from None

    def _failure(self, method: str, exc: BaseException) -> AgentError:
        return _exception_error(self.name, method, exc, self._memory_limit)


def _exception_error(name: str, method: str, exc: BaseException, memory_limit: int | None,
                     lanes: str = "") -> AgentError:
    """An AgentError naming the exception and where in the agent's code it was raised."""
    try:
        detail = str(exc)
    except Exception:
        detail = "(its message could not be printed)"
    if len(detail) > _MAX_EXCEPTION_TEXT:
        detail = detail[:_MAX_EXCEPTION_TEXT] + "..."
    message = f"agent {name}: {method}(){lanes} raised {type(exc).__name__}" + (f": {detail}" if detail else "")
    kind = "exception"
    if isinstance(exc, MemoryError):
        kind = "memory"
        limit = "" if memory_limit is None else f" (its limit is {_gib(memory_limit)})"
        message += f"\nthe agent ran out of memory{limit}"
    frames = [frame for frame in traceback.extract_tb(exc.__traceback__) if frame.filename != __file__]
    if frames:
        message += ("\nagent traceback (most recent call last):\n"
                    + "".join(traceback.format_list(frames[-_TRACEBACK_FRAMES:])).rstrip())
    return AgentError(kind, message)


Batch = tuple[list[Call], np.ndarray | None, np.ndarray | None]  # a batch as `_columns` sends it


class _Lanes:
    """Independent one-lane agents, one per lane, answering a batch call by call."""

    def __init__(self, agents: Sequence[object], num_actions: int, name: str, memory_limit: int | None) -> None:
        self.name = name
        self.calls = [_AgentCalls(agent, num_actions, name, memory_limit) for agent in agents]

    def answer(self, operation: int, args: tuple) -> int | None:
        """One call on lane 0 (the runner's one-lane methods)."""
        return self.calls[0].answer(operation, args)

    def answer_batch(self, batch: Batch, time_limit: float | None) -> list[int | None]:
        """Carry out a batch's calls in order, each within `time_limit` seconds; AgentError.index: which failed."""
        calls, observations, previous = batch
        replies = []
        for index, (lane, call, args) in enumerate(calls):
            if call == _STEP_ROW:
                call, args = _STEP, _step_arguments(args, observations, previous)
            with _call_guard(self.name, index, time_limit, CALL_NAMES.get(call, "a call")):
                replies.append(self.calls[lane].answer(call, args))
        return replies


class _VectorCalls:
    """A vector agent answering a batch: its per-lane calls grouped into at most one call of each kind,
    in the order observe, end_episode, reset_task, act, with arrays in and an action array out."""

    def __init__(self, agent: object, num_actions: int, name: str, memory_limit: int | None) -> None:
        self.name = name
        self._num_actions = num_actions
        self._memory_limit = memory_limit
        self._act: Callable[..., object] = agent.act  # type: ignore[attr-defined]
        self._reset_task, self._observe, self._end_episode = (getattr(agent, method, None) or _no_op
                                                              for method in OPTIONAL_METHODS)

    def answer(self, operation: int, args: tuple) -> int | None:
        """One call on lane 0 (the runner's one-lane methods), as a batch of one."""
        return self.answer_batch(_columns([(0, operation, args)]), None)[0]

    def answer_batch(self, batch: Batch, time_limit: float | None) -> list[int | None]:
        """Carry out a batch as grouped vector calls, each within `time_limit` seconds; the actions of its
        steps (None for the other calls). AgentError.index: the batch position of the lane blamed."""
        calls, observations, previous = batch
        observed: list[tuple[int, int, Transition]] = []  # (batch position, lane, transition)
        ending: list[tuple[int, int]] = []
        resetting: list[tuple[int, int, Any, int]] = []  # (position, lane, hidden, seed)
        acting: list[tuple[int, int, Any]] = []  # (position, lane, observation)
        for index, (lane, call, args) in enumerate(calls):
            if call == _STEP_ROW:
                call, args = _STEP, _step_arguments(args, observations, previous)
            if call == _STEP:
                transition, observation = args
                if transition is not None:
                    observed.append((index, lane, transition))
                acting.append((index, lane, observation))
            elif call == _END_EPISODE:
                if args[0] is not None:
                    observed.append((index, lane, args[0]))
                ending.append((index, lane))
            elif call == _OBSERVE:
                observed.append((index, lane, args[0]))
            elif call == _RESET_TASK:
                hidden, seed = (tuple(args) + (None, None))[:2]
                resetting.append((index, lane, hidden, 0 if seed is None else seed))
            else:
                raise AgentError("crash", f"unknown request {call!r}")
        replies: list[int | None] = [None] * len(calls)
        if observed:
            self._call("observe", [i for i, _, _ in observed], time_limit, self._observe,
                       _lane_array([lane for _, lane, _ in observed]), stack_transitions([t for _, _, t in observed]))
        if ending:
            self._call("end_episode", [i for i, _ in ending], time_limit, self._end_episode,
                       _lane_array([lane for _, lane in ending]))
        if resetting:
            hidden = [h for _, _, h, _ in resetting]
            extra = {} if all(h is None for h in hidden) else {"hidden": hidden}
            self._call("reset_task", [i for i, *_ in resetting], time_limit, self._reset_task,
                       _lane_array([lane for _, lane, _, _ in resetting]),
                       np.array([seed for *_, seed in resetting], dtype=np.int64), **extra)
        if acting:
            positions = [i for i, _, _ in acting]
            actions = self._call("act", positions, time_limit, self._act, _lane_array([lane for _, lane, _ in acting]),
                                 stack_observations([o for _, _, o in acting]))
            try:
                actions = check_actions(actions, len(acting), self._num_actions)
            except InvalidActions as exc:
                blamed = positions[0 if exc.row is None else exc.row]
                raise AgentError("invalid_action", f"agent {self.name}: {exc}", blamed) from None
            for position, action in zip(positions, actions.tolist()):
                replies[position] = action
        return replies

    def _call(self, method: str, positions: list[int], time_limit: float | None, function: Callable[..., object],
              *args: Any, **kwargs: Any) -> object:
        """One vector call within the time limit; a failure blames the first lane of the call."""
        lanes = f" for {len(positions)} lane{'s' if len(positions) != 1 else ''}"
        with _call_guard(self.name, positions[0], time_limit, f"{method}(){lanes}"):
            try:
                return function(*args, **kwargs)
            except (Exception, SystemExit) as exc:
                raise _exception_error(self.name, method, exc, self._memory_limit, lanes) from None


@contextlib.contextmanager
def _call_guard(name: str, index: int, time_limit: float | None, call: str) -> Iterator[None]:
    """Run one call of a batch within `time_limit` seconds (interval timer), its errors tagged with `index`,
    failing it too when the agent broke a sandbox rule meanwhile."""
    try:
        if time_limit is not None:
            signal.setitimer(signal.ITIMER_REAL, time_limit)
        yield
    except _CallTimeout:
        raise AgentError("timeout", f"agent {name}: {call} did not finish within the time limit of {time_limit:g} s; "
                                    "the agent process was killed", index) from None
    except AgentError as err:
        raise (_violation(name, index) if _VIOLATIONS else AgentError(err.kind, str(err), index)) from None
    finally:
        if time_limit is not None:
            signal.setitimer(signal.ITIMER_REAL, 0)
    if _VIOLATIONS:
        raise _violation(name, index)


def _lane_array(lanes: list[int]) -> np.ndarray:
    return np.array(lanes, dtype=np.int64)


def _load_lanes(path: str | Path, observation_space: Any, action_space: spaces.Discrete, agent_args: dict | None,
                checkpoint: str | None, lanes: int, memory_limit: int | None) -> _Lanes | _VectorCalls:
    """What answers batches for the agent file: its vector agent, or one agent per lane (AgentLoadError)."""
    loaded = load_lanes(path, observation_space, action_space, lanes, agent_args, checkpoint)
    name, num_actions = Path(path).name, _num_actions(action_space)
    if is_vector_agent(loaded):
        return _VectorCalls(loaded, num_actions, name, memory_limit)
    return _Lanes(loaded, num_actions, name, memory_limit)


class _FailureTracking:
    """Remembers a runner's first AgentError, after which every call raises it again."""

    _failure: AgentError | None = None
    _closed: bool = False

    def _check_usable(self) -> None:
        if self._failure is not None:
            raise AgentError(self._failure.kind, str(self._failure))
        if self._closed:
            raise RuntimeError(f"agent {getattr(self, 'name', '')} has been closed")

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Release the agent; idempotent."""
        self._closed = True


class InProcessAgent(_FailureTracking):
    """Runs an agent file's agents (one per lane, or its vector agent) in this process, for debugging (--in-process).

    Same interface and error types as IsolatedAgent, but no time or memory limit is enforced (a
    hanging agent hangs the evaluation) and the agent shares this process, env included.
    """

    def __init__(self, agent: _Lanes | _VectorCalls, lanes: int, name: str = "agent") -> None:
        self.agent = agent
        self.name = name
        self.lanes = lanes

    def batch(self, calls: Sequence[Call]) -> list[int | None]:
        """Carry out one call per lane; actions for steps, None otherwise (AgentError.index: which call failed)."""
        self._check_usable()
        try:
            return self.agent.answer_batch(_columns(calls), None)
        except AgentError as err:
            self._failure = err
            raise

    def step(self, transition: Transition | None, observation: Any) -> int:
        """Observe the previous step's `transition` (None on an episode's first step), then act."""
        return self._guarded(_STEP, transition, observation)

    def act(self, observation: Any) -> int:
        """The agent's action for `observation`."""
        return self.step(None, observation)

    def reset_task(self, hidden: dict | None = None, seed: int | None = None) -> None:
        """A new hidden task-worker pair begins (`hidden` reveals it: privileged runs only)."""
        self._guarded(_RESET_TASK, hidden, seed)

    def observe(self, transition: Transition) -> None:
        """Report one step's outcome to the agent."""
        self._guarded(_OBSERVE, transition)

    def end_episode(self, final_transition: Transition | None = None) -> None:
        """Observe the episode's last `final_transition` (unless None), then end the episode."""
        self._guarded(_END_EPISODE, final_transition)

    def _guarded(self, operation: int, *args: Any) -> Any:
        self._check_usable()
        try:
            return self.agent.answer(operation, args)
        except AgentError as err:
            self._failure = AgentError(err.kind, str(err))
            raise self._failure from None


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


def _num_actions(action_space: spaces.Discrete) -> int:
    """The number of actions of a Discrete(n) space starting at 0."""
    if not isinstance(action_space, spaces.Discrete) or int(action_space.start) != 0:
        raise ValueError(f"agents need a Discrete(n) action space starting at 0, got {action_space}")
    return int(action_space.n)


def _gib(num_bytes: int) -> str:
    return f"{num_bytes / (1 << 30):.3g} GiB"


def _no_op(*args: Any) -> None:
    return None


_VIOLATIONS: list[str] = []  # in the agent process: the sandbox rules the agent was caught breaking


def report_violation(message: str) -> None:
    """In a sandboxed agent process: the agent broke a sandbox rule (`message` says which); the call under
    way then fails with kind "sandbox", whatever the agent does with the error it got."""
    _VIOLATIONS.append(message)


def _violation(name: str, index: int | None = None) -> AgentError:
    """The error of the first sandbox rule the agent broke (call only when _VIOLATIONS is not empty)."""
    return AgentError("sandbox", f"agent {name}: {_VIOLATIONS[0]}", index)


def _child_main() -> None:
    """The agent process: load the agent, then answer requests until the parent closes the pipe."""
    read_fd, write_fd, memory_limit = (int(arg) for arg in sys.argv[1:4])
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is for the parent, which then closes us
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    if memory_limit > 0:
        _limit_address_space(memory_limit)
    reader = _FrameReader(read_fd)
    spec = reader.read()
    if spec is None:
        return
    path, observation_space, action_space, agent_args, checkpoint, lanes = pickle.loads(spec)
    sys.argv = sys.argv[:1]  # the pipe numbers are none of the agent's business
    name = Path(path).name
    try:
        agent = _load_lanes(path, observation_space, action_space, agent_args, checkpoint, lanes, memory_limit or None)
    except AgentLoadError as exc:
        _write_frame(write_fd, _error_reply(_violation(name) if _VIOLATIONS else AgentError("load", str(exc))))
        return
    if _VIOLATIONS:  # the agent caught the error its sandbox raised
        _write_frame(write_fd, _error_reply(_violation(name)))
        return
    signal.signal(signal.SIGALRM, _raise_call_timeout)
    _write_frame(write_fd, _READY)
    while (request := reader.read()) is not None:
        try:
            reply = _answer(agent, pickle.loads(request), name)
        except AgentError as err:
            reply = _error_reply(err)
        _write_frame(write_fd, reply)


def _answer(agent: _Lanes | _VectorCalls, request: tuple, name: str) -> bytes:
    """Carry out one request on the agent (lane 0) or a batch of calls on the lanes; the reply's bytes."""
    operation = request[0]
    if operation != _BATCH:
        try:
            reply = agent.answer(operation, request[1:])
        except AgentError as err:
            raise (_violation(name) if _VIOLATIONS else err) from None
        if _VIOLATIONS:
            raise _violation(name)
        return _reply_token(reply)
    _, batch, observations, previous, time_limit = request
    replies = agent.answer_batch((batch, observations, previous), time_limit)
    return _BATCHED + b",".join(map(_reply_token, replies))


def _reply_token(reply: int | None) -> bytes:
    """A call's reply on the wire: A<action> for a step, K for the other calls."""
    return _OK if reply is None else _ACTION + b"%d" % reply


def _columns(calls: Sequence[Call]) -> tuple[list[Call], np.ndarray | None, np.ndarray | None]:
    """A batch with its steps' observations stacked into two arrays (pickling one array beats pickling many).

    A step whose observation is an array like the others, and whose transition's next_obs is that
    same observation, becomes (lane, _STEP_ROW, (row, previous row or -1, action, reward,
    terminated, truncated)); anything else (sapien dicts, odd agents' inputs) travels as it is.
    """
    out: list[Call] = []
    observations: list[np.ndarray] = []
    previous: list[np.ndarray] = []
    for lane, operation, args in calls:
        if operation == _STEP and _stackable(args, observations):
            transition, observation = args
            observations.append(observation)
            if transition is None:
                out.append((lane, _STEP_ROW, (len(observations) - 1, -1, 0, 0.0, False, False)))
            else:
                previous.append(transition.obs)
                out.append((lane, _STEP_ROW, (len(observations) - 1, len(previous) - 1, transition.action,
                                              transition.reward, transition.terminated, transition.truncated)))
        else:
            out.append((lane, operation, args))
    return out, (np.stack(observations) if observations else None), (np.stack(previous) if previous else None)


def _stackable(args: tuple, stacked: list[np.ndarray]) -> bool:
    """True if a step's observation (and its transition's) can join the stacked arrays."""
    transition, observation = args
    if not isinstance(observation, np.ndarray):
        return False
    like = stacked[0] if stacked else observation
    if observation.shape != like.shape or observation.dtype != like.dtype:
        return False
    return transition is None or (transition.next_obs is observation and isinstance(transition.obs, np.ndarray)
                                  and transition.obs.shape == like.shape and transition.obs.dtype == like.dtype)


def _step_arguments(args: tuple, observations: np.ndarray, previous: np.ndarray | None) -> tuple:
    """The (transition, observation) of a stacked step, rebuilt in the agent process."""
    row, previous_row, action, reward, terminated, truncated = args
    observation = observations[row]
    if previous_row < 0:
        return None, observation
    return Transition(previous[previous_row], action, reward, observation, terminated, truncated), observation


def _raise_call_timeout(signum: int, frame: object) -> None:
    raise _CallTimeout


def _accepts_keyword(function: Callable[..., object], name: str) -> bool:
    """True if `function` can be called with keyword argument `name`."""
    try:
        parameters = inspect.signature(function).parameters.values()
    except (TypeError, ValueError):
        return False
    return any(p.name == name and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) or p.kind == p.VAR_KEYWORD
               for p in parameters)


def _error_reply(err: AgentError) -> bytes:
    return _ERROR + json.dumps({"kind": err.kind, "message": str(err), "index": err.index}).encode()


def _limit_address_space(memory_limit: int) -> None:
    """Cap this process's address space at `memory_limit` bytes (soft and hard, so the agent cannot lift it)."""
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = memory_limit if hard == resource.RLIM_INFINITY else min(memory_limit, hard)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
