"""The shipped suite is the scenario files here; `examples/` documents the format and is not part of it."""

collect_ignore = ["examples"]
