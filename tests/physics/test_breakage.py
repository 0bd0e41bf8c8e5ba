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
R_T10, E_F_T10 = 3.87e-6, 3212.1  # the spec's sphere (d = 7.74 um) and its E_f [J/kg]


def _pressed_sphere(cfg, speed=0.0):
    """The T10 sphere between the plates (touching both), its fracture energy E_F_T10."""
    sim = Simulation(cfg, capacity=200)
    sim.add_particles([[20e-6, 20e-6, R_T10]], [R_T10], ["AM"])
    sim.set_top_plate(z=2 * R_T10, velocity=-speed)
    sim.prime()
    sim.pool.fracture_energy[0] = E_F_T10
    return sim


def _pressed_energy(cfg, force):
    """Specific stressing energy [J/kg] of the pressed sphere on the EEPA loading branch of
    both plate contacts at the contact force ``force`` [N] (adhesion-free plates):
    sum over the plates of e_p k1_p^(-2/3) f^(5/3) / 2.5, over the mass."""
    am = cfg.materials["AM"]
    mass = am.density * 4 / 3 * math.pi * R_T10**3
    terms = 0.0
    for plate in (cfg.plates.top, cfg.plates.bottom):
        k1 = 4 / 3 * reduced_modulus(am, plate) * math.sqrt(R_T10)
        share = 1 / (1 + (am.youngs_modulus / (1 - am.poisson_ratio**2))
                     / (plate.youngs_modulus / (1 - plate.poisson_ratio**2)))
        terms += share * k1 ** (-1 / 1.5)
    return terms * force ** (2.5 / 1.5) / (2.5 * mass)


def _breaking_force(cfg, e_f=E_F_T10):
    """The contact force [N] at which the pressed sphere's energy reaches ``e_f``."""
    return (e_f / _pressed_energy(cfg, 1.0)) ** (1.5 / 2.5)


def _run_until_broken(sim, max_steps, chunk=50):
    events = []
    while not events and sim.step_count < max_steps:
        sim.run(chunk)
        events = sim.take_breakage()
    return events


def test_t10_single_particle_breaks_at_the_analytic_force():
    cfg = _cfg()
    e_f = E_F_T10
    sim = _pressed_sphere(cfg, speed=0.2)
    events = _run_until_broken(sim, 40_000)
    assert events, "the particle never broke"
    ev = events[0]
    f_b = _breaking_force(cfg)
    assert f_b == pytest.approx(0.03499, rel=2e-3)  # spec section 8
    # the peak load is the sum over both plate contacts: twice the force through the particle
    assert ev["peak"][0] / 2 == pytest.approx(f_b, rel=0.01)
    assert ev["energy"][0] >= e_f and ev["fracture"][0] == e_f
    assert ev["e50"][0] == pytest.approx(3212.1, rel=2e-4)  # spec 5.3 table, d = 7.74 um
    assert ev["parent_id"][0] == 0 and ev["nfrag"][0] >= 2
    sim.destroy()


# ---------------------------------------------------------------- event end rules
def _jittered_descent(sim, speed, period_steps, until):
    """Top plate history: down at ``speed`` on average, with a sin^2 wobble whose peak
    velocity is twice the mean, so that the plate backs off during a third of every
    period (0.22 x speed x period of travel)."""
    period = period_steps * sim.dt
    t = np.arange(0.0, until * sim.dt, period / 32)
    wobble = 2 * speed * period / math.pi
    z0 = sim.z_top
    sim.set_top_plate_history(t, z0 - speed * t - wobble * np.sin(math.pi * t / period) ** 2)


def test_release_rule_keeps_the_event_of_a_jittered_load_open():
    """A plate that backs off by 3 % of the contact overlap for 200 steps in every period
    (step-to-step unloading, as in a jostling bed): the ``release`` rule keeps one event
    open while the plates press on the sphere, and it breaks at the analytic force of a
    monotonic load, as in T10; the spec's ``quiet`` rule ends an event at each back-off,
    restarts the stressing energy from zero and only damages the sphere."""
    speed, period = 0.2, 660  # back-off 0.22 x 0.2 m/s x 660 dt = 8 nm (3 % of delta_b)
    f_b = _breaking_force(_cfg())
    steps = {}
    for rule in ("release", "quiet"):
        cfg = _cfg(event_end_rule=rule)
        sim = _pressed_sphere(cfg)
        _jittered_descent(sim, speed, period, until=40_000)
        events = _run_until_broken(sim, 16_000 if rule == "quiet" else 40_000)
        if rule == "release":
            assert events, "the sphere never broke"
            assert events[0]["peak"][0] / 2 == pytest.approx(f_b, rel=0.01)
            # only the first back-offs, before the overlap exceeds 8 nm, let go of the
            # sphere: events of nearly no energy, damage below 1e-4
            e_f = events[0]["fracture"][0]
            assert e_f == pytest.approx(E_F_T10, rel=1e-4) and events[0]["energy"][0] >= e_f
            steps[rule] = sim.step_count
        else:  # by 1.3 x the steps the release rule needed: no breakage, only damage
            assert sim.step_count > 1.3 * steps["release"]
            assert not events
            assert int(sim.pool.damage_events[0]) >= 5
            assert float(sim.pool.fracture_energy[0]) < E_F_T10
            load = float(sim.pool.normal_force_sum[0]) / 2
            assert load > f_b  # loaded past the monotonic breaking force, unbroken
        sim.destroy()


def _load_back_off_and_lift(rule):
    """The pressed sphere loaded to 70 % of its breaking force at 0.05 m/s, the plate
    backed off 3 % of the travel and held (load about 0.78 of the peak), then lifted clear.
    Returns (sim, its breaking force, the step count of the end of the hold)."""
    cfg = _cfg(event_end_rule=rule)
    f_b = _breaking_force(cfg)
    sim = _pressed_sphere(cfg)
    am = cfg.materials["AM"]
    travel = 0.0  # plate travel to the target load: both plate overlaps
    for plate in (cfg.plates.top, cfg.plates.bottom):
        k1 = 4 / 3 * reduced_modulus(am, plate) * math.sqrt(R_T10)
        travel += (0.7 * f_b / k1) ** (1 / 1.5)
    t_load = travel / 0.05
    z0 = sim.z_top
    times = [0.0, t_load, 1.01 * t_load, 1.5 * t_load, 1.6 * t_load]
    z = [z0, z0 - travel, z0 - 0.97 * travel, z0 - 0.97 * travel, z0 + 1e-6]
    sim.set_top_plate_history(times, z)
    return sim, f_b, int(1.45 * t_load / sim.dt), int(2.5 * t_load / sim.dt)


def test_release_rule_ends_the_event_when_the_plates_let_go_with_the_analytic_damage():
    """Load, back off and hold (:func:`_load_back_off_and_lift`): under the ``release``
    rule the event stays open through the hold (the plates press, no contact loads) and
    nothing is damaged; once the lifted plate lets go of the sphere (the plastic overlap
    of the bottom plate may stay, without force) the event ends and
    E'_f = E_f (1 - D(x)), x = E(f_peak) / E_f (spec 5.5, with the loading-branch energy of
    T10). The spec's ``quiet`` rule already ends the event in the hold, with the same
    damage."""
    for rule in ("release", "quiet"):
        sim, f_b, n_hold, n_end = _load_back_off_and_lift(rule)
        sim.run(n_hold)
        peak = float(sim.pool.peak_load[0]) / 2
        assert peak == pytest.approx(0.7 * f_b, rel=0.02)
        load = float(sim.pool.normal_force_sum[0]) / 2
        assert 0.5 * peak < load < 0.9 * peak and int(sim.pool.n_contacts[0]) == 2
        x = _pressed_energy(sim.cfg, peak) / E_F_T10
        damaged = E_F_T10 * (1 - float(bk.damage(np.array([x]), 5.549)[0]))
        assert damaged < 0.9 * E_F_T10  # x near 0.55: about 12 % damage
        if rule == "release":
            assert int(sim.pool.event_open[0]) == 1 and int(sim.pool.damage_events[0]) == 0
            assert float(sim.pool.fracture_energy[0]) == E_F_T10
        else:
            assert int(sim.pool.damage_events[0]) == 1
            assert float(sim.pool.fracture_energy[0]) == pytest.approx(damaged, rel=2e-3)
        sim.run(n_end - n_hold)
        assert float(sim.pool.normal_force_sum[0]) < 1e-9 * peak
        assert int(sim.pool.event_open[0]) == 0
        assert not sim.take_breakage()
        assert int(sim.pool.damage_events[0]) == 1
        assert float(sim.pool.fracture_energy[0]) == pytest.approx(damaged, rel=2e-3)
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
    ("damage_constant", -1.0), ("event_end_rule", "never")])
def test_bad_breakage_config_names_the_key(key, value):
    from calendaring.core.errors import ConfigError

    with pytest.raises(ConfigError, match=f"breakage.{key}"):
        load_config_dict({"breakage": {key: value}})
