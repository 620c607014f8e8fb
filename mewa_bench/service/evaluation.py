"""An agent job: evaluate a submitted agent on one board (a public suite or a hidden one) in the sandbox.

The job's results file lives in `jobs/<id>/results.json` of the data dir, outside everything the
sandbox shows the agent; the sandboxed evaluation resumes from it (`resume=True`), so a job claimed
again after a crash continues from its last finished unit. Failures are sorted into the agent's
fault (`AgentRejected`: an exception, an invalid action, a timeout, a sandbox rule broken) and the
service's (anything else, retried).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from mewa_bench.service.settings import Settings


class AgentRejected(Exception):
    """The submission is at fault; the message is the reason shown on it."""


@dataclass(frozen=True)
class AgentJob:
    """What one evaluation needs."""

    agent_file: Path
    board: str
    hidden: bool
    seeds: tuple[int, ...]
    name: str
    agent_args: dict[str, str]
    out: Path
    scratch: Path
    output_log: Path | None = None  # the agent's stdout and stderr, capped


def suite_of(settings: Settings, board: str, hidden: bool) -> str | Path:
    """The suite a board is played on: a public name, or a hidden suite's file (generated the first time)."""
    if not hidden:
        return board
    from mewa_bench.service.hidden import hidden_suites

    return hidden_suites(settings.data_dir, [board])[board]


def run_agent_job(settings: Settings, job: AgentJob, progress: Callable[[int, int], None],
                  cancel: Callable[[], str | None] | None = None) -> dict[str, Any]:
    """Evaluate in the sandbox; returns the results. Raises AgentRejected with the reason, SandboxCancelled when
    `cancel` stopped it, or another error."""
    from mewa_bench.protocol.runner import EvaluationError
    from mewa_bench.service.sandbox import (SandboxLimits, SandboxViolation, sandbox_available,
                                            sandboxed_evaluate)

    problem = sandbox_available()
    if problem is not None:
        raise RuntimeError(f"this server cannot sandbox agents: {problem}")
    suite = suite_of(settings, job.board, job.hidden)
    try:
        return sandboxed_evaluate(job.agent_file, suite, job.out, scratch=job.scratch, seeds=job.seeds,
                                  progress=progress, agent_args=job.agent_args, name=job.name,
                                  private=(settings.data_dir,), output_log=job.output_log, cancel=cancel,
                                  limits=SandboxLimits(wall_seconds=settings.job_seconds,
                                                       memory_bytes=settings.memory_bytes,
                                                       scratch_bytes=settings.scratch_bytes,
                                                       output_bytes=settings.output_bytes))
    except SandboxViolation as e:
        raise AgentRejected(f"sandbox rule broken ({e.rule}): {_without_paths(str(e), settings)}") from None
    except EvaluationError as e:
        raise AgentRejected(f"the agent failed ({e.kind}): {_without_paths(str(e), settings)}") from None


def _without_paths(message: str, settings: Settings) -> str:
    """Reasons are shown publicly: the server's own data-dir path becomes `<data dir>`."""
    return message.replace(str(settings.data_dir), "<data dir>")
