"""mewa-bench: the MEWA meta-reinforcement-learning benchmark.

Importing the package registers the Gymnasium id `mewa/MEWA-v0`; heavy libraries (torch,
lerobot, sapien, rerun) are only imported by the commands that need them.
"""

from mewa_bench.envs.registration import register_envs

__version__ = "0.1.0"

register_envs()
