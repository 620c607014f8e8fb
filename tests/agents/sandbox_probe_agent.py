"""Test agent: when built, writes what its process can see and may do to `facts.json` in $HOME; plays 0.

Agent arg `look`: paths (separated by "|") whose existence it reports."""

import json
import os
import resource
import socket
from pathlib import Path


def status_fields(*names):
    """Fields of /proc/self/status (capabilities, no_new_privs, seccomp mode)."""
    fields = dict(line.split(":\t", 1) for line in Path("/proc/self/status").read_text().splitlines() if ":\t" in line)
    return {name: fields.get(name, "").strip() for name in names}


def facts(look):
    limits = {name: list(resource.getrlimit(getattr(resource, name)))
              for name in ("RLIMIT_AS", "RLIMIT_CPU", "RLIMIT_NPROC", "RLIMIT_FSIZE", "RLIMIT_NOFILE", "RLIMIT_CORE")}
    return {"uid": os.getuid(), "gid": os.getgid(), "euid": os.geteuid(), "groups": os.getgroups(),
            "pid": os.getpid(), "hostname": socket.gethostname(), "cwd": os.getcwd(), "environment": dict(os.environ),
            "root": sorted(os.listdir("/")), "limits": limits, "exists": {p: os.path.exists(p) for p in look},
            "status": status_fields("CapEff", "CapPrm", "CapBnd", "NoNewPrivs", "Seccomp"),
            "interfaces": sorted(line.split(":")[0].strip() for line in Path("/proc/net/dev").read_text().splitlines()[2:])}


class Agent:
    def __init__(self, observation_space, action_space, look=""):
        Path(os.environ["HOME"], "facts.json").write_text(json.dumps(facts([p for p in look.split("|") if p])))

    def act(self, observation):
        return 0
