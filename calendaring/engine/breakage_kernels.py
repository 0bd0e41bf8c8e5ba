"""Tavares UFRJ breakage on the device: events, damage, breakage and fragment spawning.

Per step, after the contact forces (spec 5.11):

1. :meth:`BreakageKernels.events` over the breakable particles: the specific stressing
   energy ``E_k = (B + sum_c e_c W_c) / m`` (the contact sums are accumulated by the force
   kernels, :mod:`calendaring.engine.forces`), the particle's lifetime peak of the total contact
   normal force, loading events (opened when a contact loads, and with
   ``breakage.event_end_rule = "release"`` presses; closed by the rule: ``"quiet"`` after
   ``breakage.event_end_steps`` steps in a row without a loading contact or when the
   particle has no contact, ``"release"`` once no contact presses on it),
   damage at the end of an event (Eq. 36 solved by bisection, spec 5.5) and the breakage
   test ``E_k >= E'_f`` (5.6). Breaking parents go to a list; it returns their number.
2. Only when that number is > 0, :meth:`BreakageKernels.replace` (one kernel): progeny sizes
   of every parent from t10 (5.7-5.9), a serial prefix sum that allocates all fragment slots
   of the step at the pool tail (new ids, ``parent_id`` lineage; past the capacity nothing
   is written and the pool's overflow flag stops the run), then placement inside each parent
   (5.10) and the fragments' state, in parallel over the parents. The parents die.
3. The host then rebuilds the neighbour list, :meth:`init_new_contacts` starts the contacts
   of the new fragments (force-free siblings, 5.10) and the forces of the step are
   recomputed at the same positions.

Random numbers come from a counter-based hash of (run seed, particle id, draw number), so a
particle's fracture energy and a parent's fragment layout do not depend on thread order or
on a restart from a checkpoint.

See also: :mod:`calendaring.engine.breakage` (the host formulas),
:mod:`calendaring.engine.kernels.stressing` (the stressing work of each contact),
:mod:`calendaring.engine.state` (the pool the fragments are appended to).
"""


import math

import numpy as np
import taichi as ti

from calendaring.core.config import SimConfig
from calendaring.engine.backend import serial_loops
from calendaring.engine.breakage import (
    TN_SIZES,
    breakable_mask,
    device_factor,
    max_fragments,
    truncation_factor,
)

_KNOTS = (1, *TN_SIZES)  # n of the t_n knots: x = 1/n
_NK = len(_KNOTS)
_BINARY = 2.0 ** (-1.0 / 3.0)  # relative diameter of the two halves of a binary split
_MAX_NEIGHBOURS = 64  # touching neighbours of a parent that fragment placement avoids
_M1 = -7046029254386353131  # 0x9E3779B97F4A7C15 as a signed 64-bit integer
_M2 = -3372029247567499371  # 0xD1B54A32D192ED03
_M3 = -4658895280553007687  # 0xBF58476D1CE4E5B9
_M4 = -7723592293110705685  # 0x94D049BB133111EB


@ti.data_oriented
class BreakageKernels:
    """Breakage state that is not per particle, and the breakage kernels.

    Args:
        cfg: configuration (``breakage`` section, materials, numerics.seed).
        d_parent_max: largest diameter a breakable particle can have [m] (scratch sizing).
    """

    def __init__(self, cfg: SimConfig, d_parent_max: float) -> None:
        b = cfg.breakage
        names = cfg.material_names
        # per-step loop without the thread pool (one CPU thread only, never on CUDA)
        self.serial = serial_loops(cfg.numerics.threads)
        self.n_mat = len(names)
        self.gamma = float(b.damage_constant)
        self.d0 = float(b.d0)
        self.phi = float(b.phi)
        self.sigma = float(b.sigma_e)
        self.t10_max = float(b.alpha_percentage) / 100.0
        self.b_prime = float(b.b_prime)
        factor = truncation_factor(b)
        self.truncated = math.isfinite(factor)
        self.trunc = float(factor) if self.truncated else 0.0
        self.e_min = float(b.min_specific_energy)
        self.n_end = int(b.event_end_steps)
        self.end_when_quiet = b.event_end_rule == "quiet"
        self.d_min = float(b.min_fragment_diameter)
        self.d_break = float(b.min_breakable_diameter)
        self.force_free = b.sibling_init == "force_free"
        self.n_candidates = int(b.placement_candidates)
        self.n_relax = int(b.relax_iterations)
        self.density_scaling = float(cfg.numerics.density_scaling)
        seed = int(cfg.numerics.seed) & 0xFFFFFFFFFFFFFFFF
        self.seed = seed - (1 << 64) if seed >= (1 << 63) else seed
        self.max_frag = max_fragments(max(d_parent_max, self.d_break), b)
        self.max_breaks = int(b.max_breaks_per_step)
        fb = ti.FieldsBuilder()
        self.breakable = ti.field(ti.i32)
        self.e50_scale = ti.field(ti.f64)  # E_inf / (1 + k_p/k_s) per material [J/kg]
        fb.dense(ti.i, self.n_mat).place(self.breakable, self.e50_scale)
        nb, nf = self.max_breaks, self.max_frag
        self.brk_slot = ti.field(ti.i32)
        self.brk_nfrag = ti.field(ti.i32)
        self.brk_first = ti.field(ti.i32)  # first fragment slot
        self.brk_first_id = ti.field(ti.i64)
        self.brk_parent_id = ti.field(ti.i64)
        self.brk_energy = ti.field(ti.f64)  # E_k at breakage [J/kg]
        self.brk_fracture = ti.field(ti.f64)  # E'_f at breakage [J/kg]
        self.brk_e50 = ti.field(ti.f64)  # E50 of the parent [J/kg]
        self.brk_t10 = ti.field(ti.f64)
        self.brk_diameter = ti.field(ti.f64)  # [m]
        self.brk_peak = ti.field(ti.f64)  # [N]
        fb.dense(ti.i, nb).place(self.brk_slot, self.brk_nfrag, self.brk_first,
                                 self.brk_first_id, self.brk_parent_id, self.brk_energy,
                                 self.brk_fracture, self.brk_e50, self.brk_t10,
                                 self.brk_diameter, self.brk_peak)
        self.nb_c = ti.Vector.field(3, ti.f64)  # parent's touching neighbours, relative [m]
        self.nb_r = ti.field(ti.f64)
        self.nb_n = ti.field(ti.i32)
        fb.dense(ti.ij, (nb, _MAX_NEIGHBOURS)).place(self.nb_c, self.nb_r)
        fb.dense(ti.i, nb).place(self.nb_n)
        self.frag_r = ti.field(ti.f64)  # fragment radii [m], largest first
        self.frag_c = ti.Vector.field(3, ti.f64)  # centres relative to the parent [m]
        fb.dense(ti.ij, (nb, nf)).place(self.frag_r, self.frag_c)
        self.n_break = ti.field(ti.i32)
        self.n_deferred = ti.field(ti.i32)  # parents that had to wait for the next step
        self.n_fragments = ti.field(ti.i32)  # fragments of this step
        self.frag_overflow = ti.field(ti.i32)
        self.ok = ti.field(ti.i32)
        fb.place(self.n_break, self.n_deferred, self.n_fragments, self.frag_overflow, self.ok)
        self._tree = fb.finalize()
        mats = [cfg.materials[n] for n in names]
        self.breakable.from_numpy(breakable_mask(cfg).astype(np.int32))
        self.e50_scale.from_numpy(np.array([b.e_inf * device_factor(m, b) for m in mats]))

    def destroy(self) -> None:
        """Free the device memory."""
        if self._tree is not None:
            self._tree.destroy()
            self._tree = None

    # ------------------------------------------------------------------ random numbers
    @ti.func
    def _u01(self, key, counter):
        """Uniform in (0, 1) from a hash of (seed, key, counter) (splitmix64 finaliser)."""
        x = (ti.cast(key, ti.u64) * ti.cast(ti.i64(_M1), ti.u64)
             + ti.cast(counter, ti.u64) * ti.cast(ti.i64(_M2), ti.u64)
             + ti.cast(ti.i64(self.seed), ti.u64))
        x ^= x >> ti.u64(30)
        x *= ti.cast(ti.i64(_M3), ti.u64)
        x ^= x >> ti.u64(27)
        x *= ti.cast(ti.i64(_M4), ti.u64)
        x ^= x >> ti.u64(31)
        return (ti.cast(x >> ti.u64(11), ti.f64) + 0.5) * (1.0 / 9007199254740992.0)

    @ti.func
    def _normal2(self, key, counter):
        """Two independent standard normals (Box-Muller) from draws counter, counter + 1."""
        u1 = self._u01(key, counter)
        u2 = self._u01(key, counter + 1)
        rad = ti.sqrt(-2.0 * ti.log(u1))
        return rad * ti.cos(2.0 * math.pi * u2), rad * ti.sin(2.0 * math.pi * u2)

    @ti.func
    def _in_ball(self, key, counter, radius):
        """A point uniform in the ball |c| <= radius (draws counter .. counter + 4)."""
        z1, z2 = self._normal2(key, counter)
        z3, _ = self._normal2(key, counter + 2)
        v = ti.Vector([z1, z2, z3])
        u = self._u01(key, counter + 4)
        return v / ti.max(v.norm(), 1e-300) * (radius * ti.pow(u, 1.0 / 3.0))

    # ------------------------------------------------------------------ model formulas
    @ti.func
    def e50(self, mat, diameter):
        """Median fracture energy E50(d) [J/kg] (Eq. 33)."""
        return self.e50_scale[mat] * (1.0 + ti.pow(ti.static(self.d0) / diameter,
                                                     ti.static(self.phi)))

    @ti.func
    def fracture_energy(self, e50, key):
        """A fracture energy [J/kg] drawn from the truncated lognormal (spec 5.2)."""
        z, _ = self._normal2(key, 0)
        e_star = e50 * ti.exp(ti.static(self.sigma) * z)
        out = e_star
        if ti.static(self.truncated):
            e_max = ti.static(self.trunc) * e50
            out = e_star * e_max / (e_star + e_max)
        return out

    @ti.func
    def damage(self, x):
        """Root D in [0, 1] of D = [2 g x / (2 g - 5 D + 5)]^(2 g / 5) (bisection)."""
        g = ti.static(self.gamma)
        p = ti.static(2.0 * self.gamma / 5.0)
        lo = 0.0
        hi = 1.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if mid - ti.pow(2.0 * g * x / (2.0 * g - 5.0 * mid + 5.0), p) < 0.0:
                lo = mid
            else:
                hi = mid
        out = 0.5 * (lo + hi)
        if x >= 1.0:
            out = 1.0
        if x <= 0.0:
            out = 0.0
        return out

    @ti.func
    def _knot_value(self, q: ti.template(), t10):
        """t_n at knot q (n = 1, 2, 4, 10, 25, 50, 75)."""
        out = 1.0
        if ti.static(_KNOTS[q] > 1):
            out = 1.0 - ti.pow(1.0 - t10, ti.static(9.0 / (_KNOTS[q] - 1.0)))
        return out

    @ti.func
    def progeny_cdf(self, x, t10):
        """Mass fraction of progeny finer than x d_parent (spec 5.8)."""
        out = 1.0
        if x < 1.0:
            found = 0
            for q in ti.static(range(_NK - 1)):
                xa = ti.static(1.0 / _KNOTS[q])
                xb = ti.static(1.0 / _KNOTS[q + 1])
                if found == 0 and x >= xb:
                    pa = self._knot_value(q, t10)
                    pb = self._knot_value(q + 1, t10)
                    out = pb + (pa - pb) * (ti.log(x) - ti.log(xb)) / ti.static(
                        math.log(xa) - math.log(xb))
                    found = 1
            if found == 0:
                t75 = self._knot_value(_NK - 1, t10)
                t50 = self._knot_value(_NK - 2, t10)
                out = 0.0
                if t75 > 0.0:
                    s = ti.log(t50 / t75) / ti.static(math.log(75.0 / 50.0))
                    out = t75 * ti.pow(75.0 * x, s)
        return out

    @ti.func
    def _emit(self, k, count, n, y):
        for _ in range(n):
            if count < ti.static(self.max_frag):
                self.frag_r[k, count] = y
            else:
                self.frag_overflow[None] = 1
            count += 1
        return count

    @ti.func
    def _class(self, k, count, carry, x_hi, x_lo, t10, d_parent):
        """One size class (x_lo, x_hi] of spec 5.9 step 2; returns (count, carry)."""
        f = self.progeny_cdf(x_hi, t10) - self.progeny_cdf(x_lo, t10) + carry
        carry_out = 0.0
        if f > 0.0:
            n = ti.cast(ti.ceil(f / (x_hi * x_hi * x_hi) - 1e-12), ti.i32)
            n = ti.max(n, 1)
            y = ti.pow(f / n, 1.0 / 3.0)
            if (n == 1 and y <= x_lo) or y < ti.static(self.d_min) / d_parent:
                carry_out = f  # to the next class, or below d_min: to the fines
            else:
                count = self._emit(k, count, n, y)
        return count, carry_out

    @ti.func
    def progeny_sizes(self, k, d_parent, t10):
        """Fragment radii of break k into ``frag_r[k, :]`` (largest first); returns the
        number of fragments. Sum of d^3 equals d_parent^3 to round-off (spec 5.9)."""
        x_m = ti.static(self.d_min) / d_parent
        count = 0
        carry = 0.0
        x_hi = 1.0
        for q in ti.static(range(1, _NK)):
            if x_hi > x_m:
                x_lo = ti.max(ti.static(1.0 / _KNOTS[q]), x_m)
                count, carry = self._class(k, count, carry, x_hi, x_lo, t10, d_parent)
                x_hi = x_lo
        if x_hi > x_m:  # d_min below d_parent / 75: one class down to d_min
            count, carry = self._class(k, count, carry, x_hi, x_m, t10, d_parent)
        f_fines = self.progeny_cdf(x_m, t10) + carry
        n_fines = ti.cast(ti.floor(f_fines / (x_m * x_m * x_m) + 1e-12), ti.i32)
        count = self._emit(k, count, n_fines, x_m)
        count = ti.min(count, ti.static(self.max_frag))
        if count < 2:  # binary split (spec 5.9 step 5)
            self.frag_r[k, 0] = _BINARY
            self.frag_r[k, 1] = _BINARY
            count = 2
        total = 0.0
        for f in range(count):
            y = self.frag_r[k, f]
            total += y * y * y
        scale = 0.5 * d_parent * ti.pow(1.0 / total, 1.0 / 3.0)
        for f in range(count):
            self.frag_r[k, f] *= scale
        for f in range(1, count):  # insertion sort, largest first
            r = self.frag_r[k, f]
            g = f - 1
            while g >= 0:
                if self.frag_r[k, g] >= r:
                    break
                self.frag_r[k, g + 1] = self.frag_r[k, g]
                g -= 1
            self.frag_r[k, g + 1] = r
        return count

    @ti.func
    def place(self, k, count, r_parent, key, z_lo, z_hi):
        """Fragment centres inside the parent (spec 5.10), relative to its centre.

        Largest first, each fragment takes the best of ``placement_candidates`` random
        centres in the ball |c| <= R_p - r: the one with the smallest largest overlap with
        the fragments already placed, the parent's touching neighbours (``nb_*``) and the
        plates (at heights ``z_lo``, ``z_hi`` relative to the parent centre). Then the
        sibling overlaps are relaxed, the mass centre is moved to the parent centre and the
        layout is shrunk about it until every fragment is inside the parent.
        """
        n_cand = ti.static(self.n_candidates)
        for f in range(count):
            rf = self.frag_r[k, f]
            best = 1e300
            best_c = ti.Vector([0.0, 0.0, 0.0])
            for m in range(n_cand):
                cand = self._in_ball(key, 8 * (f * n_cand + m) + 2, r_parent - rf)
                worst = ti.max(rf - (cand[2] - z_lo), rf - (z_hi - cand[2]))
                for g in range(f):
                    worst = ti.max(worst,
                                   rf + self.frag_r[k, g] - (cand - self.frag_c[k, g]).norm())
                for q in range(self.nb_n[k]):
                    worst = ti.max(worst,
                                   rf + self.nb_r[k, q] - (cand - self.nb_c[k, q]).norm())
                if worst < best:
                    best = worst
                    best_c = cand
                if worst <= 0.0:
                    break
            self.frag_c[k, f] = best_c
        for _ in range(ti.static(self.n_relax)):
            for f in range(count):
                rf = self.frag_r[k, f]
                push = ti.Vector([0.0, 0.0, 0.0])
                for g in range(count):
                    if g != f:
                        d = self.frag_c[k, f] - self.frag_c[k, g]
                        dist = d.norm()
                        ov = rf + self.frag_r[k, g] - dist
                        if ov > 0.0 and dist > 0.0:
                            push += ov * d / dist
                c = self.frag_c[k, f] + 0.1 * push
                lim = r_parent - rf
                if c.norm() > lim:
                    c *= lim / c.norm()
                self.frag_c[k, f] = c
        mass = 0.0
        cm = ti.Vector([0.0, 0.0, 0.0])
        for f in range(count):
            w = self.frag_r[k, f] ** 3
            mass += w
            cm += w * self.frag_c[k, f]
        cm /= mass
        alpha = 1.0
        for f in range(count):
            c = self.frag_c[k, f] - cm
            self.frag_c[k, f] = c
            dist = c.norm()
            if dist + self.frag_r[k, f] > r_parent and dist > 0.0:
                alpha = ti.min(alpha, (r_parent - self.frag_r[k, f]) / dist)
        for f in range(count):  # shrink about the centroid: containment, centroid kept
            self.frag_c[k, f] *= alpha

    # ------------------------------------------------------------------ kernels
    @ti.kernel
    def init_particles(self, pool: ti.template(), start: ti.i32):
        """Fracture energies of the particles in slots >= start (new originals)."""
        for i in range(start, pool.n_slots[None]):
            if pool.alive[i] and self.breakable[pool.material[i]]:
                e50 = self.e50(pool.material[i], 2.0 * pool.radius[i])
                pool.fracture_energy[i] = self.fracture_energy(e50, pool.pid[i])

    @ti.kernel
    def reset_events(self, pool: ti.template()):
        """Close every event without damage and forget all stressing work and peak loads
        (contact work is dropped lazily through the event number)."""
        for i in range(pool.n_slots[None]):
            if pool.alive[i]:
                pool.event_id[i] += 1
                self._clear_events(pool, i)

    @ti.func
    def _clear_events(self, pool: ti.template(), i):
        """No open event, no stressing work, no peak load."""
        pool.event_open[i] = 0
        pool.event_quiet[i] = 0
        pool.event_max[i] = 0.0
        pool.stress_sum[i] = 0.0
        pool.stress_bank[i] = 0.0
        pool.wall_work_bottom[i] = 0.0
        pool.wall_work_top[i] = 0.0
        pool.peak_load[i] = 0.0

    @ti.func
    def _events_all(self, pool: ti.template()):
        """Stressing energy, events, damage and the breakage test of every breakable
        particle (called by ``Kernels.step``); returns the number of parents to replace
        this step."""
        self.n_break[None] = 0
        ti.loop_config(serialize=self.serial)
        for i in range(pool.n_slots[None]):
            self._event_item(pool, i)
        return self._n_to_replace()

    @ti.func
    def _event_item(self, pool: ti.template(), i):
        """Slot i's part of :meth:`_events_all`."""
        if pool.alive[i] and self.breakable[pool.material[i]]:
            self._event_one(pool, i)

    @ti.func
    def _n_to_replace(self):
        """Parents to replace after this step's breakage tests (at most the scratch size)."""
        return ti.min(self.n_break[None], ti.static(self.max_breaks))

    @ti.func
    def _event_one(self, pool: ti.template(), i):
        m_true = pool.mass[i] * ti.static(1.0 / self.density_scaling)
        ek = (pool.stress_bank[i] + pool.stress_sum[i]) / m_true
        pool.peak_load[i] = ti.max(pool.peak_load[i], pool.normal_force_sum[i])
        broke = 0
        if 2.0 * pool.radius[i] >= ti.static(self.d_break) and ek >= pool.fracture_energy[i]:
            k = ti.atomic_add(self.n_break[None], 1)
            if k < ti.static(self.max_breaks):
                self.brk_slot[k] = i
                self.brk_energy[k] = ek
                broke = 1
            else:
                ti.atomic_add(self.n_deferred[None], 1)
        if broke == 0:
            if pool.event_open[i]:
                pool.event_max[i] = ti.max(pool.event_max[i], ek)
                ending = 0
                if ti.static(self.end_when_quiet):
                    if pool.loading[i]:
                        pool.event_quiet[i] = 0
                    else:
                        pool.event_quiet[i] += 1
                    ending = ((pool.event_quiet[i] >= ti.static(self.n_end))
                              | (pool.n_contacts[i] == 0))
                else:  # "release": no contact presses on the particle any more
                    ending = pool.pressed[i] == 0
                if ending:
                    e_ev = pool.event_max[i]
                    if e_ev > ti.static(self.e_min) and e_ev > 0.0:
                        d = self.damage(e_ev / pool.fracture_energy[i])
                        pool.fracture_energy[i] *= 1.0 - d
                        pool.damage_events[i] += 1
                    pool.event_open[i] = 0
                    pool.event_max[i] = 0.0
                    pool.event_quiet[i] = 0
                    pool.event_id[i] += 1
                    pool.stress_bank[i] = 0.0
                    pool.wall_work_bottom[i] = 0.0
                    pool.wall_work_top[i] = 0.0
            else:
                opens = pool.loading[i]
                if ti.static(not self.end_when_quiet):  # a contact loads and presses
                    opens = opens & pool.pressed[i]
                if opens:
                    pool.event_open[i] = 1
                    pool.event_quiet[i] = 0
                    pool.event_max[i] = ek

    @ti.func
    def _neighbours(self, pool: ti.template(), grid: ti.template(), k, p):
        """The live particles touching parent p, relative to it (from the cell grid)."""
        x_p = pool.position[p]
        r_p = pool.radius[p]
        cx, cy, cz = grid.cell_coords(x_p)
        x0, x1, xa = grid.span(grid.nx, cx)
        y0, y1, ya = grid.span(grid.ny, cy)
        n = 0
        for oz in range(ti.max(cz - 1, 0), ti.min(cz + 2, grid.nz)):
            for oy in range(y0, y1):
                for ox in range(x0, x1):
                    ix = ox if xa else (ox + grid.nx) % grid.nx
                    iy = oy if ya else (oy + grid.ny) % grid.ny
                    c = grid.cell_index(ix, iy, oz)
                    for s in range(grid.start[c], grid.start[c + 1]):
                        j = grid.sorted[s]
                        if j != p and pool.alive[j] and n < _MAX_NEIGHBOURS:
                            d = grid.minimum_image(pool.position[j] - x_p)
                            if d.norm() < r_p + pool.radius[j]:
                                self.nb_c[k, n] = d
                                self.nb_r[k, n] = pool.radius[j]
                                n += 1
        self.nb_n[k] = n

    @ti.kernel
    def replace(self, pool: ti.template(), grid: ti.template(), n_break: ti.i32, step: ti.i32,
                z_bottom: ti.f64, z_top: ti.f64, lx: ti.f64, ly: ti.f64):
        """Replace the listed parents by their fragments (see the module docstring)."""
        ti.loop_config(serialize=True)
        for _ in range(1):  # slot order, so allocation does not depend on thread timing
            for k in range(1, n_break):
                s = self.brk_slot[k]
                e = self.brk_energy[k]
                g = k - 1
                while g >= 0:
                    if self.brk_slot[g] <= s:
                        break
                    self.brk_slot[g + 1] = self.brk_slot[g]
                    self.brk_energy[g + 1] = self.brk_energy[g]
                    g -= 1
                self.brk_slot[g + 1] = s
                self.brk_energy[g + 1] = e
        for k in range(n_break):
            p = self.brk_slot[k]
            d = 2.0 * pool.radius[p]
            e50 = self.e50(pool.material[p], d)
            t10 = ti.static(self.t10_max) * (1.0 - ti.exp(
                -ti.static(self.b_prime) * self.brk_energy[k] / e50))
            self.brk_e50[k] = e50
            self.brk_t10[k] = t10
            self.brk_diameter[k] = d
            self.brk_peak[k] = pool.peak_load[p]
            self.brk_fracture[k] = pool.fracture_energy[p]
            self.brk_parent_id[k] = pool.pid[p]
            self.brk_nfrag[k] = self.progeny_sizes(k, d, t10)
            self._neighbours(pool, grid, k, p)
        ti.loop_config(serialize=True)
        for k in range(n_break):  # prefix sum: slots and ids of every fragment of the step
            if k == 0:
                self.n_fragments[None] = 0
            self.brk_first[k] = pool.n_slots[None] + self.n_fragments[None]
            self.brk_first_id[k] = pool.next_id[None] + self.n_fragments[None]
            self.n_fragments[None] += self.brk_nfrag[k]
        self.ok[None] = 1
        if pool.n_slots[None] + self.n_fragments[None] > pool.capacity:
            pool.overflow[None] += pool.n_slots[None] + self.n_fragments[None] - pool.capacity
            self.ok[None] = 0
        else:
            pool.n_slots[None] += self.n_fragments[None]
            pool.next_id[None] += self.n_fragments[None]
        for k in range(n_break):
            if self.ok[None]:
                self._spawn(pool, k, step, z_bottom, z_top, lx, ly)

    @ti.func
    def _spawn(self, pool: ti.template(), k, step, z_bottom, z_top, lx, ly):
        p = self.brk_slot[k]
        count = self.brk_nfrag[k]
        r_p = pool.radius[p]
        x_p = pool.position[p]
        self.place(k, count, r_p, pool.pid[p], z_bottom - x_p[2], z_top - x_p[2])
        v_p = pool.velocity[p]
        w_p = pool.angular_velocity[p]
        mat = pool.material[p]
        for f in range(count):
            s = self.brk_first[k] + f
            r = self.frag_r[k, f]
            c = self.frag_c[k, f]
            x = x_p + c
            x[0] -= lx * ti.floor(x[0] / lx)
            x[1] -= ly * ti.floor(x[1] / ly)
            ratio = r / r_p
            m = pool.mass[p] * ratio * ratio * ratio
            new_id = self.brk_first_id[k] + f
            pool.alive[s] = 1
            pool.pid[s] = new_id
            pool.parent_id[s] = pool.pid[p]
            pool.root_id[s] = pool.root_id[p]
            pool.material[s] = mat
            pool.radius[s] = r
            pool.mass[s] = m
            pool.inv_mass[s] = 1.0 / m
            pool.inv_inertia[s] = 1.0 / (0.4 * m * r * r)
            pool.position[s] = x
            pool.velocity[s] = v_p + w_p.cross(c)
            pool.angular_velocity[s] = w_p
            pool.clear_contact_state(s)
            # a fragment born touching a plate starts that contact without stressing work
            pool.wall_delta_prev_bottom[s] = ti.max(0.0, r - (x[2] - z_bottom))
            pool.wall_delta_prev_top[s] = ti.max(0.0, r - (z_top - x[2]))
            pool.fracture_energy[s] = self.fracture_energy(self.e50(mat, 2.0 * r), new_id)
            self._clear_events(pool, s)
            pool.event_id[s] = 0
            pool.loading[s] = 0
            pool.pressed[s] = 0
            pool.damage_events[s] = 0
            pool.birth_step[s] = step
        pool.alive[p] = 0

    @ti.kernel
    def init_new_contacts(self, pool: ti.template(), table: ti.template(),
                          grid: ti.template(), step: ti.i32):
        """Start the contacts of fragments born this step (after the neighbour rebuild).

        Every such contact starts without stressing work (its overlap at birth is not work
        done on the particles). Overlapping relatives (fragments of the same original
        particle: siblings, and a fragment with the earlier fragments its parent overlapped
        force-free) start force-free when ``breakage.sibling_init = "force_free"``: the
        contact law acts on the overlap beyond the birth overlap ``delta_ref`` (which follows
        the overlap down when they move apart), with no adhesion until they separate. So
        f(delta0) = 0 and no elastic energy is injected (spec 5.10), and pressing them further
        together loads a fresh contact from that state. [A] This replaces the spec's
        delta_max = delta0 lambda_p^(-1/n): at birth overlaps comparable to the fragment
        radius, the EEPA unloading branch there is so stiff that the explicit step becomes
        unstable. With ``"fresh"`` they start as plain contacts on the loading branch (a force
        spike). Other fragment-neighbour contacts start fresh.
        """
        for c in range(table.n_pairs[None]):
            i = table.owner[c]
            j = table.partner[c]
            if pool.alive[i] and pool.alive[j] and (pool.birth_step[i] == step
                                                    or pool.birth_step[j] == step):
                d = grid.minimum_image(pool.position[j] - pool.position[i])
                delta = pool.radius[i] + pool.radius[j] - d.norm()
                if delta > 0.0:
                    table.delta_prev[c] = delta
                    table.fhys_prev[c] = 0.0
                    table.spring[c] = ti.Vector([0.0, 0.0, 0.0])
                    table.work_a[c] = 0.0
                    table.work_b[c] = 0.0
                    table.event_a[c] = pool.event_id[i]
                    table.event_b[c] = pool.event_id[j]
                    table.delta_max[c] = 0.0
                    table.delta_ref[c] = 0.0
                    table.sibling[c] = 0
                    if ti.static(self.force_free):
                        if pool.root_id[i] == pool.root_id[j]:
                            table.delta_ref[c] = delta
                            table.delta_prev[c] = 0.0
                            table.sibling[c] = 1

    # ------------------------------------------------------------------ host helpers
    def records(self, n: int) -> dict[str, np.ndarray]:
        """The first ``n`` breakage records of this step (host copies)."""
        out = {name: getattr(self, "brk_" + name).to_numpy()[:n] for name in
               ("parent_id", "diameter", "peak", "energy", "fracture", "e50", "t10", "nfrag",
                "first_id")}
        radii = self.frag_r.to_numpy()[:n]
        out["fragment_diameters"] = [2.0 * radii[k, :out["nfrag"][k]] for k in range(n)]
        return out

    # ------------------------------------------------------------------ test entry points
    @ti.kernel
    def _damage_kernel(self, x: ti.types.ndarray(), out: ti.types.ndarray()):
        for i in range(x.shape[0]):
            out[i] = self.damage(x[i])

    def damage_values(self, x) -> np.ndarray:
        """Device damage root for an array of energy ratios (tests)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        out = np.zeros_like(x)
        self._damage_kernel(x, out)
        return out

    @ti.kernel
    def _sizes_kernel(self, d_parent: ti.f64, t10: ti.f64, out: ti.types.ndarray()) -> ti.i32:
        n = 0
        for _ in range(1):
            n = self.progeny_sizes(0, d_parent, t10)
            for f in range(n):
                out[f] = 2.0 * self.frag_r[0, f]
        return n

    def progeny_diameters(self, d_parent: float, t10: float) -> np.ndarray:
        """Device progeny sizes for one parent (tests) [m]."""
        out = np.zeros(self.max_frag)
        n = self._sizes_kernel(float(d_parent), float(t10), out)
        return out[:n]

    @ti.kernel
    def _cdf_kernel(self, x: ti.types.ndarray(), t10: ti.f64, out: ti.types.ndarray()):
        for i in range(x.shape[0]):
            out[i] = self.progeny_cdf(x[i], t10)

    def progeny_cdf_values(self, x, t10: float) -> np.ndarray:
        """Device progeny cumulative distribution at size ratios ``x`` (tests)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        out = np.zeros_like(x)
        self._cdf_kernel(x, float(t10), out)
        return out

    @ti.kernel
    def _place_kernel(self, radii: ti.types.ndarray(), r_parent: ti.f64, key: ti.i64,
                      out: ti.types.ndarray()):
        for _ in range(1):
            n = radii.shape[0]
            for f in range(n):
                self.frag_r[0, f] = radii[f]
            self.nb_n[0] = 0
            self.place(0, n, r_parent, key, -1.0, 1.0)
            for f in range(n):
                for d in ti.static(range(3)):
                    out[f, d] = self.frag_c[0, f][d]

    def placement(self, radii, r_parent: float, key: int = 1) -> np.ndarray:
        """Device placement of fragments (radii largest first) in a parent (tests) [m]."""
        radii = np.ascontiguousarray(radii, dtype=np.float64)
        out = np.zeros((len(radii), 3))
        self._place_kernel(radii, float(r_parent), int(key), out)
        return out
