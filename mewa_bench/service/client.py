"""The client side: `mewa-bench submit`, `mewa-bench status` and the server's dataset catalog.

Errors from the server keep its reason: `ServiceError` carries the HTTP status and the JSON
`detail` the API answers with. Requests are retried through connection errors and 503s (a busy
server, a database outage) with a growing pause, or the server's Retry-After, for up to
RETRY_SECONDS; a submission carries an `Idempotency-Key` made once per `submit`, so sending it
again after an answer that never arrived returns the submission the first send made.
"""

from __future__ import annotations

import io
import os
import secrets
import tarfile
import time
from pathlib import Path
from typing import Any, Callable

from mewa_bench.design.suites import DEFAULT_SUITE
from mewa_bench.extras import require

TOKEN_ENV = "MEWA_TOKEN"
TIMEOUT = 300.0
FINAL = ("done", "rejected", "failed")


class ServiceError(RuntimeError):
    """The server refused a request, or could not be reached; the message says why."""

    def __init__(self, message: str, status: int | None = None, code: str | None = None) -> None:
        super().__init__(message)
        self.status, self.code = status, code


def _httpx():
    """The httpx module (the service extra)."""
    return require("httpx", "service", "talking to a mewa-bench server")


def _url(server: str, path: str) -> str:
    """A path on the server."""
    return server.rstrip("/") + path


def _answer(response: Any) -> Any:
    """The JSON of a 2xx answer, else a ServiceError with the server's reason."""
    if response.is_success:
        return response.json()
    try:
        body = response.json()
        code, detail = body.get("error"), body.get("detail", response.text)
    except ValueError:
        code, detail = None, response.text.strip() or response.reason_phrase
    raise ServiceError(f"{response.request.url}: HTTP {response.status_code}: {detail}", response.status_code, code)


RETRY_SECONDS = 120.0  # how long a request is retried through connection errors and 503s
FIRST_PAUSE, LONGEST_PAUSE = 0.5, 8.0


def _request(method: str, url: str, retry_seconds: float = RETRY_SECONDS, **kwargs: Any) -> Any:
    """One request, retried through connection errors and 503s for up to `retry_seconds` (only requests that are
    safe to repeat are sent here: reads, and submissions with an Idempotency-Key); its JSON answer, or a
    ServiceError with the reason."""
    httpx = _httpx()
    deadline, pause = time.monotonic() + retry_seconds, FIRST_PAUSE
    while True:
        try:
            response = httpx.request(method, url, timeout=TIMEOUT, **kwargs)
        except httpx.TransportError as e:
            if time.monotonic() + pause > deadline:
                raise ServiceError(f"{url}: cannot reach the server: {e}") from None
            time.sleep(pause)
            pause = min(LONGEST_PAUSE, pause * 2)
            continue
        if response.status_code == 503:
            wait = _retry_after(response, pause)
            if time.monotonic() + wait <= deadline:
                time.sleep(wait)
                pause = min(LONGEST_PAUSE, pause * 2)
                continue
        return _answer(response)


def _retry_after(response: Any, default: float) -> float:
    """The pause a 503 asks for (its Retry-After in seconds, at most 30), else `default`."""
    try:
        return min(30.0, max(0.0, float(response.headers["retry-after"])))
    except (KeyError, ValueError):
        return default


def token_or_env(token: str | None) -> str | None:
    """The token given, else $MEWA_TOKEN."""
    return token or os.environ.get(TOKEN_ENV) or None


def checkpoint_archive(path: Path) -> tuple[str, bytes]:
    """A checkpoint to upload: a .tar/.tar.gz as it is; a file or folder packed as .tar.gz (beside agent.py)."""
    path = Path(path)
    if path.is_file() and path.name.endswith((".tar", ".tar.gz", ".tgz")):
        return path.name, path.read_bytes()
    if not path.exists():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        if path.is_dir():
            for member in sorted(path.rglob("*")):
                if member.is_file() and member.name != "agent.py":
                    tar.add(member, arcname=member.relative_to(path).as_posix())
        else:
            tar.add(path, arcname=path.name)
    return f"{path.name}.tar.gz", buffer.getvalue()


def submit(server: str, file: Path, token: str | None, suite: str = DEFAULT_SUITE, name: str | None = None,
           checkpoint: Path | None = None, agent_args: dict[str, str] | None = None,
           algorithm: str | None = None, retry_seconds: float = RETRY_SECONDS) -> dict[str, Any]:
    """Upload a results file (.json) or an agent (.py, with an optional checkpoint); returns the server's answer.
    `algorithm`: what the run is a training run of (default: the algorithm of a run.json beside the file, if any)."""
    from mewa_bench.protocol.config import agent_name
    from mewa_bench.protocol.run_info import RUN_FILE, read_run_info

    file = Path(file)
    if algorithm is None and (file.parent / RUN_FILE).is_file():
        algorithm = read_run_info(file.parent).algorithm
    form: dict[str, Any] = {} if algorithm is None else {"algorithm": algorithm}
    token = token_or_env(token)
    if token is None:
        raise ServiceError(f"an API token is needed to submit: --token TOKEN or ${TOKEN_ENV}")
    headers = {"Authorization": f"Bearer {token}", "Idempotency-Key": f"mewa-{secrets.token_hex(16)}"}
    if file.suffix == ".json":
        files = {"file": (file.name, file.read_bytes(), "application/json")}
        return _request("POST", _url(server, "/api/submissions/results"), retry_seconds, files=files, data=form,
                        headers=headers)
    if file.suffix != ".py":
        raise ServiceError(f"{file}: submit a results file (.json) or an agent file (.py)")
    files: list[tuple[str, tuple[str, bytes, str]]] = [("agent", (file.name, file.read_bytes(), "text/x-python"))]
    if checkpoint is not None:
        archive_name, data = checkpoint_archive(checkpoint)
        files.append(("checkpoint", (archive_name, data, "application/gzip")))
    data: dict[str, Any] = {"suite": suite, "name": name or agent_name(file), **form}
    if agent_args:
        data["agent_arg"] = [f"{k}={v}" for k, v in agent_args.items()]
    return _request("POST", _url(server, "/api/submissions/agent"), retry_seconds, files=files, data=data,
                    headers=headers)


def status(server: str, submission_id: int) -> dict[str, Any]:
    """A submission's status, jobs and scores."""
    return _request("GET", _url(server, f"/api/submissions/{submission_id}"))


def wait(server: str, submission_id: int, timeout: float | None = None, poll: float = 1.0,
         on_update: Callable[[dict[str, Any]], None] = lambda s: None) -> dict[str, Any]:
    """Poll until the submission is done, rejected or failed (or `timeout` seconds pass); returns its status."""
    deadline = None if timeout is None else time.monotonic() + timeout
    while True:
        current = status(server, submission_id)
        on_update(current)
        if current["status"] in FINAL or (deadline is not None and time.monotonic() > deadline):
            return current
        time.sleep(poll)


def server_catalog(server: str) -> dict[str, Any]:
    """The server's dataset catalog (its archives' URLs point at the server)."""
    from mewa_bench.datasets.catalog import validate_catalog

    return validate_catalog(_request("GET", _url(server, "/api/datasets")), f"{server.rstrip('/')}/api/datasets")
