"""The per-step kernels of :class:`~calendaring.engine.forces.Kernels`, one module per concern:

- :mod:`.base`: the guard flag and the chunking every phase uses;
- :mod:`.law`: the contact law of one contact from a contact table;
- :mod:`.particles`: phase 1, particle advance and particle-plate contacts;
- :mod:`.pairs`: phases 2 and 3, pair forces and their per-particle gather;
- :mod:`.stressing`: the breakage bookkeeping of contacts (stressing work, region marks);
- :mod:`.burst`: one step, or many steps on persistent worker threads, in one launch;
- :mod:`.ledger`: plate forces and energy terms summed in a fixed order, energies;
- :mod:`.constants`: ledger slots, guard codes, chunk sizes.

Bonds and the breakage test have their own kernel classes
(:mod:`calendaring.engine.bonds`, :mod:`calendaring.engine.breakage_kernels`).

See also: :mod:`calendaring.engine.forces` (the class the mixins make up),
:mod:`calendaring.engine.laws` (the contact laws they evaluate).
"""
