"""The paper's four key outputs of a calendering run (section 3.3, Fig. 10).

From a pressure-depth curve and a breakage distribution (a 2-D histogram of probabilities,
``[load bin, diameter bin]``, as in :mod:`calendaring.data.dataset` and the surrogate's
predictions), for one run or a batch:

==================  ====  ===========================================================
output              unit  definition
==================  ====  ===========================================================
peak_pressure       Pa    largest pressure on the curve (the maximum compaction load)
stress_centroid     N     probability-weighted centroid of the distribution along the
                          peak-load axis (geometric mean for a log-spaced load axis)
diameter_centroid   m     probability-weighted centroid along the parent-diameter axis
low_stress_ratio    1     probability mass in the lowest third of the load bins
==================  ====  ===========================================================

The centroids come from :func:`calendaring.data.dataset.centroids`. An empty histogram (a run
without breakage events) has NaN centroids and a NaN low-stress ratio.

    >>> out = key_outputs(pressure, distribution, load_edges, diameter_edges)
    >>> out["peak_pressure"]          # (n,) Pa
"""

from __future__ import annotations

import numpy as np

from calendaring import ConfigError, centroids

OUTPUTS = ("peak_pressure", "stress_centroid", "diameter_centroid", "low_stress_ratio")
"""Names of the four outputs, in the paper's order (Fig. 10 a-d)."""

UNITS = {"peak_pressure": "Pa", "stress_centroid": "N", "diameter_centroid": "m",
         "low_stress_ratio": "1"}
"""SI unit of each output."""

LABELS = {"peak_pressure": "peak pressure", "stress_centroid": "stress centroid",
          "diameter_centroid": "diameter centroid", "low_stress_ratio": "low-stress ratio"}
"""Plot titles."""

DISPLAY = {"peak_pressure": ("MPa", 1e-6), "stress_centroid": ("N", 1.0),
           "diameter_centroid": ("um", 1e6), "low_stress_ratio": ("-", 1.0)}
"""Display unit and factor (value x factor = value in display unit) for plots and tables."""

LOW_STRESS_FRACTION = 1.0 / 3.0
"""Fraction of the load bins (the lowest ones) counted by the low-stress ratio (paper 3.3)."""


def is_log_spaced(edges, rtol: float = 1e-6) -> bool:
    """True when positive ``edges`` have a constant ratio (a log axis) and are not evenly
    spaced (an axis that is both, e.g. two edges, counts as linear)."""
    e = np.asarray(edges, dtype=float)
    if len(e) < 3 or np.any(e <= 0):
        return False
    r = e[1:] / e[:-1]
    d = np.diff(e)
    return bool(np.allclose(r, r[0], rtol=rtol) and not np.allclose(d, d[0], rtol=rtol))


def bin_centres(load_edges, diameter_edges, log_load: bool | None = None
                ) -> tuple[np.ndarray, np.ndarray, bool]:
    """Centres of the load bins [N] (geometric on a log axis) and diameter bins [m].

    ``log_load = None`` detects a log-spaced load axis from the edges. Returns
    ``(load_centres, diameter_centres, log_load)``.
    """
    le = np.asarray(load_edges, dtype=float)
    de = np.asarray(diameter_edges, dtype=float)
    if le.ndim != 1 or len(le) < 2 or np.any(np.diff(le) <= 0):
        raise ConfigError("load_edges", f"array of shape {le.shape}",
                          "at least 2 increasing bin edges [N]")
    if de.ndim != 1 or len(de) < 2 or np.any(np.diff(de) <= 0):
        raise ConfigError("diameter_edges", f"array of shape {de.shape}",
                          "at least 2 increasing bin edges [m]")
    if log_load is None:
        log_load = is_log_spaced(le)
    if log_load and le[0] <= 0:
        raise ConfigError("load_edges", float(le[0]), "> 0 N for a log-spaced load axis")
    lc = np.sqrt(le[:-1] * le[1:]) if log_load else 0.5 * (le[:-1] + le[1:])
    return lc, 0.5 * (de[:-1] + de[1:]), bool(log_load)


def n_low_bins(n_load_bins: int, fraction: float = LOW_STRESS_FRACTION) -> int:
    """Number of lowest load bins in the low-stress ratio: ``round(fraction * n)``, >= 1."""
    if not 0.0 < fraction <= 1.0:
        raise ConfigError("low_stress_fraction", fraction, "in (0, 1]")
    return max(1, round(fraction * n_load_bins))


def key_outputs(pressure, distribution, load_edges, diameter_edges,
                log_load: bool | None = None,
                low_fraction: float = LOW_STRESS_FRACTION) -> dict[str, np.ndarray]:
    """The four outputs of a batch of runs (or one run).

    Args:
        pressure: ``(n, n_depth)`` or ``(n_depth,)`` pressure curve(s) [Pa].
        distribution: ``(n, L, D)`` or ``(L, D)`` breakage histogram(s), ``[load, diameter]``
            (need not be normalised; the outputs use ``h / h.sum()``).
        load_edges: ``(L + 1,)`` peak-load bin edges [N].
        diameter_edges: ``(D + 1,)`` parent-diameter bin edges [m].
        log_load: the load axis is logarithmic (geometric centres and centroid); ``None``
            detects it from the edges.
        low_fraction: fraction of the load bins counted as low stress (paper: one third).

    Returns:
        ``{name: array (n,)}`` for :data:`OUTPUTS` (scalars as 0-d arrays for one run), SI.
    """
    p = np.asarray(pressure, dtype=float)
    h = np.asarray(distribution, dtype=float)
    single = p.ndim == 1
    p2 = np.atleast_2d(p)
    h3 = h[None] if h.ndim == 2 else h
    if h3.ndim != 3:
        raise ConfigError("distribution", f"array of shape {h.shape}",
                          "(n, load bins, diameter bins) or (load bins, diameter bins)")
    if p2.ndim != 2 or len(p2) != len(h3):
        raise ConfigError("pressure", f"array of shape {p.shape}",
                          f"(n, depth points) with n = {len(h3)} rows (as the distribution)")
    lc, dc, log_load = bin_centres(load_edges, diameter_edges, log_load)
    if h3.shape[1:] != (len(lc), len(dc)):
        raise ConfigError("distribution", f"array of shape {h.shape}",
                          f"(..., {len(lc)}, {len(dc)}) bins to match the edges")
    c = centroids(h3, lc, dc, log_load=log_load)  # (n, 2): load [N], diameter [m]
    total = h3.sum(axis=(1, 2))
    low = h3[:, :n_low_bins(len(lc), low_fraction), :].sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(total > 0, low / np.where(total > 0, total, 1.0), np.nan)
        peak = np.max(p2, axis=1) if p2.shape[1] else np.full(len(p2), np.nan)
    out = {"peak_pressure": peak, "stress_centroid": c[:, 0], "diameter_centroid": c[:, 1],
           "low_stress_ratio": ratio}
    if single:
        out = {k: v[0] for k, v in out.items()}
    return out


def outputs_of_prediction(pred, model, **kw) -> dict[str, np.ndarray]:
    """The four outputs of a surrogate prediction (``pred.pressure``, ``pred.distribution``)
    with the model's bin edges (``model.load_edges``, ``model.diameter_edges``)."""
    return key_outputs(pred.pressure, pred.distribution, model.load_edges,
                       model.diameter_edges, **kw)


def outputs_of_dataset(ds, **kw) -> dict[str, np.ndarray]:
    """The four outputs of every run of a :class:`calendaring.data.dataset.Dataset` (smoothed
    pressure, stored histogram and edges; the load axis scale from ``ds.load_scale``)."""
    kw.setdefault("log_load", ds.load_scale == "log")
    return key_outputs(ds.pressure, ds.histogram, ds.load_edges, ds.diameter_edges, **kw)


__all__ = ["DISPLAY", "LABELS", "LOW_STRESS_FRACTION", "OUTPUTS", "UNITS", "bin_centres",
           "is_log_spaced", "key_outputs", "n_low_bins", "outputs_of_dataset",
           "outputs_of_prediction"]
