"""Candidate-pair table with contact history that survives every neighbour-list rebuild.

Pairs are stored in CSR form by owner: the owner of a pair is its lower slot, so owner ``i``
holds the pairs ``seg_start[i] .. seg_start[i] + seg_count[i]``. A pair is a candidate while
the centre distance is below ``r_i + r_j + skin`` (Verlet list).

History (``delta_max``, tangential ``spring``, the previous overlap and hysteretic force used
by the work integrals, and the breakage bookkeeping: the stressing work of the contact on each
side since that particle's current loading event began, ``work_a`` / ``work_b`` with the
event numbers ``event_a`` / ``event_b`` they belong to, and for fragments of one particle
born overlapping the reference overlap ``delta_ref`` the contact law is measured from, with
the ``sibling`` flag that switches adhesion off until they separate) is keyed by the stable
ids: after a rebuild each new pair (i, j) looks for the old entry with
the same partner id in i's old segment (a linear scan over at most a few entries) and copies
it, or starts from zero. A pair whose overlap becomes <= 0 has its history cleared by the
force kernel (the contact ended).

Forces without atomics: the force kernel writes each touching pair's contribution into the
pair's own slots (``touch``, ``pair_force``, ``pair_nft``, arms, rolling and stressing
terms), then one loop over particles sums, for particle ``i``, its own segment and its
incoming list (``in_start``/``in_count``/``in_pair``: the pairs whose partner is ``i``, in
increasing pair order, built at every rebuild). No two threads write the same particle, so
the sums need no atomic adds and their order does not depend on the number of threads.

Capacity: the pair count is computed before filling; if it exceeds the capacity the host
grows the table (copying the history) and rebuilds, never truncating.

See also: :mod:`calendaring.engine.neighbours` (the cell grid and the blocked scans),
:mod:`calendaring.engine.kernels.pairs` (the force kernel and the gather).
"""


import numpy as np
import taichi as ti

from calendaring.engine.neighbours import exclusive_scan, scan_blocks, sort_segment

PAIR_F64 = ("delta_max", "delta_prev", "fhys_prev", "work_a", "work_b", "delta_ref",
            "normal_force")
PAIR_OUT_F64 = ("arm_i", "arm_j", "roll_force", "stress_i", "stress_j")  # per step only
HISTORY_F64 = ("delta_max", "delta_prev", "fhys_prev", "work_a", "work_b", "delta_ref")
PAIR_I32 = ("event_a", "event_b", "sibling")  # all history
# constants of a pair, set at every rebuild: reduced mass m* = m_i m_j / (m_i + m_j) [kg]
# and sqrt(R*), R* = r_i r_j / (r_i + r_j) [m^0.5] (two quotients and a root per contact
# and step fewer)
PAIR_CONST_F64 = ("m_star", "sqrt_r_star")


CANDIDATE_SCRATCH = 32  # candidate partners per owner kept between the two rebuild passes

@ti.data_oriented
class ContactTable:
    """Candidate pairs and their contact history.

    Args:
        particle_capacity: pool capacity.
        pair_capacity: number of candidate pairs the table can hold.
    """

    def __init__(self, particle_capacity: int, pair_capacity: int) -> None:
        self.particle_capacity = int(particle_capacity)
        self.capacity = int(pair_capacity)
        fb = ti.FieldsBuilder()
        self.owner = ti.field(ti.i32)
        self.partner = ti.field(ti.i32)
        self.partner_id = ti.field(ti.i64)
        self.old_partner_id = ti.field(ti.i64)
        for f in (self.owner, self.partner, self.partner_id, self.old_partner_id):
            fb.dense(ti.i, self.capacity).place(f)
        for name in (*PAIR_F64, *PAIR_OUT_F64):
            setattr(self, name, ti.field(ti.f64))
        for name in PAIR_I32:
            setattr(self, name, ti.field(ti.i32))
        for name in PAIR_CONST_F64:
            setattr(self, name, ti.field(ti.f64))
        self.spring = ti.Vector.field(3, ti.f64)
        # this step's contribution of each pair (see the module docstring)
        self.touch = ti.field(ti.i32)
        self.pair_force = ti.Vector.field(3, ti.f64)  # force on the owner [N]
        self.pair_nft = ti.Vector.field(3, ti.f64)  # normal x tangential force [N]
        # The force kernel reads and writes a pair's history and this step's contribution
        # together, and the gather reads a particle's pairs in random order: each group is
        # one record per pair (array of structures, 8-byte members first), so one pair
        # touches two or three cache lines instead of one per field.
        fb.dense(ti.i, self.capacity).place(
            self.spring, *(getattr(self, n) for n in (*HISTORY_F64, *PAIR_CONST_F64)),
            *(getattr(self, n) for n in PAIR_I32))
        fb.dense(ti.i, self.capacity).place(
            self.pair_force, self.pair_nft, self.normal_force,
            *(getattr(self, n) for n in PAIR_OUT_F64))
        fb.dense(ti.i, self.capacity).place(self.touch)  # the gather reads it for every pair
        for name in HISTORY_F64:
            f = ti.field(ti.f64)
            fb.dense(ti.i, self.capacity).place(f)
            setattr(self, "old_" + name, f)
        for name in PAIR_I32:
            f = ti.field(ti.i32)
            fb.dense(ti.i, self.capacity).place(f)
            setattr(self, "old_" + name, f)
        self.in_pair = ti.field(ti.i32)
        self.near = ti.field(ti.i32)  # scratch: the pairs within reach, by chunk (CPU)
        fb.dense(ti.i, self.capacity).place(self.in_pair)
        fb.dense(ti.i, self.capacity).place(self.near)
        names = (*HISTORY_F64, *PAIR_I32)  # f64 first
        self._history = [getattr(self, n) for n in names]
        self._history_old = [getattr(self, "old_" + n) for n in names]
        self.old_spring = ti.Vector.field(3, ti.f64)
        fb.dense(ti.i, self.capacity).place(self.old_spring)
        self.seg_start = ti.field(ti.i32)
        self.seg_count = ti.field(ti.i32)
        self.old_seg_start = ti.field(ti.i32)
        self.old_seg_count = ti.field(ti.i32)
        self.in_start = ti.field(ti.i32)
        self.in_count = ti.field(ti.i32)
        self.in_cursor = ti.field(ti.i32)
        for f in (self.seg_start, self.seg_count, self.old_seg_start, self.old_seg_count,
                  self.in_start, self.in_count, self.in_cursor):
            fb.dense(ti.i, self.particle_capacity).place(f)
        self.n_pairs = ti.field(ti.i32)
        self.required = ti.field(ti.i32)
        self.in_total = ti.field(ti.i32)
        fb.place(self.n_pairs, self.required, self.in_total)
        self.scan_block = ti.field(ti.i32)  # scratch of the two prefix sums
        fb.dense(ti.i, scan_blocks(self.particle_capacity)).place(self.scan_block)
        # the candidates the counting pass found, up to CANDIDATE_SCRATCH per owner: the
        # filling pass copies them instead of searching the cells again (4 bytes each)
        self.found = ti.field(ti.i32)
        fb.dense(ti.ij, (self.particle_capacity, CANDIDATE_SCRATCH)).place(self.found)
        self._tree = fb.finalize()

    def destroy(self) -> None:
        """Free the device memory."""
        if self._tree is not None:
            self._tree.destroy()
            self._tree = None

    # ------------------------------------------------------------- host helpers
    def history_arrays(self) -> dict:
        """Current pairs and their history as NumPy arrays (host sync)."""
        n = int(self.n_pairs[None])
        out = {name: getattr(self, name).to_numpy()[:n] for name in
               ("owner", "partner", "partner_id", *PAIR_F64, *PAIR_I32)}
        out["spring"] = self.spring.to_numpy()[:n]
        return out

    def copy_from(self, other: "ContactTable") -> None:
        """Copy the pairs, their history and their segments from a smaller table whose
        rebuild found it too small (used when growing). The segments are the ones
        :meth:`save_history` kept: the failed :meth:`count_candidates` has already
        overwritten ``other``'s own with the new, larger counts."""
        n = int(other.n_pairs[None])
        for name in ("owner", "partner", "partner_id", *PAIR_F64, *PAIR_I32):
            arr = getattr(self, name).to_numpy()
            arr[:n] = getattr(other, name).to_numpy()[:n]
            getattr(self, name).from_numpy(arr)
        sp = self.spring.to_numpy()
        sp[:n] = other.spring.to_numpy()[:n]
        self.spring.from_numpy(sp)
        for name in ("seg_start", "seg_count"):
            getattr(self, name).from_numpy(getattr(other, "old_" + name).to_numpy())
        self.n_pairs[None] = n

    def move_slots(self, new_of_old: np.ndarray, pid: np.ndarray) -> None:
        """The particles moved: slot ``s`` is now ``new_of_old[s]`` (-1: the particle is
        gone); ``pid`` holds the ids by new slot.

        Each pair keeps its history under its new owner, the lower of its two new slots. A
        pair whose particles change order swaps its per-side bookkeeping (``work_a`` /
        ``work_b``, ``event_a`` / ``event_b``) and the sign of its tangential spring (the
        spring is the force on the owner, and the normal, the relative velocity and so the
        spring all turn over with the order). Pairs with a gone particle are dropped: their
        contact ended when the particle died (``end_dead_contacts``). The table is then in
        the state a rebuild starts from (owner segments, partner ids); call
        :meth:`~calendaring.engine.simulation.Simulation.rebuild` next."""
        n = int(self.n_pairs[None])
        full = {name: getattr(self, name).to_numpy() for name in
                ("owner", "partner", "partner_id", "spring", *PAIR_F64, *PAIR_I32)}
        a = new_of_old[full["owner"][:n]]
        b = new_of_old[full["partner"][:n]]
        keep = np.nonzero((a >= 0) & (b >= 0))[0]
        a, b = a[keep], b[keep]
        swap = a > b
        owner, partner = np.where(swap, b, a), np.where(swap, a, b)
        order = np.lexsort((partner, owner))
        m = len(order)
        rows = keep[order]
        swapped = swap[order]
        columns = {name: full[name][:n][rows] for name in ("spring", *PAIR_F64, *PAIR_I32)}
        columns["spring"][swapped] *= -1.0
        for x, y in (("work_a", "work_b"), ("event_a", "event_b")):
            columns[x], columns[y] = (np.where(swapped, columns[y], columns[x]),
                                      np.where(swapped, columns[x], columns[y]))
        owner, partner = owner[order], partner[order]
        columns.update(owner=owner, partner=partner, partner_id=pid[partner])
        for name, values in columns.items():
            full[name][:] = 0
            full[name][:m] = values
            getattr(self, name).from_numpy(full[name])
        count = np.bincount(owner, minlength=self.particle_capacity).astype(np.int32)
        self.seg_count.from_numpy(count)
        self.seg_start.from_numpy((np.cumsum(count) - count).astype(np.int32))
        self.n_pairs[None] = m

    # ------------------------------------------------------------- rebuild kernels
    @ti.kernel
    def save_history(self, pool: ti.template()):
        """Move the current pairs' history into the old buffers before a rebuild."""
        for c in range(self.n_pairs[None]):
            self.old_partner_id[c] = self.partner_id[c]
            self.old_spring[c] = self.spring[c]
            for k in ti.static(range(len(self._history))):
                self._history_old[k][c] = self._history[k][c]
        for i in range(pool.n_slots[None]):
            self.old_seg_start[i] = self.seg_start[i]
            self.old_seg_count[i] = self.seg_count[i]

    @ti.func
    def _visit(self, pool: ti.template(), grid: ti.template(), i, skin, write: ti.template()):
        """Count the candidate partners j > i of particle i, keeping the first
        ``CANDIDATE_SCRATCH`` in ``found`` (``write`` False), or write them all into i's
        segment (True)."""
        pi = pool.position[i]
        ri = pool.radius[i]
        cx, cy, cz = grid.cell_coords(pi)
        k = 0
        base = self.seg_start[i]
        x0, x1, xa = grid.span(grid.nx, cx)
        y0, y1, ya = grid.span(grid.ny, cy)
        for oz in range(ti.max(cz - 1, 0), ti.min(cz + 2, grid.nz)):
            for oy in range(y0, y1):
                for ox in range(x0, x1):
                    ix = ox if xa else (ox + grid.nx) % grid.nx
                    iy = oy if ya else (oy + grid.ny) % grid.ny
                    c = grid.cell_index(ix, iy, oz)
                    for s in range(grid.start[c], grid.start[c + 1]):
                        j = grid.sorted[s]
                        if j > i:
                            d = grid.minimum_image(pool.position[j] - pi)
                            cut = ri + pool.radius[j] + skin
                            if d.norm_sqr() < cut * cut:
                                if ti.static(write):
                                    if base + k < self.capacity:
                                        self.owner[base + k] = i
                                        self.partner[base + k] = j
                                        self.partner_id[base + k] = pool.pid[j]
                                elif k < ti.static(CANDIDATE_SCRATCH):
                                    self.found[i, k] = j
                                k += 1
        return k

    @ti.kernel
    def count_candidates(self, pool: ti.template(), grid: ti.template(), skin: ti.f64) -> ti.i32:
        """Count candidates per owner, prefix-sum the segments; returns the total."""
        for i in range(pool.n_slots[None]):
            n = 0
            if pool.alive[i]:
                n = self._visit(pool, grid, i, skin, False)
            self.seg_count[i] = n
        exclusive_scan(self.seg_count, self.seg_start, self.required, self.scan_block,
                       pool.n_slots[None])
        return self.required[None]

    @ti.kernel
    def fill_candidates(self, pool: ti.template(), grid: ti.template(), skin: ti.f64):
        """Write the candidate pairs into their owners' segments: copied from what
        :meth:`count_candidates` kept, searched again for an owner with more candidates
        than that (the same pairs in the same order either way)."""
        for i in range(pool.n_slots[None]):
            if pool.alive[i]:
                n = self.seg_count[i]
                if n <= ti.static(CANDIDATE_SCRATCH):
                    base = self.seg_start[i]
                    for k in range(n):
                        if base + k < self.capacity:
                            j = self.found[i, k]
                            self.owner[base + k] = i
                            self.partner[base + k] = j
                            self.partner_id[base + k] = pool.pid[j]
                else:
                    self._visit(pool, grid, i, skin, True)
        self.n_pairs[None] = self.required[None]

    @ti.func
    def _set_constants(self, pool: ti.template(), c):
        i = self.owner[c]
        j = self.partner[c]
        mi = pool.mass[i]
        mj = pool.mass[j]
        ri = pool.radius[i]
        rj = pool.radius[j]
        self.m_star[c] = mi * mj / (mi + mj)
        self.sqrt_r_star[c] = ti.sqrt(ri * rj / (ri + rj))

    @ti.kernel
    def set_constants(self, pool: ti.template()):
        """The constants of every pair (``PAIR_CONST_F64``; after a checkpoint load)."""
        for c in range(self.n_pairs[None]):
            self._set_constants(pool, c)

    @ti.kernel
    def remap_history(self, pool: ti.template()):
        """Give each new pair the history of the same (owner, partner id) pair, if any, and
        its constants."""
        for c in range(self.n_pairs[None]):
            self._set_constants(pool, c)
            i = self.owner[c]
            key = self.partner_id[c]
            found = -1
            for o in range(self.old_seg_start[i], self.old_seg_start[i] + self.old_seg_count[i]):
                if self.old_partner_id[o] == key:
                    found = o
            if found >= 0:
                self.spring[c] = self.old_spring[found]
                for k in ti.static(range(len(self._history))):
                    self._history[k][c] = self._history_old[k][found]
            else:
                self.spring[c] = ti.Vector([0.0, 0.0, 0.0])
                for k in ti.static(range(len(HISTORY_F64))):
                    self._history[k][c] = 0.0
                # a new contact belongs to its particles' current events
                self.event_a[c] = pool.event_id[i]
                self.event_b[c] = pool.event_id[self.partner[c]]
                self.sibling[c] = 0
            self.normal_force[c] = 0.0

    @ti.kernel
    def build_incoming(self, pool: ti.template()):
        """Per particle, the pairs whose partner it is, in increasing pair order."""
        for i in range(pool.n_slots[None]):
            self.in_count[i] = 0
        for c in range(self.n_pairs[None]):
            ti.atomic_add(self.in_count[self.partner[c]], 1)
        exclusive_scan(self.in_count, self.in_start, self.in_total, self.scan_block,
                       pool.n_slots[None])
        for i in range(pool.n_slots[None]):
            self.in_cursor[i] = self.in_start[i]
        for c in range(self.n_pairs[None]):
            k = ti.atomic_add(self.in_cursor[self.partner[c]], 1)
            self.in_pair[k] = c
        for i in range(pool.n_slots[None]):  # in pair order: the scatter order is racy
            sort_segment(self.in_pair, self.in_start[i], self.in_start[i] + self.in_count[i])

    @ti.kernel
    def reset_displacements(self, pool: ti.template()):
        """Zero the displacement-since-rebuild of every particle."""
        for i in range(pool.n_slots[None]):
            pool.displacement[i] = ti.Vector([0.0, 0.0, 0.0])


def brute_force_pairs(position: np.ndarray, radius: np.ndarray, cell_x: float, cell_y: float,
                      skin: float) -> set[tuple[int, int]]:
    """O(N^2) reference: index pairs (i < j) with minimum-image distance < r_i + r_j + skin."""
    out = set()
    n = len(radius)
    for i in range(n):
        d = position[i + 1:] - position[i]
        d[:, 0] -= cell_x * np.round(d[:, 0] / cell_x)
        d[:, 1] -= cell_y * np.round(d[:, 1] / cell_y)
        cut = radius[i] + radius[i + 1:] + skin
        for k in np.nonzero((d**2).sum(1) < cut**2)[0]:
            out.add((i, i + 1 + int(k)))
    return out
