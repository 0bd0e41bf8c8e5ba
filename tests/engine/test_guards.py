"""Unstable runs stop with a diagnostic naming the particle, the step and the quantity."""

import numpy as np
import pytest

from calendaring.core.errors import SimulationError
from calendaring.engine.simulation import Simulation
from tests.engine.helpers import frictionless_pair


def _sim(**kw):
    return Simulation(frictionless_pair(**kw), capacity=8)


def test_runaway_overlap_stops_with_particle_id():
    sim = _sim()
    try:
        r = 3e-6
        ids = sim.add_particles([[20e-6, 30e-6, 30e-6], [20e-6 + 0.8 * r, 30e-6, 30e-6]],
                                [r, r], [0, 0])
        with pytest.raises(SimulationError, match="overlap") as err:
            sim.run(1)
        assert err.value.particle_ids[0] in ids.tolist()
        assert "particle id" in str(err.value) and "step" in str(err.value)
    finally:
        sim.destroy()


def test_nan_velocity_stops_the_run():
    sim = _sim()
    try:
        ids = sim.add_particles([[20e-6, 30e-6, 30e-6]], [3e-6], [0],
                                velocity=[[np.nan, 0, 0]])
        with pytest.raises(SimulationError, match="non-finite") as err:
            sim.run(20)
        assert err.value.particle_ids == [int(ids[0])]
    finally:
        sim.destroy()


def test_particle_leaving_through_the_top_plate_is_reported():
    sim = _sim(gravity=0.0)
    try:
        ids = sim.add_particles([[20e-6, 30e-6, 30e-6], [40e-6, 30e-6, 40e-6]], [3e-6, 3e-6],
                                [0, 0])
        sim.set_top_plate(z=35e-6)  # below the second particle's centre
        with pytest.raises(SimulationError, match="above the top plate") as err:
            sim.run(1)
        assert err.value.particle_ids == [int(ids[1])]
    finally:
        sim.destroy()


def test_skin_violation_is_an_error_not_a_silent_miss():
    sim = Simulation(frictionless_pair(rebuild_check_interval=50, skin=0.1e-6), capacity=8)
    try:
        sim.add_particles([[20e-6, 30e-6, 30e-6]], [3e-6], [0], velocity=[[500.0, 0, 0]])
        with pytest.raises(SimulationError, match="skin"):
            sim.run(100)
    finally:
        sim.destroy()


@pytest.mark.parametrize("allowance, depth, stops", [(0.5, 0.2, True), (1.5, 0.3, False),
                                                     (1.5, 0.7, True)])
def test_bottom_plate_guard_follows_the_overlap_allowance(allowance, depth, stops):
    # centre `depth` radii below the bottom plate (z = 0): a plate overlap of 1 + depth radii,
    # accepted when that is within numerics.max_overlap_fraction (soft CB crushed on a plate)
    sim = Simulation(frictionless_pair(max_overlap_fraction=allowance), capacity=8)
    try:
        r = 3e-6
        ids = sim.add_particles([[20e-6, 30e-6, -depth * r]], [r], [1])
        if stops:
            with pytest.raises(SimulationError, match="below the bottom plate") as err:
                sim.run(1)
            assert err.value.particle_ids == [int(ids[0])]
        else:
            sim.run(1)
            v = sim.pool.to_numpy(("velocity",))["velocity"][int(ids[0])]
            assert v[2] > 0.0  # pushed back into the cell by the plate
    finally:
        sim.destroy()
