"""Contact model tables and the per-step kernels, assembled in :class:`Kernels`.

The kernels themselves live in :mod:`calendaring.engine.kernels`, one mixin per concern
(particles, pairs, stressing work, burst scheduling, energy ledger, contact law); this
module declares the fields they share and fills the contact tables.

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

See also: :mod:`calendaring.engine.simulation` (the host side that drives these kernels).
"""

import numpy as np
import taichi as ti

from calendaring.core.config import SimConfig
from calendaring.engine.backend import burst_workers, serial_loops
from calendaring.engine.breakage import breakable_mask, breakage_enabled
from calendaring.engine.contact_params import COL, COLUMNS, pair_table, plate_table
from calendaring.engine.kernels.base import KernelBase
from calendaring.engine.kernels.burst import BurstScheduler
from calendaring.engine.kernels.constants import LEDGER, MAX_CHUNKS, TRACE_LEN
from calendaring.engine.kernels.law import ContactLaw
from calendaring.engine.kernels.ledger import EnergyLedger
from calendaring.engine.kernels.pairs import PairPhase
from calendaring.engine.kernels.particles import ParticlePhase
from calendaring.engine.kernels.stressing import StressingWork
from calendaring.engine.laws.eepa import (
    ADHESION_DIRECT,
    ADHESION_JKR_R,
    ADHESION_SURFACE_ENERGY_AP,
    DAMPING_LITERAL_K1,
    DAMPING_TANGENT_SQRT56,
)

_ADHESION = {"surface_energy_ap": ADHESION_SURFACE_ENERGY_AP, "jkr_R": ADHESION_JKR_R,
             "direct_kadh": ADHESION_DIRECT}
_DAMPING = {"tangent_sqrt56": DAMPING_TANGENT_SQRT56, "literal_k1": DAMPING_LITERAL_K1}


@ti.data_oriented
class Kernels(BurstScheduler, ParticlePhase, PairPhase, StressingWork, EnergyLedger, ContactLaw,
              KernelBase):
    """Contact constants (small fields) plus the step kernels, specialised on static switches.

    The kernels live in :mod:`calendaring.engine.kernels`, one mixin per concern; this class
    declares the fields they share and fills the contact tables.

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
        # events end on release: the force kernels flag the particles some contact presses on
        self.track_pressed = self.breakage and cfg.breakage.event_end_rule == "release"
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
