"""The agent interface of the evaluation protocol, and loading an agent from a Python file."""

from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import itertools
import re
import reprlib
import sys
import traceback
from pathlib import Path
from types import ModuleType
from typing import Any, Callable, NamedTuple, Protocol

import numpy as np

OPTIONAL_METHODS = ("reset_task", "observe", "end_episode")
ONE_LANE_FACTORIES = ("make_agent", "Agent")
VECTOR_FACTORIES = ("make_vector_agent", "VectorAgent")

_module_numbers = itertools.count()


class Transition(NamedTuple):
    """One env step as the agent sees it: `obs`, then `action` gave `reward` and `next_obs`."""

    obs: np.ndarray
    action: int
    reward: float
    next_obs: np.ndarray
    terminated: bool
    truncated: bool


class Agent(Protocol):
    """What an evaluated agent implements (SPEC section 6).

    Per (task, worker) pair and seed the evaluator calls `reset_task()`, then plays 10 episodes:
    each step `act(observation)` chooses the action and `observe(transition)` reports its outcome;
    `end_episode()` follows the last step of every episode. The agent's state carries across the
    10 episodes of a pair; it never sees the task parameters, the worker or the pair's identity.

    Only `act` is required. A user agent may leave out `reset_task`, `observe` and `end_episode`:
    the runners (`mewa_bench.protocol.isolation`) treat a missing one as a no-op.
    An agent file defines `make_agent(observation_space, action_space, **kwargs)` or a class
    `Agent` taking the same arguments; see `load_agent`.
    """

    def reset_task(self) -> None:
        """A new hidden task-worker pair begins: forget what was learnt about the previous one."""

    def act(self, observation: np.ndarray) -> int:
        """The action (an int in 0..n-1) for `observation`."""
        ...

    def observe(self, transition: Transition) -> None:
        """The outcome of the last action (called after every step, the episode's last one included)."""

    def end_episode(self) -> None:
        """The episode is over: the point where gradient-based agents adapt."""


class Transitions(NamedTuple):
    """One env step of several lanes as a vector agent sees it: the fields of `Transition`, stacked.

    `obs` and `next_obs` are float32 [n, 18] (in sapien mode dicts of stacked arrays: "state"
    [n, 18], "image" [n, H, W, 3]); `action` int64 [n]; `reward` float64 [n]; `terminated` and
    `truncated` bool [n]. Row i belongs to the i-th lane of the call's `lanes`.
    """

    obs: Any
    action: np.ndarray
    reward: np.ndarray
    next_obs: Any
    terminated: np.ndarray
    truncated: np.ndarray


class VectorAgent(Protocol):
    """A batched agent: one object plays every lane of an agent process (SPEC section 6, batched agents).

    The runner plays several (pair, seed) units side by side, one per lane (0..num_lanes-1). Every
    call names the lanes it concerns (`lanes`, int64 [n], ascending, no repeats) and carries one row
    per lane; a lane's calls come in the one-lane order (reset_task, then per episode act/observe
    per step and end_episode), and lanes are independent: a lane's actions must depend only on its
    own calls. Lanes that are not playing a step (finished, ending an episode, starting a task) are
    simply absent from `act`, so a batch shrinks as units run out. A lane that gets `reset_task`
    has begun a new hidden pair (its seed is the protocol's per-unit seed); the agent never learns
    which pair. Per step the runner makes at most one call of each kind, in the order observe,
    end_episode, reset_task, act.

    Only `act` is required. An agent file defines `make_vector_agent(observation_space,
    action_space, num_lanes, **kwargs)` or a class `VectorAgent` taking the same arguments (the
    spaces are one lane's); see `load_lanes`. A file may define both a one-lane and a vector agent:
    the runner then plays the vector one.
    """

    def reset_task(self, lanes: np.ndarray, seeds: np.ndarray) -> None:
        """New hidden pairs begin on `lanes`: forget what was learnt there; `seeds` int64 [n]."""

    def act(self, lanes: np.ndarray, observations: Any) -> np.ndarray:
        """Actions (an integer array [n], each in 0..num_actions-1) for observations [n, 18] of `lanes`."""
        ...

    def observe(self, lanes: np.ndarray, transitions: Transitions) -> None:
        """The outcome of the last action of each of `lanes` (after every step, the episode's last one included)."""

    def end_episode(self, lanes: np.ndarray) -> None:
        """The episodes of `lanes` are over: the point where gradient-based agents adapt."""


class AgentLoadError(ValueError):
    """An agent file could not be loaded; the message names the file and what was wrong."""


def load_agent(path: str | Path, observation_space: Any, action_space: Any,
               agent_args: dict[str, str] | None = None, checkpoint: str | None = None) -> Agent:
    """Import the agent file at `path` and build its agent.

    The file's `make_agent` (or else its class `Agent`) is called as
    `make_agent(observation_space, action_space, **agent_args, checkpoint=checkpoint)`, the agent
    args passed as given (strings) and `checkpoint=` only if a checkpoint is given. The returned
    object has an `act` method; its optional methods may be absent (see `Agent`).
    Raises AgentLoadError for any failure.
    """
    file = Path(path)
    kwargs = _agent_kwargs(file, agent_args, checkpoint)
    module = _import_file(file)
    if _find_factory(file, module, required=False) is None and \
            _find_factory(file, module, VECTOR_FACTORIES, required=False) is not None:
        vector_agent = load_lanes(path, observation_space, action_space, 1, agent_args, checkpoint)
        return SingleLane(vector_agent)
    return _build(file, *_find_factory(file, module), observation_space, action_space, kwargs)


def _build(file: Path, factory: Callable[..., Any], factory_name: str, observation_space: Any, action_space: Any,
           kwargs: dict[str, str]) -> Agent:
    """One one-lane agent from its factory, checked."""
    try:
        agent = factory(observation_space, action_space, **kwargs)
    except (Exception, SystemExit) as exc:
        arguments = "".join(f", {key}={value!r}" for key, value in kwargs.items())
        raise AgentLoadError(f"{file}: {factory_name}(observation_space, action_space{arguments}) raised "
                             f"{_exception_summary(exc)}") from exc
    _check_methods(file, agent, factory_name)
    return agent


def load_lanes(path: str | Path, observation_space: Any, action_space: Any, num_lanes: int,
               agent_args: dict[str, str] | None = None, checkpoint: str | None = None) -> list[Any] | Any:
    """What plays `num_lanes` lanes of the agent file at `path`: its vector agent, or a list of agents.

    A file with `make_vector_agent` (or else a class `VectorAgent`) gets one object built as
    `make_vector_agent(observation_space, action_space, num_lanes, **agent_args, checkpoint=...)`;
    otherwise `num_lanes` independent one-lane agents are built as `load_agent` would (a list).
    Raises AgentLoadError for any failure.
    """
    file = Path(path)
    kwargs = _agent_kwargs(file, agent_args, checkpoint)
    module = _import_file(file)
    vector = _find_factory(file, module, VECTOR_FACTORIES, required=False)
    if vector is None:
        return [_build(file, *_find_factory(file, module), observation_space, action_space, kwargs)
                for _ in range(num_lanes)]
    factory, name = vector
    try:
        agent = factory(observation_space, action_space, num_lanes, **kwargs)
    except (Exception, SystemExit) as exc:
        arguments = "".join(f", {key}={value!r}" for key, value in kwargs.items())
        raise AgentLoadError(f"{file}: {name}(observation_space, action_space, num_lanes={num_lanes}{arguments}) "
                             f"raised {_exception_summary(exc)}") from exc
    _check_methods(file, agent, name, "act(lanes, observations)")
    return agent


def is_vector_agent(loaded: list[Any] | Any) -> bool:
    """True if `load_lanes` gave a vector agent (not a list of one-lane agents)."""
    return not isinstance(loaded, list)


class SingleLane:
    """A one-lane agent (the protocol's `Agent`) playing lane 0 of a vector agent."""

    _LANE = np.zeros(1, dtype=np.int64)

    def __init__(self, vector_agent: Any) -> None:
        self.vector_agent = vector_agent

    def reset_task(self, seed: int | None = None) -> None:
        """A new pair begins (seed 0 when the runner gives none)."""
        method = getattr(self.vector_agent, "reset_task", None)
        if method is not None:
            method(self._LANE, np.array([0 if seed is None else seed], dtype=np.int64))

    def act(self, observation: Any) -> int:
        """The vector agent's action for this one observation."""
        return self.vector_agent.act(self._LANE, stack_observations([observation]))[0]

    def observe(self, transition: Transition) -> None:
        """Pass the step on as a batch of one."""
        method = getattr(self.vector_agent, "observe", None)
        if method is not None:
            method(self._LANE, stack_transitions([transition]))

    def end_episode(self) -> None:
        """End lane 0's episode."""
        method = getattr(self.vector_agent, "end_episode", None)
        if method is not None:
            method(self._LANE)


def stack_observations(observations: list[Any]) -> Any:
    """Observations of several lanes as one array [n, ...], or a dict of such arrays (sapien mode)."""
    first = observations[0]
    if isinstance(first, dict):
        return {key: np.stack([o[key] for o in observations]) for key in first}
    return np.stack(observations)


def stack_transitions(transitions: list[Transition]) -> Transitions:
    """Transitions of several lanes as one `Transitions` of stacked arrays."""
    return Transitions(stack_observations([t.obs for t in transitions]),
                       np.array([t.action for t in transitions], dtype=np.int64),
                       np.array([t.reward for t in transitions], dtype=np.float64),
                       stack_observations([t.next_obs for t in transitions]),
                       np.array([t.terminated for t in transitions], dtype=bool),
                       np.array([t.truncated for t in transitions], dtype=bool))


class InvalidActions(ValueError):
    """A vector agent's act() answer is not `count` valid actions; `row` is the first bad row, if one is."""

    def __init__(self, message: str, row: int | None = None) -> None:
        super().__init__(message)
        self.row = row


def check_actions(value: object, count: int, num_actions: int) -> np.ndarray:
    """`value` as int64 [count] if it is a 1-D integer array (or list, or torch tensor) of actions in
    0..num_actions-1; InvalidActions otherwise."""
    try:
        array = value if isinstance(value, np.ndarray) else np.asarray(_to_numpy(value))
    except Exception as exc:  # e.g. a ragged list
        raise InvalidActions(f"act() returned {reprlib.repr(value)}, not an array of actions ({exc})") from None
    if array.shape != (count,):
        raise InvalidActions(f"act() returned {_shape_text(array)} for {count} lane{'s' if count != 1 else ''}: "
                             f"expected an integer array of shape ({count},)")
    if array.dtype.kind not in "iu":
        if array.dtype.kind == "f" and np.isnan(array).any():
            row = int(np.flatnonzero(np.isnan(array))[0])
            raise InvalidActions(f"act() returned NaN in a {array.dtype} array: expected integer actions", row)
        raise InvalidActions(f"act() returned an array of dtype {array.dtype}: expected integer actions "
                             f"(e.g. int64)")
    bad = np.flatnonzero((array < 0) | (array >= num_actions))
    if bad.size:
        raise InvalidActions(f"act() returned action {array[bad[0]].item()!r}, out of range: expected an int in "
                             f"0..{num_actions - 1}", int(bad[0]))
    return array.astype(np.int64, copy=False)


def _to_numpy(value: object) -> object:
    """A torch tensor as a numpy array (without importing torch); anything else as it is."""
    numpy = getattr(value, "numpy", None)
    if callable(numpy) and type(value).__module__.startswith("torch"):
        return value.detach().cpu().numpy()  # type: ignore[attr-defined]
    return value


def _shape_text(array: np.ndarray) -> str:
    return "a scalar" if array.ndim == 0 else f"shape {array.shape}"


def agent_sha256(path: str | Path) -> str:
    """The sha256 hex digest of the agent file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def check_action(value: object, num_actions: int) -> int:
    """`value` as a Python int if it is an integer in 0..num_actions-1 (not a bool), else ValueError."""
    if type(value) is int and 0 <= value < num_actions:
        return value
    scalar = value[()] if isinstance(value, np.ndarray) and value.ndim == 0 else value
    if isinstance(scalar, (int, np.integer)) and not isinstance(scalar, bool):
        if 0 <= scalar < num_actions:
            return int(scalar)
        problem = "out of range"
    else:
        problem = "not an integer"
    raise ValueError(f"act() returned {reprlib.repr(value)} ({type(value).__name__}), {problem}: "
                     f"expected an int in 0..{num_actions - 1}")


def _agent_kwargs(file: Path, agent_args: dict[str, str] | None, checkpoint: str | None) -> dict[str, str]:
    """The keyword arguments the agent factory gets."""
    kwargs = dict(agent_args or {})
    if checkpoint is not None:
        if "checkpoint" in kwargs:
            raise AgentLoadError(f"{file}: the checkpoint is given twice, as checkpoint and as agent arg checkpoint=")
        kwargs["checkpoint"] = checkpoint
    return kwargs


def _import_file(file: Path) -> ModuleType:
    """Import `file` as a fresh module, its directory on sys.path meanwhile so it can import siblings."""
    if not file.is_file():
        raise AgentLoadError(f"agent file {file} {'is not a file' if file.exists() else 'does not exist'}")
    name = f"_mewa_agent_{next(_module_numbers)}_" + re.sub(r"\W", "_", file.stem)
    loader = importlib.machinery.SourceFileLoader(name, str(file))
    module = importlib.util.module_from_spec(importlib.util.spec_from_file_location(name, file, loader=loader))
    directory = str(file.resolve().parent)
    added = directory not in sys.path
    if added:
        sys.path.insert(0, directory)
    sys.modules[name] = module  # dataclasses and pickle look classes up by their module
    try:
        loader.exec_module(module)
    except SyntaxError as exc:
        sys.modules.pop(name, None)
        where = "" if exc.filename == str(file) else f" in {exc.filename}"
        raise AgentLoadError(f"{file}: syntax error{where} at line {exc.lineno}: {exc.msg}") from exc
    except (Exception, SystemExit) as exc:  # a script calling sys.exit() at import is a load error too
        sys.modules.pop(name, None)
        raise AgentLoadError(f"{file}: importing it raised {_exception_summary(exc)}") from exc
    finally:
        if added and directory in sys.path:
            sys.path.remove(directory)
    return module


def _find_factory(file: Path, module: ModuleType, names: tuple[str, str] = ONE_LANE_FACTORIES,
                  required: bool = True) -> tuple[Callable[..., Any], str] | None:
    """The module's factory function (`make_agent`), or else its class (`Agent`), with the name it goes by."""
    for name in names:
        factory = getattr(module, name, None)
        if factory is None or factory is Agent or factory is VectorAgent:  # our Protocols are no agents
            continue
        if not callable(factory):
            raise AgentLoadError(f"{file}: {name} is a {type(factory).__name__}, not a function or class")
        return factory, name
    if not required:
        return None
    raise AgentLoadError(f"{file} defines neither a function make_agent(observation_space, action_space) "
                         "nor a class Agent (nor a batched make_vector_agent / VectorAgent)")


def _check_methods(file: Path, agent: object, factory_name: str, act: str = "act(observation)") -> None:
    """Check that the agent has a callable `act` and that its optional methods present are callable."""
    if not callable(getattr(agent, "act", None)):
        what = "None" if agent is None else f"a {type(agent).__name__} object"
        raise AgentLoadError(f"{file}: {factory_name}(...) returned {what}, which has no {act} method")
    for name in OPTIONAL_METHODS:
        method = getattr(agent, name, None)
        if method is not None and not callable(method):
            raise AgentLoadError(f"{file}: the agent's {name} is a {type(method).__name__}, not a method")


def _exception_summary(exc: BaseException) -> str:
    """'Type: message (at file, line n)', the line being where the exception was raised."""
    text = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    frames = [frame for frame in traceback.extract_tb(exc.__traceback__) if not frame.filename.startswith("<frozen")]
    if frames:
        text += f" (at {frames[-1].filename}, line {frames[-1].lineno})"
    return text


def state_vector(observation: Any) -> np.ndarray:
    """The float32[18] state of an observation: the observation itself, or its "state" in sapien mode."""
    if isinstance(observation, dict):
        observation = observation["state"]
    return np.asarray(observation, dtype=np.float32)
