"""Shared by every test: the processes a test session leaves behind are ended with it; a test marked
``realtime`` checks the host's lateness first and says when the host fell behind; the learning code's
tests are marked ``learning``."""

from __future__ import annotations

import pytest
from lateness import pytest_runtest_call, pytest_runtest_makereport  # noqa: F401  (hooks)
from processes import pytest_sessionfinish  # noqa: F401  (a hook)

#: the files of the learning code's tests (networks, training, RL): `make test-fast` leaves them out
LEARNING_FILES = ("test_learning_", "test_learned_", "test_rl_")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.path.name.startswith(LEARNING_FILES):
            item.add_marker(pytest.mark.learning)
