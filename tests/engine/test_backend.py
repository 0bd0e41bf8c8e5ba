"""The runtime's start-up helpers: the cores a run may use and the memoised source positions
of Taichi's compiler front end."""

import os

import numpy as np
import pytest

from calendaring.core.config import available_cores
from calendaring.engine.backend import cpu_pool_threads, memoise_source_positions
from calendaring.engine.simulation import Simulation
from tests.engine.helpers import frictionless_pair, random_gas


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
