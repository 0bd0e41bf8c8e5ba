"""Tavares UFRJ breakage against the analytic checks of physics-spec section 9 (T8-T17).

Device code is tested through the same kernels the engine runs (``BreakageKernels`` entry
points and small simulations); reference values are computed here from the equations.
"""

import math

import numpy as np
import pytest
from scipy.stats import kstest, lognorm

from calendaring.core.config import load_config_dict, with_overrides
from calendaring.engine import breakage as bk
from calendaring.engine.breakage_kernels import BreakageKernels
from calendaring.engine.contact_params import COL, pair_table, plate_table, reduced_modulus
from calendaring.engine.simulation import Simulation
from calendaring.engine.state import ParticlePool

# the module fixture ``kernels`` keeps one simulation's fields for several tests
pytestmark = pytest.mark.shared_taichi_runtime

TABLE4 = {"gamma": 5.549, "e_inf": 2161.0, "d0": 9.396e-6, "phi": 2.587}


def _cfg(**breakage):
    return load_config_dict({
        "domain": {"cell_x": 40e-6, "cell_y": 40e-6, "height": 40e-6, "gravity": 0.0},
        "numerics": {"timestep_fraction": 0.2, "rebuild_check_interval": 1},
        "bonds": {"enabled": False},
        "breakage": {"fragment_timestep_fraction": 0.3, **breakage}})


@pytest.fixture(scope="module")
def kernels():
    cfg = _cfg()
    sim = Simulation(cfg, capacity=4)  # initialises Taichi
    sim.add_particles([[20e-6, 20e-6, 10e-6]], [4e-6], ["AM"])
    sim.prime()
    return sim.breakage


# ---------------------------------------------------------------- T8 partition
def test_t8_stiffness_partition_values():
    cfg = _cfg()
    pair, plate = pair_table(cfg), plate_table(cfg)
    e = pair[:, :, COL["stiffness_partition"]]
    assert e[0, 0] == pytest.approx(0.5, abs=1e-12)
    assert e[0, 1] == pytest.approx(0.0038, abs=5e-5)  # AM against CB
    assert e + e.T == pytest.approx(np.ones((2, 2)), abs=1e-14)
    assert plate[0, 1, COL["stiffness_partition"]] == pytest.approx(0.5606, abs=5e-5)  # steel
    assert plate[0, 0, COL["stiffness_partition"]] == pytest.approx(0.2974, abs=5e-5)  # Al
    assert bk.device_factor(cfg.materials["AM"], cfg.breakage) == pytest.approx(0.5606, abs=5e-5)


# ---------------------------------------------------------------- T9 contact work
def _approach(sim, speed, n):
    """Move particle 0 along +x at ``speed`` for n steps (infinite inertia: kinematic)."""
    v = np.zeros((sim.pool.capacity, 3))
    v[0, 0] = speed
    sim.pool.velocity.from_numpy(v)
    sim.pool.inv_mass.from_numpy(np.zeros(sim.pool.capacity))
    sim.pool.inv_inertia.from_numpy(np.zeros(sim.pool.capacity))
    sim.run(n)


def test_t9_contact_work_on_loading_unloading_and_small_cycles():
    r = 3e-6
    cfg = load_config_dict({
        "domain": {"cell_x": 40e-6, "cell_y": 40e-6, "height": 40e-6, "gravity": 0.0},
        "numerics": {"rebuild_check_interval": 1},
        "bonds": {"enabled": False},
        "breakage": {"event_end_steps": 10**6, "min_breakable_diameter": 20e-6,
                     "fragment_timestep_fraction": 0.3}})
    sim = Simulation(cfg, capacity=2)
    sim.add_particles([[20e-6 - r, 20e-6, 20e-6], [20e-6 + r, 20e-6, 20e-6]], [r, r],
                      ["AM", "AM"])
    sim.prime()
    am = cfg.materials["AM"]
    k1 = 4 / 3 * reduced_modulus(am, am) * math.sqrt(r / 2)
    n, lam = 1.5, cfg.pair("AM", "AM").plasticity_ratio
    speed = 1.0
    steps = 1500
    _approach(sim, speed, steps)
    table = sim.table.history_arrays()
    d_max = table["delta_max"][0]
    assert d_max == pytest.approx(speed * sim.dt * steps, rel=0.01)
    w1 = k1 * d_max ** (n + 1) / (n + 1)
    assert table["work_a"][0] == pytest.approx(w1, rel=1e-4)
    assert table["work_b"][0] == table["work_a"][0]
    _approach(sim, -speed, steps - 100)  # unload to below the plastic overlap
    delta_p = lam ** (1 / n) * d_max
    assert sim.table.history_arrays()["delta_prev"][0] < delta_p
    w2 = w1 * (1 - lam ** ((n + 1) / n) - (n + 1) * lam * (1 - lam ** (1 / n))) / (1 - lam)
    loop = sim.table.history_arrays()["work_a"][0]
    assert loop == pytest.approx(w1 - w2, rel=1e-3)
    assert w2 / w1 == pytest.approx(0.17064, abs=1e-5)  # spec T1 ratio for lambda = 0.8
    for _ in range(3):  # small cycles below delta_max leave the work unchanged
        _approach(sim, speed, 80)
        _approach(sim, -speed, 80)
    assert sim.table.history_arrays()["work_a"][0] == pytest.approx(loop, rel=1e-6)
    sim.destroy()


# ---------------------------------------------------------------- T10 breakage force
def test_t10_single_particle_breaks_at_the_analytic_force():
    cfg = _cfg()
    r = 3.87e-6
    sim = Simulation(cfg, capacity=200)
    sim.add_particles([[20e-6, 20e-6, r]], [r], ["AM"])
    sim.set_top_plate(z=2 * r, velocity=-0.2)
    sim.prime()
    e_f = 3212.1
    sim.pool.fracture_energy[0] = e_f
    events = []
    while not events and sim.step_count < 40_000:
        sim.run(50)
        events = sim.take_breakage()
    assert events, "the particle never broke"
    ev = events[0]
    am = cfg.materials["AM"]
    mass = 4740.0 * 4 / 3 * math.pi * r**3
    terms = 0.0
    for plate, share in ((cfg.plates.top, 0.5606), (cfg.plates.bottom, 0.2974)):
        k1 = 4 / 3 * reduced_modulus(am, plate) * math.sqrt(r)
        share = 1 / (1 + (am.youngs_modulus / (1 - am.poisson_ratio**2))
                     / (plate.youngs_modulus / (1 - plate.poisson_ratio**2)))
        terms += share * k1 ** (-1 / 1.5)
    f_b = (mass * e_f * 2.5 / terms) ** (1.5 / 2.5)
    assert f_b == pytest.approx(0.03499, rel=2e-3)  # spec section 8
    # the peak load is the sum over both plate contacts: twice the force through the particle
    assert ev["peak"][0] / 2 == pytest.approx(f_b, rel=0.01)
    assert ev["energy"][0] >= e_f and ev["fracture"][0] == e_f
    assert ev["e50"][0] == pytest.approx(3212.1, rel=2e-4)  # spec 5.3 table, d = 7.74 um
    assert ev["parent_id"][0] == 0 and ev["nfrag"][0] >= 2
    sim.destroy()


# ---------------------------------------------------------------- T11 sampling
def _sample(cfg, diameter, n=100_000):
    pool = ParticlePool(n)
    pos = np.zeros((n, 3))
    pos[:, 0] = np.arange(n)
    r = np.full(n, diameter / 2)
    pool.add(pos, r, np.zeros(n, np.int32), np.ones(n))
    kern = BreakageKernels(cfg, diameter)
    kern.init_particles(pool, 0)
    out = pool.fracture_energy.to_numpy()
    kern.destroy()
    pool.destroy()
    return out


def test_t11_fracture_energies_follow_the_truncated_lognormal(kernels):
    cfg = _cfg()
    d = 7.74e-6
    e50 = float(bk.e50(d, cfg.materials["AM"], cfg.breakage))
    factor = bk.truncation_factor(cfg.breakage)
    assert factor == pytest.approx(0.89928)
    e = _sample(cfg, d)
    stat = kstest(e, lambda x: bk.fracture_energy_cdf(x, e50, factor, 0.947)).statistic
    assert stat < 0.01
    assert np.all(e < factor * e50) and np.all(e > 0)
    assert np.median(e) == pytest.approx(e50 * factor / (1 + factor), rel=0.01)
    assert bk.fracture_energy_median(e50, factor) == pytest.approx(0.4735 * e50, rel=1e-3)
    narrow = _sample(load_config_dict({"breakage": {"sigma_e": 1e-4}}), d, 2000)
    assert narrow == pytest.approx(e50 * factor / (1 + factor), rel=1e-3)
    # percentile mode at R_t = 100 %: no truncation, a plain lognormal of median E50
    plain = _sample(load_config_dict({"breakage": {"truncation_mode": "percentile",
                                                   "truncation_ratio": 100.0}}), d, 20_000)
    assert kstest(plain, lognorm(s=0.947, scale=e50).cdf).statistic < 0.02


# ---------------------------------------------------------------- T12 size effect
def test_t12_size_effect_values():
    cfg = _cfg()
    am, b = cfg.materials["AM"], cfg.breakage
    f = bk.device_factor(am, b)
    assert bk.e50(b.d0, am, b) == pytest.approx(2 * b.e_inf * f, rel=1e-12)
    assert bk.e50(1.0, am, b) == pytest.approx(b.e_inf * f, rel=1e-6)
    table = {4.94e-6: 7604, 6e-6: 5077, 7.74e-6: 3212, 9e-6: 2566, 10.69e-6: 2079,
             3e-6: 24440, 2e-6: 67519}
    for d, value in table.items():
        assert bk.e50(d, am, b) == pytest.approx(value, rel=1e-3)


# ---------------------------------------------------------------- T13 damage
def test_t13_damage_root_values_and_repeated_events(kernels):
    x = np.array([0.2, 0.5, 0.8])
    assert kernels.damage_values(x) == pytest.approx([0.012410, 0.100928, 0.342642], abs=2e-6)
    assert bk.damage(x, 5.549) == pytest.approx(kernels.damage_values(x), abs=1e-12)
    assert bk.damage(x, 1.0) == pytest.approx([0.358197, 0.564446, 0.755947], abs=2e-6)
    assert kernels.damage_values(np.array([1 - 1e-9, 1.0]))[1] == 1.0
    assert kernels.damage_values(np.array([0.999999]))[0] > 0.99
    e0, ef = 1.0, 1.0
    ds, ratios = [], []
    broke_at = None
    for event in range(1, 10):  # constant event energy 0.5 E_f0
        if 0.5 * e0 >= ef:
            broke_at = event
            break
        d = float(kernels.damage_values(np.array([0.5 * e0 / ef]))[0])
        ef *= 1 - d
        ds.append(d)
        ratios.append(ef)
    assert ds[:4] == pytest.approx([0.10093, 0.13055, 0.18529, 0.32395], abs=1e-5)
    assert ratios[:4] == pytest.approx([0.89907, 0.78170, 0.63686, 0.43055], abs=1e-5)
    assert broke_at == 5


# ---------------------------------------------------------------- T14 t10 and t_n
def test_t14_t10_and_tn_family(kernels):
    b = _cfg().breakage
    assert bk.t10(0.0, 3000.0, b) == 0.0
    assert bk.t10(1e12, 3000.0, b) == pytest.approx(b.alpha_percentage / 100)
    assert bk.t10(3000.0, 3000.0, b) == pytest.approx(0.34274 * (1 - math.exp(-0.03)))
    for t10 in (0.001, 0.01, 0.05, 0.2, 0.34):
        tn = bk.tn(t10, np.array([2, 4, 10, 25, 50, 75]))
        assert np.all(np.diff(tn) < 0) and tn[2] == pytest.approx(t10, rel=1e-12)
        dev = kernels.progeny_cdf_values(1.0 / np.array([2, 4, 10, 25, 50, 75, 1]), t10)
        assert dev[:6] == pytest.approx(tn, rel=1e-12) and dev[6] == 1.0
        x = np.geomspace(1e-3, 1, 400)
        assert np.all(np.diff(kernels.progeny_cdf_values(x, t10)) >= 0)
    # spec 5.8 example (its figures are those of t10 = 0.0101, the rounded 0.01 of the text)
    assert bk.tn(0.0101, np.array([2, 4, 25, 50, 75])) == pytest.approx(
        [0.0873, 0.0300, 0.0038, 0.0019, 0.0012], abs=5e-5)


# ---------------------------------------------------------------- T15 progeny sizes
def test_t15_progeny_sizes_worked_examples_and_conservation(kernels):
    um = 1e-6
    d = kernels.progeny_diameters(8 * um, 0.0048) / um
    assert d == pytest.approx([7.923, 2.442], abs=1e-3)
    d = kernels.progeny_diameters(8 * um, 0.0101) / um
    assert d == pytest.approx([7.798, 3.099, 2.010], abs=1e-3)
    d = kernels.progeny_diameters(8 * um, 0.05) / um
    assert d == pytest.approx([6.864, 3.877, 3.877] + [2.001] * 9, abs=1e-3)
    d = kernels.progeny_diameters(8 * um, 0.2) / um
    assert len(d) == 36 and d[0] == pytest.approx(4.101, abs=1e-3)
    assert np.sum(np.isclose(d, 3.648, atol=1e-3)) == 4
    rng = np.random.default_rng(1)
    for _ in range(200):
        dp = rng.uniform(4e-6, 10.69e-6)
        t10 = rng.uniform(0, 0.34274)
        d = kernels.progeny_diameters(dp, t10)
        assert len(d) >= 2
        assert abs(np.sum(d**3) / dp**3 - 1) < 1e-12
        binary = len(d) == 2 and d[0] == pytest.approx(d[1], rel=1e-12)
        if not binary:
            assert np.all(d >= 2e-6 * (1 - 1e-9))
        assert np.all(np.diff(d) <= 0)


# ---------------------------------------------------------------- T16 placement
def test_t16_placement_containment_and_centroid(kernels):
    for dp, t10 in ((8e-6, 0.0048), (8e-6, 0.05), (10e-6, 0.2), (5e-6, 0.01)):
        d = kernels.progeny_diameters(dp, t10)
        r, rp = d / 2, dp / 2
        c = kernels.placement(r, rp, key=7)
        assert np.all(np.linalg.norm(c, axis=1) + r <= rp * (1 + 1e-9))
        cm = np.sum(r[:, None] ** 3 * c, axis=0) / np.sum(r**3)
        assert np.linalg.norm(cm) < 1e-9 * rp


def _doomed_parent(velocity, omega, neighbour=False, cfg=None, capacity=400):
    """A parent in free space (optionally touching one CB) that breaks on the next step
    with E_k = 50 E50 (t10 about 0.27, tens of fragments)."""
    cfg = cfg or _cfg()
    sim = Simulation(cfg, capacity=capacity)
    rp = 4e-6
    sim.add_particles([[20e-6, 20e-6, 20e-6]], [rp], ["AM"], velocity=[velocity],
                      angular_velocity=[omega])
    if neighbour:
        sim.add_particles([[20e-6 + rp + 1.2e-6, 20e-6, 20e-6]], [1.5e-6], ["CB"])
    sim.set_top_plate(z=39e-6)
    sim.prime()
    e50 = float(bk.e50(2 * rp, cfg.materials["AM"], cfg.breakage))
    mass = 4740.0 * 4 / 3 * math.pi * rp**3
    sim.pool.stress_bank[0] = 50.0 * e50 * mass
    sim.pool.fracture_energy[0] = 1.0
    return sim


def _broken_cluster(velocity, omega, neighbour=False, cfg=None):
    """:func:`_doomed_parent` after its breakage step: (sim, state before, records)."""
    sim = _doomed_parent(velocity, omega, neighbour, cfg)
    before = sim.state()
    sim.run(1)
    return sim, before, sim.take_breakage()


def test_t16_spawn_conserves_mass_momentum_centroid_and_avoids_new_overlap():
    v, w = [0.3, -0.2, 0.1], [0.0, 0.0, 0.0]
    sim, before, events = _broken_cluster(v, w, neighbour=True)
    assert len(events) == 1 and events[0]["nfrag"][0] > 5
    s = sim.state()
    frag = s["parent_id"] == 0
    assert frag.sum() == events[0]["nfrag"][0]
    assert set(s["id"][frag]) == set(range(int(events[0]["first_id"][0]),
                                           int(events[0]["first_id"][0]) + int(frag.sum())))
    m0 = before["mass"][0]
    assert s["mass"][frag].sum() == pytest.approx(m0, rel=1e-12)
    assert np.sum(s["radius"][frag] ** 3) == pytest.approx(before["radius"][0] ** 3, rel=1e-12)
    centroid = np.sum(s["mass"][frag, None] * s["position"][frag], 0) / m0
    drift = before["velocity"][0] * sim.dt  # the parent moved one step before breaking
    assert np.linalg.norm(centroid - before["position"][0] - drift) < 1e-9 * 4e-6
    cb = s["material"] == 1
    x_cb = s["position"][cb][0]
    parent_overlap = 4e-6 + 1.5e-6 - np.linalg.norm(before["position"][0] + drift - x_cb)
    gaps = 1.5e-6 + s["radius"][frag] - np.linalg.norm(s["position"][frag] - x_cb, axis=1)
    assert np.all(gaps <= parent_overlap + 1e-15)
    sim.destroy()


def test_t16_rigid_body_velocity_and_linear_momentum_with_spin():
    v, w = [0.1, 0.0, -0.2], [1e5, -2e5, 3e4]
    sim, before, _ = _broken_cluster(v, w)
    s = sim.state()
    frag = s["parent_id"] == 0
    p = np.sum(s["mass"][frag, None] * s["velocity"][frag], axis=0)
    p0 = before["mass"][0] * before["velocity"][0]
    assert p == pytest.approx(p0, rel=1e-9, abs=1e-9 * np.linalg.norm(p0))
    assert np.allclose(s["angular_velocity"][frag], w, rtol=1e-12)
    sim.destroy()


# ---------------------------------------------------------------- T17 force-free siblings
def test_t17_force_free_siblings_add_no_force_and_no_kinetic_energy():
    sim, before, events = _broken_cluster([0.2, 0.1, 0.0], [0.0, 0.0, 0.0])
    assert events[0]["nfrag"][0] > 5
    s = sim.state()
    assert np.abs(s["force"]).max() < 1e-12  # every sibling contact starts at zero force
    overlap = sim.table.history_arrays()
    assert np.any(overlap["sibling"] == 1)  # the fragments do overlap
    ke0 = 0.5 * before["mass"][0] * np.sum(np.square(before["velocity"][0]))
    ke = lambda st: 0.5 * np.sum(st["mass"] * np.sum(st["velocity"] ** 2, 1))  # noqa: E731
    assert ke(s) == pytest.approx(ke0, rel=1e-12)
    sim.run(200)
    assert ke(sim.state()) <= ke0 * (1 + 1e-12)
    sim.destroy()


def test_fresh_sibling_start_releases_the_overlap_as_a_force_spike():
    cfg = with_overrides(_cfg(sibling_init="fresh"), {"numerics.max_overlap_fraction": 2.0})
    sim, _, _ = _broken_cluster([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], cfg=cfg)
    assert np.abs(sim.state()["force"]).max() > 1e-3
    sim.destroy()


def test_worst_case_pool_and_fragment_bounds():
    b = _cfg().breakage
    assert bk.worst_case_slots(np.array([8e-6, 3e-6]), np.array([True, False]), b) == \
        2 + 2 * 64 - 2
    assert bk.worst_case_slots(np.array([3.9e-6]), np.array([True]), b) == 1  # too small
    assert bk.max_fragments(8e-6, b) >= 64 + 6


def test_a_full_pool_stops_the_run_with_a_diagnostic():
    from calendaring.core.errors import SimulationError

    sim = _doomed_parent([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], capacity=3)  # room for 2 fragments
    with pytest.raises(SimulationError, match=r"particle pool full.*breakage\.pool_capacity"):
        sim.run(1)
    assert sim.pool.slots_used == 1  # nothing was half-written
    sim.destroy()


@pytest.mark.parametrize("key, value", [
    ("truncation_mode", "median"), ("alpha_percentage", 120.0), ("truncation_ratio", 0.0),
    ("min_breakable_diameter", 3e-6), ("sibling_init", "spiky"), ("shear_weight", 2.0),
    ("damage_constant", -1.0)])
def test_bad_breakage_config_names_the_key(key, value):
    from calendaring.core.errors import ConfigError

    with pytest.raises(ConfigError, match=f"breakage.{key}"):
        load_config_dict({"breakage": {key: value}})
