"""Agent building blocks: what the shipped reference agents (and, later, learned baselines) share.

Above the protocol layer: agents may use the game, the design engine and the protocol's agent
interface, never the other way round.
"""
