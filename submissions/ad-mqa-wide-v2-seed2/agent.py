"""AD agent trained by `mewa-bench train ad --algorithm ad-mqa --set anneal=true --set kv_heads=1 --set threads=1 --suite wide-v2 --seed 2 --steps 128000 --out submissions/ad-mqa-wide-v2-seed2 --dataset mewa-datasets/wide-v2-train-task-inferring-histories`; plays the checkpoint beside this file.

Evaluate it: `mewa-bench evaluate submissions/ad-mqa-wide-v2-seed2/agent.py --suite wide-v2`.
"""

from pathlib import Path

from mewa_bench.agents.ad import ADVectorAgent

PRIVILEGED = False


def make_vector_agent(observation_space, action_space, num_lanes, seed="0", checkpoint=None, greedy="true"):
    return ADVectorAgent(checkpoint or Path(__file__).with_name("checkpoint.pt"), num_lanes, seed=seed, greedy=greedy)
