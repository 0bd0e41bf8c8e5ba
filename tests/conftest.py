"""Shared pytest fixtures: start the Taichi runtime once per test session (f64, seed 0).

The backend is chosen by ``CALENDARING_TEST_ARCH`` ("cpu" by default, "cuda" or "auto").
"""

import os

import pytest

from calendaring.backend import init_taichi


@pytest.fixture(scope="session", autouse=True)
def taichi_runtime():
    """Initialise Taichi once for the whole session; returns the BackendInfo."""
    return init_taichi(arch=os.environ.get("CALENDARING_TEST_ARCH", "cpu"), precision="f64",
                       seed=0)
