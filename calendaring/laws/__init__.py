"""Pure contact laws (``@ti.func``): scalars and vectors in, scalars and vectors out.

No law touches a field; the kernels in :mod:`calendaring.forces` map them over contacts.
"""
