"""Test agent: when it first acts, prints `megabytes` MB to stdout and stderr, forged server log lines among them;
then plays 0."""

import sys

FORGED = "2026-01-01 00:00:00,000 mewa_bench.service.worker[1] INFO job 1 done CHATTY-FORGED-LINE\n"


class Agent:
    def __init__(self, observation_space, action_space, megabytes="4"):
        self.size, self.spoke = int(megabytes) << 20, False

    def act(self, observation):
        if not self.spoke:
            self.spoke = True
            line = FORGED + "x" * 1000 + "\n"
            for i in range(self.size // len(line)):
                (sys.stdout if i % 2 else sys.stderr).write(line)
            sys.stdout.flush()
            sys.stderr.flush()
        return 0
