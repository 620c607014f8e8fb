"""The agent process: load the agent file, then answer the parent's requests until it closes the pipe.

It runs `_child_main` in a fresh interpreter (`agent_process.IsolatedAgent` starts it, directly or
through a sandbox's entry), with its address space capped (RLIMIT_AS) and no core dumps. Each call
of a batch gets its own time limit there (`agent_calls._call_guard`); a failed call goes back as an
error reply, after which the parent ends this process.
"""

from __future__ import annotations

import pickle
import resource
import signal
import sys
from pathlib import Path

from mewa_bench.protocol.agent import AgentLoadError
from mewa_bench.protocol.agent_calls import (_BATCH, _VIOLATIONS, AgentError, _Lanes, _load_lanes, _raise_call_timeout,
                                             _VectorCalls, _violation)
from mewa_bench.protocol.agent_pipe import _BATCHED, _READY, _error_reply, _FrameReader, _reply_token, _write_frame

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


def _limit_address_space(memory_limit: int) -> None:
    """Cap this process's address space at `memory_limit` bytes (soft and hard, so the agent cannot lift it)."""
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = memory_limit if hard == resource.RLIM_INFINITY else min(memory_limit, hard)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
