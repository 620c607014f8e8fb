"""DPT agent trained by `mewa-bench train dpt --suite wide-v2 --seed 3 --steps 40000 --out submissions/dpt-wide-v2-seed3 --dataset mewa-datasets/wide-v2-train-random`; plays the checkpoint beside this file.

Evaluate it: `mewa-bench evaluate submissions/dpt-wide-v2-seed3/agent.py --suite wide-v2`.
"""

from pathlib import Path

from mewa_bench.agents.dpt import DPTVectorAgent

PRIVILEGED = False


def make_vector_agent(observation_space, action_space, num_lanes, seed="0", checkpoint=None, greedy="false"):
    return DPTVectorAgent(checkpoint or Path(__file__).with_name("checkpoint.pt"), num_lanes, seed=seed, greedy=greedy)
