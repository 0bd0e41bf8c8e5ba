"""The runtime's start-up helpers: the cores a run may use, the memoised source positions
of Taichi's compiler front end and the kernel optimisation setting."""

import os

import numpy as np
import pytest

from calendaring.core.config import available_cores
from calendaring.engine.backend import cpu_pool_threads, memoise_source_positions
from calendaring.engine.simulation import Simulation
from tests.engine.helpers import frictionless_pair, jostled_lattice, random_gas


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity interface")
def test_every_core_means_the_cores_this_process_may_use():
    mine = os.sched_getaffinity(0)
    try:
        assert available_cores() == len(mine)
        os.sched_setaffinity(0, {min(mine)})
        assert available_cores() == 1
        assert cpu_pool_threads(0) == 1  # numerics.threads = 0: one thread per core
        assert cpu_pool_threads(3) == 3  # an explicit count is kept
    finally:
        os.sched_setaffinity(0, mine)
    assert available_cores() == len(mine)


def test_memoised_positions_are_the_text_taichi_formats(monkeypatch):
    """Every source-position text the front end asks for while it builds the engine's kernels
    (one step of a bed with plate and pair contacts) is the text Taichi itself formats for
    that node: the memo's key tells every node apart."""
    from taichi.lang.ast.ast_transformer_utils import ASTTransformerContext

    assert memoise_source_positions()
    memo = ASTTransformerContext.get_pos_info
    assert memo.memoised
    calls, wrong = [0], []

    def checked(ctx, node):
        text = memo(ctx, node)
        calls[0] += 1
        if text != memo.original(ctx, node):
            wrong.append((type(node).__name__, getattr(node, "lineno", None)))
        return text

    monkeypatch.setattr(ASTTransformerContext, "get_pos_info", checked)
    sim = Simulation(frictionless_pair(restitution=0.5, friction=0.3, rolling=0.05),
                     capacity=40)
    try:
        pos, rad, vel = random_gas(sim, 30, 2e-6, 4e-6, 3, 0.0, 30e-6, speed=1.0)
        sim.add_particles(pos, rad, np.zeros(len(rad), int), velocity=vel)
        sim.set_top_plate(z=30e-6, velocity=-1.0)
        sim.run(2)
    finally:
        sim.destroy()
    assert calls[0] > 10_000  # the kernels were built here, not found already built
    assert wrong == []


def _pressed_lattice_state(steps: int) -> dict:
    """128 slightly overlapping spheres on an 8 x 8 x 2 lattice, random velocities, the top
    plate pressing on them: every contact term works from the first step."""
    pos, rad, vel, top = jostled_lattice(8, 2, 2)
    sim = Simulation(frictionless_pair(restitution=0.5, plasticity=0.5, friction=0.3,
                                       rolling=0.05), capacity=128)
    try:
        sim.add_particles(pos, rad, np.arange(128) % 2, velocity=vel)
        sim.set_top_plate(z=top, velocity=-2.0)
        sim.run(steps)
        out = sim.state()
        out["top_force"] = sim.plate_forces()[1]
        out["energy"] = np.array(list(sim.energy().values()), float)
        return out
    finally:
        sim.destroy()


def test_kernel_optimisation_is_one_setting_per_runtime_and_keeps_the_results():
    """The test processes compile without Taichi's advanced optimisations (tests/conftest.py);
    users' runs compile with them. One setting holds per runtime, and the same run gives
    the same numbers under both."""
    from taichi.lang import impl

    from calendaring.engine import backend

    arch = os.environ.get("CALENDARING_TEST_ARCH", "cpu")
    mine = backend._STATE["optimise"]
    _pressed_lattice_state(0)  # the runtime is up
    assert impl.current_cfg().advanced_optimization == mine
    with pytest.raises(RuntimeError, match="other kernel optimisation"):
        backend.set_kernel_optimisation(not mine)
    backend.set_kernel_optimisation(mine)  # the setting in force: accepted
    runs = {}
    try:
        for full in (mine, not mine):
            backend.reset_taichi()
            backend.set_kernel_optimisation(full)
            backend.init_taichi(arch=arch, precision="f64", seed=0)
            assert impl.current_cfg().advanced_optimization == full
            runs[full] = _pressed_lattice_state(300)
    finally:
        backend.reset_taichi()
        backend.set_kernel_optimisation(mine)
        backend.init_taichi(arch=arch, precision="f64", seed=0)
    a, b = runs[True], runs[False]
    assert a["n_contacts"].sum() > 500 and a["top_force"][2] > 0.0  # contacts at work
    assert a["energy"].min() >= 0.0 and np.count_nonzero(a["energy"]) >= 10
    # the IR optimisations change how the arithmetic is scheduled, not what it computes:
    # identical to the bit (Taichi 1.7.4, x86 CPU)
    for key in ("position", "velocity", "angular_velocity", "top_force", "energy"):
        np.testing.assert_array_equal(b[key], a[key], err_msg=key)
