"""The service's sandboxed evaluation (bubblewrap) and its hidden suites.

The sandbox tests skip where bubblewrap cannot run, unless MEWA_REQUIRE_SANDBOX is set (CI sets it):
then they fail. The hidden-suite tests need no sandbox.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from mewa_bench.design.generate import SPECS, allowed_candidates
from mewa_bench.design.suites import SuiteError, load_suite, suite_text
from mewa_bench.game import Task
from mewa_bench.game.distributions import meta_test_candidates
from mewa_bench.protocol.config import EvalConfig, default_seeds
from mewa_bench.protocol.results import read_results, stable_view, unit_key
from mewa_bench.protocol.runner import EvaluationError, evaluate
from mewa_bench.service.hidden import SEED_FILE, hidden_suite_content, hidden_suites, suite_seed
from mewa_bench.service.sandbox import (
    SANDBOX_UID,
    SandboxLimits,
    SandboxViolation,
    sandbox_available,
    sandboxed_evaluate,
)

REPO = Path(__file__).resolve().parents[1]
AGENTS = REPO / "tests" / "agents"
FIRST_STEP = "pair 0, seed 0, episode 0, step 0"


@pytest.fixture
def sandbox() -> None:
    """Skip where bubblewrap cannot sandbox agents; fail instead under MEWA_REQUIRE_SANDBOX."""
    reason = sandbox_available()
    if reason is not None:
        if os.environ.get("MEWA_REQUIRE_SANDBOX", "").strip() not in ("", "0"):
            pytest.fail(f"MEWA_REQUIRE_SANDBOX is set but agents cannot be sandboxed here: {reason}")
        pytest.skip(f"no sandbox here: {reason}")


@pytest.fixture(scope="session")
def hidden_dir(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Path]]:
    """A data dir with the two narrow hidden suites (generated once for the session: a few seconds)."""
    data_dir = tmp_path_factory.mktemp("data")
    return data_dir, hidden_suites(data_dir, ["narrow-v1-hidden", "narrow-v2-hidden"])


def run(tmp_path: Path, agent: str, suite: str | Path = "narrow-v1", **kwargs) -> dict:
    """A sandboxed evaluation of test agent `agent` on the first unit (pair 0, seed 0) unless told otherwise."""
    kwargs = {"seeds": (0,), "pairs": (0,), **kwargs}
    return sandboxed_evaluate(AGENTS / agent, suite, tmp_path / "results.json", scratch=tmp_path / "scratch", **kwargs)


def sandbox_processes(scratch: Path) -> list[int]:
    """Processes started with this scratch directory as their HOME (the agent process and its children)."""
    marker = f"HOME={scratch}".encode()
    found = []
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and marker in (entry / "environ").read_bytes().split(b"\0"):
                found.append(int(entry.name))
        except OSError:
            pass  # gone meanwhile, or not ours to read
    return found


def wait_until_gone(scratch: Path, seconds: float = 10.0) -> list[int]:
    """The sandbox's processes still alive after waiting up to `seconds` for them to go."""
    deadline = time.monotonic() + seconds
    while (left := sandbox_processes(scratch)) and time.monotonic() < deadline:
        time.sleep(0.1)
    return left


# -- the same scores as evaluate ------------------------------------------------------------------------

@pytest.mark.parametrize("agent, suite, pairs, seeds", [
    ("random", "narrow-v1", (0, 5, 15), (0, 1, 2)),
    ("rl2-narrow-v1-seed1", "narrow-v1", (3,), (0, 1)),  # torch, a checkpoint beside the agent file
])
def test_sandboxed_results_are_byte_for_byte_those_of_evaluate(sandbox, tmp_path, agent, suite, pairs, seeds):
    agent_file = REPO / "submissions" / agent / "agent.py"
    sandboxed = sandboxed_evaluate(agent_file, suite, tmp_path / "sandboxed.json", scratch=tmp_path / "scratch",
                                   seeds=seeds, pairs=pairs)
    plain, _ = evaluate(EvalConfig(agent_path=agent_file, suite=suite, seeds=seeds, pairs=pairs,
                                   out=tmp_path / "plain.json"))
    assert len(sandboxed["units"]) == len(pairs) * len(seeds)
    assert stable_view(sandboxed) == stable_view(plain)
    on_disk = [stable_view(read_results(tmp_path / name)) for name in ("sandboxed.json", "plain.json")]
    assert json.dumps(on_disk[0], sort_keys=True) == json.dumps(on_disk[1], sort_keys=True)


# -- what the agent process is and sees -------------------------------------------------------------------

def test_the_agent_runs_unprivileged_offline_and_limited_seeing_only_what_it_needs(sandbox, tmp_path, monkeypatch,
                                                                                  hidden_dir):
    monkeypatch.setenv("MEWA_TEST_SECRET", "the server's database password")
    data_dir, suites = hidden_dir
    limits = SandboxLimits(cpu_seconds=300, processes=32, file_bytes=1 << 20, open_files=200, memory_bytes=3 << 30)
    agent_file = AGENTS / "sandbox_probe_agent.py"
    look = [str(data_dir), str(suites["narrow-v1-hidden"]), str(REPO / "README.md"), str(REPO / "results"),
            str(Path(__file__)), str(agent_file), str(tmp_path / "scratch"), "/etc/passwd", "/root/.ssh"]
    run(tmp_path, "sandbox_probe_agent.py", limits=limits, agent_args={"look": "|".join(look)})
    facts = json.loads((tmp_path / "scratch" / "facts.json").read_text())
    assert (facts["uid"], facts["gid"], facts["euid"], facts["groups"]) == (SANDBOX_UID, SANDBOX_UID, SANDBOX_UID, [])
    assert facts["status"] == {"CapEff": "0" * 16, "CapPrm": "0" * 16, "CapBnd": "0" * 16, "NoNewPrivs": "1",
                               "Seccomp": "2"}
    assert facts["interfaces"] == ["lo"] and facts["hostname"] == "sandbox"
    assert facts["pid"] < 10  # its own pid namespace
    from mewa_bench.service.cgroups import cgroup_support
    from mewa_bench.service.sandbox import SANDBOXES_SHARING_THE_UID

    processes = 32 * (1 if cgroup_support().version == 0 else SANDBOXES_SHARING_THE_UID)  # a group holds the 32
    assert facts["limits"] == {"RLIMIT_AS": [3 << 30] * 2, "RLIMIT_CPU": [300, 305], "RLIMIT_NPROC": [processes] * 2,
                               "RLIMIT_FSIZE": [1 << 20] * 2, "RLIMIT_NOFILE": [200, 200], "RLIMIT_CORE": [0, 0]}
    assert "MEWA_TEST_SECRET" not in facts["environment"] and "MEWA_SANDBOX" not in facts["environment"]
    assert facts["environment"]["HOME"] == facts["cwd"] == str(tmp_path / "scratch")
    assert set(facts["root"]) <= {"bin", "dev", "etc", "lib", "lib32", "lib64", "libx32", "proc", "root", "sbin",
                                  "tmp", "usr", "work"} | {Path(p).parts[1] for p in (sys.prefix, sys.base_prefix)}
    visible = {path for path, exists in facts["exists"].items() if exists}
    assert visible == {str(agent_file), str(tmp_path / "scratch")}


# -- hostile agents ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("how, what", [
    ("python", "the agent tried to open a network socket (AF_INET)"),
    ("caught", "the agent tried to look up a network name ('1.1.1.1')"),  # it swallows the error: fails all the same
    ("dns", "the agent tried to look up a network name ('example.com')"),
])
def test_an_agent_that_opens_a_socket_fails_with_the_reason(sandbox, tmp_path, how, what):
    with pytest.raises(SandboxViolation) as caught:
        run(tmp_path, "network_agent.py", agent_args={"how": how})
    assert caught.value.rule == "network" and caught.value.kind == "sandbox"
    assert f"{FIRST_STEP}: agent network_agent.py: {what}: agents run without network" in str(caught.value)


def test_the_kernel_refuses_a_socket_made_past_python(sandbox, tmp_path):
    with pytest.raises(EvaluationError, match=r"raw socket\(\) returned -1, errno 13") as caught:
        run(tmp_path, "network_agent.py", agent_args={"how": "raw"})  # seccomp: EACCES for any family but AF_UNIX
    assert caught.value.kind == "exception"


KEPT_FROM_IT = ("which the sandbox keeps from it (agents may read only their own directory, their checkpoint, the "
                "Python install and their scratch directory)")


def test_an_agent_that_reads_the_hidden_suite_fails_with_the_reason(sandbox, tmp_path, hidden_dir):
    _, suites = hidden_dir
    hidden = suites["narrow-v1-hidden"]
    with pytest.raises(SandboxViolation) as caught:
        run(tmp_path, "file_agent.py", suite=hidden, agent_args={"path": str(hidden)})
    assert caught.value.rule == "filesystem"
    assert f"{FIRST_STEP}: agent file_agent.py: the agent tried to read {hidden}, {KEPT_FROM_IT}" in str(caught.value)


def test_a_file_outside_the_sandbox_that_is_not_private_is_explained_by_the_missing_file(sandbox, tmp_path):
    elsewhere = tmp_path / "elsewhere.txt"
    elsewhere.write_text("not the agent's")
    with pytest.raises(SandboxViolation) as caught:
        run(tmp_path, "file_agent.py", agent_args={"path": str(elsewhere)})
    assert f"act() raised FileNotFoundError: [Errno 2] No such file or directory: '{elsewhere}'" in str(caught.value)
    assert f"the sandbox shows the agent only its own directory, its checkpoint, the Python install and its " \
           f"scratch directory; {elsewhere} is not among them" in str(caught.value)


@pytest.mark.parametrize("target, how", [
    ("hidden suite", "read"),  # the hidden suite being played
    ("seed", "read"),  # the data dir's private seed (the caller's private places: the service passes its data dir)
    ("data dir", "list"),
    ("results", "read"),  # its own results file, by a relative path from its scratch directory
    ("hidden suite", "link"),  # through a symlink made in its scratch directory
])
def test_an_agent_that_catches_its_failed_read_of_a_private_file_fails_all_the_same(sandbox, tmp_path, hidden_dir,
                                                                                   target, how):
    data_dir, suites = hidden_dir
    hidden = suites["narrow-v1-hidden"]
    path = {"hidden suite": str(hidden), "seed": str(data_dir / "hidden" / SEED_FILE), "data dir": str(data_dir),
            "results": "../results.json"}[target]
    with pytest.raises(SandboxViolation) as caught:  # without the hook the run would end well: the agent plays on
        run(tmp_path, "caught_read_agent.py", suite=hidden, agent_args={"path": path, "how": how},
            private=(data_dir,))
    assert caught.value.rule == "filesystem" and caught.value.kind == "sandbox"
    shown = {"link": f"innocent.json (that is {hidden})", "read": path, "list": path}[how]
    if target == "results":
        shown = f"{path} (that is {tmp_path / 'results.json'})"
    assert f"{FIRST_STEP}: agent caught_read_agent.py: the agent tried to read {shown}, {KEPT_FROM_IT}" \
        in str(caught.value)


def test_an_agent_that_catches_a_failed_read_of_a_public_place_plays_on(sandbox, tmp_path, hidden_dir):
    data_dir, _ = hidden_dir
    results = run(tmp_path, "caught_read_agent.py", agent_args={"path": "/sys/fs/cgroup/cpu.max"}, private=(data_dir,))
    assert len(results["units"]) == 1  # libraries probe such places: not a violation


def test_a_suite_or_results_file_the_agent_could_see_is_refused(sandbox, tmp_path, hidden_dir):
    _, suites = hidden_dir
    agent_dir = tmp_path / "submission"
    agent_dir.mkdir()
    (agent_dir / "agent.py").write_text((AGENTS / "class_agent.py").read_text())
    leaked = agent_dir / "suite.json"
    leaked.write_bytes(suites["narrow-v1-hidden"].read_bytes())
    with pytest.raises(ValueError, match=f"the suite file {leaked} would be visible to the agent"):
        sandboxed_evaluate(agent_dir / "agent.py", leaked, tmp_path / "results.json", scratch=tmp_path / "scratch")
    with pytest.raises(ValueError, match="the results file .* would be visible to the agent"):
        sandboxed_evaluate(agent_dir / "agent.py", "narrow-v1", tmp_path / "scratch" / "results.json",
                           scratch=tmp_path / "scratch")


def test_writes_outside_the_scratch_directory_fail_and_inside_it_succeed(sandbox, tmp_path):
    outside = tmp_path / "outside.txt"
    with pytest.raises(SandboxViolation) as caught:
        run(tmp_path, "file_agent.py", agent_args={"path": str(outside), "mode": "write"})
    assert caught.value.rule == "filesystem"
    assert f"{FIRST_STEP}: agent file_agent.py: the agent tried to write {outside}, outside its scratch directory " \
           f"{tmp_path / 'scratch'}" in str(caught.value)
    assert not outside.exists()
    results = run(tmp_path / "second", "file_agent.py", agent_args={"path": "note.txt", "mode": "write"})
    note = tmp_path / "second" / "scratch" / "note.txt"
    assert len(results["units"]) == 1 and note.read_text() == "the agent was here\n"
    assert note.stat().st_uid == (SANDBOX_UID if os.geteuid() == 0 else os.geteuid())


def test_a_file_beyond_the_size_limit_is_refused(sandbox, tmp_path):
    with pytest.raises(SandboxViolation) as caught:
        run(tmp_path, "file_agent.py", agent_args={"path": "big.bin", "mode": "write", "size": str(3 << 20)},
            limits=SandboxLimits(file_bytes=1 << 20))
    assert caught.value.rule == "file_size" and "OSError: [Errno 27] File too large" in str(caught.value)
    assert "the agent reached its file-size limit of 1048576 bytes" in str(caught.value)
    assert (tmp_path / "scratch" / "big.bin").stat().st_size == 1 << 20


def test_a_fork_bomb_stops_at_the_process_limit_and_leaves_nothing_behind(sandbox, tmp_path):
    with pytest.raises(SandboxViolation) as caught:
        run(tmp_path, "fork_bomb_agent.py", limits=SandboxLimits(processes=16))
    assert caught.value.rule == "processes"
    assert "act() raised BlockingIOError: [Errno 11]" in str(caught.value)
    assert "the agent reached its limit of 16 processes and threads" in str(caught.value)
    assert wait_until_gone(tmp_path / "scratch") == []


def test_one_sandboxs_processes_do_not_count_against_anothers(sandbox, tmp_path):
    from mewa_bench.service.cgroups import cgroup_support

    if cgroup_support().version == 0:  # the per-uid rlimit alone is shared by every sandbox (the fallback's limit)
        if os.environ.get("MEWA_REQUIRE_SANDBOX", "").strip() not in ("", "0"):
            pytest.fail(f"MEWA_REQUIRE_SANDBOX is set but {cgroup_support().describe()}")
        pytest.skip(f"no control groups here: {cgroup_support().describe()}")
    first, second = tmp_path / "first", tmp_path / "second"
    first.mkdir()
    second.mkdir()
    outcome: dict[str, object] = {}

    def hold_twelve() -> None:
        try:
            outcome["first"] = run(first, "fork_bomb_agent.py", agent_args={"children": "12", "hold": "8"},
                                   limits=SandboxLimits(processes=16, call_seconds=60))
        except Exception as e:  # reported below
            outcome["first"] = e

    holder = threading.Thread(target=hold_twelve)
    holder.start()
    deadline = time.monotonic() + 60
    while len(sandbox_processes(first / "scratch")) < 13 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert len(sandbox_processes(first / "scratch")) >= 13, "the first sandbox never held its 12 children"
    results = run(second, "fork_bomb_agent.py", agent_args={"children": "10"}, limits=SandboxLimits(processes=16))
    holder.join()
    assert isinstance(outcome["first"], dict), outcome  # both played their unit: neither failed for lack of processes
    assert results["suite"] == outcome["first"]["suite"] and results["scores"] and outcome["first"]["scores"]
    assert wait_until_gone(first / "scratch") == [] and wait_until_gone(second / "scratch") == []


def test_an_agent_that_burns_cpu_is_stopped_at_its_cpu_time_limit(sandbox, tmp_path):
    started = time.monotonic()
    with pytest.raises(SandboxViolation) as caught:
        run(tmp_path, "cpu_burner_agent.py", limits=SandboxLimits(cpu_seconds=2, call_seconds=60))
    assert caught.value.rule == "cpu_time"
    assert "the agent process died during a batch of 1 calls (killed by signal SIGXCPU)" in str(caught.value)
    assert "the agent process used up its CPU-time limit of 2 s" in str(caught.value)
    assert time.monotonic() - started < 30  # long before the per-call limit


@pytest.mark.parametrize("agent, args, limits, kind, message", [
    ("faulty_agent.py", {"fault": "raise"}, {}, "exception", "act() raised ValueError: boom"),
    ("faulty_agent.py", {"fault": "hang"}, {"call_seconds": 1.0}, "timeout", "did not finish within the time limit of 1 s"),
    ("faulty_agent.py", {"fault": "memory"}, {"memory_bytes": 1 << 30}, "memory", "the agent ran out of memory (its limit is 1 GiB)"),
    ("faulty_agent.py", {"fault": "exit"}, {}, "crash", "the agent process died during a batch of 1 calls (exit code 3)"),
    ("faulty_agent.py", {"fault": "segfault"}, {}, "crash", "(killed by signal SIGSEGV)"),
    ("faulty_agent.py", {"fault": "return", "value": "7"}, {}, "invalid_action", "act() returned 7"),
    ("import_error_agent.py", {}, {}, "load", "import_error_agent.py"),
    ("kills_its_worker_once.py", {"marker": "marker.txt"}, {}, "exception", "act() raised PermissionError"),
])
def test_the_protocols_hostile_agents_are_contained(sandbox, tmp_path, agent, args, limits, kind, message):
    with pytest.raises(EvaluationError) as caught:
        run(tmp_path, agent, agent_args=args, limits=SandboxLimits(**limits))
    assert caught.value.kind == kind and message in str(caught.value)
    assert wait_until_gone(tmp_path / "scratch") == []
    if agent == "kills_its_worker_once.py":  # it could not signal anything outside its sandbox; this process lives
        assert (tmp_path / "scratch" / "marker.txt").read_text() == "killed once"


# -- interruption and resumption --------------------------------------------------------------------------

_WORKER = """
import sys
from pathlib import Path
from mewa_bench.service.sandbox import SandboxLimits, sandboxed_evaluate
agent, out, scratch = (Path(a) for a in sys.argv[1:4])
sandboxed_evaluate(agent, "narrow-v1", out, scratch=scratch, seeds=(0, 1, 2, 3), pairs=(0, 1, 2, 3), lanes=4)
"""


def test_a_killed_evaluation_resumes_from_its_finished_units_to_the_uninterrupted_results(sandbox, tmp_path):
    agent_file, out, scratch = AGENTS / "paced_agent.py", tmp_path / "results.json", tmp_path / "scratch"
    units = {"seeds": (0, 1, 2, 3), "pairs": (0, 1, 2, 3)}
    reference, _ = evaluate(EvalConfig(agent_path=agent_file, suite="narrow-v1", out=tmp_path / "plain.json", **units))
    scratch.mkdir()
    (scratch / "pace").write_text("0.0005")  # slows the sandboxed agent only (it reads $HOME/pace)
    worker = subprocess.Popen([sys.executable, "-c", _WORKER, str(agent_file), str(out), str(scratch)])
    try:
        deadline = time.monotonic() + 120
        while not (out.exists() and read_results(out)["units"]) and worker.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert worker.poll() is None, "the run finished before it could be interrupted"
        worker.send_signal(signal.SIGKILL)  # a crash: no clean-up in the worker
        worker.wait()
    finally:
        worker.kill()
    assert wait_until_gone(scratch) == []  # the sandbox died with its worker
    interrupted = read_results(out)
    finished = len(interrupted["units"])
    assert not interrupted["complete"] and 0 < finished < 16
    (scratch / "pace").unlink()
    seen: list[tuple[int, int]] = []
    resumed = sandboxed_evaluate(agent_file, "narrow-v1", out, scratch=scratch, lanes=4,
                                 progress=lambda done, total: seen.append((done, total)), **units)
    assert seen[0] == (finished, 16)  # continued from the finished units, not from the start
    keys = [unit_key(u) for u in resumed["units"]]
    assert len(keys) == len(set(keys)) == 16
    assert stable_view(resumed) == stable_view(reference)


def test_the_wall_clock_limit_stops_a_run_mid_call(sandbox, tmp_path):
    started = time.monotonic()
    with pytest.raises(SandboxViolation) as caught:  # one call that hangs within its own (long) per-call limit
        run(tmp_path, "faulty_agent.py", agent_args={"fault": "hang"}, limits=SandboxLimits(wall_seconds=4,
                                                                                           call_seconds=300))
    assert caught.value.rule == "wall_time"
    assert re.search(r"the evaluation ran past its wall-clock limit of 4 s; the sandbox was stopped mid-call after "
                     r"[\d.]+ s \(0 of 1 units were done", str(caught.value))
    assert time.monotonic() - started < 30  # long before the call's own limit
    assert wait_until_gone(tmp_path / "scratch") == []


@pytest.mark.parametrize("mode", ["write", "unlinked", "mapped"])  # removed while kept open, or mapped and closed
def test_the_scratch_directory_is_capped_as_a_whole(sandbox, tmp_path, mode):
    with pytest.raises(SandboxViolation) as caught:  # each file is within the file-size limit, together they are not
        run(tmp_path, "file_agent.py", agent_args={"path": "big.bin", "mode": mode, "size": str(3 << 20),
                                                   "copies": "40"},
            limits=SandboxLimits(scratch_bytes=16 << 20, file_bytes=4 << 20))
    assert caught.value.rule == "scratch_size"
    assert "the agent's scratch directory grew past its limit of 16,777,216 bytes" in str(caught.value)
    assert wait_until_gone(tmp_path / "scratch") == []


def test_forked_children_share_one_memory_limit(sandbox, tmp_path):
    from mewa_bench.service.cgroups import cgroup_support

    if cgroup_support().version == 0:  # CI runs as root with cgroups: there it must run
        if os.environ.get("MEWA_REQUIRE_SANDBOX", "").strip() not in ("", "0"):
            pytest.fail(f"MEWA_REQUIRE_SANDBOX is set but {cgroup_support().describe()}")
        pytest.skip(f"no control groups here: {cgroup_support().describe()}")
    with pytest.raises(SandboxViolation) as caught:  # 3 x 600 MB, each below the per-process limit of 1 GiB
        run(tmp_path, "memory_children_agent.py", limits=SandboxLimits(memory_bytes=1 << 30, call_seconds=120))
    assert caught.value.rule == "memory"
    assert "the sandbox's processes together reached its memory limit of 1 GiB" in str(caught.value)
    assert wait_until_gone(tmp_path / "scratch") == []


PLANTED = "raise SystemExit('a module planted by the agent was imported: ' + __name__)\n"


def test_modules_planted_where_the_agent_writes_are_never_imported(sandbox, tmp_path):
    agent_dir = tmp_path / "submission"
    agent_dir.mkdir()
    (agent_dir / "agent.py").write_text((AGENTS / "import_probe_agent.py").read_text())
    scratch = tmp_path / "scratch"
    first = sandboxed_evaluate(agent_dir / "agent.py", "narrow-v1", tmp_path / "first.json", scratch=scratch,
                               seeds=(0,), pairs=(0,))
    seen = json.loads((scratch / "imports.json").read_text())
    names = {name.partition(".")[0] for name in seen["modules"]} | {"sitecustomize", "usercustomize"}
    assert {"resource", "json", "ctypes", "numpy", "gymnasium", "mewa_bench", "encodings"} <= names
    for place in (scratch, agent_dir):  # what a retried attempt would find if scratch were kept, and the agent's dir
        for name in names - {"agent"}:
            (place / f"{name}.py").write_text(PLANTED)
        (place / "mewa_bench").mkdir()
        (place / "mewa_bench" / "__init__.py").write_text(PLANTED)
    (scratch / "imports.json").unlink()
    second = sandboxed_evaluate(agent_dir / "agent.py", "narrow-v1", tmp_path / "second.json", scratch=scratch,
                                seeds=(0,), pairs=(0,))
    assert stable_view(second) == stable_view(first)  # the planted modules changed nothing
    again = json.loads((scratch / "imports.json").read_text())
    assert again["modules"] == seen["modules"]  # the same modules from the same files
    files = [f for f in again["modules"].values() if f]
    assert not [f for f in files if Path(f).is_relative_to(scratch) or Path(f).is_relative_to(tmp_path)
                and Path(f) != agent_dir / "agent.py"]
    assert all((Path(p).is_absolute() or p.endswith(".__path_hook__")) and not Path(p).is_relative_to(tmp_path)
               for p in again["path"]), again["path"]  # no current directory, nothing the agent may write
    assert again["flags"] == {"isolated": 1, "dont_write_bytecode": 1, "no_user_site": 1, "safe_path": True,
                              "ignore_environment": 1}


# -- hidden suites ----------------------------------------------------------------------------------------

def test_hidden_suites_are_made_once_from_a_private_seed_and_cached(hidden_dir):
    data_dir, suites = hidden_dir
    seed_file = data_dir / "hidden" / SEED_FILE
    assert seed_file.stat().st_mode & 0o777 == 0o600 and (data_dir / "hidden").stat().st_mode & 0o777 == 0o700
    private = int(json.loads(seed_file.read_text())["seed"], 16)
    before = {name: (path.read_bytes(), path.stat().st_mtime_ns) for name, path in suites.items()}
    again = hidden_suites(data_dir, list(suites))
    assert again == suites
    assert {name: (path.read_bytes(), path.stat().st_mtime_ns) for name, path in again.items()} == before
    for name, path in suites.items():
        suite = load_suite(path)  # the library's own loader verifies the hash
        public = load_suite(name.removesuffix("-hidden"))
        assert suite.name == name and 1 <= len(suite.pairs) <= 16  # curation may stop short of its cap of 16
        assert suite.content["generator"]["seed"] == suite_seed(private, name) != public.content["generator"]["seed"]
        game = ("colors", "order", "K", "M", "rewards", "worker_blocks", "T", "average_worker", "sigma")
        assert [{k: t.to_dict()[k] for k in game} for t in suite.tasks] == \
            [{k: t.to_dict()[k] for k in game} for t in public.tasks]  # the canonical task, designed the same way
        assert suite_text(hidden_suite_content(name, private)) == path.read_text()  # same seed, same bytes
        assert default_seeds(name) == default_seeds(public.name)


def test_hidden_curated_workers_are_none_of_the_public_ones(hidden_dir):
    _, suites = hidden_dir
    public = {tuple(p.worker.w) for name in ("narrow-v1", "narrow-v2") for p in load_suite(name).pairs}
    for path in suites.values():
        hidden = [tuple(p.worker.w) for p in load_suite(path).pairs]
        assert len(set(hidden)) == len(hidden) and not set(hidden) & public


def test_another_data_dir_gets_another_seed_and_other_workers(tmp_path, hidden_dir):
    _, suites = hidden_dir
    other = hidden_suites(tmp_path, ["narrow-v2-hidden"])["narrow-v2-hidden"]
    ours = {tuple(p.worker.w) for p in load_suite(suites["narrow-v2-hidden"]).pairs}
    theirs = {tuple(p.worker.w) for p in load_suite(other).pairs}
    assert ours != theirs


def test_a_damaged_hidden_suite_is_made_again_and_a_lost_seed_is_an_error(tmp_path, hidden_dir):
    data_dir, suites = hidden_dir
    copy = tmp_path / "data"
    (copy / "hidden").mkdir(parents=True)
    for file in (data_dir / "hidden").iterdir():
        (copy / "hidden" / file.name).write_bytes(file.read_bytes())
    damaged = copy / "hidden" / "narrow-v2-hidden.json"
    damaged.write_text(damaged.read_text()[:-100])
    assert hidden_suites(copy, ["narrow-v2-hidden"])["narrow-v2-hidden"].read_bytes() == \
        suites["narrow-v2-hidden"].read_bytes()
    (copy / "hidden" / SEED_FILE).unlink()
    with pytest.raises(SuiteError, match="seed.json is missing but hidden suites exist"):
        hidden_suites(copy, ["narrow-v2-hidden"])


def test_candidate_restriction_is_seeded_by_the_task_and_keeps_the_order() -> None:
    spec = SPECS["narrow"]
    task = load_suite("narrow-v1").tasks[0]
    grid = meta_test_candidates(task, 0.05)
    excluded = tuple(tuple(w) for w in grid[:3])
    restricted = dataclasses.replace(spec, seed=7, excluded_workers=excluded, candidate_fraction=0.5)
    chosen = allowed_candidates(task, grid, restricted)
    assert len(chosen) == round(0.5 * (len(grid) - 3))
    assert not {tuple(w) for w in chosen} & set(excluded)
    assert [tuple(w) for w in chosen] == sorted(tuple(w) for w in chosen)  # still lexicographic
    renamed = Task.from_dict({**task.to_dict(), "name": "another name"})
    assert np.array_equal(allowed_candidates(renamed, grid, restricted), chosen)
    assert not np.array_equal(allowed_candidates(task, grid, dataclasses.replace(restricted, seed=8)), chosen)
    assert np.array_equal(allowed_candidates(task, grid, spec), grid)  # the public suites keep every candidate


# -- control groups ---------------------------------------------------------------------------------------

def test_a_cgroup_v2_group_gets_its_limits_and_its_first_process(tmp_path):
    from mewa_bench.service.cgroups import Group, _own_group

    parent = tmp_path / (_own_group("") or "/").lstrip("/")  # a v2 hierarchy laid out as files, where we sit in it
    parent.mkdir(parents=True, exist_ok=True)
    (tmp_path / "cgroup.controllers").write_text("cpu memory pids\n")
    (parent / "cgroup.controllers").write_text("cpu memory pids\n")
    (parent / "cgroup.subtree_control").write_text("cpu\n")
    (parent / "cgroup.type").write_text("domain\n")  # not the root group,
    (parent / "cgroup.procs").write_text(f"{os.getpid()}\n")  # and it holds the server's process
    group = Group.make(tmp_path, 2, (512 << 20, 16))
    (directory,) = group.directories
    assert directory.parent == parent and directory.name.startswith("mewa-sandbox-")
    assert (directory / "memory.max").read_text() == str(512 << 20) and (directory / "pids.max").read_text() == "16"
    assert (parent / "cgroup.subtree_control").read_text() in ("+memory", "+pids")  # both were enabled in turn
    assert (parent / "mewa-server" / "cgroup.procs").read_text() == str(os.getpid())  # moved out of the way first
    joined = subprocess.run([*group.join_prefix(), "/bin/sh", "-c", "echo $$"], capture_output=True, text=True,
                            check=True)
    assert (directory / "cgroup.procs").read_text().split() == joined.stdout.split()  # it joined, then exec'd
    (directory / "cgroup.procs").write_text("")
    (directory / "memory.events").write_text("low 0\nhigh 0\nmax 3\noom 1\noom_kill 1\n")
    assert group.oom_kills() == 1 and group.pids() == set()


def test_the_fallback_says_what_it_does_not_hold(tmp_path):
    from mewa_bench.service.cgroups import cgroup_support

    support = cgroup_support(tmp_path)  # no cgroup mount there at all
    assert support.version == 0 or os.geteuid() != 0
    assert support.describe().startswith("no cgroup (")
    assert "not the memory of the sandbox's processes together" in support.describe()


def test_groups_left_by_a_killed_worker_are_swept(sandbox):
    from mewa_bench.service.cgroups import ROOT, Group, cgroup_support, sweep_stale

    support = cgroup_support()
    if support.version == 0:
        pytest.skip(f"no control groups here: {support.describe()}")
    dead = subprocess.Popen(["true"])
    dead.wait()  # its pid names no process now
    ours = Group.make(ROOT, support.version, (64 << 20, 8))
    left = Group(ours.version, tuple(d.with_name(f"mewa-sandbox-{dead.pid}-0") for d in ours.directories))
    for directory in left.directories:
        directory.mkdir()
    try:
        removed = sweep_stale(ROOT, support.version)
        assert set(left.directories) <= set(removed) and not any(d.exists() for d in left.directories)
        assert all(d.exists() for d in ours.directories)  # a live process's group stays
    finally:
        ours.remove()
        left.remove()


def test_an_attempt_that_appends_after_a_restart_keeps_the_output_log_within_its_cap(tmp_path):
    """Two attempts of a job writing one output log: the cap holds for the file, and it is cut once."""
    from mewa_bench.service.agent_output import TRUNCATED, OutputCapture

    log = tmp_path / "output-1.log"
    for _ in range(2):
        capture = OutputCapture(log, limit=1000)
        os.write(capture.fd, b"x" * 700)
        capture.close()
    data = log.read_bytes()
    assert data == b"x" * 1000 + TRUNCATED % 1000
