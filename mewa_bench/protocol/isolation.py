"""Running an agent in a separate process with time and memory limits, or in-process for debugging.

Both runners give the agent's calls one interface (`AgentRunner`) and report every failure as an
`AgentError`; `make_agent_runner` builds one. The isolated runner is a child Python process that
loads the agent file itself and never gets the env, so the agent cannot reach the hidden worker.
Parent and child talk over two pipes: requests are pickled, replies are a few plain bytes (an
action, "ok" or a JSON error), so the parent never unpickles anything the agent's process produced.

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

This module is the interface the rest of the package imports; the parts live beside it:
- `agent_calls`: an agent's calls carried out and checked (one agent per lane, or a vector agent),
  their errors, per-call time limits and sandbox violations, and a batch's stacked observations;
- `agent_pipe`: length-prefixed frames over a pipe and the replies' bytes;
- `agent_in_process`: `InProcessAgent`, and the first-error memory both runners share;
- `agent_process`: `IsolatedAgent` and `Launcher`: starting the agent process, its requests and
  replies, how it ended, stopping it;
- `agent_child`: the agent process's main loop and its address-space limit.
"""

from __future__ import annotations

from pathlib import Path
from types import TracebackType
from typing import Any, Protocol, Self, Sequence

from gymnasium import spaces

from mewa_bench.protocol.agent import AgentLoadError, Transition
from mewa_bench.protocol.agent_calls import (CALL_NAMES, END_EPISODE, ERROR_KINDS, RESET_TASK, STEP, AgentError, Call,
                                             _load_lanes, report_violation)
from mewa_bench.protocol.agent_in_process import InProcessAgent
from mewa_bench.protocol.agent_process import (AGENT_THREADS, DEFAULT_LOAD_TIME_LIMIT, DEFAULT_MEMORY_LIMIT,
                                               DEFAULT_TIME_LIMIT, IsolatedAgent, Launcher, with_agent_threads)

__all__ = ["AGENT_THREADS", "CALL_NAMES", "DEFAULT_LOAD_TIME_LIMIT", "DEFAULT_MEMORY_LIMIT", "DEFAULT_TIME_LIMIT",
           "END_EPISODE", "ERROR_KINDS", "RESET_TASK", "STEP", "AgentError", "AgentRunner", "Call", "InProcessAgent",
           "IsolatedAgent", "Launcher", "make_agent_runner", "report_violation", "with_agent_threads"]


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
