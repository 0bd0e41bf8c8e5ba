"""Shared output helpers of the analysis package: atomic JSON and PNG writing.

Every file is written to a temporary name in its folder and renamed into place, so an
interrupted command never leaves a half-written result.
"""

from __future__ import annotations

from pathlib import Path

from calendaring import save_figure as _save_figure
from calendaring import write_json


def atomic_write_json(path: str | Path, obj) -> Path:
    """Write ``obj`` as indented JSON (NaN/inf as null) atomically."""
    return write_json(path, obj, indent=2)


def save_figure(fig, path: str | Path, dpi: int = 150) -> Path:
    """Save a matplotlib figure as PNG atomically and close it."""
    return _save_figure(fig, path, dpi=dpi, format="png")


__all__ = ["atomic_write_json", "save_figure"]
