"""RL^2 agent trained by `mewa-bench train rl2 --set ent_coef=0.001 --suite wide-v2 --seed 1 --steps 4005888 --out submissions/rl2-wide-v2-seed1`; plays the checkpoint beside this file.

Evaluate it: `mewa-bench evaluate submissions/rl2-wide-v2-seed1/agent.py --suite wide-v2`.
"""

from pathlib import Path

from mewa_bench.agents.rl2 import RL2VectorAgent

PRIVILEGED = False


def make_vector_agent(observation_space, action_space, num_lanes, seed="0", checkpoint=None, greedy="false"):
    return RL2VectorAgent(checkpoint or Path(__file__).with_name("checkpoint.pt"), num_lanes, seed=seed, greedy=greedy)
