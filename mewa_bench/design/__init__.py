"""Task design: policies, exact engine, average worker, curation, suites."""
