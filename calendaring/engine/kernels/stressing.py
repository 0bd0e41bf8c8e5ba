"""Breakage bookkeeping of the contacts (spec 5.4): each contact's stressing work booked to
the breakage event open on each breakable side, banked when the contact ends; and the marks
of the region a breakage replacement changes (for the energy ledger of a replacement).

Compiled in only when some material can break (``Kernels.breakage``).

See also: :mod:`calendaring.engine.breakage_kernels` (the breakage test and the replacement).
"""

import taichi as ti

from calendaring.engine.contact_params import COL


class StressingWork:
    """Stressing work per contact side and the breakage-region marks."""

    @ti.func
    def _stress_work(self, pool: ti.template(), table: ti.template(), c, i, j, a, b, work,
                     loading, pressed):
        """Add a contact's stressing work to each breakable side's event and E_k (spec 5.4)."""
        if self.breakable[a]:
            table.stress_i[c] = self._side_work(pool, table.event_a, table.work_a, c, i,
                                                self.pair[a, b, COL["stiffness_partition"]],
                                                work, loading, pressed)
        if self.breakable[b]:
            table.stress_j[c] = self._side_work(pool, table.event_b, table.work_b, c, j,
                                                self.pair[b, a, COL["stiffness_partition"]],
                                                work, loading, pressed)

    @ti.func
    def _side_work(self, pool: ti.template(), event_f: ti.template(), work_f: ti.template(), c,
                   i, share, work, loading, pressed):
        """One side of :meth:`_stress_work`: particle i with its share of the contact work
        (returned; the gather adds it to ``stress_sum``)."""
        ev = pool.event_id[i]
        if event_f[c] != ev:  # the particle closed an event since: start afresh
            event_f[c] = ev
            work_f[c] = 0.0
        w = work_f[c] + work
        work_f[c] = w
        if loading:
            pool.loading[i] = 1
        if ti.static(self.track_pressed):
            if pressed:
                pool.pressed[i] = 1
        return share * w

    @ti.func
    def _bank(self, pool: ti.template(), table: ti.template(), c, i, j):
        """A contact ends: the open events of its particles keep their shares (spec 5.4)."""
        a = pool.material[i]
        b = pool.material[j]
        self._bank_side(pool, table.event_a, table.work_a, c, i,
                        self.pair[a, b, COL["stiffness_partition"]])
        self._bank_side(pool, table.event_b, table.work_b, c, j,
                        self.pair[b, a, COL["stiffness_partition"]])

    @ti.func
    def _bank_side(self, pool: ti.template(), event_f: ti.template(), work_f: ti.template(), c,
                   i, share):
        if pool.alive[i] and pool.event_open[i] and event_f[c] == pool.event_id[i]:
            pool.stress_bank[i] += share * work_f[c]
        work_f[c] = 0.0

    @ti.kernel
    def mark_breakage_region(self, pool: ti.template(), table: ti.template(),
                             bonds: ti.template(), breakage: ti.template(), mark: ti.template(),
                             n_break: ti.i32):
        """Before the ``n_break`` listed parents are replaced: ``mark`` = 2 for them, 1 for
        their candidate partners and bond partners (the particles whose loads the
        replacement can change: a fragment lies inside its parent, so whatever touches it
        touched the parent), 0 elsewhere."""
        for i in range(pool.n_slots[None]):
            mark[i] = 0
        for k in range(n_break):
            mark[breakage.brk_slot[k]] = 2
        for c in range(table.n_pairs[None]):
            i = table.owner[c]
            j = table.partner[c]
            if mark[i] == 2:
                ti.atomic_max(mark[j], 1)
            if mark[j] == 2:
                ti.atomic_max(mark[i], 1)
        if ti.static(bonds != None):  # noqa: E711
            for k in range(n_break):
                p = breakage.brk_slot[k]
                lo = bonds.list_start[p]
                for e in range(lo, lo + bonds.list_count[p]):
                    entry = bonds.list_entry[e]  # b: p is side A; -b - 1: side B
                    b = ti.select(entry < 0, -entry - 1, entry)
                    q = ti.select(entry < 0, bonds.slot_a[b], bonds.slot_b[b])
                    ti.atomic_max(mark[q], 1)

    @ti.kernel
    def mark_from(self, pool: ti.template(), mark: ti.template(), lo: ti.i32):
        """``mark`` = 1 for the slots from ``lo`` on (the fragments just spawned)."""
        for i in range(lo, pool.n_slots[None]):
            mark[i] = 1
