"""The two helpers every phase of a step uses: the first-failure guard flag and the cut of a
phase's work into chunks.

See also: :mod:`calendaring.engine.forces` (the class that assembles the phases).
"""

import taichi as ti

from calendaring.engine.kernels.constants import (
    MAX_CHUNKS,
)


class KernelBase:
    """Guard flag and chunking, for the phase mixins of :class:`~calendaring.engine.forces.Kernels`.

    Reads the guard fields (``guard_count``, ``guard_code``, ``guard_slot``, ``guard_step``,
    ``guard_value``) that :class:`~calendaring.engine.forces.Kernels` declares.
    """

    @ti.func
    def _flag(self, code, slot, step, value):
        if ti.atomic_add(self.guard_count[None], 1) == 0:
            self.guard_code[None] = code
            self.guard_slot[None] = slot
            self.guard_step[None] = step
            self.guard_value[None] = value

    @ti.func
    def _chunks(self, n, base):
        """(chunk size, number of chunks) for ``n`` items: chunks of at least ``base``
        items, at most MAX_CHUNKS of them."""
        size = ti.max(base, (n + MAX_CHUNKS - 1) // MAX_CHUNKS)
        return size, (n + size - 1) // size
