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
    factory, factory_name = _find_factory(file, _import_file(file))
    try:
        agent = factory(observation_space, action_space, **kwargs)
    except (Exception, SystemExit) as exc:
        arguments = "".join(f", {key}={value!r}" for key, value in kwargs.items())
        raise AgentLoadError(f"{file}: {factory_name}(observation_space, action_space{arguments}) raised "
                             f"{_exception_summary(exc)}") from exc
    _check_methods(file, agent, factory_name)
    return agent


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


def _find_factory(file: Path, module: ModuleType) -> tuple[Callable[..., Any], str]:
    """The module's `make_agent`, or else its class `Agent`, with the name it goes by."""
    for name in ("make_agent", "Agent"):
        factory = getattr(module, name, None)
        if factory is None or factory is Agent:  # our Protocol, imported for type hints, is no agent
            continue
        if not callable(factory):
            raise AgentLoadError(f"{file}: {name} is a {type(factory).__name__}, not a function or class")
        return factory, name
    raise AgentLoadError(f"{file} defines neither a function make_agent(observation_space, action_space) "
                         "nor a class Agent")


def _check_methods(file: Path, agent: object, factory_name: str) -> None:
    """Check that the agent has a callable `act` and that its optional methods present are callable."""
    if not callable(getattr(agent, "act", None)):
        what = "None" if agent is None else f"a {type(agent).__name__} object"
        raise AgentLoadError(f"{file}: {factory_name}(...) returned {what}, which has no act(observation) method")
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
