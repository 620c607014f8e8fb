"""Generated reports: the task-design report of the suites."""
