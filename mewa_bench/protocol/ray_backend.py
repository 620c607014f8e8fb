"""Evaluation units as Ray tasks (`evaluate --ray` / `--ray-address`): a local Ray instance or a cluster.

The driver (this process) splits the units into batches of `lanes` units, submits one Ray task per
batch (`runner._worker_play`, the same function the local `--jobs` pool runs) and records each
batch's units as its task finishes: the results file, logs and datasets are written by the driver,
incrementally and atomically, exactly as in a local run, and hold the same bytes (timing fields
aside) because every unit's seeds depend only on (suite, pair, seed, episode).

Faults: a task whose worker process dies (killed, out of memory, node lost) is retried by Ray
(`MAX_RETRIES`) from the start of its batch; only finished tasks are recorded, so nothing is counted
twice. An agent error inside a task is not retried: it stops the run with the runner's usual error.
A cluster that cannot be reached, or dies, stops the run with a clear error; what finished is kept
and `--resume` continues it, with or without Ray.

On a remote cluster every node needs this mewa-bench version installed and the agent file (and
checkpoint) at the same absolute path, e.g. on a shared file system.
"""

from __future__ import annotations

from contextlib import closing, contextmanager
from dataclasses import replace
from typing import Any, Callable, Iterator, Sequence

MAX_RETRIES = 3  # attempts after the first when a task's worker process dies
LOCAL = "local"  # EvalConfig.ray value: start a Ray instance on this machine
REACH_TIMEOUT = 5.0  # seconds to open a TCP connection to a cluster address before giving up


class RayUnavailable(RuntimeError):
    """Ray is not installed, or the cluster cannot be reached."""


def import_ray() -> Any:
    """The `ray` module, or a clear error naming the extra to install."""
    try:
        import ray
    except ImportError:
        raise RayUnavailable("--ray needs Ray: pip install 'mewa-bench[ray]'") from None
    return ray


def connect(address: str, num_cpus: int | None) -> bool:
    """Join the Ray cluster at `address` (or start a local one); True if this call started the connection.

    A process already connected to Ray (e.g. by the caller's own `ray.init`) keeps that connection."""
    ray = import_ray()
    if address != LOCAL:
        check_reachable(address)
    if ray.is_initialized():
        return False
    options: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
    try:
        if address == LOCAL:
            ray.init(address="local", num_cpus=num_cpus, _node_ip_address="127.0.0.1", **options)
        else:
            ray.init(address=address, **options)
    except Exception as e:  # ConnectionError, or Ray's own errors for a bad address
        raise RayUnavailable(f"cannot reach the Ray cluster at {address}: {e}") from None
    return True


@contextmanager
def session(address: str, num_cpus: int | None = None) -> Iterator[None]:
    """Connected to Ray for the block; a connection this opened is closed after it (a local instance stops)."""
    started = connect(address, num_cpus)
    try:
        yield
    finally:
        if started:
            import_ray().shutdown()


def check_reachable(address: str, timeout: float = REACH_TIMEOUT) -> None:
    """Fail fast on a host:port nobody listens on (Ray itself keeps retrying for minutes)."""
    import socket

    host, _, port = address.rpartition(":")
    if "://" in address or not host or not port.isdigit():
        return  # "auto", "ray://...": left to Ray
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as e:
        raise RayUnavailable(f"cannot reach the Ray cluster at {address}: {e.strerror or e}") from None


def play_batches(config: Any, batches: Sequence[list[tuple[int, int]]], collect: bool,
                 worker_play: Callable, on_finished: Callable[..., None], error_type: type[Exception]) -> None:
    """Run `worker_play(batch, config, collect)` as one Ray task per batch; `on_finished(*unit)` per unit."""
    from ray.exceptions import RayError, RayTaskError

    # Ray workers do not run in the driver's working directory: hand them absolute paths.
    config = replace(config, agent_path=config.agent_path.resolve(),
                     checkpoint=None if config.checkpoint is None else str(_absolute(config.checkpoint)))
    try:
        with closing(completed(worker_play, list(batches), config, collect)) as finished_batches:
            for _, finished in finished_batches:
                for unit in finished:
                    on_finished(*unit)
    except RayTaskError as e:  # the task raised: an agent error, reported as in a local run
        cause = e.cause if isinstance(getattr(e, "cause", None), BaseException) else e
        if isinstance(cause, error_type):
            raise cause from None
        raise error_type("crash", f"a Ray task failed: {cause}") from None
    except RayError as e:  # workers died more than MAX_RETRIES times, or the cluster went away
        raise error_type("crash", f"Ray could not finish a batch of units ({type(e).__name__}: {e}); "
                                  "the units finished so far are kept: run again with --resume") from None


def _absolute(path: str) -> Any:
    """A checkpoint path made absolute (left as is if it is a URL-like string)."""
    from pathlib import Path

    return path if "://" in path else Path(path).resolve()


def completed(function: Callable, items: list, *args: Any) -> Iterator[tuple[int, Any]]:
    """`function(item, *args)` for every item as Ray tasks (retried if a worker dies): (index, result) as
    each finishes. Closing the iterator early (an error, Ctrl-C) cancels what is still queued or running."""
    ray = import_ray()
    remote = ray.remote(num_cpus=1, max_retries=MAX_RETRIES, retry_exceptions=False)(function)
    refs = [remote.remote(item, *args) for item in items]
    index = {ref: i for i, ref in enumerate(refs)}
    pending = list(refs)
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield index[done[0]], ray.get(done[0])
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)


def ray_map(function: Callable, items: list, *args: Any, on_done: Callable[[Any], None] = lambda result: None) -> list:
    """`[function(item, *args) for item in items]` as Ray tasks, in item order; `on_done(result)` as each finishes."""
    results: dict[int, Any] = {}
    with closing(completed(function, items, *args)) as finished:
        for i, result in finished:
            results[i] = result
            on_done(result)
    return [results[i] for i in range(len(items))]
