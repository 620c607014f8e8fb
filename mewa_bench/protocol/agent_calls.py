"""An agent's calls, carried out and checked: the runners' common core, in the agent process or in-process.

`_AgentCalls` calls one agent object's methods (a missing optional one is a no-op) and turns what
goes wrong into an `AgentError` naming the call and the agent's own traceback frames; `_Lanes`
answers a batch with one such agent per lane, `_VectorCalls` with one vector agent, its calls
grouped by kind. `_call_guard` gives each call of a batch its time limit (an interval timer whose
SIGALRM raises `_CallTimeout`) and fails it when the agent broke a sandbox rule meanwhile
(`report_violation`). `_columns` packs a batch's step observations into two stacked arrays for the
trip to the agent process; `_step_arguments` unpacks one there.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import signal
import traceback
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np
from gymnasium import spaces

from mewa_bench.protocol.agent import (OPTIONAL_METHODS, InvalidActions, Transition, check_action, check_actions,
                                       is_vector_agent, load_lanes, stack_observations, stack_transitions)

ERROR_KINDS = ("load", "exception", "invalid_action", "timeout", "memory", "crash", "sandbox")

_TRACEBACK_FRAMES = 3
_MAX_EXCEPTION_TEXT = 2000

_STEP, _RESET_TASK, _OBSERVE, _END_EPISODE, _BATCH, _STEP_ROW = range(6)
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
