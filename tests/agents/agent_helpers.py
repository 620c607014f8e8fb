"""A sibling module the recording agent imports, to check that agent files can import their neighbours."""


def cycle_action(start: int, calls: int, num_actions: int) -> int:
    """The action after `calls` acts when starting from `start`."""
    return (start + calls) % num_actions
