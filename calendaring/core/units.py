"""Display units. Code, configs and files are SI; micrometres and MPa appear only in
plots and printed summaries, through these helpers.

See also: :mod:`calendaring.process.plots` (axes in micrometres and MPa),
:mod:`calendaring.cli` (printed summaries).
"""

from __future__ import annotations

MICROMETRE = 1.0e-6  # m
MEGAPASCAL = 1.0e6  # Pa
GIGAPASCAL = 1.0e9  # Pa


def to_um(x_m):
    """Metres -> micrometres (display only)."""
    return x_m / MICROMETRE


def to_mpa(p_pa):
    """Pascals -> megapascals (display only)."""
    return p_pa / MEGAPASCAL
