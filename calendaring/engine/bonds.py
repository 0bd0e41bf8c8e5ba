"""Carbon-black virtual bonds: Potyondy & Cundall (2004) parallel bonds (spec section 4).

Bonds are created once, at the first step of calendering, between every particle pair with
at least one particle of a bonding material (``bonds.materials``, default CB) whose centres
are within ``xi_b (R_A + R_B)`` (paper Eq. 30, ``bonds.radius_ratio`` = 1.5). They are never
re-created. Each bond is a disk of radius ``R_b = lambda_b min(R_A, R_B)`` with area
``A = pi R_b^2``, bending moment of area ``I = pi R_b^4 / 4`` and polar moment ``J = 2 I``.
Starting from zero, every step adds (spec 4.2, the dimensionally consistent P&C forms)::

    dF_n = +S_n A (v_rel . n) dt        compression positive
    dF_t = -S_t A v_t dt                 tangential force on A (rotated with the frame)
    dM_n = -S_t J (w_rel . n) dt         twisting moment on A
    dM_t = -S_n I w_t dt                 bending moment on A (rotated with the frame)

with the relative velocity taken at the bond point ``x_b = x_A + n (R_A + g/2)`` (g the gap).
Force on A is ``-F_n n + F_t``, torque ``M_n n + M_t + (x_b - x_A) x F_t``; B gets the
opposite force and moments. A bond fails for good when (paper Eqs. 28-29)::

    sigma = -F_n / A + |M_t| R_b / I >= sigma_c     (tension positive; "abs": |F_n| / A)
    tau   = |F_t| / A + |M_n| R_b / J >= tau_c

Bonds act in addition to the EEPA contact. A bond whose particle dies (breakage) is removed
and counted apart from failures. There is no bond damping (P&C parallel bonds are undamped).

Bond states: ``INTACT`` 0, ``FAILED_NORMAL`` 1, ``FAILED_SHEAR`` 2, ``REMOVED`` 3.

See also: :mod:`calendaring.engine.laws.tangential` (the spring rotation reused for F_t
and M_t), :mod:`calendaring.engine.simulation` (``create_bonds`` at the start of calendering).
"""


import math

import numpy as np
import taichi as ti
from scipy.spatial import cKDTree

from calendaring.core.config import BondsConfig
from calendaring.engine.laws.tangential import rotate_spring
from calendaring.engine.neighbours import minimum_image

INTACT, FAILED_NORMAL, FAILED_SHEAR, REMOVED = 0, 1, 2, 3
STATE_NAMES = {INTACT: "intact", FAILED_NORMAL: "failed_normal", FAILED_SHEAR: "failed_shear",
               REMOVED: "removed"}
BOND_ARRAYS = ("slot_a", "slot_b", "id_a", "id_b", "radius", "state", "break_step", "f_n",
               "m_n", "f_t", "m_t")


def find_bond_pairs(position: np.ndarray, radius: np.ndarray, material: np.ndarray,
                    cell_x: float, cell_y: float, ratio: float,
                    bonding_materials: list[int]) -> np.ndarray:
    """Pairs (a, b), a < b (row indices), to bond: one of them of a bonding material and
    ``|x_a - x_b| <= ratio (R_a + R_b)`` with the periodic minimum image in x and y.

    Returns an (m, 2) int64 array sorted by (a, b).
    """
    position = np.asarray(position, float)
    n = len(radius)
    if n < 2:
        return np.zeros((0, 2), np.int64)
    bonding = np.isin(material, bonding_materials)
    if not bonding.any():
        return np.zeros((0, 2), np.int64)
    pts = position.copy()
    pts[:, 0] %= cell_x
    pts[:, 1] %= cell_y
    z0 = pts[:, 2].min()
    pts[:, 2] -= z0
    span_z = 4.0 * (pts[:, 2].max() + 2 * radius.max()) + 1e-12  # z is not periodic
    tree = cKDTree(pts, boxsize=[cell_x, cell_y, span_z])
    reach = ratio * (radius[bonding].max() + radius.max())
    pairs = tree.query_pairs(reach, output_type="ndarray")
    if pairs.size == 0:
        return np.zeros((0, 2), np.int64)
    a, b = pairs[:, 0], pairs[:, 1]
    d = pts[b] - pts[a]
    d[:, 0] -= cell_x * np.round(d[:, 0] / cell_x)
    d[:, 1] -= cell_y * np.round(d[:, 1] / cell_y)
    dist = np.sqrt(np.einsum("ij,ij->i", d, d))
    keep = (bonding[a] | bonding[b]) & (dist <= ratio * (radius[a] + radius[b]))
    out = np.sort(pairs[keep], axis=1).astype(np.int64)
    order = np.lexsort((out[:, 1], out[:, 0]))
    return out[order]


@ti.func
def _disk(rb):
    """Area A = pi R_b^2 and bending moment of area I = pi R_b^4 / 4 of a bond disk of
    radius ``rb`` (its polar moment is J = 2 I)."""
    return math.pi * rb * rb, 0.25 * math.pi * (rb * rb) * (rb * rb)


@ti.data_oriented
class BondTable:
    """Fixed list of bonds created once (capacity = number of bonds, at least 1).

    Args:
        cfg: bond parameters.
        capacity: number of bonds the table holds.
    """

    def __init__(self, cfg: BondsConfig, capacity: int, serial: bool = False,
                 particle_capacity: int = 0) -> None:
        self.cfg = cfg
        self.serial = bool(serial)  # run the per-step loop without the thread pool
        self.capacity = max(1, int(capacity))
        # > 0: per-particle bond lists for the engine's gather (see :meth:`_update_all`)
        self.particle_capacity = int(particle_capacity)
        self.abs_mode = cfg.normal_criterion == "abs"
        fb = ti.FieldsBuilder()
        self.slot_a = ti.field(ti.i32)
        self.slot_b = ti.field(ti.i32)
        self.id_a = ti.field(ti.i64)
        self.id_b = ti.field(ti.i64)
        self.radius = ti.field(ti.f64)  # bond disk radius R_b [m]
        self.state = ti.field(ti.i32)
        self.break_step = ti.field(ti.i32)  # step of failure or removal (-1 while intact)
        self.f_n = ti.field(ti.f64)  # normal force, compression positive [N]
        self.m_n = ti.field(ti.f64)  # twisting moment on A along n [N m]
        self.f_t = ti.Vector.field(3, ti.f64)  # shear force on A [N]
        self.m_t = ti.Vector.field(3, ti.f64)  # bending moment on A [N m]
        # what a step reads and writes of a bond, one record per bond (8-byte members
        # first); the ids and the failure step apart
        fb.dense(ti.i, self.capacity).place(self.f_t, self.m_t, self.f_n, self.m_n,
                                            self.radius, self.slot_a, self.slot_b, self.state)
        for f in (self.id_a, self.id_b, self.break_step):
            fb.dense(ti.i, self.capacity).place(f)
        # this step's loads of each bond, summed per particle by the engine's gather: force
        # on A; torque on A at [2 b] and on B at [2 b + 1]. A bond that fails or is removed
        # zeroes them, and they stay zero.
        self.load_force = ti.Vector.field(3, ti.f64)
        self.load_torque = ti.Vector.field(3, ti.f64)
        fb.dense(ti.i, self.capacity).place(self.load_force)
        fb.dense(ti.i, 2 * self.capacity).place(self.load_torque)
        # per particle slot, its bonds: entry b (it is A) or -b - 1 (it is B), by bond index
        self.list_start = ti.field(ti.i32)
        self.list_count = ti.field(ti.i32)
        self.list_entry = ti.field(ti.i32)
        if self.particle_capacity:
            fb.dense(ti.i, self.particle_capacity).place(self.list_start, self.list_count)
            fb.dense(ti.i, 2 * self.capacity).place(self.list_entry)
        self.n_bonds = ti.field(ti.i32)
        self.released = ti.field(ti.f64)  # elastic energy lost by failed/removed bonds [J]
        fb.place(self.n_bonds, self.released)
        self._tree = fb.finalize()

    def destroy(self) -> None:
        """Free the device memory."""
        if self._tree is not None:
            self._tree.destroy()
            self._tree = None

    # ------------------------------------------------------------------ host API
    def set_bonds(self, slot_a, slot_b, id_a, id_b, bond_radius) -> None:
        """Load freshly created bonds (all intact, zero force)."""
        k = len(slot_a)
        if k > self.capacity:
            raise ValueError(f"{k} bonds exceed the table capacity {self.capacity}")
        arrays = self._empty()
        arrays["slot_a"][:k] = slot_a
        arrays["slot_b"][:k] = slot_b
        arrays["id_a"][:k] = id_a
        arrays["id_b"][:k] = id_b
        arrays["radius"][:k] = bond_radius
        self.load({**arrays, "n_bonds": k, "released": 0.0})

    def _empty(self) -> dict:
        c = self.capacity
        return {"slot_a": np.zeros(c, np.int32), "slot_b": np.zeros(c, np.int32),
                "id_a": np.zeros(c, np.int64), "id_b": np.zeros(c, np.int64),
                "radius": np.zeros(c), "state": np.zeros(c, np.int32),
                "break_step": np.full(c, -1, np.int32), "f_n": np.zeros(c), "m_n": np.zeros(c),
                "f_t": np.zeros((c, 3)), "m_t": np.zeros((c, 3))}

    def load(self, arrays: dict) -> None:
        """Restore every bond array (a checkpoint or :meth:`set_bonds`)."""
        full = self._empty()
        k = int(arrays["n_bonds"])
        for name in BOND_ARRAYS:
            full[name][:k] = np.asarray(arrays[name])[:k]
            getattr(self, name).from_numpy(full[name])
        self.n_bonds[None] = k
        self.released[None] = float(arrays["released"])
        if self.particle_capacity:
            self._build_lists(full["slot_a"][:k], full["slot_b"][:k], full["state"][:k])

    def _build_lists(self, slot_a: np.ndarray, slot_b: np.ndarray, state: np.ndarray) -> None:
        """Per-slot lists of the intact bonds, by bond index. A bond that fails or loses a
        particle later stays listed, with zero loads, until the lists are built again
        (:meth:`load`, :meth:`move_slots`); one that has failed already is left out (its
        loads are zero: the sums are the same to the bit), and so is its slot, which may
        be gone (``-1``) after :meth:`move_slots`."""
        k = len(slot_a)
        keep = np.nonzero(np.asarray(state)[:k] == INTACT)[0]
        slots = np.concatenate([slot_a[keep], slot_b[keep]]).astype(np.int64)
        bad = slots[(slots < 0) | (slots >= self.particle_capacity)]
        if len(bad):
            raise ValueError(f"intact bond with slot {bad[0]} outside [0, "
                             f"{self.particle_capacity})")
        index = np.concatenate([keep, keep])
        entry = np.concatenate([keep, -keep - 1]).astype(np.int32)
        order = np.lexsort((index, slots))
        count = np.bincount(slots, minlength=self.particle_capacity).astype(np.int32)
        start = (np.cumsum(count) - count).astype(np.int32)
        full = np.zeros(2 * self.capacity, np.int32)
        full[:len(entry)] = entry[order]
        self.list_entry.from_numpy(full)
        self.list_start.from_numpy(start)
        self.list_count.from_numpy(count)

    def move_slots(self, new_of_old: np.ndarray) -> None:
        """The particles moved: slot ``s`` is now ``new_of_old[s]`` (-1: the particle is gone).
        Every intact bond must keep both particles; the others get -1 for a gone one."""
        arrays = self.to_numpy()
        for side in ("slot_a", "slot_b"):
            old = arrays[side]
            arrays[side] = np.where(old >= 0, new_of_old[np.maximum(old, 0)], -1).astype(
                np.int32)
        lost = (arrays["state"] == INTACT) & ((arrays["slot_a"] < 0) | (arrays["slot_b"] < 0))
        if lost.any():
            raise ValueError(f"{int(lost.sum())} intact bond(s) lose a particle in the move")
        self.load(arrays)

    def to_numpy(self) -> dict:
        """Every bond array for the bonds in use, plus ``n_bonds`` and ``released``."""
        k = int(self.n_bonds[None])
        out = {name: getattr(self, name).to_numpy()[:k] for name in BOND_ARRAYS}
        out["n_bonds"] = k
        out["released"] = float(self.released[None])
        return out

    def counts(self) -> dict[str, int]:
        """Number of bonds in each state (host sync)."""
        state = self.state.to_numpy()[: int(self.n_bonds[None])]
        return {name: int(np.count_nonzero(state == code)) for code, name in STATE_NAMES.items()}

    # ------------------------------------------------------------------ kernels
    @ti.kernel
    def update(self, pool: ti.template(), dt: ti.f64, lx: ti.f64, ly: ti.f64, step: ti.i32):
        """Increment every intact bond, apply its loads, check failure (one step)."""
        self._update_all(pool, dt, lx, ly, step, True)

    @ti.kernel
    def compute(self, pool: ti.template(), dt: ti.f64, lx: ti.f64, ly: ti.f64, step: ti.i32):
        """:meth:`update` storing the loads per bond (``load_force``, ``load_torque``) for
        the engine's gather."""
        self._update_all(pool, dt, lx, ly, step, False)

    @ti.func
    def _update_all(self, pool: ti.template(), dt, lx, ly, step, apply: ti.template()):
        """The bond step. ``apply``: add the loads to the particles here (atomic adds);
        otherwise store them per bond (``load_force``, ``load_torque``) for the engine's
        per-particle gather, which sums them in a fixed order."""
        ti.loop_config(serialize=self.serial)
        for b in range(self.n_bonds[None]):
            self._bond_item(pool, b, dt, lx, ly, step, apply)

    @ti.func
    def _bond_item(self, pool: ti.template(), b, dt, lx, ly, step, apply: ti.template()):
        """Bond b's step (the body of :meth:`_update_all`)."""
        sn = ti.static(self.cfg.normal_stiffness)
        st = ti.static(self.cfg.shear_stiffness)
        sig_c = ti.static(self.cfg.normal_strength)
        tau_c = ti.static(self.cfg.shear_strength)
        if self.state[b] == INTACT:
            i = self.slot_a[b]
            j = self.slot_b[b]
            if pool.alive[i] == 0 or pool.alive[j] == 0:
                self.released[None] += self._stored(b)
                self.state[b] = REMOVED
                self.break_step[b] = step
                self._clear_loads(b)
            else:
                self._update_one(pool, b, i, j, dt, lx, ly, sn, st, sig_c, tau_c, step, apply)

    @ti.func
    def _update_one(self, pool: ti.template(), b, i, j, dt, lx, ly, sn, st, sig_c, tau_c, step,
                    apply: ti.template()):
        d = minimum_image(pool.position[j] - pool.position[i], lx, ly)
        dist = d.norm()
        if dist > 0.0:
            nrm = d * (1.0 / dist)
            ri = pool.radius[i]
            rj = pool.radius[j]
            gap = dist - ri - rj
            # lever arms to the bond point: (R_A + g/2) n from A and -(R_B + g/2) n from B,
            # so w_A x arm_A - w_B x arm_B = (a_A w_A + a_B w_B) x n: one cross product
            a_i = ri + 0.5 * gap
            a_j = rj + 0.5 * gap
            v_rel = (pool.velocity[i] - pool.velocity[j]
                     + (a_i * pool.angular_velocity[i] + a_j * pool.angular_velocity[j]).cross(
                         nrm))
            w_rel = pool.angular_velocity[i] - pool.angular_velocity[j]
            rb = self.radius[b]
            area, inertia = _disk(rb)
            polar = 2.0 * inertia
            inv_rb = 1.0 / rb  # one quotient: 1/A = 1/(pi R_b^2), R_b/I = 2 R_b/J = 4/(pi R_b^3)
            inv_area = ti.static(1.0 / math.pi) * inv_rb * inv_rb
            rb_over_i = 4.0 * inv_area * inv_rb
            vn = v_rel.dot(nrm)
            v_t = v_rel - vn * nrm
            wn = w_rel.dot(nrm)
            w_t = w_rel - wn * nrm
            f_n = self.f_n[b] + sn * area * vn * dt
            f_t = rotate_spring(self.f_t[b], nrm) - st * area * v_t * dt
            m_n = self.m_n[b] - st * polar * wn * dt
            m_t = rotate_spring(self.m_t[b], nrm) - sn * inertia * w_t * dt
            self.f_n[b] = f_n
            self.f_t[b] = f_t
            self.m_n[b] = m_n
            self.m_t[b] = m_t
            # sigma = s0 + |M_t| R_b/I >= sigma_c and tau = |F_t|/A + t0 >= tau_c, tested
            # without the two roots: |x| c >= rest <=> rest <= 0 or x.x c^2 >= rest^2
            s0 = 0.0
            if ti.static(self.abs_mode):
                s0 = ti.abs(f_n) * inv_area
            else:
                s0 = -f_n * inv_area
            rest_n = sig_c - s0
            rest_t = tau_c - ti.abs(m_n) * (0.5 * rb_over_i)
            fail_n = (rest_n <= 0.0) | (m_t.norm_sqr() * (rb_over_i * rb_over_i)
                                        >= rest_n * rest_n)
            fail_t = (rest_t <= 0.0) | (f_t.norm_sqr() * (inv_area * inv_area)
                                        >= rest_t * rest_t)
            if fail_n or fail_t:
                self.released[None] += self._stored(b)
                self.state[b] = FAILED_NORMAL if fail_n else FAILED_SHEAR
                self.break_step[b] = step
                self._clear_loads(b)
            else:
                force_i = -f_n * nrm + f_t
                moment_i = m_n * nrm + m_t
                nft = nrm.cross(f_t)  # arm x F_t = a_A n x F_t on A, -a_B n x (-F_t) on B
                if ti.static(apply):
                    pool.force[i] += force_i
                    pool.force[j] -= force_i
                    pool.torque[i] += moment_i + a_i * nft
                    pool.torque[j] += -moment_i + a_j * nft
                else:
                    self.load_force[b] = force_i
                    self.load_torque[2 * b] = moment_i + a_i * nft
                    self.load_torque[2 * b + 1] = -moment_i + a_j * nft

    @ti.func
    def _clear_loads(self, b):
        """Bond b no longer loads its particles (it failed or lost a particle)."""
        zero = ti.Vector([0.0, 0.0, 0.0])
        self.load_force[b] = zero
        self.load_torque[2 * b] = zero
        self.load_torque[2 * b + 1] = zero

    @ti.func
    def _stored(self, b):
        """Elastic energy held by bond b [J] (linear springs)."""
        area, inertia = _disk(self.radius[b])
        sn = ti.static(self.cfg.normal_stiffness)
        st = ti.static(self.cfg.shear_stiffness)
        return 0.5 * (self.f_n[b] ** 2 / (sn * area) + self.f_t[b].norm_sqr() / (st * area)
                      + self.m_n[b] ** 2 / (st * 2.0 * inertia)
                      + self.m_t[b].norm_sqr() / (sn * inertia))

    @ti.kernel
    def stored_energy(self) -> ti.f64:
        """Elastic energy held by the intact bonds [J]."""
        e = 0.0
        for b in range(self.n_bonds[None]):
            if self.state[b] == INTACT:
                e += self._stored(b)
        return e


def make_bonds(cfg: BondsConfig, state: dict, slots: np.ndarray, material_names: list[str],
               cell_x: float, cell_y: float) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                      np.ndarray, np.ndarray]:
    """Bond pairs of the live particles in ``state`` (arrays by row, ``slots`` their slots).

    Returns (slot_a, slot_b, id_a, id_b, bond radius [m]).
    """
    mats = [material_names.index(m) for m in cfg.materials]
    pairs = find_bond_pairs(state["position"], state["radius"], state["material"], cell_x,
                            cell_y, cfg.radius_ratio, mats)
    a, b = pairs[:, 0], pairs[:, 1]
    r = state["radius"]
    return (slots[a].astype(np.int32), slots[b].astype(np.int32), state["id"][a],
            state["id"][b], cfg.disk_scale * np.minimum(r[a], r[b]))
