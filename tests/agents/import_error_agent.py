"""An agent file whose import fails."""

import a_module_that_does_not_exist  # noqa: F401


def make_agent(observation_space, action_space):
    return None
