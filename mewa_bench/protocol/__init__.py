"""The evaluation protocol: the agent interface, agent loading and process isolation (SPEC section 6)."""
