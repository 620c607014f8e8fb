"""DPT agent trained by `mewa-bench train dpt --suite narrow-v2 --seed 2 --steps 40000 --out submissions/dpt-narrow-v2-seed2 --dataset mewa-datasets/narrow-v2-train-random`; plays the checkpoint beside this file.

Evaluate it: `mewa-bench evaluate submissions/dpt-narrow-v2-seed2/agent.py --suite narrow-v2`.
"""

from pathlib import Path

from mewa_bench.agents.dpt import DPTVectorAgent

PRIVILEGED = False


def make_vector_agent(observation_space, action_space, num_lanes, seed="0", checkpoint=None, greedy="false"):
    return DPTVectorAgent(checkpoint or Path(__file__).with_name("checkpoint.pt"), num_lanes, seed=seed, greedy=greedy)
