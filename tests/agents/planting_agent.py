"""Test agent: fails if its scratch directory ($HOME) is not empty when it starts; then plants modules named after
what its launcher imports in $HOME and its working directory (once per process) (each would end the process if imported) and plays at
random, sleeping `delay` seconds per act (a run long enough to interrupt)."""

import os
import time

import numpy as np

PLANTED = "raise SystemExit('a module planted by the agent was imported: ' + __name__)\n"
NAMES = ("resource", "json", "numpy", "ctypes", "pickle", "signal", "sitecustomize", "usercustomize", "encodings")


_PLANTED = []  # this process planted already (an agent object per lane: the first one looks and plants)


class Agent:
    def __init__(self, observation_space, action_space, delay="0"):
        self.delay, self.rng = float(delay), np.random.default_rng(0)
        if _PLANTED:
            return
        _PLANTED.append(True)
        home = os.environ["HOME"]
        left = sorted(os.listdir(home))
        if left:
            raise RuntimeError(f"the scratch directory is not fresh: it holds {left}")
        for place in {home, os.getcwd()}:
            for name in NAMES:
                with open(os.path.join(place, f"{name}.py"), "w") as f:
                    f.write(PLANTED)
            os.makedirs(os.path.join(place, "mewa_bench"), exist_ok=True)
            with open(os.path.join(place, "mewa_bench", "__init__.py"), "w") as f:
                f.write(PLANTED)

    def reset_task(self, seed=None):
        self.rng = np.random.default_rng(seed)

    def act(self, observation):
        time.sleep(self.delay)
        return int(self.rng.integers(0, 4))
