"""Multi-step launches (``numerics.steps_per_launch`` > 1, :meth:`Kernels.burst`) against one
launch per step: the same trajectory, the same plate trace, the host acting on the device
flags (rebuilds, guards, breakage, callbacks) after the same steps; a thread pool that cannot
start every worker makes the engine fall back to one launch per step.

In this process Taichi runs the test session's thread count (every core); the single-thread
bit-for-bit comparison of whole calendering runs with breakage is in
tests/system/test_threads.py (each thread count needs its own process).
"""

import numpy as np
import pytest

from calendaring.core.errors import SimulationError
from calendaring.engine.simulation import Simulation
from tests.engine.helpers import frictionless_pair, random_gas

# the workers of a launch on every core of this process: outside the pinned parallel workers
pytestmark = pytest.mark.multicore


def _gas_run(steps_per_launch, n_steps=6000, interval=1, chunks=6, callback_interval=0,
             **contact):
    """300 spheres falling under gravity onto the bottom plate, the top plate coming down:
    plate contacts, pair contacts and several Verlet rebuilds."""
    cfg = frictionless_pair(restitution=0.5, friction=0.3, rolling=0.05, gravity=9.81,
                            steps_per_launch=steps_per_launch,
                            rebuild_check_interval=interval, **contact)
    sim = Simulation(cfg, capacity=400)
    pos, rad, vel = random_gas(sim, 300, 2e-6, 4e-6, 1, 0.0, 60e-6, speed=2.0)
    sim.add_particles(pos, rad, np.zeros(len(rad), int), velocity=vel)
    sim.set_top_plate(z=60e-6, velocity=-5.0)
    seen = []
    traj = []
    try:
        for _ in range(chunks):
            sim.run(n_steps // chunks, callback=lambda s: seen.append(s.step_count),
                    callback_interval=callback_interval)
            traj.append(sim.state()["position"].copy())
        return dict(traj=np.array(traj), trace=sim.take_trace(), rebuilds=sim.n_rebuilds,
                    steps=sim.step_count, time=sim.time, z_top=sim.z_top, seen=seen,
                    energy=sim.energy())
    finally:
        sim.destroy()


@pytest.mark.parametrize("interval", [1, 7])
def test_multi_step_launches_follow_the_one_step_path(interval):
    ref = _gas_run(1, interval=interval, callback_interval=250)
    got = _gas_run(1024, interval=interval, callback_interval=250)
    assert got["steps"] == ref["steps"] == 6000
    assert got["time"] == ref["time"] and got["z_top"] == ref["z_top"]
    # the rebuilds happen after the same steps, so the candidate lists (and the order of
    # every per-particle sum) are the same: positions agree to the last bits
    assert got["rebuilds"] == ref["rebuilds"] >= 3
    np.testing.assert_allclose(got["traj"], ref["traj"], rtol=1e-12, atol=1e-20)
    # the plate trace: same steps and plate heights; forces to rounding (atomic sums)
    assert np.array_equal(got["trace"][:, :2], ref["trace"][:, :2])
    np.testing.assert_allclose(got["trace"][:, 2:], ref["trace"][:, 2:], rtol=1e-9,
                               atol=1e-12 * np.abs(ref["trace"][:, 2:]).max())
    assert np.abs(ref["trace"][:, 2:]).max() > 0  # the plates were loaded
    assert got["seen"] == ref["seen"] == list(range(250, 6001, 250))
    scale = max(abs(v) for v in ref["energy"].values())
    for key, value in ref["energy"].items():
        assert got["energy"][key] == pytest.approx(value, abs=1e-9 * scale), key


def test_plate_history_is_followed_step_by_step():
    """A piecewise-linear plate history inside one launch: the same heights as step by step."""
    out = {}
    for spl in (1, 4096):
        cfg = frictionless_pair(gravity=9.81, steps_per_launch=spl, rebuild_check_interval=1)
        sim = Simulation(cfg, capacity=50)
        pos, rad, _ = random_gas(sim, 30, 3e-6, 4e-6, 2, 0.0, 40e-6)
        sim.add_particles(pos, rad, np.zeros(len(rad), int))
        sim.set_top_plate(z=50e-6)
        sim.prime()
        t = 1500 * sim.dt
        sim.set_top_plate_history([0.0, 0.3 * t, t], [50e-6, 45e-6, 47e-6])
        sim.run(1700)
        out[spl] = sim.take_trace()
        sim.destroy()
    assert np.array_equal(out[1][:, :2], out[4096][:, :2])
    assert out[1][-1, 1] == pytest.approx(47e-6)


def test_workers_that_cannot_all_start_fall_back_to_one_launch_per_step(caplog):
    """More workers than the CPU thread pool holds: the rendezvous times out, nothing is
    done by the burst, and the run continues (and ends the same) one launch per step."""
    ref = _gas_run(1, n_steps=600, chunks=1)
    cfg = frictionless_pair(restitution=0.5, friction=0.3, rolling=0.05, gravity=9.81,
                            steps_per_launch=1024, rebuild_check_interval=1)
    sim = Simulation(cfg, capacity=400)
    sim.kernels.workers = 64  # compiled into the burst kernel at its first launch
    pos, rad, vel = random_gas(sim, 300, 2e-6, 4e-6, 1, 0.0, 60e-6, speed=2.0)
    sim.add_particles(pos, rad, np.zeros(len(rad), int), velocity=vel)
    sim.set_top_plate(z=60e-6, velocity=-5.0)
    try:
        with caplog.at_level("WARNING", logger="calendaring.engine.simulation"):
            sim.run(600)
        assert not sim._burst_ok
        assert any("did not all start" in r.message for r in caplog.records)
        assert sim.step_count == 600
        np.testing.assert_allclose(sim.state()["position"], ref["traj"][-1], rtol=1e-12,
                                   atol=1e-20)
    finally:
        sim.destroy()


@pytest.mark.parametrize("interval", [30, 50])
def test_a_guard_inside_a_launch_stops_the_run_where_one_step_launches_do(interval):
    """A sphere crossing the Verlet skin in a few steps: the skin guard fires inside a
    multi-step launch and the run stops at the same step, with the same message, as with
    one launch per step."""
    errors = {}
    for spl in (1, 4096):
        cfg = frictionless_pair(steps_per_launch=spl, rebuild_check_interval=interval,
                                skin=0.1e-6)
        sim = Simulation(cfg, capacity=4)
        sim.add_particles([[20e-6, 30e-6, 30e-6]], [3e-6], [0], velocity=[[500.0, 0, 0]])
        try:
            with pytest.raises(SimulationError, match="skin") as err:
                sim.run(2000)
            errors[spl] = (str(err.value), err.value.step, sim.step_count)
        finally:
            sim.destroy()
    assert errors[1] == errors[4096]
    assert 0 < errors[1][1] <= errors[1][2] < 2000 and errors[1][2] % interval == 0
