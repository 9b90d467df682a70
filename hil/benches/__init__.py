"""Bench groups for `hil bench`: one module per area, each with ``collect(quick) -> rows``."""
