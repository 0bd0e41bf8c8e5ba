"""Pure contact laws (``@ti.func``): scalars and vectors in, scalars and vectors out.

No law touches a field; the kernels in :mod:`calendaring.engine.forces` map them over contacts.
:func:`calendaring.engine.laws.eepa.evaluate` maps the normal law over NumPy overlaps on the host
(plots, checks of contact parameters, the law's tests).

See also: :mod:`calendaring.engine.kernels.law` (the law of one contact from a table),
:mod:`calendaring.engine.contact_params` (the per-pair constants the laws take).
"""
