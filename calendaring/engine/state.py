"""Particle pool: Taichi fields with a fixed capacity (one array per field, except the
fields the pair loop reads of both particles, kept together per slot: ``PAIR_READ``).

Slots ``[0, n_slots)`` have been used; a slot holds a live particle while ``alive == 1``.
Ids are never reused. Breakage kills a parent (``alive = 0``) and appends its fragments at
the tail, so contact owners (the lower slot of a pair) stay valid between neighbour-list
rebuilds. Once the appended slots reach ``numerics.resort_fraction`` of the pool,
:meth:`calendaring.engine.simulation.Simulation.resort` stores the live particles along the
space-filling curve again and drops the dead slots, moving contact history and bonds with
them.

Insertion:
- host: :meth:`ParticlePool.add` (arrays in, ids out; ``order`` sets which input goes to
  which slot: :meth:`calendaring.engine.simulation.Simulation.add_particles` stores a bed along a
  space-filling curve, so that neighbours sit in nearby slots);
- device: :func:`allocate_slot` inside a kernel (atomic tail counter); a kernel that runs
  past the capacity sets ``overflow`` and the host raises :class:`SimulationError`.

Every per-particle array is SI: position [m] (f64), velocity [m/s], angular velocity
[rad/s], force [N], torque [N m], radius [m], mass [kg] (density scaling included).

See also: :mod:`calendaring.engine.breakage_kernels` (appends fragments at the tail),
:mod:`calendaring.engine.contacts` (pairs owned by the lower slot, history keyed by id).
"""


import numpy as np
import taichi as ti

from calendaring.core.errors import SimulationError

VEC_FIELDS = ("position", "velocity", "angular_velocity", "force", "torque", "displacement",
              "wall_spring_bottom", "wall_spring_top")
SCALAR_FIELDS = {
    "alive": ti.i32,
    "material": ti.i32,
    "pid": ti.i64,  # stable unique id
    "parent_id": ti.i64,  # id of the particle this one broke from (-1 for originals)
    "root_id": ti.i64,  # id of the original particle this one descends from (itself if original)
    "radius": ti.f64,
    "mass": ti.f64,
    "inv_mass": ti.f64,
    "inv_inertia": ti.f64,
    "roll_magnitude": ti.f64,  # sum over contacts of mu_r |f_hys| |r| this step [N m]
    "normal_force_sum": ti.f64,  # sum over contacts of |F_n| this step [N]
    "n_contacts": ti.i32,  # touching contacts (particles and plates) this step
    "wall_delta_max_bottom": ti.f64,
    "wall_delta_max_top": ti.f64,
    "wall_delta_prev_bottom": ti.f64,
    "wall_delta_prev_top": ti.f64,
    "wall_fhys_prev_bottom": ti.f64,
    "wall_fhys_prev_top": ti.f64,
    # breakage (spec 5.4-5.6); specific energies per unit of true (unscaled) mass
    "fracture_energy": ti.f64,  # current (damaged) fracture energy E'_f [J/kg]
    "stress_sum": ti.f64,  # sum over particle contacts of e_i W_c this step [J]
    "stress_bank": ti.f64,  # shares of contacts that ended during the open event [J]
    "wall_work_bottom": ti.f64,  # stressing work of the bottom-plate contact this event [J]
    "wall_work_top": ti.f64,  # stressing work of the top-plate contact this event [J]
    "event_max": ti.f64,  # largest specific stressing energy of the open event [J/kg]
    "peak_load": ti.f64,  # largest total contact normal force over the particle's life [N]
    "event_open": ti.i32,  # a loading event is open
    "event_quiet": ti.i32,  # steps since a contact of the open event last loaded
    "event_id": ti.i32,  # events closed so far (contact work of older events is stale)
    "loading": ti.i32,  # some contact of the particle loaded this step
    "pressed": ti.i32,  # some contact pressed on the particle this step (f_hys > 0; "release")
    "damage_events": ti.i32,  # events that damaged the particle
    "birth_step": ti.i32,  # step at which a fragment was created (-1 for originals)
}

PAIR_READ = ("position", "velocity", "angular_velocity", "radius", "mass", "material", "alive")


@ti.data_oriented
class ParticlePool:
    """Preallocated particle storage (SoA). Create after :func:`init_taichi`.

    Args:
        capacity: number of slots (original particles plus every fragment ever spawned).
    """

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"pool capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        fb = ti.FieldsBuilder()
        for name, dtype in SCALAR_FIELDS.items():
            setattr(self, name, ti.field(dtype))
        for name in VEC_FIELDS:
            setattr(self, name, ti.Vector.field(3, ti.f64))
        # what the pair loop reads of both particles of a contact, in random order: one
        # record per slot (8-byte members first); the rest one array per field
        for name in (*VEC_FIELDS, *SCALAR_FIELDS):
            if name not in PAIR_READ:
                fb.dense(ti.i, self.capacity).place(getattr(self, name))
        fb.dense(ti.i, self.capacity).place(*(getattr(self, n) for n in PAIR_READ))
        self.n_slots = ti.field(ti.i32)  # high-water mark of used slots
        self.next_id = ti.field(ti.i64)  # next id to hand out
        self.overflow = ti.field(ti.i32)  # slots requested beyond capacity (device)
        fb.place(self.n_slots, self.next_id, self.overflow)
        self._tree = fb.finalize()

    # ------------------------------------------------------------------ host API
    def destroy(self) -> None:
        """Free the device memory of this pool."""
        if self._tree is not None:
            self._tree.destroy()
            self._tree = None

    @property
    def slots_used(self) -> int:
        """Number of slots ever used (host sync)."""
        return int(self.n_slots[None])

    def n_alive(self) -> int:
        """Number of live particles (host sync)."""
        n = self.slots_used
        return int(self.alive.to_numpy()[:n].sum())

    def add(self, position, radius, material, mass, inertia_factor=0.4, velocity=None,
            angular_velocity=None, parent_id=None, order=None) -> np.ndarray:
        """Append particles at the tail; returns their new ids (in input order: input k gets
        id ``first + k``).

        Args:
            position: (k, 3) centres [m].
            radius: (k,) radii [m].
            material: (k,) material indices.
            mass: (k,) masses [kg] (already density-scaled).
            inertia_factor: I = factor m R^2 (2/5 for a solid sphere).
            velocity, angular_velocity: (k, 3) initial values (default 0).
            parent_id: (k,) lineage (default -1).
            order: (k,) permutation: slot ``tail + s`` takes input ``order[s]`` (default:
                input order).
        """
        position = np.ascontiguousarray(position, dtype=np.float64).reshape(-1, 3)
        k = position.shape[0]
        radius = np.ascontiguousarray(radius, dtype=np.float64).reshape(k)
        material = np.ascontiguousarray(material, dtype=np.int32).reshape(k)
        mass = np.ascontiguousarray(mass, dtype=np.float64).reshape(k)
        vel = np.zeros((k, 3)) if velocity is None else np.asarray(velocity, float).reshape(k, 3)
        om = (np.zeros((k, 3)) if angular_velocity is None
              else np.asarray(angular_velocity, float).reshape(k, 3))
        parent = (np.full(k, -1, np.int64) if parent_id is None
                  else np.asarray(parent_id, np.int64).reshape(k))
        if np.any(radius <= 0) or np.any(mass <= 0) or not np.all(np.isfinite(position)):
            raise ValueError("particles need radius > 0, mass > 0 and finite positions")
        start = self.slots_used
        if start + k > self.capacity:
            raise SimulationError(
                f"particle pool full: {start} slots used + {k} new > capacity {self.capacity}; "
                "raise the pool capacity"
            )
        if k == 0:
            return np.zeros(0, np.int64)
        first_id = int(self.next_id[None])
        ids = np.arange(first_id, first_id + k, dtype=np.int64)
        inv_inertia = 1.0 / (inertia_factor * mass * radius**2)
        perm = np.arange(k) if order is None else np.asarray(order, np.int64).reshape(-1)
        if perm.shape != (k,) or not np.array_equal(np.sort(perm), np.arange(k)):
            raise ValueError(f"order must be a permutation of 0..{k - 1}")
        cols = [np.ascontiguousarray(a[perm]) for a in (position, vel, om, radius, mass,
                                                        inv_inertia, material, parent, ids)]
        self._insert(*cols, start)
        self.next_id[None] = first_id + k
        return ids

    def remove(self, ids) -> None:
        """Mark the particles with these ids dead (host-side deletion)."""
        ids = np.asarray(ids, dtype=np.int64)
        n = self.slots_used
        pid = self.pid.to_numpy()[:n]
        alive = self.alive.to_numpy()[:n]
        slots = np.nonzero(np.isin(pid, ids) & (alive == 1))[0]
        if slots.size != np.unique(ids).size:
            missing = sorted(set(ids.tolist()) - set(pid[slots].tolist()))
            raise KeyError(f"no live particle with id(s) {missing}")
        self._kill(np.ascontiguousarray(slots.astype(np.int32)))

    def to_numpy(self, names=("pid", "alive", "material", "radius", "mass", "position",
                              "velocity", "angular_velocity", "force", "parent_id")) -> dict:
        """Copy of the used slots of the named arrays (host sync)."""
        n = self.slots_used
        return {name: getattr(self, name).to_numpy()[:n] for name in names}

    def check_overflow(self, context: str = "") -> None:
        """Raise if a device-side allocation ran past the capacity."""
        over = int(self.overflow[None])
        if over:
            raise SimulationError(
                f"particle pool full: device insertion asked for {over} slot(s) beyond the "
                f"capacity {self.capacity}{context}; no particle was dropped silently, the "
                "run stops"
            )

    # ------------------------------------------------------------------ kernels
    @ti.kernel
    def _insert(self, pos: ti.types.ndarray(), vel: ti.types.ndarray(), om: ti.types.ndarray(),
                rad: ti.types.ndarray(), mass: ti.types.ndarray(), inv_i: ti.types.ndarray(),
                mat: ti.types.ndarray(), parent: ti.types.ndarray(), ids: ti.types.ndarray(),
                start: ti.i32):
        for k in range(rad.shape[0]):
            i = start + k
            self.alive[i] = 1
            self.pid[i] = ids[k]
            self.parent_id[i] = parent[k]
            self.root_id[i] = ids[k]
            self.material[i] = mat[k]
            self.radius[i] = rad[k]
            self.mass[i] = mass[k]
            self.inv_mass[i] = 1.0 / mass[k]
            self.inv_inertia[i] = inv_i[k]
            for d in ti.static(range(3)):
                self.position[i][d] = pos[k, d]
                self.velocity[i][d] = vel[k, d]
                self.angular_velocity[i][d] = om[k, d]
            self.clear_contact_state(i)
            self.birth_step[i] = -1
        self.n_slots[None] = start + rad.shape[0]

    @ti.func
    def clear_contact_state(self, i):
        """A new particle in slot i: no force, no displacement, no plate-contact history."""
        zero = ti.Vector([0.0, 0.0, 0.0])
        self.force[i] = zero
        self.torque[i] = zero
        self.displacement[i] = zero
        self.wall_spring_bottom[i] = zero
        self.wall_spring_top[i] = zero
        self.wall_delta_max_bottom[i] = 0.0
        self.wall_delta_max_top[i] = 0.0
        self.wall_delta_prev_bottom[i] = 0.0
        self.wall_delta_prev_top[i] = 0.0
        self.wall_fhys_prev_bottom[i] = 0.0
        self.wall_fhys_prev_top[i] = 0.0
        self.roll_magnitude[i] = 0.0
        self.normal_force_sum[i] = 0.0
        self.n_contacts[i] = 0

    @ti.kernel
    def _kill(self, slots: ti.types.ndarray()):
        for k in range(slots.shape[0]):
            self.alive[slots[k]] = 0

    @ti.func
    def allocate_slot(self):
        """Device-side insertion: a fresh slot and id, or slot -1 (and overflow) if full."""
        slot = ti.atomic_add(self.n_slots[None], 1)
        new_id = ti.cast(-1, ti.i64)
        if slot >= self.capacity:
            ti.atomic_add(self.overflow[None], 1)
            ti.atomic_sub(self.n_slots[None], 1)
            slot = -1
        else:
            new_id = ti.atomic_add(self.next_id[None], ti.cast(1, ti.i64))
            self.pid[slot] = new_id
        return slot, new_id
