"""Shared pytest fixtures: start the Taichi runtime once per test session (f64, seed 0).

The backend is chosen by ``CALENDARING_TEST_ARCH`` ("cpu" by default, "cuda" or "auto").
Every :class:`~calendaring.engine.simulation.Simulation` a test builds then runs on that backend,
whatever its configuration's ``numerics.arch`` says: a process holds one Taichi runtime, and
the tests' configurations leave ``numerics.arch`` at its default, "cpu".
"""

import os

import pytest

import calendaring.engine.simulation as _simulation
from calendaring.engine.backend import init_taichi

TEST_ARCH = os.environ.get("CALENDARING_TEST_ARCH", "cpu")

if TEST_ARCH != "cpu":
    _init = _simulation.init_taichi

    def _init_on_test_arch(arch="cpu", **kwargs):
        return _init(arch=TEST_ARCH, **kwargs)

    _simulation.init_taichi = _init_on_test_arch


@pytest.fixture(scope="session", autouse=True)
def taichi_runtime():
    """Initialise Taichi once for the whole session; returns the BackendInfo."""
    return init_taichi(arch=TEST_ARCH, precision="f64", seed=0)
