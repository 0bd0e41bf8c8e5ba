"""The DEM engine: owns the particle pool, neighbour grid, contact table and kernels.

Typical use::

    from calendaring.core.config import SimConfig
    from calendaring.engine.simulation import Simulation

    sim = Simulation(SimConfig(), capacity=1000)
    sim.add_particles(position, radius, material)
    sim.set_top_plate(z=80e-6, velocity=-0.05)
    sim.run(10_000)
    print(sim.top_pressure(), sim.energy())

Order of one step (spec 5.11), all in one kernel launch (``Kernels.step``): kick + drift +
plate contacts, pair contacts and bonds (each writes its loads in its own slot; one loop
over particles then sums them in a fixed order, without atomic adds on the particle loads;
plate forces and the energy ledger are summed by chunks of items in a fixed order; stressing
work banked by ending contacts, energy released by failing bonds and the order of
simultaneous breakage events still use atomics, so runs on different thread counts agree
to rounding, not bit for bit), then the breakage test (stressing energy, events, damage).
Back on the host: every ``rebuild_check_interval`` steps the device flags are acted on (a
guard stops the run; the Verlet rebuild trigger rebuilds the candidate list before the
next step: the list stays valid until a particle moved skin/2, which is a guard), and when
some particle broke, its replacement by fragments, a neighbour rebuild and the forces of
the step recomputed (see :mod:`calendaring.engine.breakage_kernels`). On the CPU up to
``numerics.steps_per_launch`` such steps run in one launch (``Kernels.burst``, persistent
worker threads meeting at barriers), which returns after the step whose flags the host must
act on: the same steps, bit for bit on one thread. The time step is
``timestep_fraction`` x the Rayleigh time of the smallest particle
(``calendaring.engine.timestep``), and with breakage at most
``breakage.fragment_timestep_fraction`` x the Rayleigh time of the smallest fragment; it is
fixed when the run starts.

See also: :mod:`calendaring.engine.forces` (the per-step kernels),
:mod:`calendaring.process.run` (the staged run that drives a Simulation).
"""

from __future__ import annotations

import functools
import logging
import math
import time
from contextlib import contextmanager

import numpy as np

from calendaring.core.config import SimConfig
from calendaring.core.errors import ConfigError, SimulationError
from calendaring.engine.backend import init_taichi
from calendaring.engine.contacts import ContactTable
from calendaring.engine.forces import Kernels
from calendaring.engine.kernels.constants import (
    GUARD_NAMES,
    GUARD_SKIN,
    GUARD_SYNC,
    L_HYST,
    LEDGER,
    TRACE_LEN,
)
from calendaring.engine.neighbours import CellGrid, space_filling_order
from calendaring.engine.state import ParticlePool
from calendaring.engine.timestep import critical_timestep, fragment_timestep

log = logging.getLogger(__name__)


def _timed(name: str):
    """Method decorator: each call's wall time is booked under phase ``name``
    (:meth:`Simulation.phase`)."""
    def wrap(method):
        @functools.wraps(method)
        def timed(self, *args, **kwargs):
            with self.phase(name):
                return method(self, *args, **kwargs)
        return timed
    return wrap


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
        self.n_resorts = 0  # re-stores along the space-filling curve (:meth:`resort`)
        self._sorted_slots = 0  # slots in use after the last host insertion or resort
        self.gravity = float(cfg.domain.gravity)  # body force per unit mass along -z [m s^-2]
        self.bonds = None  # BondTable once create_bonds() ran
        self.check_interval = cfg.numerics.rebuild_check_interval  # steps between host checks
        self.steps_per_launch = cfg.numerics.steps_per_launch
        self._burst_ok = self.kernels.workers > 0  # CPU: multi-step launches
        self._trace_n = 0
        self._trace_z = np.zeros(TRACE_LEN)
        self._trace_steps = np.zeros(TRACE_LEN, np.int64)
        self._traced: list[np.ndarray] = []
        self.breakage_on = self.kernels.breakage  # breakage.enabled and a breakable material
        self.breakage = None  # BreakageKernels, made at prime() (scratch sized from the bed)
        self._breakage_dmax = 0.0
        self._fracture_init_upto = 0  # slots whose fracture energy has been drawn
        self.breakage_ledger = 0.0  # stored energy removed by particle replacements [J]
        self.n_breakage_events = 0
        self._break_log: list[dict] = []
        self.breakage_active = True  # False: stressing energy is not evaluated (no breakage)
        self.local_energy = True  # a replacement's energy change over its region only
        self._mark = None  # per slot: the region of a replacement (made with the breakage)
        self._mark_tree = None
        # wall seconds and calls per host-side phase (see :meth:`phase`)
        self.phase_seconds: dict[str, float] = {}
        self.phase_calls: dict[str, int] = {}
        self._phase_stack: list[list[float]] = []

    @contextmanager
    def phase(self, name: str):
        """Book the wall time of a block under ``name`` in :attr:`phase_seconds` (and one
        call in :attr:`phase_calls`), exclusive of the phases nested inside it: ``steps``
        (time-step launches), ``rebuild`` (neighbour lists), ``breakage`` (replacing broken
        particles, without its rebuild), ``checks`` and ``trace``; the run adds its own."""
        t0 = time.perf_counter()
        self._phase_stack.append([0.0])
        try:
            yield
        finally:
            inner = self._phase_stack.pop()[0]
            el = time.perf_counter() - t0
            self.phase_seconds[name] = self.phase_seconds.get(name, 0.0) + el - inner
            self.phase_calls[name] = self.phase_calls.get(name, 0) + 1
            if self._phase_stack:
                self._phase_stack[-1][0] += el

    # ------------------------------------------------------------------ set-up
    def add_particles(self, position, radius, material, velocity=None,
                      angular_velocity=None, order: str = "input") -> np.ndarray:
        """Add spheres (material given by index or name); returns their ids, in input order.

        ``order`` is where they go in the pool: ``"input"`` (default), slot order = input
        order; ``"space"``, along a space-filling curve
        (:func:`calendaring.engine.neighbours.space_filling_order`), so that particles close in
        space sit in nearby slots: the step's loops then reuse cached data, and the threads
        of a multi-step launch share cache lines only along the boundaries of their regions.
        Calendering runs (:mod:`calendaring.process.run`) store their beds in space order. Either
        way :meth:`state` lists particles by id.
        """
        if order not in ("space", "input"):
            raise ConfigError("order", order, "'space' or 'input'")
        radius = np.asarray(radius, dtype=float).reshape(-1)
        material = np.asarray(material).reshape(-1)
        if material.dtype.kind in "US":
            material = np.array([self.material_names.index(m) for m in material])
        material = material.astype(np.int32)
        if material.size and (material.min() < 0 or material.max() >= len(self.material_names)):
            raise ConfigError("material", material.max(),
                              f"indices 0..{len(self.material_names) - 1}")
        rho = np.array([self.cfg.materials[n].density for n in self.material_names])
        mass = self.cfg.numerics.density_scaling * rho[material] * (4.0 / 3.0) * math.pi * radius**3
        perm = None
        position = np.asarray(position, dtype=float)
        if order == "space" and np.all(np.isfinite(position)):  # else pool.add says why
            d = self.cfg.domain
            perm = space_filling_order(position, d.cell_x, d.cell_y)
        ids = self.pool.add(position, radius, material, mass, velocity=velocity,
                            angular_velocity=angular_velocity, order=perm)
        self._sorted_slots = self.pool.slots_used
        if radius.size and radius.max() > self._r_max:
            reach = 2 * radius.max() + self.cfg.numerics.skin
            if self.grid is not None and reach > self.grid.cutoff:
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
        dt = critical_timestep(arr["radius"][live], arr["material"][live], mats,
                               self.cfg.numerics.timestep_fraction,
                               self.cfg.numerics.density_scaling, self.min_radius)
        if self.breakage_on:
            for mat in mats:
                if mat.breakable:
                    dt = min(dt, fragment_timestep(self.cfg.breakage, mat,
                                                   self.cfg.numerics.density_scaling))
        return dt

    # ------------------------------------------------------------------ neighbour list
    def _ensure_grid(self) -> None:
        if self.grid is None:
            d = self.cfg.domain
            cutoff = 2.0 * self._r_max + self.cfg.numerics.skin
            self.grid = CellGrid(self.pool.capacity, d.cell_x, d.cell_y, self.z_bottom,
                                 self.z_bottom + d.height, cutoff)
        if self.table is None:  # sized for the particles present; grows when needed
            cap = max(64, self.cfg.numerics.pairs_per_particle * max(1, self.pool.n_alive()))
            self.table = ContactTable(self.pool.capacity, cap)

    @_timed("rebuild")
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
        self.table.build_incoming(self.pool)
        self.table.reset_displacements(self.pool)
        self.kernels.need_rebuild[None] = 0
        self.n_rebuilds += 1

    def _resort_due(self) -> bool:
        """The slots appended since the last sort (fragments, at the tail of the pool) have
        reached ``numerics.resort_fraction`` of the slots sorted then."""
        f = self.cfg.numerics.resort_fraction
        appended = self.pool.slots_used - self._sorted_slots
        return f > 0.0 and appended > 0 and appended >= f * self._sorted_slots

    @_timed("resort")
    def resort(self) -> None:
        """Store the live particles along the space-filling curve again, in slots
        ``0 .. n_alive - 1`` (the slots of dead parents are dropped), then rebuild.

        Fragments are appended at the tail of the pool, so as a bed breaks, the particles
        close in space drift apart in memory and the step's loops reuse less of their
        cached data. Every per-particle array moves with its particle; each contact keeps
        its history and each bond its state under the new slots
        (:meth:`ContactTable.move_slots`, :meth:`BondTable.move_slots`); ids do not change.
        The physics is the same; a particle's contacts are summed in a new order, so the
        run departs from an unsorted one by round-off (tested). A run calls it at the end
        of a replacement step once the fragments appended since the last sort reach
        ``numerics.resort_fraction`` of the slots sorted then: the parents' contacts have
        been ended and their bonds removed by then.
        """
        from calendaring.engine.state import SCALAR_FIELDS, VEC_FIELDS

        if self.grid is None or self.table is None:
            raise SimulationError("resort needs a primed simulation")
        self._ensure_breakage()  # fracture energies drawn for every slot before they move
        n = self.pool.slots_used
        pos = self.pool.position.to_numpy()[:n]
        live = np.nonzero(self.pool.alive.to_numpy()[:n] == 1)[0]
        d = self.cfg.domain
        order = live[space_filling_order(pos[live], d.cell_x, d.cell_y)]
        m = len(order)
        new_of_old = np.full(n, -1, np.int64)
        new_of_old[order] = np.arange(m)
        for name in (*SCALAR_FIELDS, *VEC_FIELDS):
            f = getattr(self.pool, name)
            full = f.to_numpy()
            full[:m] = full[order]
            full[m:n] = 0  # the freed slots as a fresh pool has them
            f.from_numpy(full)
        self.pool.n_slots[None] = m
        self.table.move_slots(new_of_old, self.pool.pid.to_numpy()[:m])
        if self.bonds is not None:
            self.bonds.move_slots(new_of_old)
        self._fracture_init_upto = m
        self._sorted_slots = m
        self.n_resorts += 1
        self.rebuild()

    # ------------------------------------------------------------------ stepping
    def _advance(self, kick: float, drift: float) -> None:
        d = self.cfg.domain
        self.kernels.advance(self.pool, kick, drift, self.dt, self.gravity, self.z_bottom,
                             self.z_top, self.v_top, d.cell_x, d.cell_y,
                             0.5 * self.cfg.numerics.skin, self.step_count, self._trace_n)

    def _pairs(self, dt: float) -> None:
        self.kernels.pair_forces(self.pool, self.table, self.grid, dt,
                                 self.cfg.numerics.max_overlap_fraction, self.step_count)
        if self.bonds is not None:
            d = self.cfg.domain
            self.bonds.compute(self.pool, dt, d.cell_x, d.cell_y, self.step_count)
        self.kernels.gather_pair_forces(self.pool, self.table, self.bonds)

    def _ensure_breakage(self) -> None:
        """Breakage kernels sized for the largest breakable particle; fracture energies of
        the particles added since the last call."""
        from calendaring.engine.breakage import breakable_mask
        from calendaring.engine.breakage_kernels import BreakageKernels

        if not self.breakage_on:
            return
        arr = self.pool.to_numpy(("radius", "material", "alive"))
        sel = (arr["alive"] == 1) & breakable_mask(self.cfg)[arr["material"]]
        d_max = float(2 * arr["radius"][sel].max()) if sel.any() else 0.0
        if self.breakage is None or d_max > self._breakage_dmax:
            if self.breakage is not None:
                self.breakage.destroy()
            self.breakage = BreakageKernels(self.cfg, d_max)
            self._breakage_dmax = d_max
        if self._mark is None:
            import taichi as ti

            fb = ti.FieldsBuilder()
            self._mark = ti.field(ti.i32)
            fb.dense(ti.i, self.pool.capacity).place(self._mark)
            self._mark_tree = fb.finalize()
        if self._fracture_init_upto < self.pool.slots_used:
            self.breakage.init_particles(self.pool, self._fracture_init_upto)
            self._fracture_init_upto = self.pool.slots_used

    def _stored_energy(self, marked: bool = False) -> tuple[float, float]:
        """(kinetic + rotational + gravity + contact elastic, contact elastic) [J] of every
        particle and pair, or (``marked``) of the breakage region only (see
        :meth:`Kernels.mark_breakage_region`); the bonds of a broken particle book their
        energy as ``bond_released`` themselves."""
        args = (self.pool, self.table, self.grid, self.dt, self.gravity, self.z_bottom,
                self.z_top)
        if marked:
            ek, er, eg, ee = self.kernels.energies_marked(*args, self._mark).to_numpy()
        else:
            ek, er, eg, ee = self.kernels.energies(*args).to_numpy()
        return float(ek + er + eg + ee), float(ee)

    @_timed("breakage")
    def _replace(self, n: int) -> None:
        """Replace the ``n`` parents flagged this step by their fragments."""
        track = self.cfg.numerics.track_energy
        # the energy the replacement removes: over the parents, the fragments and whatever
        # touches or is bonded to them (the rest of the bed does not change), unless
        # local_energy is off (every particle and pair; the same to round-off, tested)
        local = track and self.local_energy
        if local:
            self.kernels.mark_breakage_region(self.pool, self.table, self.bonds, self.breakage,
                                              self._mark, n)
            first_fragment = self.pool.slots_used
        if track:
            before, ee_before = self._stored_energy(local)
        d = self.cfg.domain
        self.breakage.replace(self.pool, self.grid, n, self.step_count, self.z_bottom, self.z_top,
                              d.cell_x, d.cell_y)
        if local:
            self.kernels.mark_from(self.pool, self._mark, first_fragment)
        if int(self.breakage.frag_overflow[None]):
            raise SimulationError(f"step {self.step_count}: more fragments than the scratch "
                                  f"size {self.breakage.max_frag} (internal sizing error)",
                                  step=self.step_count)
        self.pool.check_overflow(f" while {n} particle(s) broke at step {self.step_count} "
                                 "(raise breakage.pool_capacity)")
        rec = self.breakage.records(n)
        rec["step"] = self.step_count
        rec["time"] = self.time
        rec["z_top"] = self.z_top
        self._break_log.append(rec)
        self.n_breakage_events += n
        self._fracture_init_upto = self.pool.slots_used
        self.kernels.end_dead_contacts(self.pool, self.table)
        self.rebuild()
        self.breakage.init_new_contacts(self.pool, self.table, self.grid, self.step_count)
        self._recompute_forces()
        if track:
            after, ee_after = self._stored_energy(local)
            self.breakage_ledger += before - after
            # the plastic work done so far is unchanged by the replacement
            self.kernels.ledger[L_HYST] += ee_after - ee_before
        if self._resort_due():
            self.resort()

    def _recompute_forces(self) -> None:
        """Forces of the current step again at the same positions (after a replacement)."""
        d = self.cfg.domain
        slot = self._trace_n - 1 if self._trace_n > 0 else 0
        self.kernels.advance(self.pool, 0.0, 0.0, self.dt, self.gravity, self.z_bottom,
                             self.z_top, self.v_top, d.cell_x, d.cell_y,
                             0.5 * self.cfg.numerics.skin, self.step_count, slot)
        if self._trace_n == 0 and self._traced:  # this step's row went to the host already
            self._traced[-1][-1, 2:] = self.kernels.trace.to_numpy()[0]
        self._pairs(0.0)

    def start_breakage(self) -> None:
        """Switch breakage on with a clean slate: stressing work, events and peak loads of
        the history so far are discarded (fracture energies are kept)."""
        if not self._primed:
            self.prime()
        if self.breakage is not None:
            self.breakage.reset_events(self.pool)
        self.breakage_active = True

    def take_breakage(self) -> list[dict]:
        """Breakage records since the last call (one dict of arrays per breaking step)."""
        out, self._break_log = self._break_log, []
        return out

    def prime(self) -> None:
        """Compute dt, build the neighbour list and the forces at the current state."""
        if self.pool.n_alive() == 0:
            raise SimulationError("no particles: add particles before running")
        self._ensure_breakage()
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

        On the CPU up to ``numerics.steps_per_launch`` steps go to the device in one launch
        (:meth:`Kernels.burst`); the result is the same as one launch per step (bit for bit
        on one thread), the host acting on the device flags after the same steps.

        Args:
            n_steps: number of steps.
            callback: optional ``f(sim)`` called every ``callback_interval`` steps.
        """
        if not self._primed:
            self.prime()
        remaining = int(n_steps)
        while remaining > 0:
            n = min(remaining, self.steps_per_launch, TRACE_LEN - self._trace_n)
            if callback is not None and callback_interval:
                n = min(n, callback_interval - self.step_count % callback_interval)
            with self.phase("steps"):
                done = self._burst(n) if n > 1 and self._burst_ok else self._step()
            remaining -= done
            if callback is not None and callback_interval and \
                    self.step_count % callback_interval == 0:
                callback(self)
        self.check()

    def _step(self) -> int:
        """One step in one launch (:meth:`Kernels.step`); returns 1."""
        d = self.cfg.domain
        self._update_plate()
        kick = 0.5 if self._first_kick else 1.0
        self._first_kick = False
        # advance, pair forces and their gather in one launch; the candidate list is valid
        # while no particle moved more than skin/2 (the guard), so a rebuild flagged by
        # this step's drift is done after its forces, before the next step
        breakage = self.breakage if self.breakage_active else None
        flags = self.kernels.step(self.pool, self.table, self.grid, self.bonds, breakage, kick,
                                  self.dt, self.gravity, self.z_bottom, self.z_top, self.v_top,
                                  d.cell_x, d.cell_y, 0.5 * self.cfg.numerics.skin,
                                  self.step_count, self._trace_n,
                                  self.cfg.numerics.max_overlap_fraction)
        self.time += self.dt
        self._after_steps(np.array([self.z_top]), flags & 7, flags >> 3)
        return 1

    def _plate_path(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Top-plate height [m], velocity [m/s] and time [s] after each of the next ``n``
        steps, with the arithmetic of ``n`` calls of :meth:`_update_plate` (sequential
        sums: the same bits)."""
        dt = self.dt
        steps = np.full(n + 1, dt)
        steps[0] = self.time
        t = np.add.accumulate(steps)  # time after each step: t[k + 1]
        if self._plate_schedule is None:
            dz = np.full(n + 1, self.v_top * dt)
            dz[0] = self.z_top
            return np.add.accumulate(dz)[1:], np.full(n, self.v_top), t[1:]
        times, zs = self._plate_schedule
        z = np.interp(t, times, zs)
        z[0] = self.z_top
        return z[1:], (z[1:] - z[:-1]) / dt, t[1:]

    def _burst(self, n: int) -> int:
        """Up to ``n`` steps in one launch (:meth:`Kernels.burst`); returns the steps done
        (0 when the worker threads could not all start: the engine then stays with one
        launch per step)."""
        d = self.cfg.domain
        z, v, t = self._plate_path(n)
        k = self.kernels
        buf = np.zeros(TRACE_LEN)
        buf[:n] = z
        k.plate_z.from_numpy(buf)
        buf[:n] = v
        k.plate_v.from_numpy(buf)
        breakage = self.breakage if self.breakage_active else None
        done, flags, n_break, status = (int(x) for x in k.burst(
            self.pool, self.table, self.grid, self.bonds, breakage, n,
            0.5 if self._first_kick else 1.0, self.dt, self.gravity, self.z_bottom, d.cell_x,
            d.cell_y, 0.5 * self.cfg.numerics.skin, self.step_count, self._trace_n,
            self.cfg.numerics.max_overlap_fraction, self.check_interval))
        if status == 1:
            self._burst_ok = False
            log.warning("the %d worker threads of a multi-step launch did not all start; "
                        "running one launch per step from here", k.workers)
            return 0
        if done:
            self._first_kick = False
            self.z_top = float(z[done - 1])
            self.v_top = float(v[done - 1])
            self.time = float(t[done - 1])
        if status == 2:
            self.check()
        self._after_steps(z[:done], flags, n_break)
        return done

    def _after_steps(self, z: np.ndarray, flags: int, n_break: int) -> None:
        """Book ``len(z)`` steps just done (top-plate heights ``z``) and act on the device
        flags and breakage count of the last one."""
        done = len(z)
        lo = self._trace_n
        self._trace_z[lo:lo + done] = z
        self._trace_steps[lo:lo + done] = self.step_count + np.arange(1, done + 1)
        self._trace_n += done
        self.step_count += done
        if self._trace_n == TRACE_LEN:
            self._flush_trace()
        if self.step_count % self.check_interval == 0:
            if flags & 3:
                self.check()
            if flags & 4:
                self.rebuild()
        if n_break:
            self._replace(n_break)

    # ------------------------------------------------------------------ stages
    def change_timestep(self, dt: float) -> None:
        """Switch to a new time step between stages (velocities synchronised first) [s]."""
        if not self._primed:
            self.prime()
        self.kernels.synchronise(self.pool, self.dt)
        self.dt = float(dt)
        self._first_kick = True

    def create_bonds(self) -> int:
        """Bond the live particles now (spec 4.1); returns the number of bonds created."""
        from calendaring.engine.bonds import BondTable, make_bonds

        if self.bonds is not None:
            raise SimulationError("bonds exist already: they are created once and never again")
        if not self._primed:
            self.prime()
        arr = self.pool.to_numpy(("pid", "alive", "material", "radius", "position"))
        slots = np.nonzero(arr["alive"] == 1)[0]
        live = {k: v[slots] for k, v in arr.items()}
        live["id"] = live.pop("pid")
        d = self.cfg.domain
        sa, sb, ia, ib, rb = make_bonds(self.cfg.bonds, live, slots, self.material_names,
                                        d.cell_x, d.cell_y)
        self.bonds = BondTable(self.cfg.bonds, len(sa), serial=self.kernels.serial,
                               particle_capacity=self.pool.capacity)
        self.bonds.set_bonds(sa, sb, ia, ib, rb)
        return len(sa)

    @_timed("trace")
    def _flush_trace(self) -> None:
        """Move the device's per-step plate record to the host."""
        n = self._trace_n
        if n:
            forces = self.kernels.trace.to_numpy()[:n]
            self._traced.append(np.column_stack([self._trace_steps[:n], self._trace_z[:n],
                                                 forces]))
            self._trace_n = 0

    def take_trace(self) -> np.ndarray:
        """Per-step plate record since the last call: columns (step, top-plate z [m], z force
        on the bottom plate [N], z force on the top plate [N]); compressive loads give a
        negative bottom and a positive top force."""
        self._flush_trace()
        out = np.concatenate(self._traced) if self._traced else np.zeros((0, 4))
        self._traced = []
        return out

    def contact_stats(self) -> tuple[int, float]:
        """(touching particle pairs, largest overlap / smaller radius) at the last step."""
        n, worst = self.kernels.contact_stats(self.pool, self.table).to_numpy()
        return int(n), float(worst)

    @_timed("checks")
    def check(self) -> None:
        """Raise :class:`SimulationError` if a device guard fired (host sync)."""
        self.pool.check_overflow()
        if int(self.kernels.guard_count[None]) == 0:
            return
        code = int(self.kernels.guard_code[None])
        slot = int(self.kernels.guard_slot[None])
        step = int(self.kernels.guard_step[None])
        value = float(self.kernels.guard_value[None])
        what = GUARD_NAMES.get(code, f"guard {code}")
        if code == GUARD_SYNC:
            raise SimulationError(f"simulation stopped after step {self.step_count}: {what}; "
                                  "give the run its own cores or set "
                                  "numerics.steps_per_launch = 1", step=self.step_count)
        pid = int(self.pool.pid[slot])
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
        ek, er, eg, ee = self.kernels.energies(self.pool, self.table, self.grid, self.dt,
                                               self.gravity, self.z_bottom,
                                               self.z_top).to_numpy()
        led = dict(zip(LEDGER, self.kernels.ledger.to_numpy(), strict=True))
        out = {"kinetic": ek, "rotational": er, "gravity": eg, "elastic": ee, **led}
        out["plastic"] = led["hysteretic_work"] - ee
        out["bond_elastic"] = self.bonds.stored_energy() if self.bonds is not None else 0.0
        out["bond_released"] = float(self.bonds.released[None]) if self.bonds is not None else 0.0
        out["breakage"] = self.breakage_ledger
        out["total"] = (ek + er + eg + ee + led["damping_normal"] + led["damping_tangential"]
                        + led["friction"] + led["rolling"] + out["plastic"] - led["plate_work"]
                        + out["bond_elastic"] + out["bond_released"] + out["breakage"])
        return out

    def state(self) -> dict[str, np.ndarray]:
        """Live particles as NumPy arrays, by id (velocities synchronised to the current step)."""
        names = ("pid", "alive", "material", "radius", "mass", "position", "velocity",
                 "angular_velocity", "force", "torque", "inv_mass", "inv_inertia",
                 "normal_force_sum", "n_contacts", "parent_id", "fracture_energy",
                 "peak_load", "damage_events")
        a = self.pool.to_numpy(names)
        live = np.nonzero(a.pop("alive") == 1)[0]
        live = live[np.argsort(a["pid"][live], kind="stable")]  # by id, whatever the slots
        a = {k: v[live] for k, v in a.items()}
        if self.dt is not None and self._primed:
            a["velocity"] = a["velocity"] + 0.5 * self.dt * a["inv_mass"][:, None] * a["force"]
            a["angular_velocity"] = (a["angular_velocity"]
                                     + 0.5 * self.dt * a["inv_inertia"][:, None] * a["torque"])
        a["id"] = a.pop("pid")
        return a

    # ------------------------------------------------------------------ checkpoints
    _HOST_STATE = ("z_bottom", "z_top", "v_top", "dt", "step_count", "time", "_primed",
                   "_first_kick", "_r_max", "n_rebuilds", "gravity", "check_interval",
                   "_fracture_init_upto", "breakage_ledger", "n_breakage_events",
                   "breakage_active", "n_resorts", "_sorted_slots")

    def save_state(self) -> dict:
        """Everything needed to continue this run bit for bit (host copies, no side effects).

        Keys: ``host`` (scalars), ``pool``, ``table``, ``bonds`` (or None), ``ledger``,
        ``schedule`` (or None) and ``trace`` (unread per-step plate records).
        """
        from calendaring.engine.contacts import PAIR_F64, PAIR_I32
        from calendaring.engine.state import SCALAR_FIELDS, VEC_FIELDS

        if self.grid is None or self.table is None:
            raise SimulationError("save_state needs a primed simulation")
        n = self.pool.slots_used
        pool = {name: getattr(self.pool, name).to_numpy()[:n]
                for name in (*SCALAR_FIELDS, *VEC_FIELDS)}
        pool["next_id"] = int(self.pool.next_id[None])
        t = self.table
        table = {name: getattr(t, name).to_numpy() for name in
                 ("owner", "partner", "partner_id", "spring", "seg_start", "seg_count",
                  *PAIR_F64, *PAIR_I32)}
        table["n_pairs"] = int(t.n_pairs[None])
        table["capacity"] = t.capacity
        host = {k: getattr(self, k) for k in self._HOST_STATE}
        self._flush_trace()
        if self._break_log:
            raise SimulationError("save_state: take_breakage() the pending breakage records first")
        return {
            "host": host, "pool": pool, "table": table,
            "bonds": self.bonds.to_numpy() if self.bonds is not None else None,
            "ledger": self.kernels.ledger.to_numpy(),
            "need_rebuild": int(self.kernels.need_rebuild[None]),
            "schedule": None if self._plate_schedule is None else
            np.vstack(self._plate_schedule),
            "trace": np.concatenate(self._traced) if self._traced else np.zeros((0, 4)),
        }

    def load_state(self, state: dict) -> None:
        """Restore :meth:`save_state` output into this (fresh, same-config) simulation."""
        from calendaring.engine.bonds import BondTable
        from calendaring.engine.contacts import ContactTable
        from calendaring.engine.state import SCALAR_FIELDS, VEC_FIELDS

        pool = state["pool"]
        n = len(pool["alive"])
        if n > self.pool.capacity:
            raise SimulationError(
                f"checkpoint holds {n} slots > pool capacity {self.pool.capacity}")
        for name in (*SCALAR_FIELDS, *VEC_FIELDS):
            f = getattr(self.pool, name)
            full = f.to_numpy()
            full[:] = 0
            full[:n] = pool[name]
            f.from_numpy(full)
        self.pool.n_slots[None] = n
        self.pool.next_id[None] = int(pool["next_id"])
        for k, v in state["host"].items():
            setattr(self, k, v)
        self._drop_grid()
        if self.table is not None:
            self.table.destroy()
        tab = state["table"]
        self.table = ContactTable(self.pool.capacity, int(tab["capacity"]))
        self._ensure_grid()
        for name, arr in tab.items():
            if name not in ("n_pairs", "capacity"):
                getattr(self.table, name).from_numpy(np.asarray(arr))
        self.table.n_pairs[None] = int(tab["n_pairs"])
        self.table.set_constants(self.pool)
        self.table.build_incoming(self.pool)
        self.kernels.ledger.from_numpy(np.asarray(state["ledger"], float))
        self.kernels.need_rebuild[None] = int(state["need_rebuild"])
        sched = state["schedule"]
        self._plate_schedule = None if sched is None else (sched[0].copy(), sched[1].copy())
        if self.bonds is not None:
            self.bonds.destroy()
            self.bonds = None
        if state["bonds"] is not None:
            self.bonds = BondTable(self.cfg.bonds, max(1, int(state["bonds"]["n_bonds"])),
                                   serial=self.kernels.serial,
                                   particle_capacity=self.pool.capacity)
            self.bonds.load(state["bonds"])
        self._trace_n = 0
        self._traced = [np.asarray(state["trace"])] if len(state["trace"]) else []
        self._ensure_breakage()  # scratch kernels only; the per-particle state is in the pool

    def destroy(self) -> None:
        """Free every device allocation of this simulation."""
        for obj in (self.pool, self.kernels, self.grid, self.table, self.bonds, self.breakage):
            if obj is not None:
                obj.destroy()
        if self._mark_tree is not None:
            self._mark_tree.destroy()
        self.grid = self.table = self.bonds = self.breakage = None
        self._mark = self._mark_tree = None
