"""The energy ledger and the plate forces: energy terms and plate forces summed per chunk,
then over the chunks in order at the end of each step (the same sums on any number of threads
and on either launch path); and the observables kernels (kinetic, rotational, gravity and
stored elastic energy).

See also: :meth:`calendaring.engine.simulation.Simulation.energy` (the host side).
"""

import taichi as ti

from calendaring.engine.kernels.constants import (
    L_DAMP_N,
    L_DAMP_T,
    L_FRICTION,
    L_HYST,
    MAX_CHUNKS,
    N_LEDGER,
)


class EnergyLedger:
    """Chunk rows folded in order into ``ledger``, ``plate_force`` and ``trace``; energies."""

    @ti.func
    def _ledger_add(self, slot, value, row):
        """Add ``value`` [J] to energy-ledger term ``slot`` through chunk row ``row``."""
        self.ledger_part[row, slot] += value

    @ti.func
    def _fold_ledger(self, lo, hi, top: ti.template()):
        """Add ledger rows ``lo:hi`` to the ledger in row order and clear them (``top``: at
        the top level of a kernel, where the loop must be told to run serially)."""
        if ti.static(self.track_energy):
            acc = ti.Vector.zero(ti.f64, N_LEDGER)
            if ti.static(top):
                ti.loop_config(serialize=True)
            for r in range(lo, hi):
                for k in ti.static(range(N_LEDGER)):
                    acc[k] += self.ledger_part[r, k]
                    self.ledger_part[r, k] = 0.0
            for k in ti.static(range(N_LEDGER)):
                self.ledger[k] += acc[k]

    @ti.func
    def _close_plates(self, n_chunks, trace_slot, top: ti.template()):
        """The plate forces of this step: the chunk rows in order (then cleared) to
        ``plate_force`` and ``trace[trace_slot]``."""
        fb = ti.Vector([0.0, 0.0, 0.0])
        ft = ti.Vector([0.0, 0.0, 0.0])
        if ti.static(top):
            ti.loop_config(serialize=True)
        for r in range(n_chunks):
            fb += self.plate_part[r, 0]
            ft += self.plate_part[r, 1]
            self.plate_part[r, 0] = ti.Vector([0.0, 0.0, 0.0])
            self.plate_part[r, 1] = ti.Vector([0.0, 0.0, 0.0])
        self.plate_force[0] = fb
        self.plate_force[1] = ft
        self.trace[trace_slot, 0] = fb[2]
        self.trace[trace_slot, 1] = ft[2]

    @ti.func
    def _close_step(self, n_p, n_c, trace_slot, top: ti.template()):
        """The sums of a whole step over ``n_p`` particle chunks and ``n_c`` pair chunks:
        plate forces (and trace row ``trace_slot``), then the energy terms, in chunk order;
        the one-launch and multi-step paths both close a step here."""
        self._close_plates(n_p, trace_slot, top)
        self._fold_ledger(0, n_p, top)
        self._fold_ledger(MAX_CHUNKS, MAX_CHUNKS + n_c, top)

    @ti.func
    def _ledger_pairs(self, energy, row):
        """Add a pair's or a chunk's energy terms (normal and tangential damping, friction,
        hysteretic work) to ledger row ``row``."""
        if ti.static(self.track_energy):
            self._ledger_add(L_DAMP_N, energy[0], row)
            self._ledger_add(L_DAMP_T, energy[1], row)
            self._ledger_add(L_FRICTION, energy[2], row)
            self._ledger_add(L_HYST, energy[3], row)

    @ti.kernel
    def energies(self, pool: ti.template(), table: ti.template(), grid: ti.template(),
                 dt: ti.f64, gravity: ti.f64, z_bottom: ti.f64, z_top: ti.f64) -> ti.types.vector(
            4, ti.f64):
        """(kinetic translational, kinetic rotational, gravity potential, elastic) [J]."""
        return self._energies(pool, table, grid, dt, gravity, z_bottom, z_top, None)

    @ti.kernel
    def energies_marked(self, pool: ti.template(), table: ti.template(), grid: ti.template(),
                        dt: ti.f64, gravity: ti.f64, z_bottom: ti.f64, z_top: ti.f64,
                        mark: ti.template()) -> ti.types.vector(4, ti.f64):
        """:meth:`energies` of the particles with ``mark > 0`` and of the pairs with at
        least one such particle."""
        return self._energies(pool, table, grid, dt, gravity, z_bottom, z_top, mark)

    @ti.func
    def _energies(self, pool: ti.template(), table: ti.template(), grid: ti.template(), dt,
                  gravity, z_bottom, z_top, mark: ti.template()):
        ek = 0.0
        er = 0.0
        eg = 0.0
        ee = 0.0
        for i in range(pool.n_slots[None]):
            take = pool.alive[i] != 0
            if ti.static(mark != None):  # noqa: E711
                take = take and mark[i] > 0
            if take:
                m = pool.mass[i]
                v = pool.velocity[i] + 0.5 * dt * pool.inv_mass[i] * pool.force[i]
                w = pool.angular_velocity[i] + 0.5 * dt * pool.inv_inertia[i] * pool.torque[i]
                ek += 0.5 * m * v.norm_sqr()
                er += 0.5 * w.norm_sqr() / pool.inv_inertia[i]
                eg += m * gravity * pool.position[i][2]
                r = pool.radius[i]
                z = pool.position[i][2]
                a = pool.material[i]
                ee += self._stored(self.plate, a, 0, r - (z - z_bottom), r,
                                   pool.wall_delta_max_bottom[i])
                ee += self._stored(self.plate, a, 1, r - (z_top - z), r,
                                   pool.wall_delta_max_top[i])
        for c in range(table.n_pairs[None]):
            i = table.owner[c]
            j = table.partner[c]
            take = pool.alive[i] != 0 and pool.alive[j] != 0
            if ti.static(mark != None):  # noqa: E711
                take = take and (mark[i] > 0 or mark[j] > 0)
            if take:
                d = grid.minimum_image(pool.position[j] - pool.position[i])
                ri = pool.radius[i]
                rj = pool.radius[j]
                sr = table.sqrt_r_star[c]  # the R* the contact law uses
                ee += self._stored(self.pair, pool.material[i], pool.material[j],
                                   ri + rj - d.norm() - table.delta_ref[c], sr * sr,
                                   table.delta_max[c])
        return ti.Vector([ek, er, eg, ee])
