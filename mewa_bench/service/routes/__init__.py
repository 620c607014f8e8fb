"""The HTTP API's routes, one module per resource: suites, leaderboards, datasets, submissions."""
