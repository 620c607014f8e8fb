"""Imitation agent trained by `mewa-bench train imitation --suite wide-v2 --seed 3 --steps 19200 --out submissions/imitation-wide-v2-seed3 --dataset mewa-datasets/wide-v2-train-learning-histories`; plays the checkpoint beside this file.

Evaluate it: `mewa-bench evaluate submissions/imitation-wide-v2-seed3/agent.py --suite wide-v2`.
"""

from pathlib import Path

from mewa_bench.agents.imitation import ImitationVectorAgent

PRIVILEGED = False


def make_vector_agent(observation_space, action_space, num_lanes, seed="0", checkpoint=None, greedy="true"):
    return ImitationVectorAgent(checkpoint or Path(__file__).with_name("checkpoint.pt"), num_lanes, seed=seed, greedy=greedy)
