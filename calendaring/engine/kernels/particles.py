"""Phase 1 of a step, over particles: kick with the previous forces, drift, periodic wrap,
the guards, loads reset to gravity, then the particle-plate contacts at the new positions;
and the host-facing particle kernels (``advance``, ``synchronise``) and device flags.

See also: :mod:`.pairs` (phase 2), :mod:`.burst` (the steps in one launch).
"""

import taichi as ti

from calendaring.engine.contact_params import COL
from calendaring.engine.kernels.constants import (
    CHUNK_P,
    GUARD_BOTTOM,
    GUARD_NAN,
    GUARD_SKIN,
    GUARD_TOP,
    L_DAMP_N,
    L_DAMP_T,
    L_FRICTION,
    L_HYST,
    L_PLATE,
    L_ROLLING,
)
from calendaring.engine.laws.rolling import rolling_torque


class ParticlePhase:
    """Particle advance and plate contacts (phase 1 of :meth:`Kernels.step`)."""

    @ti.kernel
    def advance(self, pool: ti.template(), kick: ti.f64, drift: ti.f64, dt: ti.f64,
                gravity: ti.f64, z_bottom: ti.f64, z_top: ti.f64, v_top: ti.f64,
                lx: ti.f64, ly: ti.f64, half_skin: ti.f64, step: ti.i32, trace_slot: ti.i32):
        """Kick, drift, guards, reset to gravity, particle-plate contacts; the plate z forces
        of this step go to ``trace[trace_slot]``."""
        self._advance_all(pool, kick, drift, dt, gravity, z_bottom, z_top, v_top, lx, ly,
                          half_skin, step)
        _, n_p = self._chunks(pool.n_slots[None], CHUNK_P)
        self._close_plates(n_p, trace_slot, True)
        self._fold_ledger(0, n_p, True)

    @ti.func
    def _advance_all(self, pool: ti.template(), kick, drift, dt, gravity, z_bottom, z_top,
                     v_top, lx, ly, half_skin, step):
        s_p, _ = self._chunks(pool.n_slots[None], CHUNK_P)
        ti.loop_config(serialize=self.serial)
        for i in range(pool.n_slots[None]):
            if pool.alive[i]:
                self._advance_one(pool, i, kick, drift, dt, gravity, z_bottom, z_top, v_top,
                                  lx, ly, half_skin, step, i // s_p)

    @ti.func
    def _flags(self, pool: ti.template()):
        """The device flags: 1 pool overflow, 2 a guard fired, 4 the neighbour list needs a
        rebuild."""
        out = 0
        if pool.overflow[None] != 0:
            out |= 1
        if self.guard_count[None] != 0:
            out |= 2
        if self.need_rebuild[None] != 0:
            out |= 4
        return out

    @ti.kernel
    def synchronise(self, pool: ti.template(), dt: ti.f64):
        """Half-step velocities -> velocities at the current step (v_n = v_{n-1/2} + dt/2 a_n)."""
        for i in range(pool.n_slots[None]):
            if pool.alive[i]:
                pool.velocity[i] += 0.5 * dt * pool.inv_mass[i] * pool.force[i]
                pool.angular_velocity[i] += 0.5 * dt * pool.inv_inertia[i] * pool.torque[i]

    @ti.func
    def _advance_one(self, pool: ti.template(), i, kick, drift, dt, gravity, z_bottom, z_top,
                     v_top, lx, ly, half_skin, step, row):
        """Particle i: kick, drift, guards, loads reset, plate contacts. Plate forces and
        energy terms go to chunk row ``row``."""
        inv_m = pool.inv_mass[i]
        inv_i = pool.inv_inertia[i]
        w = pool.angular_velocity[i]
        tau_roll = rolling_torque(pool.roll_magnitude[i], w, inv_i, dt)
        v = pool.velocity[i] + kick * dt * inv_m * pool.force[i]
        w_new = w + kick * dt * inv_i * (pool.torque[i] + tau_roll)
        if ti.static(self.track_energy):
            self._ledger_add(L_ROLLING, -kick * dt * tau_roll.dot(0.5 * (w + w_new)), row)
        dx = drift * dt * v
        x = pool.position[i] + dx
        x[0] -= lx * ti.floor(x[0] / lx)
        x[1] -= ly * ti.floor(x[1] / ly)
        pool.velocity[i] = v
        pool.angular_velocity[i] = w_new
        pool.position[i] = x
        disp = pool.displacement[i] + dx
        pool.displacement[i] = disp
        r = pool.radius[i]
        if not (ti.math.isinf(x).any() or ti.math.isnan(x).any() or ti.math.isnan(v).any()):
            d2 = disp.norm_sqr()
            if d2 > ti.static(self.rebuild_fraction**2) * half_skin * half_skin:
                self.need_rebuild[None] = 1
                if d2 > half_skin * half_skin:
                    self._flag(GUARD_SKIN, i, step, ti.sqrt(d2))
            if x[2] < z_bottom - ti.static(self.plate_slack) * r:
                self._flag(GUARD_BOTTOM, i, step, x[2])
            if x[2] > z_top + ti.static(self.plate_slack) * r:
                self._flag(GUARD_TOP, i, step, x[2])
        else:
            self._flag(GUARD_NAN, i, step, x[2])
        m = pool.mass[i]
        pool.force[i] = ti.Vector([0.0, 0.0, -gravity * m])
        pool.torque[i] = ti.Vector([0.0, 0.0, 0.0])
        pool.roll_magnitude[i] = 0.0
        pool.normal_force_sum[i] = 0.0
        pool.n_contacts[i] = 0
        if ti.static(self.breakage):
            pool.stress_sum[i] = 0.0
            pool.loading[i] = 0
            if ti.static(self.track_pressed):
                pool.pressed[i] = 0
        self._plate_contact(pool, i, 0, pool.wall_delta_max_bottom, pool.wall_delta_prev_bottom,
                            pool.wall_fhys_prev_bottom, pool.wall_spring_bottom,
                            pool.wall_work_bottom, r - (x[2] - z_bottom), 0.0, dt, row)
        self._plate_contact(pool, i, 1, pool.wall_delta_max_top, pool.wall_delta_prev_top,
                            pool.wall_fhys_prev_top, pool.wall_spring_top, pool.wall_work_top,
                            r - (z_top - x[2]), v_top, dt, row)

    @ti.func
    def _plate_contact(self, pool: ti.template(), i, w: ti.template(), dmax_f: ti.template(),
                       prev_f: ti.template(), fprev_f: ti.template(), spring_f: ti.template(),
                       work_f: ti.template(), delta, v_plate, dt, row):
        """Particle i against plate w (0 = bottom, normal from particle -z; 1 = top, +z)."""
        if delta > 0.0:
            nrm = ti.Vector([0.0, 0.0, 2.0 * w - 1.0])
            r = pool.radius[i]
            arm = r - 0.5 * delta
            v_rel = (pool.velocity[i] + pool.angular_velocity[i].cross(arm * nrm)
                     - ti.Vector([0.0, 0.0, v_plate]))
            a = pool.material[i]
            (force, f_t, f_hys, dmax, s, fn_abs, d_n, d_t, fric, hyst, work) = self._law(
                self.plate, a, w, delta, prev_f[i], nrm, v_rel, pool.mass[i], r, ti.sqrt(r),
                dt, dmax_f[i], spring_f[i], fprev_f[i], 0)
            if ti.static(self.breakage):
                if self.breakable[a]:
                    wk = work_f[i] + work
                    work_f[i] = wk
                    pool.stress_sum[i] += self.plate[a, w, COL["stiffness_partition"]] * wk
                    if delta > prev_f[i]:
                        pool.loading[i] = 1
                    if ti.static(self.track_pressed):
                        if f_hys > 0.0:
                            pool.pressed[i] = 1
            dmax_f[i] = dmax
            spring_f[i] = s
            prev_f[i] = delta
            fprev_f[i] = f_hys
            pool.force[i] += force
            pool.torque[i] += (arm * nrm).cross(f_t)
            pool.roll_magnitude[i] += self.plate[a, w, COL["rolling_friction"]] * ti.abs(
                f_hys) * arm
            pool.normal_force_sum[i] += fn_abs
            pool.n_contacts[i] += 1
            self.plate_part[row, w] -= force
            if ti.static(self.track_energy):
                self._ledger_add(L_DAMP_N, d_n, row)
                self._ledger_add(L_DAMP_T, d_t, row)
                self._ledger_add(L_FRICTION, fric, row)
                self._ledger_add(L_HYST, hyst, row)
                self._ledger_add(L_PLATE, force[2] * v_plate * dt, row)
        elif dmax_f[i] > 0.0 or prev_f[i] != 0.0:
            if ti.static(self.breakage):  # the contact ended: bank its share (spec 5.4)
                if pool.event_open[i]:
                    pool.stress_bank[i] += self.plate[pool.material[i], w, COL[
                        "stiffness_partition"]] * work_f[i]
                work_f[i] = 0.0
            dmax_f[i] = 0.0
            spring_f[i] = ti.Vector([0.0, 0.0, 0.0])
            if ti.static(self.track_energy):
                self._ledger_add(L_HYST, -0.5 * fprev_f[i] * prev_f[i], row)
            prev_f[i] = 0.0
            fprev_f[i] = 0.0
