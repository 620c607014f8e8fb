"""A control group per sandbox: memory and process count for the agent's whole process tree.

The group is made under this process's own group (so whatever limits that group has still hold),
in cgroup v1's `memory` and `pids` hierarchies or in the v2 unified hierarchy, whichever this
machine mounts writable for us. The sandbox's first process joins it before it execs bubblewrap
(`join_prefix`), so every process of the sandbox is in it from the start and cannot leave (the
agent runs unprivileged, without write access to /sys/fs/cgroup, which the sandbox does not show).

Where no group can be made (no cgroup mount, not root, no delegation), `cgroup_support` says so and
what the fallback does not hold: the per-process rlimits still apply (address space per process,
processes per sandbox user), but not the memory of the processes together.
"""

from __future__ import annotations

import functools
import itertools
import os
import signal
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path("/sys/fs/cgroup")
GROUP_PREFIX = "mewa-sandbox"
SERVER_LEAF = "mewa-server"  # cgroup v2: where the server's own processes go so that its group can delegate
_COUNTER = itertools.count()
FALLBACK = ("per-process rlimits only: each process's address space and the sandbox user's process count are capped, "
            "but not the memory of the sandbox's processes together")


@dataclass(frozen=True)
class Support:
    """Which cgroup version this machine gives us (1, 2, or 0 for none), and why not when none."""

    version: int
    reason: str

    def describe(self) -> str:
        """One line for logs and /api/health."""
        if self.version == 1:
            return "cgroup v1 (memory and pids hierarchies): memory and processes are limited per sandbox"
        if self.version == 2:
            return "cgroup v2 (memory and pids controllers): memory and processes are limited per sandbox"
        return f"no cgroup ({self.reason}): {FALLBACK}"


def _own_group(controller: str) -> str | None:
    """This process's group path in a v1 hierarchy (`controller`), or in v2 (controller '')."""
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        _, controllers, path = line.split(":", 2)
        if (controller and controller in controllers.split(",")) or (not controller and controllers == ""):
            return path
    return None


def _v1_parents(root: Path) -> dict[str, Path] | None:
    """Where this process may make v1 groups: {controller: directory}, or None."""
    parents = {}
    for controller in ("memory", "pids"):
        own = _own_group(controller)
        mount = root / controller
        if own is None or not (mount / "cgroup.procs").exists():
            return None
        parents[controller] = mount / own.lstrip("/")
    return parents


def _v2_parent(root: Path) -> Path | None:
    """Where this process may make v2 groups (memory and pids enabled), or None."""
    if not (root / "cgroup.controllers").exists():
        return None
    own = _own_group("")
    if own is None:
        return None
    parent = root / own.lstrip("/")
    if parent.name == SERVER_LEAF:  # this process was moved into the leaf: the sandboxes' groups go beside it
        parent = parent.parent
    try:
        available = (parent / "cgroup.controllers").read_text().split()
    except OSError:
        return None
    return parent if {"memory", "pids"} <= set(available) else None


@functools.lru_cache(maxsize=None)
def cgroup_support(root: Path = ROOT) -> Support:
    """Make and remove a trial group: which version works here, or why none does."""
    if os.geteuid() != 0:
        return Support(0, "the server does not run as root, which making groups needs")
    for version, parents in ((1, _v1_parents(root)), (2, None if _v1_parents(root) else _v2_parent(root))):
        if not parents:
            continue
        try:
            trial = Group.make(root, version, limits=(64 << 20, 8))
        except OSError as e:
            return Support(0, f"cgroup v{version} is mounted but a group cannot be made: {e}")
        trial.remove()
        return Support(version, "")
    return Support(0, f"neither cgroup v1 memory and pids hierarchies nor a v2 hierarchy with both controllers "
                      f"under {root}")


@dataclass
class Group:
    """One sandbox's group: its directories (one per v1 hierarchy, or one v2 directory)."""

    version: int
    directories: tuple[Path, ...]

    @classmethod
    def make(cls, root: Path, version: int, limits: tuple[int, int]) -> Group:
        """A new group with `limits` = (memory bytes, processes)."""
        memory, processes = limits
        name = f"{GROUP_PREFIX}-{os.getpid()}-{next(_COUNTER)}"
        if version == 1:
            parents = _v1_parents(root) or {}
            group = cls(1, (parents["memory"] / name, parents["pids"] / name))
        else:
            parent = _v2_parent(root)
            if parent is None:
                raise OSError("no cgroup v2 hierarchy with the memory and pids controllers")
            _enable_v2_controllers(parent)
            group = cls(2, (parent / name,))
        try:
            for directory in group.directories:
                directory.mkdir()
            group._limit(memory, processes)
        except OSError:
            group.remove()
            raise
        return group

    def _limit(self, memory: int, processes: int) -> None:
        """Write the limits (no swap: memory is memory)."""
        if self.version == 1:
            memory_dir, pids_dir = self.directories
            (memory_dir / "memory.limit_in_bytes").write_text(str(memory))
            if (memory_dir / "memory.memsw.limit_in_bytes").exists():
                (memory_dir / "memory.memsw.limit_in_bytes").write_text(str(memory))
            (pids_dir / "pids.max").write_text(str(processes))
        else:
            directory = self.directories[0]
            (directory / "memory.max").write_text(str(memory))
            if (directory / "memory.swap.max").exists():
                (directory / "memory.swap.max").write_text("0")
            (directory / "pids.max").write_text(str(processes))

    def procs_files(self) -> list[str]:
        """The files a process writes its pid to, to join the group."""
        return [str(d / "cgroup.procs") for d in self.directories]

    def join_prefix(self) -> list[str]:
        """A command prefix that puts its process in the group, then execs the rest of the command."""
        script = ('n=$1; shift; while [ "$n" -gt 0 ]; do echo $$ > "$1" || exit 125; shift; n=$((n - 1)); done; '
                  'exec "$@"')
        files = self.procs_files()
        return ["/bin/sh", "-c", script, "mewa-cgroup", str(len(files)), *files]

    def pids(self) -> set[int]:
        """Every process in the group."""
        found: set[int] = set()
        for directory in self.directories:
            try:
                found |= {int(p) for p in (directory / "cgroup.procs").read_text().split()}
            except OSError:
                pass
        return found

    def oom_kills(self) -> int:
        """How many processes of the group the kernel's out-of-memory killer stopped."""
        name = "memory.oom_control" if self.version == 1 else "memory.events"
        try:
            for line in (self.directories[0] / name).read_text().splitlines():
                key, _, value = line.partition(" ")
                if key == "oom_kill":
                    return int(value)
        except (OSError, ValueError):
            pass
        return 0

    def peak_memory(self) -> int | None:
        """The most memory the group used, where the kernel says."""
        name = "memory.max_usage_in_bytes" if self.version == 1 else "memory.peak"
        try:
            return int((self.directories[0] / name).read_text())
        except (OSError, ValueError):
            return None

    def kill(self, timeout: float = 10.0) -> bool:
        """SIGKILL every process of the group until none is left; False if some outlived `timeout`."""
        kill_file = self.directories[0] / "cgroup.kill"
        deadline = time.monotonic() + timeout
        while pids := self.pids():
            if self.version == 2 and kill_file.exists():
                try:
                    kill_file.write_text("1")
                except OSError:
                    pass
            for pid in pids:
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            if time.monotonic() > deadline:
                return False
            time.sleep(0.02)
        return True

    def remove(self) -> None:
        """Kill what is left and remove the directories (the kernel removes a group only once it is empty)."""
        self.kill()
        for directory in self.directories:
            for _ in range(50):
                try:
                    directory.rmdir()
                    break
                except FileNotFoundError:
                    break
                except OSError:
                    time.sleep(0.02)


def sweep_stale(root: Path, version: int) -> list[Path]:
    """Remove the groups left by processes that died without removing theirs (a killed worker); returns them."""
    if version == 1:
        parents = list((_v1_parents(root) or {}).values())
    else:
        parents = [p for p in [_v2_parent(root)] if p is not None]
    removed = []
    for parent in parents:
        for directory in parent.glob(f"{GROUP_PREFIX}-*-*"):
            owner = directory.name.split("-")[-2]
            if owner.isdigit() and not Path("/proc", owner).exists():
                group = Group(version, (directory,))
                group.remove()
                if not directory.exists():
                    removed.append(directory)
    return removed


def _enable_v2_controllers(parent: Path) -> None:
    """Let groups under `parent` use the memory and pids controllers.

    cgroup v2 hands controllers to a group's children only while the group itself holds no process (the
    root group aside, which has no `cgroup.type`): a server started in a group of its own (a systemd
    service with Delegate=yes, a container) first moves that group's processes into a leaf, SERVER_LEAF,
    beside the sandboxes' groups."""
    control = parent / "cgroup.subtree_control"
    missing = {"memory", "pids"} - set(control.read_text().split())
    if not missing:
        return
    procs = (parent / "cgroup.procs").read_text().split() if (parent / "cgroup.procs").exists() else []
    if procs and (parent / "cgroup.type").exists():
        leaf = parent / SERVER_LEAF
        leaf.mkdir(exist_ok=True)
        for pid in procs:
            try:
                (leaf / "cgroup.procs").write_text(pid)
            except ProcessLookupError:  # it ended meanwhile
                pass
    for controller in sorted(missing):
        control.write_text(f"+{controller}")
