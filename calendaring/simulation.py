"""The DEM engine: owns the particle pool, neighbour grid, contact table and kernels.

Typical use::

    from calendaring.config import SimConfig
    from calendaring.simulation import Simulation

    sim = Simulation(SimConfig(), capacity=1000)
    sim.add_particles(position, radius, material)
    sim.set_top_plate(z=80e-6, velocity=-0.05)
    sim.run(10_000)
    print(sim.top_pressure(), sim.energy())

Order of one step (spec 5.11 without bonds and breakage): kick + drift + plate contacts,
every ``rebuild_check_interval`` steps a host check of the device flags (guards and the
Verlet rebuild trigger), pair contacts. The time step is ``timestep_fraction`` x the Rayleigh
time of the smallest particle (``calendaring.timestep``), fixed when the run starts.
"""

from __future__ import annotations

import math

import numpy as np

from calendaring.backend import init_taichi
from calendaring.config import SimConfig
from calendaring.contacts import ContactTable
from calendaring.errors import ConfigError, SimulationError
from calendaring.forces import GUARD_NAMES, GUARD_SKIN, LEDGER, Kernels
from calendaring.neighbours import CellGrid
from calendaring.state import ParticlePool
from calendaring.timestep import critical_timestep


class Simulation:
    """A periodic (x, y) DEM cell between a fixed bottom plate and a moving top plate.

    Args:
        cfg: configuration (materials, contact laws, domain, numerics).
        capacity: particle-pool capacity (slots for all particles ever present).
        min_radius: smallest radius per material name that may appear later (fragments);
            included in the time-step minimum.
        z_bottom: height of the bottom plate surface [m].
    """

    def __init__(self, cfg: SimConfig, capacity: int, min_radius: dict[str, float] | None = None,
                 z_bottom: float = 0.0) -> None:
        nm = cfg.numerics
        self.backend = init_taichi(arch=nm.arch, precision=nm.precision, seed=nm.seed,
                                   threads=nm.threads, offline_cache=nm.offline_cache)
        self.cfg = cfg
        self.material_names = cfg.material_names
        self.pool = ParticlePool(capacity)
        self.kernels = Kernels(cfg)
        self.grid: CellGrid | None = None
        self.table: ContactTable | None = None
        self.min_radius = {self.material_names.index(k): v for k, v in (min_radius or {}).items()}
        self.z_bottom = float(z_bottom)
        self.z_top = float(z_bottom + cfg.domain.height)
        self.v_top = 0.0
        self._plate_schedule = None  # (times, z) for a displacement history
        self.dt: float | None = None
        self.step_count = 0
        self.time = 0.0
        self._primed = False
        self._r_max = 0.0
        self.n_rebuilds = 0

    # ------------------------------------------------------------------ set-up
    def add_particles(self, position, radius, material, velocity=None,
                      angular_velocity=None) -> np.ndarray:
        """Add spheres (material given by index or name); returns their ids."""
        radius = np.asarray(radius, dtype=float).reshape(-1)
        material = np.asarray(material).reshape(-1)
        if material.dtype.kind in "US":
            material = np.array([self.material_names.index(m) for m in material])
        material = material.astype(np.int32)
        if material.size and (material.min() < 0 or material.max() >= len(self.material_names)):
            raise ConfigError("material", material.max(), f"indices 0..{len(self.material_names)-1}")
        rho = np.array([self.cfg.materials[n].density for n in self.material_names])
        mass = self.cfg.numerics.density_scaling * rho[material] * (4.0 / 3.0) * math.pi * radius**3
        ids = self.pool.add(position, radius, material, mass, velocity=velocity,
                            angular_velocity=angular_velocity)
        if radius.size and radius.max() > self._r_max:
            if self.grid is not None and 2 * radius.max() + self.cfg.numerics.skin > self.grid.cutoff:
                self._drop_grid()
            self._r_max = float(radius.max())
        self._primed = False
        return ids

    def _drop_grid(self) -> None:
        if self.grid is not None:
            self.grid.destroy()
            self.grid = None

    def set_top_plate(self, z: float | None = None, velocity: float = 0.0) -> None:
        """Place the top plate at ``z`` [m] (default: where it is) moving at ``velocity`` [m/s]."""
        if z is not None:
            self.z_top = float(z)
        self.v_top = float(velocity)
        self._plate_schedule = None

    def set_top_plate_history(self, times, z) -> None:
        """Prescribe the top-plate height as a piecewise-linear function of time.

        Args:
            times: increasing times [s] relative to the current simulation time.
            z: plate heights [m] at those times (held at the last value afterwards).
        """
        times = np.asarray(times, float) + self.time
        z = np.asarray(z, float)
        if times.ndim != 1 or times.shape != z.shape or np.any(np.diff(times) <= 0):
            raise ConfigError("plate history", (times.shape, z.shape),
                              "matching 1-D arrays with strictly increasing times")
        self._plate_schedule = (times, z)
        self.z_top = float(np.interp(self.time, times, z))

    def _update_plate(self) -> None:
        if self._plate_schedule is None:
            self.z_top += self.v_top * self.dt
            return
        times, z = self._plate_schedule
        t = self.time + self.dt
        z_new = float(np.interp(t, times, z))
        self.v_top = (z_new - self.z_top) / self.dt
        self.z_top = z_new

    def compute_timestep(self) -> float:
        """dt = timestep_fraction x smallest Rayleigh time of the particles present [s]."""
        arr = self.pool.to_numpy(("radius", "material", "alive"))
        live = arr["alive"] == 1
        mats = [self.cfg.materials[n] for n in self.material_names]
        return critical_timestep(arr["radius"][live], arr["material"][live], mats,
                                 self.cfg.numerics.timestep_fraction,
                                 self.cfg.numerics.density_scaling, self.min_radius)

    # ------------------------------------------------------------------ neighbour list
    def _ensure_grid(self) -> None:
        if self.grid is None:
            d = self.cfg.domain
            cutoff = 2.0 * self._r_max + self.cfg.numerics.skin
            self.grid = CellGrid(self.pool.capacity, d.cell_x, d.cell_y, self.z_bottom,
                                 self.z_bottom + d.height, cutoff)
        if self.table is None:
            cap = max(64, self.cfg.numerics.pairs_per_particle * self.pool.capacity)
            self.table = ContactTable(self.pool.capacity, cap)

    def rebuild(self) -> None:
        """Rebuild the candidate-pair list, keeping every contact's history."""
        self._ensure_grid()
        skin = self.cfg.numerics.skin
        self.table.save_history(self.pool)
        self.grid.bin(self.pool)
        total = self.table.count_candidates(self.pool, self.grid, skin)
        if total > self.table.capacity:
            new_cap = int(total * 1.5) + 64
            bigger = ContactTable(self.pool.capacity, new_cap)
            bigger.copy_from(self.table)
            self.table.destroy()
            self.table = bigger
            self.table.save_history(self.pool)
            total = self.table.count_candidates(self.pool, self.grid, skin)
        self.table.fill_candidates(self.pool, self.grid, skin)
        self.table.remap_history(self.pool)
        self.table.reset_displacements(self.pool)
        self.kernels.need_rebuild[None] = 0
        self.n_rebuilds += 1

    # ------------------------------------------------------------------ stepping
    def _advance(self, kick: float, drift: float) -> None:
        d = self.cfg.domain
        self.kernels.advance(self.pool, kick, drift, self.dt, d.gravity, self.z_bottom,
                             self.z_top, self.v_top, d.cell_x, d.cell_y,
                             0.5 * self.cfg.numerics.skin, self.step_count)

    def _pairs(self, dt: float) -> None:
        self.kernels.pair_forces(self.pool, self.table, self.grid, dt,
                                 self.cfg.numerics.max_overlap_fraction, self.step_count)

    def prime(self) -> None:
        """Compute dt, build the neighbour list and the forces at the current state."""
        if self.pool.n_alive() == 0:
            raise SimulationError("no particles: add particles before running")
        self.dt = self.compute_timestep()
        self._ensure_grid()
        self.rebuild()
        self._advance(0.0, 0.0)
        self._pairs(0.0)
        self.check()
        self._primed = False if self.dt is None else True
        self._first_kick = True

    def run(self, n_steps: int, callback=None, callback_interval: int = 0) -> None:
        """Advance ``n_steps`` time steps.

        Args:
            n_steps: number of steps.
            callback: optional ``f(sim)`` called every ``callback_interval`` steps.
        """
        if not self._primed:
            self.prime()
        interval = self.cfg.numerics.rebuild_check_interval
        for _ in range(int(n_steps)):
            self._update_plate()
            kick = 0.5 if self._first_kick else 1.0
            self._first_kick = False
            self._advance(kick, 1.0)
            self.step_count += 1
            self.time += self.dt
            if self.step_count % interval == 0:
                self.check()
                if self.kernels.need_rebuild[None]:
                    self.rebuild()
            self._pairs(self.dt)
            if callback is not None and callback_interval and self.step_count % callback_interval == 0:
                callback(self)
        self.check()

    def check(self) -> None:
        """Raise :class:`SimulationError` if a device guard fired (host sync)."""
        self.pool.check_overflow()
        if int(self.kernels.guard_count[None]) == 0:
            return
        code = int(self.kernels.guard_code[None])
        slot = int(self.kernels.guard_slot[None])
        step = int(self.kernels.guard_step[None])
        value = float(self.kernels.guard_value[None])
        pid = int(self.pool.pid[slot])
        what = GUARD_NAMES.get(code, f"guard {code}")
        hint = " (reduce numerics.rebuild_check_interval or increase numerics.skin)" \
            if code == GUARD_SKIN else ""
        raise SimulationError(
            f"simulation stopped at step {step}: {what}{hint}; particle id {pid} "
            f"(slot {slot}), value {value:.6g}, position {self.pool.position[slot].to_numpy()}",
            step=step, particle_ids=[pid])

    # ------------------------------------------------------------------ observables
    def plate_forces(self) -> tuple[np.ndarray, np.ndarray]:
        """Forces ON the (bottom, top) plates at the last step [N]."""
        f = self.kernels.plate_force.to_numpy()
        return f[0], f[1]

    @property
    def cell_area(self) -> float:
        """Plate area of the periodic cell [m^2]."""
        return self.cfg.domain.cell_x * self.cfg.domain.cell_y

    def top_pressure(self) -> float:
        """Normal force on the top plate / cell area [Pa] (positive in compression)."""
        return float(self.plate_forces()[1][2]) / self.cell_area

    def bottom_pressure(self) -> float:
        """Normal force on the bottom plate / cell area [Pa] (positive in compression)."""
        return float(-self.plate_forces()[0][2]) / self.cell_area

    def energy(self) -> dict[str, float]:
        """Energy ledger [J] (Yade-style): stored terms now and dissipation accumulated.

        ``total`` = kinetic + rotational + gravity potential + elastic + every dissipated
        term - work done by the plates; it is constant up to the integration error.
        ``plastic`` = hysteretic work - elastic energy still stored in the contacts.
        """
        if not self._primed:
            self.prime()
        d = self.cfg.domain
        ek, er, eg, ee = self.kernels.energies(self.pool, self.table, self.grid, self.dt,
                                               d.gravity, self.z_bottom, self.z_top).to_numpy()
        led = dict(zip(LEDGER, self.kernels.ledger.to_numpy(), strict=True))
        out = {"kinetic": ek, "rotational": er, "gravity": eg, "elastic": ee, **led}
        out["plastic"] = led["hysteretic_work"] - ee
        out["total"] = (ek + er + eg + ee + led["damping_normal"] + led["damping_tangential"]
                        + led["friction"] + led["rolling"] + out["plastic"] - led["plate_work"])
        return out

    def state(self) -> dict[str, np.ndarray]:
        """Live particles as NumPy arrays (velocities synchronised to the current step)."""
        names = ("pid", "alive", "material", "radius", "mass", "position", "velocity",
                 "angular_velocity", "force", "torque", "inv_mass", "inv_inertia",
                 "normal_force_sum", "n_contacts", "parent_id")
        a = self.pool.to_numpy(names)
        live = a.pop("alive") == 1
        a = {k: v[live] for k, v in a.items()}
        if self.dt is not None and self._primed:
            a["velocity"] = a["velocity"] + 0.5 * self.dt * a["inv_mass"][:, None] * a["force"]
            a["angular_velocity"] = (a["angular_velocity"]
                                     + 0.5 * self.dt * a["inv_inertia"][:, None] * a["torque"])
        a["id"] = a.pop("pid")
        return a

    def destroy(self) -> None:
        """Free every device allocation of this simulation."""
        for obj in (self.pool, self.kernels, self.grid, self.table):
            if obj is not None:
                obj.destroy()
        self.grid = self.table = None
