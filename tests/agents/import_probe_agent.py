"""Test agent: when built, writes to `imports.json` in $HOME the modules its process has imported (with their
files), its import path and its interpreter flags; plays 0. It imports only what its launcher has imported."""

import json
import os
import sys


class Agent:
    def __init__(self, observation_space, action_space):
        modules = {name: getattr(module, "__file__", None) for name, module in list(sys.modules.items())}
        flags = {"isolated": sys.flags.isolated, "dont_write_bytecode": sys.flags.dont_write_bytecode,
                 "no_user_site": sys.flags.no_user_site, "safe_path": sys.flags.safe_path,
                 "ignore_environment": sys.flags.ignore_environment}
        with open(os.path.join(os.environ["HOME"], "imports.json"), "w") as f:
            json.dump({"modules": modules, "path": sys.path, "flags": flags}, f)

    def act(self, observation):
        return 0
