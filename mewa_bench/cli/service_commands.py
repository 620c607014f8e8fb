"""The service's commands: `mewa-bench serve` (and its `token` and `worker` subcommands), `submit`, `status`.

Thin: they build settings, call `mewa_bench.service`, and print. The web stack is imported only
when one of them runs.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from mewa_bench.design.suites import DEFAULT_SUITE

console = Console()
DATA_DIR_HELP = "The service's data dir: uploads, job results, hidden suites, and the SQLite database by default."
DB_HELP = "Database URL (default: SQLite in the data dir), e.g. postgresql://USER:PASSWORD@HOST:5432/DB."
SERVER_HELP = "The server's URL, e.g. http://127.0.0.1:8000 (default: $MEWA_SERVER)."
TOKEN_HELP = "Your API token (default: $MEWA_TOKEN)."

serve_app = typer.Typer(help="Run the benchmark as a web service: API, leaderboards, datasets, submissions, workers.")
token_app = typer.Typer(no_args_is_help=True, help="API tokens of submitters (the server keeps only their hashes).")
serve_app.add_typer(token_app, name="token")


def _fail(error: Exception) -> None:
    """Print an error and exit with status 1."""
    console.print(f"[red]error:[/red] {escape(str(error))}")
    raise typer.Exit(1)


def _settings(data_dir: Path, db: str | None, **fields):
    """Settings from the command-line options (None: the default)."""
    from mewa_bench.service.settings import Settings

    return Settings(data_dir=data_dir, db_url=db, **{k: v for k, v in fields.items() if v is not None})


@serve_app.callback(invoke_without_command=True)
def serve(ctx: typer.Context,
          data_dir: Path = typer.Option(Path("mewa-service"), "--data-dir", help=DATA_DIR_HELP),
          db: str = typer.Option(None, "--db", help=DB_HELP),
          host: str = typer.Option("127.0.0.1", help="Address to listen on."),
          port: int = typer.Option(8000, help="Port to listen on."),
          workers: int = typer.Option(1, min=0, help="Evaluation worker processes (0: run them with `serve worker`)."),
          seeds: int = typer.Option(None, min=1, help="Rank runs with seeds 0..n-1 on every suite (default: the "
                                                       "protocol's seeds; fewer for a demo or test server)."),
          hidden: bool = typer.Option(True, "--hidden/--no-hidden", metavar="",
                                      help="Evaluate agents on the hidden test suites too."),
          lease_seconds: float = typer.Option(60.0, help="A job whose worker stops renewing it for this long is re-run."),
          max_attempts: int = typer.Option(3, min=1, help="Claims of a job before it is given up."),
          max_infra_retries: int = typer.Option(None, min=0, help="Hand-backs of a job after infrastructure faults "
                                                                   "(database, disk), not counted as attempts, before "
                                                                   "it fails (default 10)."),
          reserve_mb: float = typer.Option(None, min=0, help="Free space kept on the data dir's disk, in MB: an upload "
                                                             "that would go below it gets a 507 (default 256)."),
          rate_limit: int = typer.Option(None, min=0, help="Submissions per token and minute (default 60)."),
          daily_results: int = typer.Option(None, min=0, help="Results uploads per token and day (default 200)."),
          daily_agents: int = typer.Option(None, min=0, help="Agent submissions per token and day (default 20)."),
          max_results_mb: float = typer.Option(None, help="Largest results file in MB (default 16)."),
          max_agent_mb: float = typer.Option(None, help="Largest agent file in MB (default 1)."),
          max_checkpoint_mb: float = typer.Option(None, help="Largest checkpoint archive in MB (default 256)."),
          uploads_in_flight: int = typer.Option(None, min=1, help="Submissions received at once; more get a 503 "
                                                                   "with Retry-After (default 4)."),
          job_seconds: float = typer.Option(None, min=1, help="Wall-clock limit of an agent job's attempt, enforced "
                                                              "mid-call (default 21600)."),
          scratch_mb: float = typer.Option(None, help="An agent job's scratch directory on disk, in MB (default 1024)."),
          memory_mb: float = typer.Option(None, help="Memory of an agent's process and of its sandbox as a whole, in "
                                                     "MB (default 4096)."),
          rank_uploads: bool = typer.Option(False, "--rank-uploads", metavar="", help="Rank self-reported results uploads beside "
                                                                         "server-evaluated agents (default: unranked)."),
          log_level: str = typer.Option("info", help="debug, info, warning or error.")) -> None:
    """Serve the API (OpenAPI at /openapi.json, pages at /) with its evaluation workers, until Ctrl-C."""
    if ctx.invoked_subcommand is not None:
        return
    from mewa_bench.extras import MissingExtra

    try:
        from mewa_bench.service.server import run_server
        from mewa_bench.service.settings import Limits, MiB

        limits = {"rate_per_minute": rate_limit, "daily_results": daily_results, "daily_agents": daily_agents,
                  "results_bytes": None if max_results_mb is None else int(max_results_mb * MiB),
                  "agent_bytes": None if max_agent_mb is None else int(max_agent_mb * MiB),
                  "checkpoint_bytes": None if max_checkpoint_mb is None else int(max_checkpoint_mb * MiB),
                  "uploads_in_flight": uploads_in_flight}
        settings = _settings(data_dir, db, seeds=seeds, hidden=hidden, lease_seconds=lease_seconds,
                             max_attempts=max_attempts, limits=Limits(**{k: v for k, v in limits.items() if v is not None}),
                             job_seconds=job_seconds, rank_uploads=rank_uploads, max_infra_retries=max_infra_retries,
                             reserve_bytes=None if reserve_mb is None else int(reserve_mb * MiB),
                             scratch_bytes=None if scratch_mb is None else int(scratch_mb * MiB),
                             memory_bytes=None if memory_mb is None else int(memory_mb * MiB))
        console.print(f"mewa-bench service on http://{host}:{port} (data dir {settings.data_dir}, "
                      f"{'database ' + db.split('@')[-1] if db else 'SQLite in the data dir'}, {workers} worker(s))")
        run_server(settings, host, port, workers, log_level)
    except (MissingExtra, ValueError, OSError) as e:
        _fail(e)


@serve_app.command("worker")
def serve_worker(data_dir: Path = typer.Option(Path("mewa-service"), "--data-dir", help=DATA_DIR_HELP),
                 db: str = typer.Option(None, "--db", help=DB_HELP),
                 lease_seconds: float = typer.Option(60.0, help="Lease length of a claimed job."),
                 job_seconds: float = typer.Option(None, min=1, help="Wall-clock limit of an agent job's attempt "
                                                                     "(default 21600)."),
                 memory_mb: float = typer.Option(None, help="Memory of an agent's process and of its sandbox as a "
                                                            "whole, in MB (default 4096)."),
                 scratch_mb: float = typer.Option(None, help="An agent job's scratch directory on disk, in MB "
                                                             "(default 1024)."),
                 max_jobs: int = typer.Option(None, min=1, help="Stop after this many jobs (default: run until stopped).")
                 ) -> None:
    """Run one evaluation worker against a server's database and data dir (for more workers, or other machines)."""
    import logging

    from mewa_bench.service.db import make_engine, migrate
    from mewa_bench.service.worker import run_worker

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s[%(process)d] %(levelname)s %(message)s")
    from mewa_bench.service.app import make_data_dir
    from mewa_bench.service.settings import MiB

    settings = _settings(data_dir, db, lease_seconds=lease_seconds, job_seconds=job_seconds,
                         memory_bytes=None if memory_mb is None else int(memory_mb * MiB),
                         scratch_bytes=None if scratch_mb is None else int(scratch_mb * MiB))
    try:
        make_data_dir(settings)
        engine = make_engine(settings.database_url)
        migrate(engine)
        engine.dispose()
        run_worker(settings, max_jobs=max_jobs)
    except (ValueError, OSError) as e:
        _fail(e)


def _with_session(data_dir: Path, db: str | None, action):
    """Run `action(session)` in one transaction on the migrated database."""
    from mewa_bench.service.db import make_engine, migrate, session_factory, transaction

    from mewa_bench.service.app import make_data_dir

    settings = _settings(data_dir, db)
    make_data_dir(settings)
    engine = make_engine(settings.database_url)
    try:
        migrate(engine)
        with transaction(session_factory(engine)) as session:
            return action(session)
    finally:
        engine.dispose()


@token_app.command("create")
def token_create(name: str = typer.Argument(..., metavar="NAME", help="The submitter's name."),
                 data_dir: Path = typer.Option(Path("mewa-service"), "--data-dir", help=DATA_DIR_HELP),
                 db: str = typer.Option(None, "--db", help=DB_HELP),
                 rate_limit: int = typer.Option(None, min=0, help="Submissions per minute (default: the server's)."),
                 daily_results: int = typer.Option(None, min=0, help="Results uploads per day (default: the server's)."),
                 daily_agents: int = typer.Option(None, min=0, help="Agent submissions per day (default: the server's).")
                 ) -> None:
    """Make an API token for a submitter and print it (only its hash is stored: it cannot be shown again)."""
    from mewa_bench.service.tokens import TokenError, create_token

    try:
        token = _with_session(data_dir, db, lambda s: create_token(s, name, rate_limit, daily_results, daily_agents))
    except (TokenError, ValueError, OSError) as e:
        _fail(e)
    print(token)


@token_app.command("revoke")
def token_revoke(name: str = typer.Argument(..., metavar="NAME", help="The submitter's name."),
                 data_dir: Path = typer.Option(Path("mewa-service"), "--data-dir", help=DATA_DIR_HELP),
                 db: str = typer.Option(None, "--db", help=DB_HELP)) -> None:
    """Revoke a submitter's token (their submissions stay)."""
    from mewa_bench.service.tokens import TokenError, revoke_token

    try:
        _with_session(data_dir, db, lambda s: revoke_token(s, name))
    except (TokenError, ValueError, OSError) as e:
        _fail(e)
    console.print(f"revoked the token of {escape(name)}")


@token_app.command("list")
def token_list(data_dir: Path = typer.Option(Path("mewa-service"), "--data-dir", help=DATA_DIR_HELP),
               db: str = typer.Option(None, "--db", help=DB_HELP)) -> None:
    """The submitters and their limits (never the tokens)."""
    import time

    from mewa_bench.service.tokens import list_tokens

    table = Table("name", "created", "revoked", "rate/min", "results/day", "agents/day")
    for t in _with_session(data_dir, db, list_tokens):
        table.add_row(escape(t.name), time.strftime("%Y-%m-%d %H:%M", time.gmtime(t.created)), "yes" if t.revoked else "",
                      *("default" if v is None else str(v) for v in (t.rate_per_minute, t.daily_results, t.daily_agents)))
    console.print(table)


@serve_app.command("show")
def serve_show(submission_id: int = typer.Argument(..., metavar="ID", help="The submission's id."),
               data_dir: Path = typer.Option(Path("mewa-service"), "--data-dir", help=DATA_DIR_HELP),
               db: str = typer.Option(None, "--db", help=DB_HELP),
               output: bool = typer.Option(False, "--output", metavar="", help="Add what the agent printed, per job and attempt "
                                                                   "(hidden suites' too).")) -> None:
    """The admin's view of a submission, as JSON: its hidden-suite jobs whole (errors, unit counts, every score)."""
    from sqlalchemy import select

    from mewa_bench.service.models import Job, Submission
    from mewa_bench.service.routes.submissions import describe, job_output

    def full(session):
        """The whole record, or None."""
        submission = session.get(Submission, submission_id)
        if submission is None:
            return None
        record = describe(session, submission, full=True)
        if output:
            settings = _settings(data_dir, db)
            record["output"] = {job.board: job_output(settings, job.id) for job in
                                session.scalars(select(Job).where(Job.submission_id == submission_id))}
        return record

    try:
        record = _with_session(data_dir, db, full)
    except (ValueError, OSError) as e:
        _fail(e)
    if record is None:
        _fail(LookupError(f"submission {submission_id} does not exist in this service's database"))
    print(json.dumps(record, indent=1))


def submit(file: Path = typer.Argument(..., metavar="FILE", exists=True, dir_okay=False,
                                       help="A results file (.json) of `mewa-bench evaluate`, or an agent file (.py)."),
           server: str = typer.Option(..., envvar="MEWA_SERVER", help=SERVER_HELP),
           token: str = typer.Option(None, help=TOKEN_HELP),
           suite: str = typer.Option(DEFAULT_SUITE, help="Agents: the public suite to evaluate on (and its hidden twin)."),
           name: str = typer.Option(None, help="Agents: the name on the boards (default: from the file name)."),
           checkpoint: Path = typer.Option(None, help="Agents: a .tar(.gz), or a file or folder to pack; unpacked "
                                                      "beside the agent file on the server."),
           agent_arg: list[str] = typer.Option([], "--agent-arg", help="Agents: key=value passed to make_agent (repeatable)."),
           algorithm: str = typer.Option(None, help="The algorithm this run is a training run of: your runs under one "
                                                    "name share a row of the boards' algorithms table (default: "
                                                    "run.json's beside the file, else a one-run algorithm)."),
           wait: bool = typer.Option(False, "--wait", metavar="", help="Wait until it is scored, rejected or failed."),
           timeout: float = typer.Option(None, help="With --wait: give up waiting after this many seconds."),
           retry_seconds: float = typer.Option(120.0, min=0, help="Keep resending through connection errors and "
                                                                  "503s for this long (safe: the submission carries "
                                                                  "an Idempotency-Key).")) -> None:
    """Submit a results file (re-scored by the server) or an agent (evaluated in its sandbox) to a server."""
    from mewa_bench.service import client

    args = {}
    for item in agent_arg:
        key, sep, value = item.partition("=")
        if not sep:
            _fail(ValueError(f"--agent-arg {item!r}: expected key=value"))
        args[key] = value
    try:
        answer = client.submit(server, file, token, suite, name, checkpoint, args, algorithm, retry_seconds)
    except (client.ServiceError, OSError, ValueError) as e:  # ValueError: a run.json that cannot be read
        _fail(e)
    again = " (it had arrived before: its answer had been lost)" if answer.get("resent") else ""
    console.print(f"submission [bold]{answer['id']}[/bold] accepted ({answer['status']}){again}")
    if wait:
        _print_status(client.wait(server, answer["id"], timeout))
    else:
        console.print(f"follow it with: mewa-bench status {answer['id']} --server {server}")


def status(submission_id: int = typer.Argument(..., metavar="ID", help="The submission's id."),
           server: str = typer.Option(..., envvar="MEWA_SERVER", help=SERVER_HELP),
           wait: bool = typer.Option(False, "--wait", metavar="", help="Wait until it is scored, rejected or failed."),
           timeout: float = typer.Option(None, help="With --wait: give up waiting after this many seconds.")) -> None:
    """A submission's status on a server: its jobs, their progress, and its scores once done."""
    from mewa_bench.service import client

    try:
        current = client.wait(server, submission_id, timeout) if wait else client.status(server, submission_id)
    except client.ServiceError as e:
        _fail(e)
    _print_status(current)
    if current["status"] in ("rejected", "failed"):
        raise typer.Exit(1)


def _print_status(current: dict) -> None:
    """A submission's status, jobs and scores as a table."""
    colour = {"done": "green", "rejected": "red", "failed": "red"}.get(current["status"], "yellow")
    console.print(f"submission {current['id']} ({current['kind']}, {escape(current['agent'])}, {current['suite']}): "
                  f"[{colour}]{current['status']}[/{colour}]")
    if current.get("reason"):
        console.print(f"reason: {escape(current['reason'])}")
    table = Table("board", "state", "units", "attempts", "mean score", "adaptability")
    for job in current["jobs"]:
        scores = current["scores"].get(job["board"])
        units = f"{job['units_done']}/{job['units_total']}" if job["units_total"] else ""
        if job["units_total"] is None and job.get("progress") is not None:  # a hidden suite: its size is not shown
            units = f"{100 * job['progress']:.0f}%"
        table.add_row(job["board"] + (" (hidden)" if job["hidden"] else ""), job["state"], units, str(job["attempts"]),
                      "" if scores is None else f"{scores['mean']['mean']:.4f}",
                      "" if scores is None else f"{scores['adaptability']['mean']:.4f}")
    console.print(table)
    for job in current["jobs"]:
        if job.get("note"):
            console.print(f"{job['board']}: {escape(job['note'])}")
