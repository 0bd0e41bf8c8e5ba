"""Phase 2 of a step, over candidate pairs: the contact law of each touching pair, its
history and loads written to the pair's own slot; then phase 3, those loads summed per
particle in a fixed order (no atomic adds on particle loads); and contacts with a dead particle
closed.

See also: :mod:`.stressing` (the breakage bookkeeping of each contact), :mod:`.burst`.
"""

import taichi as ti

from calendaring.engine.contact_params import COL
from calendaring.engine.kernels.constants import (
    CHUNK_C,
    GUARD_OVERLAP,
    MAX_CHUNKS,
)


class PairPhase:
    """Pair forces and the per-particle gather (phases 2 and 3 of :meth:`Kernels.step`)."""

    @ti.kernel
    def contact_stats(self, pool: ti.template(), table: ti.template()) -> ti.types.vector(
            2, ti.f64):
        """(number of touching particle pairs, largest overlap / smaller radius)."""
        n = 0.0
        worst = 0.0
        for c in range(table.n_pairs[None]):
            i = table.owner[c]
            j = table.partner[c]
            if pool.alive[i] and pool.alive[j] and table.delta_prev[c] > 0.0:
                n += 1.0
                ti.atomic_max(worst, table.delta_prev[c] / ti.min(pool.radius[i],
                                                                  pool.radius[j]))
        return ti.Vector([n, worst])

    @ti.kernel
    def pair_forces(self, pool: ti.template(), table: ti.template(), grid: ti.template(),
                    dt: ti.f64, max_overlap_fraction: ti.f64, step: ti.i32):
        """Particle-particle contacts over the candidate pairs."""
        self._pairs_all(pool, table, grid, dt, max_overlap_fraction, step)
        _, n_c = self._chunks(table.n_pairs[None], CHUNK_C)
        self._fold_ledger(MAX_CHUNKS, MAX_CHUNKS + n_c, True)

    @ti.func
    def _pairs_all(self, pool: ti.template(), table: ti.template(), grid: ti.template(), dt,
                   max_overlap_fraction, step):
        s_c, n_c = self._chunks(table.n_pairs[None], CHUNK_C)
        if ti.static(self.workers > 0):  # CPU: by chunk, as the multi-step launch does
            ti.loop_config(serialize=self.serial)
            for k in range(n_c):
                self._pair_chunk(pool, table, grid, k * s_c,
                                 ti.min(table.n_pairs[None], (k + 1) * s_c), dt,
                                 max_overlap_fraction, step, MAX_CHUNKS + k)
        else:  # CUDA: a thread per pair
            for c in range(table.n_pairs[None]):
                self._pair_item(pool, table, grid, c, dt, max_overlap_fraction, step,
                                MAX_CHUNKS + c // s_c)

    @ti.func
    def _pair_chunk(self, pool: ti.template(), table: ti.template(), grid: ti.template(), lo,
                    hi, dt, max_overlap_fraction, step, row):
        """Candidate pairs ``lo:hi`` on a CPU core, in two passes: the distances, listing
        the pairs within reach in ``table.near[lo:]`` (about half of them, in no
        predictable order: the list is written without a branch) and ending the contacts of
        those out of reach; then the contacts of the listed pairs (:meth:`_pair_one`)."""
        m = lo
        energy = ti.Vector.zero(ti.f64, 4)  # the chunk's ledger terms, summed in registers
        for c in range(lo, hi):
            i = table.owner[c]
            j = table.partner[c]
            table.touch[c] = 0
            near = 0
            if pool.alive[i] and pool.alive[j]:
                d = grid.minimum_image(pool.position[j] - pool.position[i])
                reach = pool.radius[i] + pool.radius[j]
                near = ti.select((table.delta_ref[c] > 0.0) | (d.norm_sqr() < reach * reach),
                                 1, 0)
                if near == 0 and (table.delta_max[c] > 0.0 or table.delta_prev[c] != 0.0):
                    energy[3] += self._end_touch(pool, table, c, i, j)
            table.near[m] = c
            m += near
        for k in range(lo, m):
            c = table.near[k]
            energy += self._pair_one(pool, table, grid, c, table.owner[c], table.partner[c],
                                     dt, max_overlap_fraction, step)
        self._ledger_pairs(energy, row)

    @ti.func
    def _pair_item(self, pool: ti.template(), table: ti.template(), grid: ti.template(), c, dt,
                   max_overlap_fraction, step, row):
        """Candidate pair c; its energy terms go to chunk row ``row``."""
        i = table.owner[c]
        j = table.partner[c]
        table.touch[c] = 0
        if pool.alive[i] and pool.alive[j]:
            self._ledger_pairs(self._pair_one(pool, table, grid, c, i, j, dt,
                                              max_overlap_fraction, step), row)

    @ti.kernel
    def gather_pair_forces(self, pool: ti.template(), table: ti.template(),
                           bonds: ti.template()):
        """Add this step's pair contributions to each particle: its own segment, then its
        incoming pairs, then (``bonds`` not None) the loads its bonds stored with
        ``BondTable.compute`` (no atomics: one thread per particle, fixed order)."""
        self._gather_all(pool, table, bonds)

    @ti.func
    def _gather_all(self, pool: ti.template(), table: ti.template(), bonds: ti.template()):
        """Per particle: its pairs' contributions, then (``bonds`` not None) its bonds'
        loads stored by ``BondTable._update_all(apply=False)``."""
        ti.loop_config(serialize=self.serial)
        for i in range(pool.n_slots[None]):
            if pool.alive[i]:
                self._gather_one(pool, table, bonds, i)

    @ti.func
    def _gather_one(self, pool: ti.template(), table: ti.template(), bonds: ti.template(), i):
        """Live particle i: the sums of :meth:`_gather_all`."""
        f = ti.Vector([0.0, 0.0, 0.0])
        t = ti.Vector([0.0, 0.0, 0.0])
        roll = 0.0
        fn = 0.0
        st = 0.0
        nc = 0
        lo = table.seg_start[i]
        for c in range(lo, lo + table.seg_count[i]):
            if table.touch[c]:
                f += table.pair_force[c]
                t += table.arm_i[c] * table.pair_nft[c]
                roll += table.roll_force[c] * table.arm_i[c]
                fn += table.normal_force[c]
                st += table.stress_i[c]
                nc += 1
        lo = table.in_start[i]
        for k in range(lo, lo + table.in_count[i]):
            c = table.in_pair[k]
            if table.touch[c]:
                f -= table.pair_force[c]
                t += table.arm_j[c] * table.pair_nft[c]
                roll += table.roll_force[c] * table.arm_j[c]
                fn += table.normal_force[c]
                st += table.stress_j[c]
                nc += 1
        if nc > 0:
            pool.roll_magnitude[i] = pool.roll_magnitude[i] + roll
            pool.normal_force_sum[i] = pool.normal_force_sum[i] + fn
            pool.n_contacts[i] = pool.n_contacts[i] + nc
            if ti.static(self.breakage):
                pool.stress_sum[i] = pool.stress_sum[i] + st
        if ti.static(bonds != None):  # noqa: E711
            # entry e >= 0: particle i is side A of bond e; else side B of bond -e - 1. The
            # loads of a failed or removed bond are zero: summed without a test (which
            # side, and whether the bond holds, vary from entry to entry at random)
            lo = bonds.list_start[i]
            for k in range(lo, lo + bonds.list_count[i]):
                e = bonds.list_entry[k]
                side_b = e < 0
                b = ti.select(side_b, -e - 1, e)
                f += ti.select(side_b, -1.0, 1.0) * bonds.load_force[b]
                t += bonds.load_torque[2 * b + ti.select(side_b, 1, 0)]
        pool.force[i] = pool.force[i] + f
        pool.torque[i] = pool.torque[i] + t

    @ti.func
    def _pair_one(self, pool: ti.template(), table: ti.template(), grid: ti.template(), c, i, j,
                  dt, max_overlap_fraction, step):
        """Candidate pair c = (i, j) of live particles this step; returns its energy terms
        (see :meth:`_ledger_pairs`)."""
        d = grid.minimum_image(pool.position[j] - pool.position[i])
        d2 = d.norm_sqr()
        ri = pool.radius[i]
        rj = pool.radius[j]
        reach = ri + rj
        ref = table.delta_ref[c]
        touching = False
        energy = ti.Vector.zero(ti.f64, 4)
        # most candidates are apart: the root only for those within reach (sqrt(fl(r^2))
        # = r, so the test is the same as reach - |d| > 0) and for relatives
        if ref > 0.0 or d2 < reach * reach:
            dist = ti.sqrt(d2)
            overlap = reach - dist
            if ref > 0.0 and overlap < ref:  # relatives born overlapping move apart: the
                ref = ti.max(overlap, 0.0)  # reference overlap follows (running minimum)
                table.delta_ref[c] = ref
                if ref == 0.0:
                    table.sibling[c] = 0
            delta = overlap - ref  # the contact law acts on the overlap beyond the reference
            if delta > 0.0 and dist > 0.0:
                touching = True
                energy = self._contact(pool, table, c, i, j, d, dist, overlap, delta, ri, rj,
                                       dt, max_overlap_fraction, step)
        if not touching and (table.delta_max[c] > 0.0 or table.delta_prev[c] != 0.0):
            energy[3] += self._end_touch(pool, table, c, i, j)
        return energy

    @ti.func
    def _end_touch(self, pool: ti.template(), table: ti.template(), c, i, j):
        """Pair c separated this step: :meth:`_end_contact`; returns the last trapezoid of
        the hysteretic work down to separation."""
        hyst = -0.5 * table.fhys_prev[c] * table.delta_prev[c]
        self._end_contact(pool, table, c, i, j)
        return hyst

    @ti.func
    def _contact(self, pool: ti.template(), table: ti.template(), c, i, j, d, dist, overlap,
                 delta, ri, rj, dt, max_overlap_fraction, step):
        """Pair c = (i, j) touches (``delta`` > 0 beyond its reference overlap): the contact
        law, the history, this step's contribution and the overlap guard; returns the energy
        terms (see :meth:`_ledger_pairs`)."""
        nrm = d * (1.0 / dist)
        arm_i = ri - 0.5 * overlap
        arm_j = rj - 0.5 * overlap
        v_rel = (pool.velocity[i] + pool.angular_velocity[i].cross(arm_i * nrm)
                 - pool.velocity[j] - pool.angular_velocity[j].cross(-arm_j * nrm))
        a = pool.material[i]
        b = pool.material[j]
        sr = table.sqrt_r_star[c]  # the pair's constants, set at each rebuild
        (force, f_t, f_hys, dmax, s, fn_abs, d_n, d_t, fric, hyst, work) = self._law(
            self.pair, a, b, delta, table.delta_prev[c], nrm, v_rel, table.m_star[c], sr * sr,
            sr, dt, table.delta_max[c], table.spring[c], table.fhys_prev[c],
            table.sibling[c])
        table.stress_i[c] = 0.0
        table.stress_j[c] = 0.0
        if ti.static(self.breakage):
            self._stress_work(pool, table, c, i, j, a, b, work, delta > table.delta_prev[c],
                              f_hys > 0.0)
        table.delta_max[c] = dmax
        table.spring[c] = s
        table.delta_prev[c] = delta
        table.fhys_prev[c] = f_hys
        table.normal_force[c] = fn_abs
        # this pair's contribution, summed per particle by gather_pair_forces
        table.touch[c] = 1
        table.pair_force[c] = force
        table.pair_nft[c] = nrm.cross(f_t)
        table.arm_i[c] = arm_i
        table.arm_j[c] = arm_j
        table.roll_force[c] = self.pair[a, b, COL["rolling_friction"]] * ti.abs(f_hys)
        if delta > max_overlap_fraction * ti.min(ri, rj):
            self._flag(GUARD_OVERLAP, i, step, delta / ti.min(ri, rj))
        return ti.Vector([d_n, d_t, fric, hyst])

    @ti.func
    def _end_contact(self, pool: ti.template(), table: ti.template(), c, i, j):
        """The contact ended: bank the stressing work, clear the history (not the reference
        overlap of relatives, which ends only when they separate)."""
        if ti.static(self.breakage):
            self._bank(pool, table, c, i, j)
        table.delta_max[c] = 0.0
        table.delta_prev[c] = 0.0
        table.fhys_prev[c] = 0.0
        table.spring[c] = ti.Vector([0.0, 0.0, 0.0])
        table.normal_force[c] = 0.0

    @ti.kernel
    def end_dead_contacts(self, pool: ti.template(), table: ti.template()):
        """Contacts with a particle that died (a broken parent): the survivor banks its share
        and the contact history is cleared."""
        for c in range(table.n_pairs[None]):
            i = table.owner[c]
            j = table.partner[c]
            if (pool.alive[i] == 0 or pool.alive[j] == 0) and (
                    table.delta_max[c] > 0.0 or table.delta_prev[c] != 0.0):
                self._end_contact(pool, table, c, i, j)
                table.delta_ref[c] = 0.0
                table.sibling[c] = 0
