"""VariBAD agent trained by `mewa-bench train varibad --suite wide-v2 --seed 1 --steps 4000000 --out submissions/varibad-wide-v2-seed1` (default settings; renamed varibad-untuned-wide-v2-seed1); plays the checkpoint beside this file.

Evaluate it: `mewa-bench evaluate submissions/varibad-untuned-wide-v2-seed1/agent.py --suite wide-v2`.
"""

from pathlib import Path

from mewa_bench.agents.varibad import VariBADVectorAgent

PRIVILEGED = False


def make_vector_agent(observation_space, action_space, num_lanes, seed="0", checkpoint=None, greedy="false"):
    return VariBADVectorAgent(checkpoint or Path(__file__).with_name("checkpoint.pt"), num_lanes, seed=seed, greedy=greedy)
