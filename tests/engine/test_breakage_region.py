"""The energy a particle replacement removes, evaluated over the breakage region only.

``Simulation._replace`` books the stored energy (kinetic, rotational, gravity, contact
elastic) that the replacement of broken parents by fragments removes. It evaluates it over
the parents, the fragments and every particle touching or bonded to a parent
(``Kernels.mark_breakage_region``) instead of the whole bed. The rest of the bed does not
change, so both give the same ledger to round-off, while the dynamics are untouched.
"""


import numpy as np
import pytest

from calendaring.core.config import load_config_dict
from calendaring.engine.kernels.constants import L_HYST
from calendaring.engine.simulation import Simulation
from tests.engine.helpers import doom


def _cfg():
    return load_config_dict({
        "domain": {"cell_x": 40e-6, "cell_y": 40e-6, "height": 40e-6, "gravity": 9.81},
        "numerics": {"timestep_fraction": 0.2, "rebuild_check_interval": 1},
        "breakage": {"fragment_timestep_fraction": 0.3}})


def _bed(local: bool) -> Simulation:
    """Two doomed AM parents in a cluster of AM and bonded CB spheres; they break at the
    first step."""
    cfg = _cfg()
    rng = np.random.default_rng(11)
    rp = 4e-6
    am = np.array([[12e-6, 12e-6, 8e-6], [22e-6, 12e-6, 8e-6], [12e-6, 22e-6, 8e-6],
                   [22e-6, 22e-6, 8e-6], [17e-6, 17e-6, 15.5e-6]])
    pos, rad = list(am), [rp] * len(am)
    for k, c in enumerate(am):  # CB spheres just inside bonding reach of each AM sphere
        placed = 0
        while placed < 4:
            u = rng.normal(size=3)
            x = c + u / np.linalg.norm(u) * (rp + 1.3e-6)
            if x[2] > 1.5e-6 and all(np.linalg.norm(x - y) > 1.4e-6 + r or q == k
                                     for q, (y, r) in enumerate(zip(pos, rad, strict=True))):
                pos.append(x)
                rad.append(1.4e-6)
                placed += 1
    pos, rad = np.array(pos), np.array(rad)
    cb = rad[len(am):]
    mat = ["AM"] * len(am) + ["CB"] * len(cb)
    sim = Simulation(cfg, capacity=2000)
    sim.local_energy = local
    vel = rng.normal(scale=0.05, size=(len(rad), 3))
    sim.add_particles(pos, rad, mat, velocity=vel)
    sim.set_top_plate(z=21e-6, velocity=-1.0)
    sim.create_bonds()
    sim.start_breakage()
    for pid, factor in ((0, 50.0), (4, 20.0)):
        doom(sim, pid, factor)
    return sim


def test_region_energy_of_a_replacement_matches_the_whole_bed():
    runs = {}
    for local in (True, False):
        sim = _bed(local)
        try:
            assert sim.bonds is not None and int(sim.bonds.n_bonds[None]) > 10
            sim.run(5)
            doom(sim, 3, 30.0)
            sim.run(55)
            events = sim.take_breakage()
            total = sim.energy()
            runs[local] = {
                "ledger": sim.breakage_ledger, "hyst": float(sim.kernels.ledger[L_HYST]),
                "events": sum(len(e["parent_id"]) for e in events),
                "steps": [int(e["step"]) for e in events],
                "state": sim.state(), "scale": abs(total["kinetic"]) + abs(total["elastic"])}
        finally:
            sim.destroy()
    loc, whole = runs[True], runs[False]
    assert loc["events"] >= 3 and len(loc["steps"]) >= 2  # two replacement steps at least
    assert loc["steps"] == whole["steps"]
    # the evaluation does not feed back into the dynamics: the same bits
    for key in ("position", "velocity", "angular_velocity"):
        assert np.array_equal(loc["state"][key], whole["state"][key])
    assert loc["ledger"] != 0.0
    scale = max(whole["scale"], abs(whole["ledger"]))
    assert loc["ledger"] == pytest.approx(whole["ledger"], rel=1e-9, abs=1e-12 * scale)
    assert loc["hyst"] == pytest.approx(whole["hyst"], rel=1e-9, abs=1e-12 * scale)
