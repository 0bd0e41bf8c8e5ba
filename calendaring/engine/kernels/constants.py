"""Constants of the step kernels: energy-ledger slots, trace length, the multi-step launch's
grain, spin limits, synchronisation words and phases, chunk sizes, and the guard codes with
their messages.

See also: :mod:`calendaring.engine.forces`.
"""

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
