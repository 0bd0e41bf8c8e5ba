"""Pressure-curve maths shared by run digests and datasets: exact interval means of a
piecewise-linear trace and the Savitzky-Golay smoothing of resampled curves.

See also: :mod:`calendaring.data.digest` (interval means kept per run),
:mod:`calendaring.data.dataset` (the training curves).
"""

from __future__ import annotations

import numpy as np

from calendaring.core.errors import ConfigError


def resample_pressure(depth, pressure, stroke: float, n_points: int = 196
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Mean pressure over ``n_points`` equal depth intervals of ``[0, stroke]``.

    Exact for a piecewise-linear trace: the cumulative trapezoid integral of ``pressure``
    over ``depth`` is differenced at the interval ends. Returns (midpoint depths, means).
    Raises ``ValueError`` if the trace does not cover the stroke or is not increasing.
    """
    d = np.asarray(depth, dtype=float)
    p = np.asarray(pressure, dtype=float)
    if len(d) < 2 or not np.all(np.isfinite(p)) or not np.all(np.isfinite(d)):
        raise ValueError("pressure trace has fewer than 2 samples or non-finite values")
    if np.any(np.diff(d) < 0):
        raise ValueError("pressure depths are not non-decreasing")
    if d[-1] < stroke * (1 - 1e-3):
        raise ValueError(f"trace ends at {d[-1]:.4g} m, short of the {stroke:.4g} m stroke")
    d = np.concatenate([[0.0], d]) if d[0] > 0 else d
    p = np.concatenate([[p[0]], p]) if len(p) < len(d) else p
    h = np.diff(d)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (p[1:] + p[:-1]) * h)])
    edges = np.linspace(0.0, stroke, n_points + 1)
    # integral of the piecewise-linear trace from 0 to each edge, exact inside a segment
    k = np.clip(np.searchsorted(d, edges, side="right") - 1, 0, len(d) - 2)
    t = np.clip(edges - d[k], 0.0, None)
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = np.where(h[k] > 0, (p[k + 1] - p[k]) / h[k], 0.0)
    at = cum[k] + p[k] * t + 0.5 * slope * t * t
    return 0.5 * (edges[1:] + edges[:-1]), np.diff(at) / np.diff(edges)


def smooth(p: np.ndarray, window: int = 17, order: int = 3) -> np.ndarray:
    """Savitzky-Golay smoothing along the last axis (scipy, ``mode="interp"``)."""
    from scipy.signal import savgol_filter

    if window % 2 == 0 or window <= order:
        raise ConfigError("savgol_window", window, f"an odd number > savgol_order = {order}")
    return savgol_filter(np.asarray(p, dtype=float), window, order, axis=-1, mode="interp")
