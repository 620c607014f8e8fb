"""Running an agent file's agents in this process (--in-process, for debugging), and what both runners share.

`_FailureTracking` is the runners' common state: the first AgentError, after which every call
raises it again, and closing. `InProcessAgent` answers the calls directly through `agent_calls`;
`agent_process.IsolatedAgent` sends them to a child process.
"""

from __future__ import annotations

from types import TracebackType
from typing import Any, Self, Sequence

from mewa_bench.protocol.agent import Transition
from mewa_bench.protocol.agent_calls import (_END_EPISODE, _OBSERVE, _RESET_TASK, _STEP, AgentError, Call, _columns,
                                             _Lanes, _VectorCalls)

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
