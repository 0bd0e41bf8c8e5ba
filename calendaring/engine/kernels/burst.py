"""One whole step in one launch (``step``) and, on the CPU, many steps in one launch
(``burst``): one persistent task per worker thread, the workers claiming chunks of each phase's
particles, pairs and bonds from shared counters, the phases separated by spin barriers (about 1
us each, against ~50 us for a parallel loop of Taichi's CPU thread pool and ~65 us for a kernel
launch from Python). A burst stops after the step whose device flags the host must act on,
exactly where the one-launch-per-step path would act.

See also: :mod:`.particles`, :mod:`.pairs` (the phases it schedules), :mod:`.ledger` (the
sums that close each step).
"""

import taichi as ti

from calendaring.engine.kernels.constants import (
    BARRIER_SPINS,
    CHUNK_C,
    CHUNK_P,
    GRAIN,
    GUARD_SYNC,
    MAX_CHUNKS,
    P_ADVANCE,
    P_BONDS,
    P_GATHER,
    P_PAIRS,
    RENDEZVOUS_SPINS,
    S_ABORT,
    S_ARRIVE,
    S_CLAIM,
    S_COUNT,
    S_GEN,
    S_READY,
    S_STOP,
)


class BurstScheduler:
    """``step``, ``burst`` and the workers' claims, barriers and end of step."""

    @ti.kernel
    def step(self, pool: ti.template(), table: ti.template(), grid: ti.template(),
             bonds: ti.template(), breakage: ti.template(), kick: ti.f64, dt: ti.f64,
             gravity: ti.f64, z_bottom: ti.f64, z_top: ti.f64, v_top: ti.f64, lx: ti.f64,
             ly: ti.f64, half_skin: ti.f64, step: ti.i32, trace_slot: ti.i32,
             max_overlap_fraction: ti.f64) -> ti.i32:
        """One whole time step in one launch (each top-level loop is still its own parallel
        task): :meth:`advance` (drift 1) to step ``step + 1``, :meth:`pair_forces` over the
        current candidate list, the bonds' update (``bonds`` not None; loads stored per
        bond), the per-particle gather of pair and bond loads, then the breakage test
        (``breakage`` not None).

        Returns the device flags (:meth:`_flags`) plus 8 x the number of parents to
        replace this step.
        """
        self._advance_all(pool, kick, 1.0, dt, gravity, z_bottom, z_top, v_top, lx, ly,
                          half_skin, step)
        self._pairs_all(pool, table, grid, dt, max_overlap_fraction, step + 1)
        if ti.static(bonds != None):  # noqa: E711 (a compile-time test in Taichi scope)
            bonds._update_all(pool, dt, lx, ly, step + 1, False)
        self._gather_all(pool, table, bonds)
        n_break = 0
        if ti.static(breakage != None):  # noqa: E711
            n_break = breakage._events_all(pool)
        _, n_p = self._chunks(pool.n_slots[None], CHUNK_P)
        _, n_c = self._chunks(table.n_pairs[None], CHUNK_C)
        self._close_step(n_p, n_c, trace_slot, True)
        return self._flags(pool) | (n_break << 3)

    @ti.kernel
    def burst(self, pool: ti.template(), table: ti.template(), grid: ti.template(),
              bonds: ti.template(), breakage: ti.template(), n_max: ti.i32, kick0: ti.f64,
              dt: ti.f64, gravity: ti.f64, z_bottom: ti.f64, lx: ti.f64, ly: ti.f64,
              half_skin: ti.f64, step0: ti.i32, trace0: ti.i32, max_overlap_fraction: ti.f64,
              interval: ti.i32) -> ti.types.vector(4, ti.i32):
        """Up to ``n_max`` calls of :meth:`step` in one launch (CPU backend only).

        Step s (from 0) takes the run from step ``step0 + s`` to ``step0 + s + 1`` with the
        top plate at ``plate_z[s]`` moving at ``plate_v[s]`` (filled by the host), kick
        ``kick0`` for s = 0 and 1 after, and writes its plate forces to
        ``trace[trace0 + s]``. The burst ends after ``n_max`` steps, after a step that
        flags parents to replace, or after a step whose number is a multiple of
        ``interval`` with a device flag up (overflow, guard, rebuild): where the
        one-launch-per-step loop acts on its flags. The ``workers`` persistent tasks claim
        chunks of each phase's work (advance; pairs and bonds; gather and breakage test)
        from shared counters and meet at a barrier after each phase.

        Returns (steps done, flags of the last step as :meth:`_flags`, parents to replace,
        status: 0 done, 1 the workers did not all start (nothing was done; run one launch
        per step), 2 a worker missed a barrier (``GUARD_SYNC`` raised)).
        """
        for q in ti.static(range(16)):
            self.sync[q, 0] = 0
        for ph in ti.static(range(4)):
            for v in ti.static(range(self.claim_rows)):
                self.claims[ph, v, 0] = 0
        for q in ti.static(range(3)):
            self.outcome[q] = 0
        nw = ti.static(self.workers)
        self.n_tasks[None] = nw * GRAIN  # a run-time bound: blocks of GRAIN iterations
        if ti.static(nw == 1):
            ti.loop_config(serialize=True)
            for _ in range(1):
                self._burst_worker(pool, table, grid, bonds, breakage, n_max, kick0, dt,
                                   gravity, z_bottom, lx, ly, half_skin, step0, trace0,
                                   max_overlap_fraction, interval, 0)
        else:
            for k in range(self.n_tasks[None]):
                if k % GRAIN == 0:
                    if self._rendezvous():
                        self._burst_worker(pool, table, grid, bonds, breakage, n_max, kick0,
                                           dt, gravity, z_bottom, lx, ly, half_skin, step0,
                                           trace0, max_overlap_fraction, interval,
                                           k // GRAIN)
        return ti.Vector([self.outcome[0], self.outcome[1], self.outcome[2],
                          self.sync[S_ABORT, 0]])

    @ti.func
    def _claim(self, phase, n_chunks, wk):
        """The next chunk of ``phase`` for worker ``wk``, or -1 when none is left: first
        from the worker's own share of the chunks (the same particles and pairs every step,
        so their data stay in its core's cache), then from the others' shares."""
        nw = ti.static(self.workers)
        k = -1
        for o in range(nw):
            v = (wk + o) % nw
            lo = v * n_chunks // nw
            j = ti.atomic_add(self.claims[phase, v, 0], 1)
            if lo + j < (v + 1) * n_chunks // nw:
                k = lo + j
                break
        return k

    @ti.func
    def _burst_worker(self, pool: ti.template(), table: ti.template(), grid: ti.template(),
                      bonds: ti.template(), breakage: ti.template(), n_max, kick0, dt, gravity,
                      z_bottom, lx, ly, half_skin, step0, trace0, max_overlap_fraction,
                      interval, wk):
        """Worker ``wk``'s part of :meth:`burst`."""
        n_slots = pool.n_slots[None]
        n_pairs = table.n_pairs[None]
        s_p, n_p = self._chunks(n_slots, CHUNK_P)
        s_c, n_c = self._chunks(n_pairs, CHUNK_C)
        n_bonds = 0
        if ti.static(bonds != None):  # noqa: E711
            n_bonds = bonds.n_bonds[None]
        s_b, n_b = self._chunks(n_bonds, CHUNK_C)
        for s in range(n_max):
            step = step0 + s
            kick = kick0
            if s > 0:
                kick = 1.0
            z_top = self.plate_z[s]
            v_top = self.plate_v[s]
            if ti.static(breakage != None):  # noqa: E711
                breakage.n_break[None] = 0  # every worker: before the first barrier
            while True:
                k = self._claim(P_ADVANCE, n_p, wk)
                if k < 0:
                    break
                for i in range(k * s_p, ti.min(n_slots, (k + 1) * s_p)):
                    if pool.alive[i]:
                        self._advance_one(pool, i, kick, 1.0, dt, gravity, z_bottom, z_top,
                                          v_top, lx, ly, half_skin, step, k)
            self._barrier()
            while True:
                k = self._claim(P_PAIRS, n_c, wk)
                if k < 0:
                    break
                self._pair_chunk(pool, table, grid, k * s_c, ti.min(n_pairs, (k + 1) * s_c),
                                 dt, max_overlap_fraction, step + 1, MAX_CHUNKS + k)
            if ti.static(bonds != None):  # noqa: E711
                while True:
                    k = self._claim(P_BONDS, n_b, wk)
                    if k < 0:
                        break
                    for b in range(k * s_b, ti.min(n_bonds, (k + 1) * s_b)):
                        bonds._bond_item(pool, b, dt, lx, ly, step + 1, False)
            self._barrier()
            while True:
                k = self._claim(P_GATHER, n_p, wk)
                if k < 0:
                    break
                for i in range(k * s_p, ti.min(n_slots, (k + 1) * s_p)):
                    if pool.alive[i]:
                        self._gather_one(pool, table, bonds, i)
                        if ti.static(breakage != None):  # noqa: E711
                            breakage._event_item(pool, i)
            if ti.static(self.workers == 1):
                self._end_step(pool, breakage, s, n_max, step0, trace0, interval, n_p, n_c)
            else:
                gen, last = self._arrive()
                if last:  # the others wait while the last to arrive closes the step
                    self._end_step(pool, breakage, s, n_max, step0, trace0, interval, n_p,
                                   n_c)
                    self._release()
                else:
                    self._wait(gen)
            if ti.atomic_add(self.sync[S_STOP, 0], 0) != 0 or ti.atomic_add(
                    self.sync[S_ABORT, 0], 0) != 0:
                break

    @ti.func
    def _end_step(self, pool: ti.template(), breakage: ti.template(), s, n_max, step0, trace0,
                  interval, n_p, n_c):
        """Close step s of a burst (one worker, the others held at the barrier): the plate
        forces and energy terms summed in chunk order, the trace row, the flags, whether
        the burst stops here, and the phases' work counters reset."""
        self._close_step(n_p, n_c, trace0 + s, False)
        flags = self._flags(pool)
        n_break = 0
        if ti.static(breakage != None):  # noqa: E711
            n_break = breakage._n_to_replace()
        done = s + 1
        stop = 0
        if n_break > 0 or done >= n_max:
            stop = 1
        if (step0 + done) % interval == 0 and (flags & 7) != 0:
            stop = 1
        self.outcome[0] = done
        self.outcome[1] = flags
        self.outcome[2] = n_break
        for ph in ti.static(range(4)):
            for v in ti.static(range(self.claim_rows)):
                self.claims[ph, v, 0] = 0
        self.sync[S_STOP, 0] = stop

    @ti.func
    def _rendezvous(self):
        """Every worker of a burst waits here until all have started; True to go on. A
        worker still alone after ``RENDEZVOUS_SPINS`` (the thread pool gave two workers'
        blocks to one thread) calls the burst off for all, unless the last worker
        arrived first: the first to claim the decision makes it."""
        nw = ti.static(self.workers)
        if ti.atomic_add(self.sync[S_ARRIVE, 0], 1) == nw - 1:
            if ti.atomic_add(self.sync[S_CLAIM, 0], 1) == 0:
                ti.atomic_add(self.sync[S_READY, 0], 1)
        spins = 0
        while ti.atomic_add(self.sync[S_READY, 0], 0) == 0:
            spins += 1
            if spins > RENDEZVOUS_SPINS:
                spins = 0
                if ti.atomic_add(self.sync[S_CLAIM, 0], 1) == 0:
                    self.sync[S_ABORT, 0] = 1
                    ti.atomic_add(self.sync[S_READY, 0], 1)
        return ti.atomic_add(self.sync[S_ABORT, 0], 0) == 0

    @ti.func
    def _barrier(self):
        """All workers of a burst reach this point before any goes on."""
        if ti.static(self.workers > 1):
            gen, last = self._arrive()
            if last:
                self._release()
            else:
                self._wait(gen)

    @ti.func
    def _arrive(self):
        """A worker reaches a barrier: (the barrier's generation, whether it is the last
        to arrive). The last one calls :meth:`_release`, the others :meth:`_wait`."""
        gen = ti.atomic_add(self.sync[S_GEN, 0], 0)
        last = ti.atomic_add(self.sync[S_COUNT, 0], 1) == ti.static(self.workers) - 1
        return gen, last

    @ti.func
    def _release(self):
        """Reset the count and open the next generation: the waiting workers go on."""
        ti.atomic_sub(self.sync[S_COUNT, 0], ti.static(self.workers))
        ti.atomic_add(self.sync[S_GEN, 0], 1)

    @ti.func
    def _wait(self, gen):
        spins = 0
        while ti.atomic_add(self.sync[S_GEN, 0], 0) == gen:
            spins += 1
            if spins > BARRIER_SPINS:
                self._flag(GUARD_SYNC, 0, 0, 0.0)
                ti.atomic_max(self.sync[S_ABORT, 0], 2)
                break
