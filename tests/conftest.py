"""Shared pytest fixtures: start the Taichi runtime once per test session (f64, seed 0).

The backend is chosen by ``CALENDARING_TEST_ARCH`` ("cpu" by default, "cuda" or "auto").
Every :class:`~calendaring.engine.simulation.Simulation` a test builds then runs on that backend,
whatever its configuration's ``numerics.arch`` says: a process holds one Taichi runtime, and
the tests' configurations leave ``numerics.arch`` at its default, "cpu".
"""

import os

import pytest

import calendaring.engine.simulation as _simulation
from calendaring.engine.backend import init_taichi, set_kernel_optimisation

TEST_ARCH = os.environ.get("CALENDARING_TEST_ARCH", "cpu")

# Kernels built in the test processes skip Taichi's advanced IR optimisations: they compile
# about 3 x faster, which is most of a fresh clone's test time, and run about 10 % slower.
# The runs that tests start as subprocesses (the CLI, sweeps, notebooks) compile as users'
# runs do; CALENDARING_TEST_FULL_OPTIMISATION=1 makes the test processes do so too.
set_kernel_optimisation(os.environ.get("CALENDARING_TEST_FULL_OPTIMISATION", "") == "1")


def _pin_parallel_worker() -> None:
    """Under pytest-xdist (``-n N``) each worker process keeps to one core of its own.

    The engine's multi-step launches spin at barriers, one worker thread per core the
    process may use (``numerics.threads = 0``); two test processes that each used every
    core would share cores and wait for the scheduler at each barrier. A pinned worker
    (and every run it starts as a subprocess, which inherits the affinity) sees one core.
    Tests that need several cores in one process are marked ``multicore`` and run in a
    session of their own (scripts/test.sh)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if not worker.startswith("gw") or not hasattr(os, "sched_setaffinity"):
        return
    cores = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cores[int(worker[2:]) % len(cores)]})


_pin_parallel_worker()

if TEST_ARCH != "cpu":
    _init = _simulation.init_taichi

    def _init_on_test_arch(arch="cpu", **kwargs):
        return _init(arch=TEST_ARCH, **kwargs)

    _simulation.init_taichi = _init_on_test_arch


@pytest.fixture(scope="session", autouse=True)
def taichi_runtime():
    """Initialise Taichi once for the whole session; returns the BackendInfo."""
    return _start_taichi()


def _start_taichi():
    return init_taichi(arch=TEST_ARCH, precision="f64", seed=0)


# ------------------------------------------------------------ a fresh runtime per test
# Taichi numbers every field (SNode) of a process in the order it is allocated, and those
# numbers are part of each compiled kernel's key in the offline cache. Without a restart a
# test's kernels would hit the cache only after the very same tests had run before it in
# the same order, so adding, removing or reordering tests (or choosing a subset) compiled
# most kernels again. A restart (about 0.5 s) numbers fields from 0 again: a test's kernels
# are then found in the cache whatever ran before, and tests that build the same beds share
# their kernels within a run. Modules whose module-scoped fixtures keep Taichi fields for
# several tests are marked ``shared_taichi_runtime`` and restart once, when they start.

def _runtime_holds_fields() -> bool:
    from taichi.lang import impl

    return impl.get_runtime().prog is not None and \
        impl.get_runtime().prog.get_snode_tree_size() > 0


def _restart_taichi() -> None:
    from calendaring.engine.backend import reset_taichi

    reset_taichi()
    _start_taichi()


@pytest.fixture(scope="module", autouse=True)
def fresh_taichi_module(taichi_runtime):
    """A module starts with a Taichi runtime that holds no fields."""
    if _runtime_holds_fields():
        _restart_taichi()


@pytest.fixture(autouse=True)
def fresh_taichi_test(request, fresh_taichi_module):
    """A test starts with a Taichi runtime that holds no fields (unless its module is
    marked ``shared_taichi_runtime``)."""
    if request.node.get_closest_marker("shared_taichi_runtime") is None \
            and _runtime_holds_fields():
        _restart_taichi()
