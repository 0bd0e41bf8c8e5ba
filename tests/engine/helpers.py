"""Small builders shared by the engine tests."""

import math

import numpy as np

from calendaring.core.config import load_config_dict
from calendaring.engine.simulation import Simulation


def frictionless_pair(restitution=0.5, plasticity=0.0, friction=0.0, rolling=0.0,
                      exponent=1.5, fraction=0.01, gravity=0.0, **numerics):
    """Config where every pair and particle-plate contact has the given parameters
    (breakage off: these tests are about the contact engine)."""
    pair = {"plasticity_ratio": plasticity, "surface_energy": 0.0, "restitution": restitution,
            "friction": friction, "rolling_friction": rolling}
    return load_config_dict({
        "domain": {"gravity": gravity, "cell_x": 60e-6, "cell_y": 60e-6, "height": 60e-6},
        "contact": {"loading_exponent": exponent,
                    "pairs": {"AM-AM": pair, "AM-CB": pair, "CB-CB": pair},
                    "plate_pairs": {"AM": pair, "CB": pair}},
        "numerics": {"timestep_fraction": fraction, **numerics},
        "breakage": {"enabled": False},
    })


def random_gas(sim: Simulation, n, r_lo, r_hi, seed, z_lo, z_hi, speed=0.0):
    """Non-overlapping random spheres in the periodic cell between z_lo and z_hi."""
    rng = np.random.default_rng(seed)
    lx, ly = sim.cfg.domain.cell_x, sim.cfg.domain.cell_y
    pos, rad = [], []
    tries = 0
    while len(pos) < n and tries < 200000:
        tries += 1
        r = rng.uniform(r_lo, r_hi)
        p = np.array([rng.uniform(0, lx), rng.uniform(0, ly), rng.uniform(z_lo + r, z_hi - r)])
        if pos:
            d = np.array(pos) - p
            d[:, 0] -= lx * np.round(d[:, 0] / lx)
            d[:, 1] -= ly * np.round(d[:, 1] / ly)
            if np.any(np.sqrt((d**2).sum(1)) < np.array(rad) + r):
                continue
        pos.append(p)
        rad.append(r)
    pos, rad = np.array(pos), np.array(rad)
    vel = rng.normal(size=(len(rad), 3)) * speed
    return pos, rad, vel


def jostled_lattice(side: int, layers: int, seed: int, cell: float = 60e-6):
    """``side`` x ``side`` x ``layers`` slightly overlapping spheres on a jittered lattice
    filling the ``cell`` (the periodic cell of :func:`frictionless_pair`), random velocities
    of 0.5 m/s scale; returns (positions, radii, velocities, the height of the top layer's
    tops, where a resting top plate goes)."""
    rng = np.random.default_rng(seed)
    n = side * side * layers
    a = cell / side
    g = (np.arange(side) + 0.5) * a
    x, y, z = np.meshgrid(g, g, (np.arange(layers) + 0.5) * a, indexing="ij")
    pos = np.column_stack([x.ravel(), y.ravel(), z.ravel()]) + rng.normal(0, 0.01 * a, (n, 3))
    rad = rng.uniform(0.5, 0.508, n) * a
    vel = rng.normal(0, 0.5, (n, 3))
    return pos, rad, vel, layers * a


def doom(sim: Simulation, pid: int, factor: float, radius: float = 4e-6) -> None:
    """The AM sphere with id ``pid`` (of ``radius``) breaks at its next step, with stressing
    energy ``factor`` x E50 and a unit fracture energy. Found by id: a replacement may have
    moved it to another slot (``Simulation.resort``)."""
    from calendaring.engine import breakage as bk

    slot = int(np.nonzero(sim.pool.pid.to_numpy()[:sim.pool.slots_used] == pid)[0][0])
    am = sim.cfg.materials["AM"]
    e50 = float(bk.e50(2 * radius, am, sim.cfg.breakage))
    sim.pool.stress_bank[slot] = factor * e50 * am.density * 4 / 3 * math.pi * radius**3
    sim.pool.fracture_energy[slot] = 1.0
