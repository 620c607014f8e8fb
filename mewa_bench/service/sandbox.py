"""Sandboxed evaluation of submitted agents: the protocol's evaluation with the agent process in bubblewrap.

The trusted evaluator (`protocol.runner.evaluate`) runs in the server's worker process: it holds the
env, the suite and the results file. Only the agent's process (`protocol.isolation.IsolatedAgent`,
which talks to it over two pipes) is started inside the sandbox, through a `Launcher`:

- bwrap: new network, pid, IPC, UTS (and cgroup) namespaces; a new mount namespace that shows only
  /usr (system libraries), the Python install and virtual env, the mewa_bench package, the agent's
  directory and checkpoint (all read-only), the scratch directory (read-write), fresh /proc and
  /dev, size-limited /tmp and /dev/shm, the rest of the root read-only. The data dir, the hidden
  suites and the results are not in it at all. `--die-with-parent`, `--new-session`.
- an unprivileged user: uid/gid 65534 (nobody) with no capabilities, no supplementary groups and
  no_new_privs. As root, bwrap runs without a user namespace and `setpriv` drops to 65534 (a real
  unprivileged uid, so RLIMIT_NPROC is enforced; root's processes are exempt from it); as any other
  user, bwrap maps that user to 65534 in a new user namespace (`--disable-userns` forbids nesting).
- the agent process: `python -I -B` (isolated mode: no current directory, script directory, user
  site or PYTHON* variables on its import path; no bytecode written), started in / (read-only), so
  everything it imports before the agent loads comes from the read-only Python install and
  package; it confines itself (below), then changes to the scratch directory and loads the agent.
- a control group per sandbox (`service.cgroups`, v1 or v2, made under the server's own group):
  memory and processes of the whole process tree; where none can be made, the per-process rlimits
  below are all there is (`cgroups.cgroup_support` says which), and the process rlimit, which counts
  the sandbox user's processes everywhere, is then shared by the sandboxes that run at once.
- rlimits set by the agent process on itself before the agent loads: address space (the protocol's
  memory limit), CPU time, processes + threads, file size, open files, no core dumps.
- seccomp (x86_64, aarch64): socket() of any family but AF_UNIX fails with EACCES; no new
  namespaces (unshare, setns, clone with CLONE_NEW*), no io_uring, bpf, perf_event_open,
  userfaultfd, ptrace or keyrings.
- an audit hook that names what the agent tried: opening a network socket or resolving a name,
  writing outside the scratch directory and /tmp, and opening or listing anything in the private
  places (`private`: the hidden suite file, the results file, and whatever the caller adds; the
  service adds its whole data dir) other than what the sandbox shows it (its own directory and
  checkpoint, which may lie in the data dir, the Python install, its scratch directory), after
  resolving symlinks. The call fails with kind "sandbox" (`isolation.report_violation`) even if the
  agent catches the PermissionError it gets. The hook only explains; the kernel enforces the rules
  (the private places are not in the sandbox at all; an agent can reach past Python with ctypes).
  Reads elsewhere outside the sandbox's mounts are not reported: libraries probe /sys and /etc.
- a watchdog thread (`service.watchdog`): the wall-clock limit of the whole evaluation, the scratch
  directory's size, the group's out-of-memory kills and the caller's cancel, checked while units run;
  it kills every process of the sandbox mid-call.
- output: the agent's stdout and stderr go to a log of its own, capped (`service.agent_output`).
- time: the protocol's per-call limit, the CPU-time rlimit, and the watchdog's wall-clock limit.

A resumed evaluation continues from the units in the results file (`evaluate(resume=True)`);
the scores are byte for byte those of `mewa-bench evaluate` with the same agent file and seeds.

This file is longer than 500 lines because the sandbox is one set of rules, read and checked together:
the list above, the bwrap command that mounts them and the confinement the agent process applies to
itself (rlimits, seccomp, the audit hook) before the agent loads.
"""

from __future__ import annotations

import ctypes
import errno
import functools
import json
import os
import platform
import re
import resource
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ClassVar

from mewa_bench.protocol.isolation import (DEFAULT_MEMORY_LIMIT, DEFAULT_TIME_LIMIT, Launcher, report_violation,
                                           with_agent_threads)
from mewa_bench.service.agent_output import OutputCapture
from mewa_bench.service.cgroups import ROOT, Group, cgroup_support, sweep_stale
from mewa_bench.service.watchdog import Stop, Watchdog

SANDBOX_UID = 65534  # nobody
_SETTINGS_VARIABLE = "MEWA_SANDBOX"  # carries the limits into the agent process, which removes it
_PYTHON_FLAGS = ("-I", "-B")  # isolated mode (a clean import path, no PYTHON* variables), no bytecode written
_ENTRY = ("import sys; sys.path.append({root!r}); "
          "from mewa_bench.service.sandbox import confined_child_main; confined_child_main()")
_PASSED_ENVIRONMENT = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
_SYSTEM_DIRS = ("/bin", "/sbin", "/lib", "/lib32", "/lib64", "/libx32")  # beside /usr: symlinks into it on Debian


@dataclass(frozen=True)
class SandboxLimits:
    """What a sandboxed agent may use. The first two are the protocol's, recorded in the results file."""

    call_seconds: float | None = DEFAULT_TIME_LIMIT  # wall time of one agent call (act, observe, ...)
    memory_bytes: int = DEFAULT_MEMORY_LIMIT  # address space of the agent process (RLIMIT_AS)
    cpu_seconds: int = 2 * 3600  # CPU time of the agent process over the evaluation (RLIMIT_CPU)
    processes: int = 64  # processes and threads of the sandbox user (RLIMIT_NPROC)
    file_bytes: int = 256 << 20  # the largest file the agent may write (RLIMIT_FSIZE)
    open_files: int = 1024  # RLIMIT_NOFILE
    tmp_bytes: int = 64 << 20  # size of /tmp and of /dev/shm (memory-backed)
    wall_seconds: float | None = 6 * 3600  # the whole sandboxed_evaluate call, enforced mid-call by the watchdog
    group_memory_bytes: int | None = None  # memory of the whole process tree (its control group); None: memory_bytes
    scratch_bytes: int = 1 << 30  # the scratch directory's size on disk (removed files kept open count), polled
    output_bytes: int = 1 << 20  # the agent's stdout and stderr kept in its log (output_log)


SANDBOXES_SHARING_THE_UID = 32  # the per-uid process rlimit, in sandboxes' worth, when a group holds each one


class SandboxCancelled(RuntimeError):
    """The caller's `cancel` stopped the evaluation (e.g. the job's lease was lost); the message says why."""


class SandboxViolation(RuntimeError):
    """The agent broke a sandbox rule; `rule` names it and the message says what it did and where.

    Rules: network, filesystem, cpu_time, processes, file_size, wall_time, memory (the whole process
    tree's), scratch_size. Other agent failures
    (exceptions, invalid actions, per-call timeouts, memory) stay `protocol.runner.EvaluationError`s.
    """

    kind = "sandbox"

    def __init__(self, rule: str, message: str) -> None:
        super().__init__(message)
        self.rule = rule


def sandbox_available() -> str | None:
    """None if agents can be sandboxed here (bwrap works), else why not."""
    return _probe()


def sandboxed_evaluate(agent_file: Path, suite: str | Path, out: Path, *, scratch: Path,
                       checkpoint_dir: Path | None = None, seeds: tuple[int, ...] | None = None,
                       limits: SandboxLimits | None = None,
                       progress: Callable[[int, int], None] = lambda done, total: None,
                       agent_args: dict[str, str] | None = None, pairs: tuple[int, ...] | None = None,
                       name: str | None = None, lanes: int | None = None,
                       private: tuple[Path, ...] = (), output_log: Path | None = None,
                       cancel: Callable[[], str | None] | None = None) -> dict[str, Any]:
    """Evaluate `agent_file` on `suite` with the agent in the sandbox; continue `out` if it holds part of this run.

    `scratch` is the agent's only writable directory (created; HOME and TMPDIR point there);
    `checkpoint_dir` (read-only) is given to the agent as its checkpoint argument; `agent_args`,
    `pairs`, `name` and `lanes` are evaluate's (lanes change nothing in the results); `private`:
    places whose reading (beside the suite file and `out`) fails the run as a sandbox violation; `output_log`:
    where the agent's stdout and stderr go, capped at `limits.output_bytes` (None: this process's own);
    `cancel`: polled while the agent runs, a reason stops the sandbox at once (SandboxCancelled). Returns the
    results (also in `out`). Raises SandboxViolation when the agent breaks a sandbox rule,
    `protocol.runner.EvaluationError` when it fails otherwise, RuntimeError if there is no sandbox here.
    """
    from mewa_bench.design.suites import ALL_SUITES, resolve, shipped_path
    from mewa_bench.protocol.config import EvalConfig
    from mewa_bench.protocol.runner import EvaluationError, evaluate

    problem = sandbox_available()
    if problem is not None:
        raise RuntimeError(f"cannot sandbox the agent: {problem}")
    limits = limits or SandboxLimits()
    agent_file, out, scratch = Path(agent_file).absolute(), Path(out).absolute(), Path(scratch).absolute()
    checkpoint = None if checkpoint_dir is None else Path(checkpoint_dir).absolute()
    if not agent_file.is_file():
        raise FileNotFoundError(f"agent file {agent_file} does not exist")
    _prepare_scratch(scratch)
    readable = [agent_file.parent] + ([checkpoint] if checkpoint is not None else [])
    visible = [*_python_dirs(), *readable, scratch]
    suite_file = Path(resolve(suite)).resolve()
    shipped = suite_file in {shipped_path(n).resolve() for n in ALL_SUITES}
    if not shipped:
        _check_hidden(suite_file, "the suite file", visible)
    _check_hidden(out, "the results file", visible)
    if os.geteuid() == 0 and not agent_file.stat().st_mode & 0o004:
        raise PermissionError(f"{agent_file} is not readable by the sandbox user (uid {SANDBOX_UID}): make it "
                              f"world-readable (chmod o+r), as everything the agent loads must be")
    kept_from_agent = [out, *(Path(p).absolute() for p in private)] + ([] if shipped else [suite_file])
    group = _make_group(limits)
    output = None
    try:  # the group and the output pipe are released however this ends, set-up failures included
        output = None if output_log is None else OutputCapture(Path(output_log), limits.output_bytes)
        launcher = sandbox_launcher(readable, scratch, limits, kept_from_agent, group=group,
                                    output=None if output is None else output.fd)
        config = EvalConfig(agent_path=agent_file, suite=str(suite), seeds=seeds, out=out, name=name,
                            agent_args=dict(agent_args or {}),
                            checkpoint=None if checkpoint is None else str(checkpoint),
                            time_limit=limits.call_seconds, memory_limit=limits.memory_bytes, resume=True,
                            pairs=pairs, launcher=launcher, **({} if lanes is None else {"lanes": lanes}))
        watchdog = Watchdog(functools.partial(_kill_sandbox, group, scratch), wall_seconds=limits.wall_seconds,
                            scratch=scratch, scratch_bytes=limits.scratch_bytes, memory_bytes=_group_memory(limits),
                            oom_kills=None if group is None else group.oom_kills, cancel=cancel,
                            pids=functools.partial(_sandbox_pids, group, scratch))
        units: list[tuple[int, int]] = [(0, 0)]

        def watched(done: int, total: int) -> None:
            units[0] = (done, total)
            if watchdog.stop is not None:
                raise _stopped(watchdog.stop, agent_file, units[0], out)
            progress(done, total)

        try:
            with watchdog:
                results, _ = evaluate(config, progress=watched)
        except EvaluationError as e:
            stop = watchdog.stop or watchdog.check_memory()  # an out-of-memory kill is the cause, whatever followed
            if stop is not None:
                raise _stopped(stop, agent_file, units[0], out) from None
            raise _explained(e, limits, visible) from None
    finally:
        _kill_sandbox(group, scratch)
        if group is not None:
            group.remove()
        if output is not None:
            output.close()
    return results


def sandbox_isolation() -> str:
    """What holds the sandbox as a whole on this machine (a control group, or the rlimits' fallback)."""
    return cgroup_support(ROOT).describe()


def _group_memory(limits: SandboxLimits) -> int:
    """The memory limit of the sandbox's whole process tree."""
    return limits.memory_bytes if limits.group_memory_bytes is None else limits.group_memory_bytes


def _make_group(limits: SandboxLimits) -> Group | None:
    """A control group for one sandbox, or None where this machine gives none (the rlimits then hold alone)."""
    support = cgroup_support(ROOT)
    if support.version == 0:
        return None
    _sweep_once(support.version)
    return Group.make(ROOT, support.version, (_group_memory(limits), limits.processes))


@functools.lru_cache(maxsize=1)
def _sweep_once(version: int) -> None:
    """Once per process: remove the groups that killed workers left behind."""
    sweep_stale(ROOT, version)


def _stopped(stop: Stop, agent_file: Path, units: tuple[int, int], out: Path) -> Exception:
    """The error of a sandbox the watchdog stopped."""
    done, total = units
    if stop.rule == "cancelled":
        return SandboxCancelled(f"agent {agent_file.name}: {stop.message}")
    return SandboxViolation(stop.rule, f"agent {agent_file.name}: {stop.message} ({done} of {total} units were done; "
                                       f"they are kept in {out})")


def _sandbox_pids(group: Group | None, scratch: Path) -> set[int]:
    """The sandbox's processes: its group's, or (without one) those started with its scratch as HOME."""
    if group is not None:
        return group.pids()
    marker, found = f"HOME={scratch}".encode(), set()
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and marker in (entry / "environ").read_bytes().split(b"\0"):
                found.add(int(entry.name))
        except OSError:
            pass  # gone meanwhile, or not ours
    return found


def _kill_sandbox(group: Group | None, scratch: Path) -> None:
    """SIGKILL every process of the sandbox."""
    if group is not None:
        group.kill()
        return
    for pid in _sandbox_pids(None, scratch):
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass  # gone meanwhile


def sandbox_launcher(readable: list[Path], scratch: Path, limits: SandboxLimits,
                     private: list[Path] | None = None, group: Group | None = None,
                     output: int | None = None) -> Launcher:
    """The Launcher that starts the agent process in bwrap, seeing `readable` (read-only) and `scratch`; reading
    `private` (outside those) is reported as a violation; its first process joins `group`; `output` takes its
    stdout and stderr."""
    shown = [*_python_dirs(), *readable]
    prefix, layout = _bwrap_command(shown, scratch, limits)
    if group is not None:
        prefix = [*group.join_prefix(), *prefix]
    # RLIMIT_NPROC counts every process of the sandbox user, in every sandbox at once; with a group, whose pids
    # limit is this sandbox's own, the rlimit is only a backstop that leaves room for the other sandboxes
    processes = limits.processes * (1 if group is None else SANDBOXES_SHARING_THE_UID)
    settings = {"cpu_seconds": limits.cpu_seconds, "processes": processes, "file_bytes": limits.file_bytes,
                "open_files": limits.open_files, "scratch": str(scratch), "writable": ["/tmp", "/dev", "/proc/self"],
                "read_only": [str(p) for p in layout], "private": [os.path.realpath(p) for p in private or []],
                "visible": [os.path.realpath(p) for p in [*shown, scratch]]}
    package_parent = Path(__file__).resolve().parents[2]
    environment = with_agent_threads({
        "PATH": "/usr/local/bin:/usr/bin:/bin", "HOME": str(scratch), "TMPDIR": str(scratch), "LANG": "C.UTF-8",
        "USER": "nobody", "LOGNAME": "nobody", _SETTINGS_VARIABLE: json.dumps(settings),
        **{k: os.environ[k] for k in _PASSED_ENVIRONMENT if k in os.environ}})
    return Launcher(tuple(prefix), _ENTRY.format(root=str(package_parent)), tuple(sorted(environment.items())),
                    python=sys.executable, flags=_PYTHON_FLAGS, output=output)


def _python_dirs() -> list[Path]:
    """What every agent process needs to read: the Python install, the virtual env, the mewa_bench package."""
    dirs = {Path(p) for p in (sys.base_prefix, sys.prefix, sys.base_exec_prefix, sys.exec_prefix)}
    dirs.add(Path(sys.executable).resolve().parent)
    dirs.add(Path(__file__).resolve().parents[1])  # the mewa_bench package (not the checkout around it)
    return sorted(dirs)


def _bwrap_command(readable: list[Path], scratch: Path, limits: SandboxLimits) -> tuple[list[str], list[Path]]:
    """bwrap's command line up to and including "--" (and setpriv's, as root), and the read-only places it
    makes for the mounts (the directories leading to them, the read-only mounts), which may lie under /tmp."""
    as_root = os.geteuid() == 0
    command = ["bwrap", "--unshare-ipc", "--unshare-pid", "--unshare-net", "--unshare-uts", "--unshare-cgroup-try",
               "--hostname", "sandbox", "--die-with-parent", "--new-session"]
    if not as_root:
        command += ["--unshare-user", "--uid", str(SANDBOX_UID), "--gid", str(SANDBOX_UID), "--disable-userns"]
    command += ["--ro-bind", "/usr", "/usr"]
    for directory in _SYSTEM_DIRS:
        if os.path.islink(directory):
            command += ["--symlink", os.readlink(directory), directory]
        elif os.path.isdir(directory):
            command += ["--ro-bind", directory, directory]
    command += ["--perms", "0755", "--dir", "/etc", "--ro-bind-try", "/etc/ld.so.cache", "/etc/ld.so.cache",
                "--proc", "/proc", "--dev", "/dev",  # then the tmpfs, before the binds that may lie under /tmp
                "--perms", "1777", "--size", str(limits.tmp_bytes), "--tmpfs", "/tmp",
                "--perms", "1777", "--size", str(limits.tmp_bytes), "--tmpfs", "/dev/shm"]
    mounts = sorted({(p, False) for p in readable} | {(scratch, True)}, key=lambda m: (len(m[0].parts), str(m[0])))
    made = {Path(p) for p in ("/", "/usr", "/etc", "/proc", "/dev", "/tmp", "/dev/shm")}
    mounted = [Path("/usr")]
    layout: list[Path] = []
    for path, writable in mounts:
        if any(path.is_relative_to(m) and not writable for m in mounted):
            continue  # already visible inside another read-only mount
        for parent in reversed(path.parents):
            if parent not in made and not any(parent.is_relative_to(m) for m in mounted):
                command += ["--perms", "0755", "--dir", str(parent)]  # bwrap would make them 0700
                made.add(parent)
                layout.append(parent)
        command += ["--bind" if writable else "--ro-bind", str(path.resolve()), str(path)]
        mounted.append(path)
        made.add(path)
        if not writable:
            layout.append(path)
    command += ["--remount-ro", "/", "--chdir", "/", "--"]  # the agent process changes to scratch once confined
    if as_root:
        command += [shutil.which("setpriv") or "setpriv", f"--reuid={SANDBOX_UID}", f"--regid={SANDBOX_UID}",
                    "--clear-groups", "--inh-caps=-all", "--bounding-set=-all", "--no-new-privs", "--"]
    return command, layout


def _prepare_scratch(scratch: Path) -> None:
    """Create the scratch directory, owned by the sandbox user when we are root."""
    scratch.mkdir(parents=True, exist_ok=True)
    if os.geteuid() == 0:
        os.chown(scratch, SANDBOX_UID, SANDBOX_UID)
    os.chmod(scratch, 0o700)


def _check_hidden(path: Path, what: str, visible: list[Path]) -> None:
    """Refuse to run if `path` would be inside something the agent sees."""
    real = Path(path).resolve()
    for place in visible:
        if real.is_relative_to(place.resolve()):
            raise ValueError(f"{what} {path} would be visible to the agent (it is inside {place}, which the sandbox "
                             f"shows it): keep it out of the agent's directory, checkpoint, scratch and the Python install")


_NO_SUCH_FILE = re.compile(r"(?:FileNotFoundError|PermissionError): \[Errno \d+\] [^:\n]*: '([^'\n]*)'")


def _explained(error: Exception, limits: SandboxLimits, visible: list[Path]) -> Exception:
    """A SandboxViolation for an evaluation error that is a broken sandbox rule; the error itself otherwise."""
    message, kind = str(error), getattr(error, "kind", "")
    if kind == "sandbox":
        return SandboxViolation("network" if "agents run without network" in message else "filesystem", message)
    if kind == "crash" and "signal SIGXCPU" in message:
        return SandboxViolation("cpu_time", f"{message}\nthe agent process used up its CPU-time limit of "
                                            f"{limits.cpu_seconds} s")
    if kind == "exception" and ("BlockingIOError: [Errno 11]" in message or "can't start new thread" in message):
        return SandboxViolation("processes", f"{message}\nthe agent reached its limit of {limits.processes} processes "
                                             f"and threads")
    if kind == "exception" and "[Errno 27] File too large" in message:
        return SandboxViolation("file_size", f"{message}\nthe agent reached its file-size limit of "
                                             f"{limits.file_bytes} bytes")
    match = _NO_SUCH_FILE.search(message) if kind == "exception" else None
    missing = Path(match.group(1)) if match else None
    if missing is not None and missing.is_absolute() and not any(missing.is_relative_to(p) for p in visible):
        return SandboxViolation("filesystem", f"{message}\nthe sandbox shows the agent only its own directory, its "
                                              f"checkpoint, the Python install and its scratch directory; "
                                              f"{match.group(1)} is not among them")
    return error


# -- inside the sandbox: the agent process confines itself before the agent loads -------------------------

def confined_child_main() -> None:
    """The agent process in the sandbox: rlimits, seccomp and the audit hook, then the protocol's child loop.

    It runs with a clean import path (`python -I` in /): nothing it imports comes from a place the agent can write.
    """
    from mewa_bench.protocol.agent_child import _child_main

    settings = json.loads(os.environ.pop(_SETTINGS_VARIABLE))
    cpu = settings["cpu_seconds"]
    for limit, value in ((resource.RLIMIT_CPU, (cpu, cpu + 5)),  # SIGXCPU at the limit, SIGKILL 5 s later
                         (resource.RLIMIT_NPROC, (settings["processes"],) * 2),
                         (resource.RLIMIT_FSIZE, (settings["file_bytes"],) * 2),
                         (resource.RLIMIT_NOFILE, (settings["open_files"],) * 2)):
        resource.setrlimit(limit, value)
    _install_seccomp()
    sys.addaudithook(_AuditHook(settings["scratch"], settings["writable"], settings["read_only"], settings["private"],
                                settings["visible"]))
    os.chdir(settings["scratch"])  # relative paths are the agent's scratch; never on the import path (-I)
    _child_main()


class _AuditHook:
    """Names the network use, the writes outside the scratch directory and the reads of private places that the
    kernel will refuse."""

    _NAME_LOOKUPS = frozenset({"socket.getaddrinfo", "socket.gethostbyname", "socket.gethostbyname_ex",
                               "socket.gethostbyaddr", "socket.getnameinfo"})
    _PATH_WRITES: ClassVar[dict[str, tuple[int, ...]]] = {  # event: the positions of its paths
        "os.mkdir": (0,), "os.remove": (0,), "os.rmdir": (0,), "os.rename": (0, 1), "os.symlink": (1,), "os.link": (1,),
        "os.truncate": (0,), "os.chmod": (0,), "os.chown": (0,), "os.utime": (0,)}
    _WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND

    _PATH_READS = frozenset({"os.listdir", "os.scandir"})

    def __init__(self, scratch: str, writable: list[str], read_only: list[str], private: list[str] = (),
                 visible: list[str] = ()) -> None:
        self._scratch, self._in_scratch = scratch, os.path.join(scratch, "")
        self._writable = tuple(os.path.join(w, "") for w in writable)  # the tmpfs mounts ...
        self._read_only = tuple(os.path.join(r, "") for r in read_only)  # ... but not the mounts' ways in them
        self._private = tuple(os.path.join(p, "") for p in private)  # the places the agent must not look into ...
        self._visible = tuple(os.path.join(v, "") for v in visible)  # ... but for what the sandbox shows it there
        self._watched = frozenset({"socket.__new__", "open", *self._NAME_LOOKUPS, *self._PATH_WRITES,
                                   *self._PATH_READS})

    def __call__(self, event: str, args: tuple) -> None:
        if event not in self._watched:
            return
        if event == "socket.__new__":
            if args[1] != socket.AF_UNIX:
                self._refuse(f"the agent tried to open a network socket ({_family_name(args[1])}): agents run "
                             f"without network")
        elif event in self._NAME_LOOKUPS:
            self._refuse(f"the agent tried to look up a network name ({args[0]!r}): agents run without network")
        elif event == "open":
            path, mode, flags = args
            writes = (flags != -1 and flags & self._WRITE_FLAGS) or (isinstance(mode, str) and set(mode) & set("wax+"))
            if writes:
                self._check_write(path)
            else:
                self._check_read(path)
        elif event in self._PATH_READS:
            self._check_read(args[0])
        else:
            for position in self._PATH_WRITES[event]:
                self._check_write(args[position])

    def _check_write(self, path: object) -> None:
        if not isinstance(path, (str, bytes, os.PathLike)):
            return  # a file descriptor
        where = os.path.join(os.path.abspath(os.fsdecode(path)), "")
        if not where.startswith(self._in_scratch) and (not where.startswith(self._writable)
                                                       or where.startswith(self._read_only)):
            self._refuse(f"the agent tried to write {os.fsdecode(path)}, outside its scratch directory {self._scratch} "
                         f"(agents may write only there and in /tmp)")

    def _check_read(self, path: object) -> None:
        if not self._private or not isinstance(path, (str, bytes, os.PathLike)):
            return  # nothing private, or a file descriptor
        given = os.fsdecode(path)
        where = os.path.join(os.path.realpath(given), "")  # a symlink in the scratch dir leads where it points
        if where.startswith(self._private) and not where.startswith(self._visible):
            real = where.rstrip("/") or "/"
            shown = given if real == given else f"{given} (that is {real})"
            self._refuse(f"the agent tried to read {shown}, which the sandbox keeps from it (agents may read only "
                         f"their own directory, their checkpoint, the Python install and their scratch directory)")

    @staticmethod
    def _refuse(message: str) -> None:
        report_violation(message)
        raise PermissionError(errno.EACCES, f"sandbox: {message}")


def _family_name(family: int) -> str:
    try:
        return socket.AddressFamily(family).name
    except ValueError:
        return f"address family {family}"


# seccomp: a classic-BPF filter over (arch, syscall number, first argument), installed with prctl
_BPF_LD_W_ABS, _BPF_JEQ, _BPF_JGE, _BPF_JSET, _BPF_RET = 0x20, 0x15, 0x35, 0x45, 0x06
_RET_ALLOW, _RET_ERRNO = 0x7FFF0000, 0x00050000
_CLONE_NEW_NAMESPACES = 0x7E020000  # CLONE_NEWNS | NEWCGROUP | NEWUTS | NEWIPC | NEWUSER | NEWPID | NEWNET
_X32_BIT = 0x40000000
_DENIED = {"unshare": errno.EPERM, "setns": errno.EPERM, "ptrace": errno.EPERM, "bpf": errno.EPERM,
           "perf_event_open": errno.EPERM, "userfaultfd": errno.EPERM, "keyctl": errno.EPERM,
           "add_key": errno.EPERM, "request_key": errno.EPERM, "clone3": errno.ENOSYS,  # glibc then uses clone
           "io_uring_setup": errno.ENOSYS, "io_uring_enter": errno.ENOSYS, "io_uring_register": errno.ENOSYS}
_SYSCALLS = {  # machine: (AUDIT_ARCH_*, syscall numbers)
    "x86_64": (0xC000003E, {"socket": 41, "clone": 56, "ptrace": 101, "add_key": 248, "request_key": 249,
                            "keyctl": 250, "unshare": 272, "perf_event_open": 298, "setns": 308, "bpf": 321,
                            "userfaultfd": 323, "io_uring_setup": 425, "io_uring_enter": 426,
                            "io_uring_register": 427, "clone3": 435}),
    "aarch64": (0xC00000B7, {"socket": 198, "clone": 220, "ptrace": 117, "add_key": 217, "request_key": 218,
                             "keyctl": 219, "unshare": 97, "perf_event_open": 241, "setns": 268, "bpf": 280,
                             "userfaultfd": 282, "io_uring_setup": 425, "io_uring_enter": 426,
                             "io_uring_register": 427, "clone3": 435}),
}


def seccomp_filter(machine: str) -> bytes | None:
    """The filter program for `machine` (platform.machine()), or None where there is none."""
    if machine not in _SYSCALLS:
        return None
    arch, numbers = _SYSCALLS[machine]
    code = [(_BPF_LD_W_ABS, 0, 0, 4), (_BPF_JEQ, 1, 0, arch), (_BPF_RET, 0, 0, _RET_ERRNO | errno.EPERM),
            (_BPF_LD_W_ABS, 0, 0, 0)]  # another ABI (i386 on x86_64) gets nothing; then the syscall number
    if machine == "x86_64":
        code += [(_BPF_JGE, 0, 1, _X32_BIT), (_BPF_RET, 0, 0, _RET_ERRNO | errno.EPERM)]
    for name, error in _DENIED.items():
        code += [(_BPF_JEQ, 0, 1, numbers[name]), (_BPF_RET, 0, 0, _RET_ERRNO | error)]
    code += [(_BPF_JEQ, 0, 4, numbers["socket"]), (_BPF_LD_W_ABS, 0, 0, 16),  # args[0], the address family
             (_BPF_JEQ, 1, 0, socket.AF_UNIX), (_BPF_RET, 0, 0, _RET_ERRNO | errno.EACCES), (_BPF_RET, 0, 0, _RET_ALLOW)]
    code += [(_BPF_JEQ, 0, 4, numbers["clone"]), (_BPF_LD_W_ABS, 0, 0, 16),  # args[0], the clone flags
             (_BPF_JSET, 0, 1, _CLONE_NEW_NAMESPACES), (_BPF_RET, 0, 0, _RET_ERRNO | errno.EPERM),
             (_BPF_RET, 0, 0, _RET_ALLOW)]
    code += [(_BPF_RET, 0, 0, _RET_ALLOW)]
    return b"".join(struct.pack("<HBBI", *instruction) for instruction in code)


class _SockFprog(ctypes.Structure):
    _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]


def _install_seccomp() -> bool:
    """Load the filter into this process (inherited by its children); False where there is no filter."""
    program = seccomp_filter(platform.machine())
    if program is None:
        return False
    libc = ctypes.CDLL(None, use_errno=True)
    prctl = libc.prctl
    prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    buffer = ctypes.create_string_buffer(program, len(program))
    fprog = _SockFprog(len(program) // 8, ctypes.addressof(buffer))
    pr_set_no_new_privs, pr_set_seccomp, seccomp_mode_filter = 38, 22, 2
    if prctl(pr_set_no_new_privs, 1, 0, 0, 0) != 0 or \
            prctl(pr_set_seccomp, seccomp_mode_filter, ctypes.addressof(fprog), 0, 0) != 0:
        error = ctypes.get_errno()
        raise OSError(error, f"cannot install the sandbox's seccomp filter: {os.strerror(error)}")
    return True


@functools.lru_cache(maxsize=1)
def _probe() -> str | None:
    """Start a sandbox once and check it: None if it works, else the reason."""
    if not sys.platform.startswith("linux"):
        return f"the sandbox needs Linux (bubblewrap), not {sys.platform}"
    if shutil.which("bwrap") is None:
        return "bubblewrap is not installed (Debian: apt-get install bubblewrap)"
    if os.geteuid() == 0 and shutil.which("setpriv") is None:
        return "setpriv (util-linux) is not installed; as root it drops the agent to an unprivileged user"
    check = (f"import sys; sys.path.append({str(Path(__file__).resolve().parents[2])!r}); import os, socket; "
             f"from mewa_bench.service.sandbox import _install_seccomp; "
             f"seccomp = _install_seccomp(); print(os.getuid(), os.getgid(), seccomp)")
    with tempfile.TemporaryDirectory(prefix="mewa-sandbox-probe-") as directory:
        scratch = Path(directory) / "scratch"
        _prepare_scratch(scratch)
        launcher = sandbox_launcher([], scratch, SandboxLimits())
        try:
            done = subprocess.run([*launcher.prefix, launcher.python, *launcher.flags, "-c", check],
                                  env=dict(launcher.environment),
                                  capture_output=True, text=True, timeout=60, check=False)
        except (OSError, subprocess.TimeoutExpired) as e:
            return f"bwrap could not start a sandbox: {e}"
    if done.returncode != 0:
        return f"bwrap could not start a sandbox (exit code {done.returncode}): {done.stderr.strip()[-2000:]}"
    if done.stdout.split()[:2] != [str(SANDBOX_UID)] * 2:
        return f"the sandboxed process did not run as uid/gid {SANDBOX_UID}: {done.stdout.strip()}"
    return None
