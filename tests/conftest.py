"""Test-wide settings: one torch intra-op thread, and the ``sim`` marker.

``sim`` marks the tests that run the ManiSkill simulator (an env, a subprocess of ``rtv3``, a
scene-pool worker); ``bash scripts/test.sh -m "not sim"`` runs the pure tests alone in under a minute.
"""

from __future__ import annotations

import pytest
import torch


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "sim: runs the ManiSkill simulator (deselect with -m 'not sim')")


@pytest.fixture(scope="session", autouse=True)
def single_thread():
    """One intra-op thread: the CI machine has 2 shared cores; spinning OpenMP threads oversubscribe it."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
