"""MAML agent trained by `mewa-bench train maml --suite wide-v1 --seed 3 --steps 4005888 --out submissions/maml-wide-v1-seed3`; plays the checkpoint beside this file.

Evaluate it: `mewa-bench evaluate submissions/maml-wide-v1-seed3/agent.py --suite wide-v1`.
"""

from pathlib import Path

from mewa_bench.agents.maml import MAMLVectorAgent

PRIVILEGED = False


def make_vector_agent(observation_space, action_space, num_lanes, seed="0", checkpoint=None, greedy="false"):
    return MAMLVectorAgent(checkpoint or Path(__file__).with_name("checkpoint.pt"), num_lanes, seed=seed, greedy=greedy)
