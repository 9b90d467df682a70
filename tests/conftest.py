"""Shared by every test: the processes a test session leaves behind are ended with it."""

from processes import pytest_sessionfinish  # noqa: F401  (a hook)
