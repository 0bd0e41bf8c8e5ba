"""Contact model tables and the per-step kernels.

One step (:meth:`Kernels.step`) is three phases:

1. over particles (:meth:`Kernels.advance`): kick with the previous forces (leapfrog form
   of velocity Verlet), drift, periodic wrap, guards, then reset the accumulators to
   gravity and add the particle-plate contacts at the new positions;
2. over candidate pairs (:meth:`Kernels.pair_forces`) and bonds: the contact law, each
   pair's or bond's loads written to its own slot;
3. over particles: those loads summed per particle in a fixed order (no atomic adds on
   particle loads), then the breakage test.

Velocities held between steps are half-step velocities v_{n-1/2}; observables use the
synchronised v_n = v_{n-1/2} + dt/2 a_n.

On the CPU, :meth:`Kernels.burst` runs up to ``numerics.steps_per_launch`` whole steps in
one launch: one persistent task per worker thread, the workers claiming chunks of each
phase's particles, pairs and bonds from shared counters, the phases of a step separated by
spin barriers (about 1 us each, against ~50 us for a parallel loop of Taichi's CPU thread
pool and ~65 us for a kernel launch from Python). The burst stops after the step whose
device flags the host must act on, exactly where the one-launch-per-step path would act.
Plate forces and energy terms are summed per chunk, then over the chunks in order: the
same sums on any number of threads and on either path.
"""


import numpy as np
import taichi as ti

from calendaring.backend import burst_workers, serial_loops
from calendaring.breakage import breakable_mask, breakage_enabled
from calendaring.config import SimConfig
from calendaring.contact_params import COL, COLUMNS, pair_table, plate_table
from calendaring.laws.eepa import (
    ADHESION_DIRECT,
    ADHESION_JKR_R,
    ADHESION_SURFACE_ENERGY_AP,
    DAMPING_LITERAL_K1,
    DAMPING_TANGENT_SQRT56,
    eepa_adhesion_stiffness,
    eepa_damping_coefficient,
    eepa_hysteretic_force,
    eepa_loading_stiffness,
    eepa_potential,
    power_n,
)
from calendaring.laws.rolling import rolling_torque
from calendaring.laws.tangential import coulomb_limit, rotate_spring, tangential_stiffness

# Energy ledger slots (accumulated every step when numerics.track_energy is on) [J].
LEDGER = ("damping_normal", "damping_tangential", "friction", "rolling", "hysteretic_work",
          "plate_work")
L_DAMP_N, L_DAMP_T, L_FRICTION, L_ROLLING, L_HYST, L_PLATE = range(len(LEDGER))
N_LEDGER = len(LEDGER)

TRACE_LEN = 4096  # steps of plate forces buffered on the device between host reads

# Multi-step launches (:meth:`Kernels.burst`, CPU only). Taichi's CPU range-for hands its
# iterations out in blocks of 512 when the bound is known only at run time: a loop over
# workers x GRAIN iterations gives one block, hence one pool thread, to each worker.
GRAIN = 512
# Spin iterations (~20-50 ns each) a worker waits for the others to start before the burst
# is abandoned and the engine falls back to one launch per step, and the much longer wait at
# a step barrier after which the run stops with GUARD_SYNC.
RENDEZVOUS_SPINS = 1 << 24
BARRIER_SPINS = 1 << 30
# words of Kernels.sync (one cache line each): rendezvous, barrier, stop, status and the
# work counters of the phases (chunks claimed)
S_ARRIVE, S_CLAIM, S_READY, S_COUNT, S_GEN, S_STOP, S_ABORT = range(7)
# phases whose chunks are claimed (Kernels.claims[phase, worker])
P_ADVANCE, P_PAIRS, P_BONDS, P_GATHER = range(4)
# Work is cut into chunks of at least CHUNK_P particle slots or CHUNK_C pairs or bonds, at
# most MAX_CHUNKS of each. Each chunk adds its plate forces and energy terms to its own row,
# summed in chunk order at the end of the step: the same sums whoever ran the chunk.
CHUNK_P = 64
CHUNK_C = 256
MAX_CHUNKS = 1024

# Guard codes (first failure wins; the host turns them into SimulationError).
GUARD_NAN, GUARD_OVERLAP, GUARD_BOTTOM, GUARD_TOP, GUARD_SKIN, GUARD_SYNC = 1, 2, 3, 4, 5, 6
GUARD_NAMES = {GUARD_NAN: "non-finite position or velocity",
               GUARD_OVERLAP: "overlap above numerics.max_overlap_fraction of the smaller radius",
               GUARD_BOTTOM: "particle centre below the bottom plate by more than "
                             "max(0, numerics.max_overlap_fraction - 1) radii (left the cell)",
               GUARD_TOP: "particle centre above the top plate by more than "
                          "max(0, numerics.max_overlap_fraction - 1) radii (left the cell)",
               GUARD_SKIN: "particle moved more than skin/2 between neighbour-list checks",
               GUARD_SYNC: "a worker thread did not reach a step barrier of the multi-step "
                           "launch in time (threads oversubscribed?)"}

_ADHESION = {"surface_energy_ap": ADHESION_SURFACE_ENERGY_AP, "jkr_R": ADHESION_JKR_R,
             "direct_kadh": ADHESION_DIRECT}
_DAMPING = {"tangent_sqrt56": DAMPING_TANGENT_SQRT56, "literal_k1": DAMPING_LITERAL_K1}


@ti.data_oriented
class Kernels:
    """Contact constants (small fields) plus the step kernels, specialised on static switches.

    Args:
        cfg: simulation configuration (materials, contact laws, numerics).
    """

    def __init__(self, cfg: SimConfig) -> None:
        c = cfg.contact
        self.n = float(c.loading_exponent)
        self.chi = float(c.adhesive_exponent)
        self.xi_t = float(c.tangential_stiffness_ratio)
        self.adhesion_mode = _ADHESION[c.adhesion_mode]
        self.damping_mode = _DAMPING[c.damping_mode]
        self.track_energy = bool(cfg.numerics.track_energy)
        # one CPU thread: the per-step loops run serialised, without the thread pool's
        # dispatch (about 45 us per parallel loop on a 2-core x86 VM, more than a small
        # bed's work); never on CUDA
        self.serial = serial_loops(cfg.numerics.threads)
        # threads of a multi-step launch (0: none, one launch per step; see burst)
        self.workers = burst_workers(cfg.numerics.threads)
        # The candidate list is rebuilt once some particle moved this fraction of skin/2
        # since the last build (skin/2 itself is the guard: beyond it a contact could be
        # missed). Flags read every step leave one step of travel to cover: 0.8; read every
        # k > 1 steps, k steps: 0.5.
        self.rebuild_fraction = 0.8 if cfg.numerics.rebuild_check_interval == 1 else 0.5
        # A particle has left the cell once its plate overlap exceeds max(1,
        # max_overlap_fraction) radii: with an allowance above 1 (soft carbon black crushed
        # against a plate) the centre may lie up to (allowance - 1) radii beyond the plate,
        # the same overlap the pair guard accepts between two particles.
        self.plate_slack = max(0.0, float(cfg.numerics.max_overlap_fraction) - 1.0)
        # stressing-work bookkeeping of the breakage model (spec 5.4), compiled in only when
        # some material can break
        self.breakage = breakage_enabled(cfg)
        self.shear_weight = float(cfg.breakage.shear_weight)
        self.n_mat = len(cfg.materials)
        ncol = len(COLUMNS)
        fb = ti.FieldsBuilder()
        self.pair = ti.field(ti.f64)
        self.plate = ti.field(ti.f64)
        self.breakable = ti.field(ti.i32)  # per material: stressing work is tracked
        fb.dense(ti.i, self.n_mat).place(self.breakable)
        fb.dense(ti.ijk, (self.n_mat, self.n_mat, ncol)).place(self.pair)
        fb.dense(ti.ijk, (self.n_mat, 2, ncol)).place(self.plate)
        self.ledger = ti.field(ti.f64)
        fb.dense(ti.i, len(LEDGER)).place(self.ledger)
        # energy terms and plate forces by chunk (rows 0.. particle chunks, MAX_CHUNKS..
        # pair chunks; 16 doubles a row: no two rows on one cache line), summed in a fixed
        # order at the end of each step (a shared atomic would also bounce its cache line
        # between cores at every contact)
        self.ledger_part = ti.field(ti.f64)
        fb.dense(ti.ij, (2 * MAX_CHUNKS, 16)).place(self.ledger_part)
        self.plate_part = ti.Vector.field(3, ti.f64)
        fb.dense(ti.ij, (MAX_CHUNKS, 2)).place(self.plate_part)
        self.plate_force = ti.Vector.field(3, ti.f64)  # force ON plate w (0 bottom, 1 top) [N]
        fb.dense(ti.i, 2).place(self.plate_force)
        self.guard_count = ti.field(ti.i32)
        self.guard_code = ti.field(ti.i32)
        self.guard_slot = ti.field(ti.i32)
        self.guard_step = ti.field(ti.i32)
        self.guard_value = ti.field(ti.f64)
        self.need_rebuild = ti.field(ti.i32)
        self.trace = ti.field(ti.f64)  # per-step z force ON (bottom, top) plate [N]
        fb.dense(ti.ij, (TRACE_LEN, 2)).place(self.trace)
        fb.place(self.guard_count, self.guard_code, self.guard_slot, self.guard_step,
                 self.guard_value, self.need_rebuild)
        # multi-step launches: top-plate height and velocity of each step, each worker's
        # share of the plate forces, the synchronisation words and the burst's outcome
        self.plate_z = ti.field(ti.f64)
        self.plate_v = ti.field(ti.f64)
        fb.dense(ti.i, TRACE_LEN).place(self.plate_z, self.plate_v)
        self.sync = ti.field(ti.i32)
        fb.dense(ti.ij, (16, 16)).place(self.sync)  # word w is sync[w, 0]
        self.claims = ti.field(ti.i32)  # chunks claimed from each worker's share
        self.claim_rows = max(1, self.workers)
        fb.dense(ti.ijk, (4, self.claim_rows, 16)).place(self.claims)
        self.n_tasks = ti.field(ti.i32)
        fb.place(self.n_tasks)
        self.outcome = ti.field(ti.i32)  # (steps done, flags, parents to replace)
        fb.dense(ti.i, 3).place(self.outcome)
        self._tree = fb.finalize()
        tables = (pair_table(cfg), plate_table(cfg))
        # static switches of the contact law (see _law)
        self.adhesive = any(bool(np.any(t[..., COL[k]] != 0.0)) for t in tables for k in (
            "pull_off_force", "surface_energy", "adhesion_stiffness"))
        self.plastic = any(bool(np.any(t[..., COL["plasticity_ratio"]] != 0.0))
                           for t in tables)
        self.pair.from_numpy(tables[0])
        self.breakable.from_numpy(breakable_mask(cfg).astype(np.int32))
        self.plate.from_numpy(tables[1])

    def destroy(self) -> None:
        """Free the device memory."""
        if self._tree is not None:
            self._tree.destroy()
            self._tree = None

    # ------------------------------------------------------------------ helpers
    @ti.func
    def _flag(self, code, slot, step, value):
        if ti.atomic_add(self.guard_count[None], 1) == 0:
            self.guard_code[None] = code
            self.guard_slot[None] = slot
            self.guard_step[None] = step
            self.guard_value[None] = value

    @ti.func
    def _ledger_add(self, slot, value, row):
        """Add ``value`` [J] to energy-ledger term ``slot`` through chunk row ``row``."""
        self.ledger_part[row, slot] += value

    @ti.func
    def _chunks(self, n, base):
        """(chunk size, number of chunks) for ``n`` items: chunks of at least ``base``
        items, at most MAX_CHUNKS of them."""
        size = ti.max(base, (n + MAX_CHUNKS - 1) // MAX_CHUNKS)
        return size, (n + size - 1) // size

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
    def _law(self, tab: ti.template(), a, b, delta, delta_prev, nrm, v_rel, m_star, r_star, sr,
             dt, delta_max, spring, fhys_prev, no_adhesion):
        """Contact force of one contact (spec 2-3), shared by particle pairs and plates
        (``m_star``, ``r_star``: reduced mass and radius; ``sr`` = sqrt(r_star)).

        Returns the force on body i, the tangential force, f_hys, the updated history, the
        normal force magnitude, the energy increments (damping n/t, friction, hysteresis) and
        the stressing-work increment of the contact (spec 5.4: repulsive hysteretic work plus
        ``breakage.shear_weight`` x tangential spring work). ``no_adhesion`` switches the
        adhesive terms off (force-free sibling fragments until they first separate).
        """
        n = ti.static(self.n)
        chi = ti.static(self.chi)
        # n = 1.5 with the default damping: sqrt(delta) taken once and both damping
        # coefficients from one root, sqrt(m* sqrt(R* delta)) (the factors are table
        # columns): five square roots fewer per contact than the general forms
        hertz = ti.static(n == 1.5)
        fused = ti.static(n == 1.5 and self.damping_mode == DAMPING_TANGENT_SQRT56)
        e_star = tab[a, b, COL["e_star"]]
        beta_hat = tab[a, b, COL["beta_hat"]]
        k1 = 0.0
        sd = 0.0
        if ti.static(hertz):
            sd = ti.sqrt(delta)
            k1 = (4.0 / 3.0) * e_star * sr
        else:
            k1 = eepa_loading_stiffness(e_star, r_star, n)
        dmax = ti.max(delta_max, delta)
        # compiled without the terms that every contact of the model has at zero (no
        # adhesion: f0 = k_adh = 0; no plasticity: k2 = k1, delta_p = 0): the same numbers,
        # f_hys = k1 delta^n to the bit
        f0 = 0.0
        k2 = k1
        delta_p = 0.0
        k_adh = 0.0
        if ti.static(self.plastic):
            k2 = k1 * tab[a, b, COL["unloading_factor"]]
            delta_p = tab[a, b, COL["plastic_factor"]] * dmax  # lambda_p^(1/n) delta_max
        if ti.static(self.adhesive):
            f0 = tab[a, b, COL["pull_off_force"]]
            k_adh = eepa_adhesion_stiffness(delta_p, r_star, k2,
                                            tab[a, b, COL["surface_energy"]],
                                            tab[a, b, COL["adhesion_stiffness"]], n, chi,
                                            ti.static(self.adhesion_mode))
            if no_adhesion:
                f0 = 0.0
                k_adh = 0.0
        f_hys = 0.0
        if ti.static(self.adhesive or self.plastic):
            f_hys = eepa_hysteretic_force(delta, delta_p, k1, k2, k_adh, f0, n, chi)
        elif ti.static(hertz):
            f_hys = k1 * (delta * sd)
        else:
            f_hys = k1 * power_n(delta, n)
        beta_n = 0.0
        k_t = 0.0
        beta_t = 0.0
        if ti.static(fused):
            root = ti.sqrt(m_star * sr * sd)
            beta_n = tab[a, b, COL["normal_damping_factor"]] * root
            k_t = ti.static(8.0 * self.xi_t) * tab[a, b, COL["g_star"]] * sr * sd
            beta_t = tab[a, b, COL["tangential_damping_factor"]] * root
        else:
            beta_n = eepa_damping_coefficient(m_star, k1, delta, beta_hat, n,
                                              ti.static(self.damping_mode))
            k_t = tangential_stiffness(tab[a, b, COL["g_star"]], r_star, delta, k1,
                                       ti.static(self.xi_t), n)
            beta_t = 2.0 * beta_hat * ti.sqrt(m_star * k_t)
        delta_dot = v_rel.dot(nrm)
        f_nd = beta_n * delta_dot
        f_n = f_hys + f_nd
        v_t = v_rel - delta_dot * nrm
        s_old = rotate_spring(spring, nrm)
        s = s_old - k_t * v_t * dt
        f_t = s - beta_t * v_t
        limit = 0.0
        if ti.static(self.adhesive):
            limit = coulomb_limit(tab[a, b, COL["friction"]], f_hys, k_adh, delta, f0, chi)
        else:
            limit = tab[a, b, COL["friction"]] * ti.abs(f_hys)
        friction_loss = 0.0
        damp_t = beta_t * v_t.norm_sqr() * dt
        ft2 = f_t.norm_sqr()
        # Sliding (the spring sits on the Coulomb limit): about half the contacts of a
        # compacting bed slide, at random, so the root and the quotient are taken for
        # every contact and the test only selects values (a branch around them was
        # mispredicted often enough to cost ~10 % of the pair loop)
        s_new = ti.sqrt(limit * limit / ti.max(ft2, 1e-300)) * f_t
        slide = ft2 > limit * limit
        if ti.static(self.track_energy):  # |s_new| = limit when sliding; selected, too
            friction_loss = ti.select(slide & (k_t > 0.0),
                                      (s.norm_sqr() - limit * limit) / (2.0 * k_t), 0.0)
        s = ti.select(slide, s_new, s)
        f_t = ti.select(slide, s_new, f_t)
        damp_t = ti.select(slide, 0.0, damp_t)
        force_i = -f_n * nrm + f_t
        hyst = 0.5 * (fhys_prev + f_hys) * (delta - delta_prev)
        work = 0.0
        if ti.static(self.breakage):
            work = 0.5 * (ti.max(fhys_prev, 0.0) + ti.max(f_hys, 0.0)) * (delta - delta_prev)
            if ti.static(self.shear_weight > 0.0):
                work += ti.static(self.shear_weight) * (-0.5) * (s_old + s).dot(v_t) * dt
        return (force_i, f_t, f_hys, dmax, s, ti.abs(f_n), f_nd * delta_dot * dt, damp_t,
                friction_loss, hyst, work)

    # ------------------------------------------------------------------ step kernels
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
            self._stress_work(pool, table, c, i, j, a, b, work, delta > table.delta_prev[c])
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

    @ti.func
    def _stress_work(self, pool: ti.template(), table: ti.template(), c, i, j, a, b, work,
                     loading):
        """Add a contact's stressing work to each breakable side's event and E_k (spec 5.4)."""
        if self.breakable[a]:
            table.stress_i[c] = self._side_work(pool, table.event_a, table.work_a, c, i,
                                                self.pair[a, b, COL["stiffness_partition"]],
                                                work, loading)
        if self.breakable[b]:
            table.stress_j[c] = self._side_work(pool, table.event_b, table.work_b, c, j,
                                                self.pair[b, a, COL["stiffness_partition"]],
                                                work, loading)

    @ti.func
    def _side_work(self, pool: ti.template(), event_f: ti.template(), work_f: ti.template(), c,
                   i, share, work, loading):
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

    # ------------------------------------------------------------------ observables
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

    @ti.func
    def _stored(self, tab: ti.template(), a, b, delta, r_star, delta_max):
        n = ti.static(self.n)
        chi = ti.static(self.chi)
        e = 0.0
        if delta > 0.0:
            k1 = eepa_loading_stiffness(tab[a, b, COL["e_star"]], r_star, n)
            k2 = k1 * tab[a, b, COL["unloading_factor"]]  # as the contact law has it
            dmax = ti.max(delta_max, delta)
            delta_p = tab[a, b, COL["plastic_factor"]] * dmax  # lambda_p^(1/n) delta_max
            k_adh = eepa_adhesion_stiffness(delta_p, r_star, k2, tab[a, b, COL["surface_energy"]],
                                            tab[a, b, COL["adhesion_stiffness"]], n, chi,
                                            ti.static(self.adhesion_mode))
            e = eepa_potential(delta, delta_p, k2, k_adh, tab[a, b, COL["pull_off_force"]], n,
                               chi)
        return e
