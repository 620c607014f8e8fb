"""A make_agent-style agent with every optional method, logging its calls as JSON lines to `log`."""

import json

from agent_helpers import cycle_action


class RecordingAgent:
    """Cycles through the actions from `start`; appends one JSON line per call to the file `log`."""

    def __init__(self, observation_space, action_space, log=None, start="0", **extra):
        self.num_actions = int(action_space.n)
        self.start = int(start)
        self.log = log
        self.extra = extra
        self.acts = 0
        self.record("init", obs_shape=list(observation_space.shape), num_actions=self.num_actions,
                    log=log, start=start, extra=extra)

    def record(self, call, **fields):
        if self.log:
            with open(self.log, "a") as file:
                file.write(json.dumps({"call": call, **fields}) + "\n")

    def reset_task(self):
        self.acts = 0
        self.record("reset_task")

    def act(self, observation):
        self.record("act", obs_type=type(observation).__name__, obs=[float(x) for x in observation])
        action = cycle_action(self.start, self.acts, self.num_actions)
        self.acts += 1
        return action

    def observe(self, transition):
        self.record("observe", action=transition.action, reward=float(transition.reward),
                    obs=[float(x) for x in transition.obs], next_obs=[float(x) for x in transition.next_obs],
                    terminated=bool(transition.terminated), truncated=bool(transition.truncated))

    def end_episode(self):
        self.record("end_episode")


def make_agent(observation_space, action_space, **kwargs):
    """The agent file's entry point."""
    return RecordingAgent(observation_space, action_space, **kwargs)
