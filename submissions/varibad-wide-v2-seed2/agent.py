"""VariBAD agent trained by `mewa-bench train varibad --set ent_coef=0.001 --suite wide-v2 --seed 2 --steps 4005888 --out submissions/varibad-wide-v2-seed2`; plays the checkpoint beside this file.

Evaluate it: `mewa-bench evaluate submissions/varibad-wide-v2-seed2/agent.py --suite wide-v2`.
"""

from pathlib import Path

from mewa_bench.agents.varibad import VariBADVectorAgent

PRIVILEGED = False


def make_vector_agent(observation_space, action_space, num_lanes, seed="0", checkpoint=None, greedy="false"):
    return VariBADVectorAgent(checkpoint or Path(__file__).with_name("checkpoint.pt"), num_lanes, seed=seed, greedy=greedy)
