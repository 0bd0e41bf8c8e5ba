"""Uniform cell grid built by counting sort: atomic count, exclusive prefix sum, scatter.

Periodic in x and y (minimum image), bounded in z. The cell edge is at least the largest
contact cutoff ``2 r_max + skin``, so every candidate pair lies in adjacent cells. When a
periodic direction has fewer than three cells, every cell along it is visited instead of
the three neighbours (no pair is visited twice), which needs a cell at least twice the
cutoff so that a particle cannot touch two images of the same neighbour.

The prefix sums (cells here, pair segments and incoming lists in
:mod:`calendaring.engine.contacts`) are blocked scans (:func:`exclusive_scan`): serial within
blocks of ``SCAN_BLOCK`` entries, parallel over blocks, then a serial scan of the block
totals. They run on both backends (Taichi's ``PrefixSumExecutor`` is CUDA-only) and keep a
single GPU thread from walking a million entries at every rebuild.

See also: :mod:`calendaring.engine.contacts` (the candidate pairs found in the grid),
:mod:`calendaring.engine.simulation` (when the grid is rebuilt).
"""


import math

import numpy as np
import taichi as ti

from calendaring.core.errors import ConfigError

SCAN_BLOCK = 256  # entries per block of exclusive_scan


def space_filling_order(position, lx: float, ly: float, bits: int = 10) -> np.ndarray:
    """Permutation that sorts points along a Z-order (Morton) curve.

    x and y are taken modulo the periodic lengths, z over the points' own range; each is
    cut into ``2**bits`` bins and the bins' bits interleaved with x most significant, then
    y, then z. Points close in space get close ranks, and a split of the ranks into
    contiguous parts is a split of the box into slabs across x (then y): the particle
    chunks and pair chunks a worker thread takes first (:mod:`calendaring.engine.forces`) form a
    compact region, and the cache lines shared with another core lie on its boundary.
    Ties keep the input order.
    """
    p = np.asarray(position, dtype=float).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros(0, np.int64)
    top = (1 << bits) - 1
    z_lo, z_span = p[:, 2].min(), np.ptp(p[:, 2])
    frac = (np.mod(p[:, 0], lx) / lx, np.mod(p[:, 1], ly) / ly,
            (p[:, 2] - z_lo) / z_span if z_span > 0 else np.zeros(len(p)))
    q = [np.clip((f * (top + 1)).astype(np.int64), 0, top) for f in frac]
    key = np.zeros(len(p), np.int64)
    for b in range(bits):
        for axis, shift in ((0, 2), (1, 1), (2, 0)):  # x above y above z
            key |= ((q[axis] >> b) & 1) << (3 * b + shift)
    return np.argsort(key, kind="stable")


@ti.func
def minimum_image(d, lx, ly):
    """Shortest periodic image of a separation vector ``d`` in a cell periodic in x and y
    with lengths ``lx``, ``ly`` (z untouched). The quotient and the rounding (a library call
    on x86) are taken only for the components longer than half the cell, which few pairs
    have: d - L round(d/L) is d itself below that."""
    if ti.abs(d[0]) >= 0.5 * lx:
        d[0] -= lx * ti.round(d[0] / lx)
    if ti.abs(d[1]) >= 0.5 * ly:
        d[1] -= ly * ti.round(d[1] / ly)
    return d


def scan_blocks(n: int) -> int:
    """Size of the block-total scratch field :func:`exclusive_scan` needs for ``n`` entries."""
    return max(1, (int(n) + SCAN_BLOCK - 1) // SCAN_BLOCK)


@ti.func
def exclusive_scan(count: ti.template(), start: ti.template(), total: ti.template(),
                   block: ti.template(), n):
    """start[i] = count[0] + ... + count[i - 1] for i < n; total[None] = the whole sum.

    Call at a kernel's top level (its loops are then the kernel's own tasks). ``block``
    holds at least :func:`scan_blocks` ``(n)`` i32 entries of scratch.
    """
    nb = (n + SCAN_BLOCK - 1) // SCAN_BLOCK
    for b in range(nb):  # parallel over blocks, serial within one
        s = 0
        for i in range(b * SCAN_BLOCK, ti.min(n, (b + 1) * SCAN_BLOCK)):
            start[i] = s
            s += count[i]
        block[b] = s
    ti.loop_config(serialize=True)
    for b in range(nb + 1):  # the block totals, in order
        if b == 0:
            total[None] = 0
        if b < nb:
            v = block[b]
            block[b] = total[None]
            total[None] += v
    for i in range(n):
        start[i] += block[i // SCAN_BLOCK]


@ti.func
def sort_segment(a: ti.template(), lo, hi):
    """Insertion sort of a[lo:hi] in increasing order (short segments: a cell's particles,
    a particle's incoming pairs, whose scatter order by atomic ranks is racy)."""
    for k in range(lo + 1, hi):
        v = a[k]
        m = k
        while m > lo and a[m - 1] > v:
            a[m] = a[m - 1]
            m -= 1
        a[m] = v


@ti.data_oriented
class CellGrid:
    """Cell lists over a pool.

    Args:
        capacity: pool capacity (slots).
        cell_x, cell_y: periodic lengths [m].
        z_lo, z_hi: z range covered by cells [m] (particles outside go to the end cells).
        cutoff: largest centre distance at which two particles are candidates [m].
    """

    def __init__(self, capacity: int, cell_x: float, cell_y: float, z_lo: float, z_hi: float,
                 cutoff: float) -> None:
        if cell_x < 2 * cutoff or cell_y < 2 * cutoff:
            raise ConfigError(
                "domain.cell_x/cell_y", (cell_x, cell_y),
                f">= 2 x the contact cutoff ({2 * cutoff:.3e} m: largest diameter + skin)",
            )
        self.lx, self.ly = float(cell_x), float(cell_y)
        self.z_lo = float(z_lo)
        self.nx = max(1, int(cell_x // cutoff))
        self.ny = max(1, int(cell_y // cutoff))
        self.nz = max(1, math.ceil((z_hi - z_lo) / cutoff))
        self.hx, self.hy = self.lx / self.nx, self.ly / self.ny
        self.hz = (z_hi - z_lo) / self.nz
        self.n_cells = self.nx * self.ny * self.nz
        self.cutoff = float(cutoff)
        fb = ti.FieldsBuilder()
        self.count = ti.field(ti.i32)
        self.start = ti.field(ti.i32)
        fb.dense(ti.i, self.n_cells).place(self.count)
        fb.dense(ti.i, self.n_cells + 1).place(self.start)
        self.block = ti.field(ti.i32)  # scratch of the cell scan
        fb.dense(ti.i, scan_blocks(self.n_cells)).place(self.block)
        self.total = ti.field(ti.i32)
        fb.place(self.total)
        self.cell_of = ti.field(ti.i32)
        self.rank = ti.field(ti.i32)
        self.sorted = ti.field(ti.i32)
        for f in (self.cell_of, self.rank, self.sorted):
            fb.dense(ti.i, capacity).place(f)
        self._tree = fb.finalize()

    def destroy(self) -> None:
        """Free the device memory."""
        if self._tree is not None:
            self._tree.destroy()
            self._tree = None

    @ti.func
    def cell_coords(self, p):
        """Integer cell coordinates of a (wrapped) position; z clamped to the grid."""
        ix = ti.cast(ti.floor(p[0] / self.hx), ti.i32) % self.nx
        iy = ti.cast(ti.floor(p[1] / self.hy), ti.i32) % self.ny
        iz = ti.min(ti.max(ti.cast(ti.floor((p[2] - self.z_lo) / self.hz), ti.i32), 0),
                    self.nz - 1)
        return ix, iy, iz

    @ti.func
    def cell_index(self, ix, iy, iz):
        """Flat index of cell (ix, iy, iz)."""
        return (iz * self.ny + iy) * self.nx + ix

    @ti.func
    def minimum_image(self, d):
        """Shortest periodic image of a separation vector (x and y only)."""
        return minimum_image(d, self.lx, self.ly)

    @ti.kernel
    def bin(self, pool: ti.template()):
        """Counting sort of the live particles into cells (count, scan, scatter), each cell
        in increasing slot order, so that the candidate pairs and the order in which a
        particle's forces are summed do not depend on thread timing or on the backend."""
        for c in range(self.n_cells):
            self.count[c] = 0
        for i in range(pool.n_slots[None]):
            if pool.alive[i]:
                ix, iy, iz = self.cell_coords(pool.position[i])
                c = self.cell_index(ix, iy, iz)
                self.cell_of[i] = c
                self.rank[i] = ti.atomic_add(self.count[c], 1)
        exclusive_scan(self.count, self.start, self.total, self.block, self.n_cells)
        self.start[self.n_cells] = self.total[None]
        for i in range(pool.n_slots[None]):
            if pool.alive[i]:
                self.sorted[self.start[self.cell_of[i]] + self.rank[i]] = i
        for c in range(self.n_cells):  # by slot: the atomic ranks are racy
            sort_segment(self.sorted, self.start[c], self.start[c + 1])

    @ti.func
    def span(self, n: ti.template(), c):
        """Range of neighbour-cell offsets (or absolute cells) along one axis."""
        lo, hi, absolute = c - 1, c + 2, 0
        if n < 3:
            lo, hi, absolute = 0, n, 1
        return lo, hi, absolute
