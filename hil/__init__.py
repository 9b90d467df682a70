"""The harness: links between the two sides, scenario files, the runner, recording, checks, reports,
the pytest plugin and the `hil` command line."""

__version__ = "0.1.0"
