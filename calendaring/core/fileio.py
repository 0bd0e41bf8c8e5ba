"""Atomic text, JSON, HDF5 and figure writers shared by every package (host only).

Every file is written under a temporary name in its destination folder, then renamed, so a
crash never leaves a half-written file under the real name. JSON goes through
:func:`json_safe`: NumPy scalars and arrays become Python values, paths become strings and
non-finite floats become ``null`` (strict JSON).

See also: :mod:`calendaring.process.plots` (figures), :mod:`calendaring.data.sweep` (the
manifest, rewritten atomically after every task).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np


def json_safe(obj: Any) -> Any:
    """A JSON-serialisable copy of ``obj`` (see the module docstring)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        return json_safe(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _tmp(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | Path, fsync: bool = False, previous: Path | None = None,
                keep_suffix: bool = False):
    """Yield a temporary path next to ``path`` for the caller to write; when the block ends
    without an error it is (with ``fsync``, flushed to disk and) renamed to ``path``,
    otherwise removed. With ``previous``, the file ``path`` held is first renamed to
    ``previous``. The temporary is ``.NAME.tmp-PID`` (what sweeps and keep scripts skip
    and clean up), or ``.STEM.tmp-PID.SUFFIX`` with ``keep_suffix``, for writers that pick
    the format from the suffix (matplotlib)."""
    path = Path(path)
    tmp = (path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}") if keep_suffix
           else _tmp(path))
    try:
        yield tmp
        if fsync:
            _fsync(tmp)
        if previous is not None and path.exists():
            os.replace(path, previous)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` atomically; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def write_h5(path: str | Path, fill, previous: Path | None = None) -> Path:
    """Write an HDF5 file atomically: ``fill(f)`` writes it under a temporary name, which
    is flushed to disk and renamed to ``path``; with ``previous``, the file ``path`` held is
    first renamed to ``previous`` (so a kill at any moment leaves at least one complete
    file). Temporaries left by killed writers are removed."""
    import h5py

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    for stale in path.parent.glob(f".{path.name}.tmp-*"):  # left by a killed writer
        pid = stale.name.rsplit("-", 1)[-1]
        if pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)):
            stale.unlink(missing_ok=True)
    with atomic_path(path, fsync=True, previous=previous) as tmp, h5py.File(tmp, "w") as f:
        fill(f)
    return path


def write_json(path: str | Path, obj: Any, indent: int = 1) -> Path:
    """Write ``json_safe(obj)`` as indented strict JSON, atomically."""
    return write_text(path, json.dumps(json_safe(obj), indent=indent, allow_nan=False) + "\n")


def save_figure(fig, path: str | Path, dpi: int = 150, **kwargs) -> Path:
    """Save a matplotlib figure atomically (format from the suffix) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_path(path, keep_suffix=True) as tmp:
            fig.savefig(tmp, dpi=dpi, **kwargs)
    finally:
        plt.close(fig)
    return path


__all__ = ["atomic_path", "json_safe", "save_figure", "write_h5", "write_json",
           "write_text"]
