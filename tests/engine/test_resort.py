"""Re-storing the pool along the space-filling curve mid-run (``Simulation.resort``): the
particles, their contacts' history and their bonds move to new slots, the physics does not
change."""

import math

import numpy as np
import pytest

import calendaring.engine.simulation as simulation
from calendaring.core.config import load_config_dict
from calendaring.core.errors import ConfigError
from calendaring.engine.simulation import Simulation
from tests.engine.helpers import doom

RP = 4e-6  # AM radius [m]


def _cfg(resort_fraction: float):
    return load_config_dict({
        "domain": {"cell_x": 40e-6, "cell_y": 40e-6, "height": 40e-6, "gravity": 9.81},
        "numerics": {"timestep_fraction": 0.2, "rebuild_check_interval": 1,
                     "resort_fraction": resort_fraction},
        "breakage": {"fragment_timestep_fraction": 0.3}})


def _bed(resort_fraction: float = 0.0) -> Simulation:
    """Nine AM spheres, each with four bonded CB spheres just inside bonding reach, squeezed
    by the top plate; AM ids 0 and 4 break at the first step."""
    rng = np.random.default_rng(5)
    am = np.array([[x, y, 5e-6] for x in (8e-6, 18e-6, 28e-6) for y in (8e-6, 18e-6, 28e-6)])
    am[4, 2] = 12.5e-6  # the middle one sits on the others
    pos, rad = list(am), [RP] * len(am)
    for k, c in enumerate(am):
        placed = 0
        while placed < 4:
            u = rng.normal(size=3)
            x = c + u / np.linalg.norm(u) * (RP + 1.3e-6)
            if x[2] > 1.5e-6 and all(np.linalg.norm(x - y) > 1.4e-6 + r or q == k
                                     for q, (y, r) in enumerate(zip(pos, rad, strict=True))):
                pos.append(x)
                rad.append(1.4e-6)
                placed += 1
    mat = ["AM"] * len(am) + ["CB"] * (len(rad) - len(am))
    sim = Simulation(_cfg(resort_fraction), capacity=3000)
    sim.add_particles(np.array(pos), np.array(rad), mat,
                      velocity=rng.normal(scale=0.05, size=(len(rad), 3)))
    sim.set_top_plate(z=19e-6, velocity=-1.0)
    sim.create_bonds()
    sim.start_breakage()
    doom(sim, 0, 50.0)
    doom(sim, 4, 20.0)
    return sim


def _contacts_by_ids(sim):
    """Touching contacts keyed by (lower id, higher id): overlap history, the stressing work
    of each id's side and the tangential spring as the force on the lower id."""
    t = sim.table.history_arrays()
    pid = sim.pool.pid.to_numpy()
    out = {}
    for c in np.nonzero(t["delta_max"] > 0.0)[0]:
        a, b = int(pid[t["owner"][c]]), int(t["partner_id"][c])
        flip = a > b
        work = (t["work_a"][c], t["work_b"][c])
        out[(min(a, b), max(a, b))] = (
            t["delta_max"][c], t["delta_prev"][c], t["fhys_prev"][c],
            *(work[::-1] if flip else work), *(-t["spring"][c] if flip else t["spring"][c]))
    return out


def _bonds_by_ids(sim):
    b = sim.bonds.to_numpy()
    return {(int(x), int(y)): (int(s), float(fn)) for x, y, s, fn in
            zip(b["id_a"], b["id_b"], b["state"], b["f_n"], strict=True)}


def _run(resort: bool, reverse: bool, monkeypatch) -> dict:
    if reverse:  # every pair changes order: the swap of owner and partner is exercised
        monkeypatch.setattr(simulation, "space_filling_order",
                            lambda pos, lx, ly: np.arange(len(pos))[::-1])
    sim = _bed()
    try:
        sim.run(3)  # the two parents broke at the first step; fragments at the tail
        assert sim.n_breakage_events == 2
        doom(sim, 2, 30.0)  # a third one breaks after the move
        slots_before = sim.pool.slots_used
        contacts_before = _contacts_by_ids(sim)
        if resort:
            sim.resort()
            assert sim.n_resorts == 1
            assert sim.pool.slots_used == sim.pool.n_alive() < slots_before
            assert _contacts_by_ids(sim).keys() == contacts_before.keys()
        else:
            sim.rebuild()  # a resort ends with one: the same work apart from the move
        sim.run(400)
        events = sim.take_breakage()
        return {"state": sim.state(), "energy": sim.energy(), "bonds": _bonds_by_ids(sim),
                "contacts": _contacts_by_ids(sim), "top": sim.plate_forces()[1][2],
                "events": [(int(e["step"]), sorted(e["parent_id"].tolist())) for e in events],
                "pid": sim.pool.pid.to_numpy()[:sim.pool.slots_used],
                "moved_contacts": contacts_before}
    finally:
        sim.destroy()


@pytest.mark.parametrize("reverse", [False, True], ids=["space", "reversed"])
def test_resort_keeps_the_physics_of_a_breaking_bonded_bed(reverse, monkeypatch):
    ref = _run(False, False, monkeypatch)
    new = _run(True, reverse, monkeypatch)
    # something to keep: open contacts with history and stressing work, intact bonds
    moved = ref["moved_contacts"]
    assert len(moved) > 20 and any(v[3] > 0 or v[4] > 0 for v in moved.values())
    assert sum(s == 0 for s, _ in ref["bonds"].values()) > 10
    # the pool really moved: ids rise along the slots as the run left them (input order,
    # fragments appended), not after the move, which also dropped the dead parents' slots
    assert np.all(np.diff(ref["pid"]) > 0) and not np.all(np.diff(new["pid"]) > 0)
    assert len(new["pid"]) < len(ref["pid"])
    # the same breakage, after the move too
    assert ref["events"][-1][1] == [2] and new["events"] == ref["events"]
    a, b = ref["state"], new["state"]
    assert np.array_equal(a["id"], b["id"])
    scale_v = np.abs(a["velocity"]).max()
    np.testing.assert_allclose(b["position"], a["position"], rtol=0, atol=1e-15)
    np.testing.assert_allclose(b["velocity"], a["velocity"], rtol=0, atol=1e-8 * scale_v)
    np.testing.assert_allclose(b["angular_velocity"], a["angular_velocity"], rtol=0,
                               atol=1e-8 * np.abs(a["angular_velocity"]).max())
    assert new["top"] == pytest.approx(ref["top"], rel=1e-8)
    scale_e = ref["energy"]["kinetic"] + ref["energy"]["elastic"] + abs(ref["energy"]["total"])
    for key, value in ref["energy"].items():
        assert new["energy"][key] == pytest.approx(value, rel=1e-8, abs=1e-10 * scale_e), key
    assert new["bonds"].keys() == ref["bonds"].keys()
    for key, (state, fn) in ref["bonds"].items():
        assert new["bonds"][key][0] == state
        assert new["bonds"][key][1] == pytest.approx(fn, rel=1e-7, abs=1e-12)
    assert new["contacts"].keys() == ref["contacts"].keys()
    for key, hist in ref["contacts"].items():
        np.testing.assert_allclose(new["contacts"][key], hist, rtol=1e-6,
                                   atol=1e-9 * np.abs(hist).max(), err_msg=str(key))


def test_fragments_trigger_a_resort_only_past_the_fraction():
    counts = {}
    for fraction in (0.0, 0.1, 10.0):
        sim = _bed(fraction)
        try:
            sim.run(60)
            assert sim.n_breakage_events == 2
            counts[fraction] = (sim.n_resorts, sim.pool.slots_used, sim.pool.n_alive())
        finally:
            sim.destroy()
    never, often, rarely = counts[0.0], counts[0.1], counts[10.0]
    assert never[0] == 0 and never[1] == never[2] + 2  # the two parents' slots stay
    assert often[0] == 1 and often[1] == often[2]  # moved once: no dead slot left
    assert rarely[0] == 0  # 10 x the bed in fragments never came


def test_resort_fraction_is_checked():
    with pytest.raises(ConfigError, match="resort_fraction"):
        _cfg(-0.1)
    with pytest.raises(ConfigError, match="resort_fraction"):
        _cfg(math.nan)
