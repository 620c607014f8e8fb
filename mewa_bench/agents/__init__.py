"""Agent building blocks: what the shipped reference agents share, and the learned baselines.

Learned baselines: one file per algorithm (`rl2`, `varibad`, `pearl`, `maml`), registered in
`training_io.ALGORITHMS`, which also holds what they truly share (the meta-train env, metrics and
checkpoint files, the submission folder). Torch is imported only inside the functions that need it.

Above the protocol layer: agents may use the game, the design engine and the protocol's agent
interface, never the other way round.
"""
