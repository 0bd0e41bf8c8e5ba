"""Calibration targets: a measured pressure-depth curve on the surrogate's depth grid.

A :class:`Target` holds the curve resampled onto the surrogate's 196 depths (interval
midpoints over the trained stroke), a mask of the points the measurement covers, an optional
uncertainty and optional breakage information (a 30 x 30 distribution binned with the model's
edges, or just its centroids). SI units throughout: depth [m], pressure and sigma [Pa],
centroid load [N], centroid diameter [m].

Sources:

* a run file (:func:`target_from_run`), read with :func:`calendaring.process.runfile.read_run`: the
  top-plate trace is averaged over each depth interval of the model's grid that the trace
  covers (as the dataset builder does) and Savitzky-Golay smoothed (order 3, window 17,
  paper section 3.2); the breakage events are binned with the model's edges
  (:func:`calendaring.data.dataset.bin_events`);
* a CSV file (:func:`target_from_csv`) whose header declares the units in the column names.

CSV convention (comma separated, ``#`` starts a comment line, one header line)::

    depth_um,pressure_MPa,sigma_MPa
    0.5,0.8,0.05
    ...

Columns: ``depth_<unit>`` with unit ``m``, ``mm`` or ``um``; ``pressure_<unit>`` with unit
``Pa``, ``kPa``, ``MPa`` or ``GPa``; optional ``sigma_<unit>`` (a pressure unit; one standard
deviation of the measurement). ``depth [um]`` and ``depth (um)`` are accepted spellings of
``depth_um``. Depth is the calendering displacement from the initial thickness, strictly
increasing, within ``[0, stroke]`` of the model; pressure and sigma are non-negative and
finite (sigma > 0). The CSV curve is interpolated linearly at the model depths inside its
range; points outside it are masked out.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calendaring import ConfigError, bin_events, centroids

DEPTH_UNITS = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "μm": 1e-6}
PRESSURE_UNITS = {"pa": 1.0, "kpa": 1e3, "mpa": 1e6, "gpa": 1e9}
SAVGOL_WINDOW = 17  # paper section 3.2: window of 17 points
SAVGOL_ORDER = 3  # paper section 3.2: third-order polynomial
STROKE_TOL = 1e-3  # relative slack on the trained stroke (rounding in files)
_HEADER = ("depth_<m|mm|um>, pressure_<Pa|kPa|MPa|GPa>[, sigma_<Pa|kPa|MPa|GPa>] "
           "(e.g. depth_um,pressure_MPa,sigma_MPa)")


@dataclass
class Target:
    """A calibration target on the model's depth grid (SI units).

    Attributes:
        depth: (m,) model depths [m].
        pressure: (m,) target pressure [Pa]; NaN where ``valid`` is False.
        valid: (m,) bool, the points the measurement covers.
        sigma: (m,) one standard deviation [Pa] or None (then a default is used by the
            posterior, see :func:`inverse.posterior.observation_sigma`).
        distribution: (L, D) breakage probabilities [load bin, diameter bin] or None.
        centroids: (2,) target centroid (load [N], diameter [m]) or None.
        source: a description of where the target came from.
    """

    depth: np.ndarray
    pressure: np.ndarray
    valid: np.ndarray
    sigma: np.ndarray | None = None
    distribution: np.ndarray | None = None
    centroids: np.ndarray | None = None
    source: str = ""

    def __post_init__(self) -> None:
        self.depth = np.asarray(self.depth, float)
        self.pressure = np.asarray(self.pressure, float)
        self.valid = np.asarray(self.valid, bool)
        if not (self.depth.shape == self.pressure.shape == self.valid.shape):
            raise ConfigError("target", f"shapes {self.depth.shape}, {self.pressure.shape}, "
                              f"{self.valid.shape}", "depth, pressure and valid of one shape")
        if self.valid.sum() < 2:
            raise ConfigError("target.depth", f"{int(self.valid.sum())} covered model depths",
                              "a curve covering at least 2 of the model's depths")
        if self.sigma is not None:
            self.sigma = np.asarray(self.sigma, float)
        if self.centroids is not None:
            self.centroids = np.asarray(self.centroids, float)

    @property
    def n_valid(self) -> int:
        return int(self.valid.sum())

    def to_json(self) -> dict:
        """Serialisable form (NaN written as null)."""
        def arr(a):
            return None if a is None else [None if not np.isfinite(v) else float(v)
                                           for v in np.ravel(a)]
        return {"source": self.source, "depth_m": arr(self.depth),
                "pressure_Pa": arr(self.pressure), "valid": self.valid.tolist(),
                "sigma_Pa": arr(self.sigma),
                "centroids": None if self.centroids is None else
                {"load_N": float(self.centroids[0]), "diameter_m": float(self.centroids[1])},
                "distribution": None if self.distribution is None
                else np.asarray(self.distribution).tolist()}

    @classmethod
    def from_json(cls, d: dict) -> Target:
        def arr(a):
            return None if a is None else np.array([np.nan if v is None else v for v in a])
        c = d.get("centroids")
        return cls(depth=arr(d["depth_m"]), pressure=arr(d["pressure_Pa"]),
                   valid=np.array(d["valid"], bool), sigma=arr(d.get("sigma_Pa")),
                   distribution=None if d.get("distribution") is None
                   else np.array(d["distribution"], float),
                   centroids=None if c is None else np.array([c["load_N"], c["diameter_m"]]),
                   source=d.get("source", ""))


# ---------------------------------------------------------------------- model geometry
def model_stroke(model_depth: np.ndarray) -> float:
    """The stroke [m] the model was trained on: its depths are interval midpoints of
    ``[0, stroke]``, so ``stroke = depth[-1] + (depth[1] - depth[0]) / 2``."""
    d = np.asarray(model_depth, float)
    return float(d[-1] + 0.5 * (d[1] - d[0]))


def is_log_axis(edges: np.ndarray) -> bool:
    """True if the bin edges are geometrically spaced (the dataset's log load axis)."""
    e = np.asarray(edges, float)
    if np.any(e <= 0):
        return False
    r = np.diff(np.log(e))
    return bool(np.allclose(r, r[0], rtol=1e-6))


def bin_centres(load_edges, diameter_edges) -> tuple[np.ndarray, np.ndarray, bool]:
    """(load centres [N], diameter centres [m], log load axis?) as the dataset defines them."""
    le, de = np.asarray(load_edges, float), np.asarray(diameter_edges, float)
    log = is_log_axis(le)
    lc = np.sqrt(le[:-1] * le[1:]) if log else 0.5 * (le[:-1] + le[1:])
    return lc, 0.5 * (de[:-1] + de[1:]), log


def attach_distribution(target: Target, model) -> Target:
    """Fill ``target.centroids`` from ``target.distribution`` with the model's bin centres
    (:func:`calendaring.data.dataset.centroids` semantics); checks the distribution's shape."""
    if target.distribution is None:
        return target
    h = np.asarray(target.distribution, float)
    shape = (len(model.load_edges) - 1, len(model.diameter_edges) - 1)
    if h.shape != shape:
        raise ConfigError("target.distribution", f"shape {h.shape}", f"shape {shape} "
                          "(the model's load x diameter bins)")
    if not np.all(np.isfinite(h)) or np.any(h < 0) or h.sum() <= 0:
        raise ConfigError("target.distribution", "values", "finite, >= 0, not all zero")
    target.distribution = h / h.sum()
    if target.centroids is None:
        lc, dc, log = bin_centres(model.load_edges, model.diameter_edges)
        target.centroids = centroids(target.distribution, lc, dc, log_load=log)
    return target


# ---------------------------------------------------------------------- resampling
def interval_means(depth, pressure, model_depth) -> tuple[np.ndarray, np.ndarray]:
    """Mean of a piecewise-linear trace over each interval of the model's grid that the
    trace covers (exact: the trace's integral, piecewise quadratic, at the interval ends).

    Returns (means [Pa] with NaN where not covered, covered mask).
    """
    d = np.asarray(depth, float)
    p = np.asarray(pressure, float)
    md = np.asarray(model_depth, float)
    half = 0.5 * (md[1] - md[0])
    lo, hi = md - half, md + half
    if d[0] > 0:  # the trace starts after the plate touched: hold the first value
        d, p = np.concatenate([[0.0], d]), np.concatenate([[p[0]], p])
    keep = np.concatenate([[True], np.diff(d) > 0])  # repeated depths: keep the first
    d, p = d[keep], p[keep]
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (p[1:] + p[:-1]) * np.diff(d))])

    def integral(x):  # exact integral of the piecewise-linear trace from d[0] to x
        k = np.clip(np.searchsorted(d, x, side="right") - 1, 0, len(d) - 2)
        t = x - d[k]
        slope = (p[k + 1] - p[k]) / (d[k + 1] - d[k])
        return cum[k] + p[k] * t + 0.5 * slope * t**2

    covered = (lo >= d[0] - 1e-15) & (hi <= d[-1] * (1 + 1e-9))
    out = np.full(len(md), np.nan)
    out[covered] = (integral(hi[covered]) - integral(lo[covered])) / (hi[covered] - lo[covered])
    return out, covered


def smooth_valid(p: np.ndarray, valid: np.ndarray, window: int = SAVGOL_WINDOW,
                 order: int = SAVGOL_ORDER) -> np.ndarray:
    """Savitzky-Golay smoothing of the covered part of a curve (the window shrinks to the
    covered length when that is shorter)."""
    from scipy.signal import savgol_filter

    out = p.copy()
    idx = np.nonzero(valid)[0]
    n = len(idx)
    w = min(window, n if n % 2 else n - 1)
    if w > order:
        out[idx] = savgol_filter(p[idx], w, order, mode="interp")
    return out


# ---------------------------------------------------------------------- run files
def target_from_run(path: str | Path, model, smooth: bool = True) -> Target:
    """Target from a run file: top-plate pressure over the covered model depths and the
    breakage events binned with the model's edges (no events: no distribution)."""
    from calendaring import read_run

    rec = read_run(path)
    d, p = np.asarray(rec.pressure["depth"], float), np.asarray(rec.pressure["value"], float)
    if len(d) < 2:
        raise ConfigError(f"{path}: pressure/depth", f"{len(d)} samples", ">= 2 samples")
    if np.any(np.diff(d) < 0):
        raise ConfigError(f"{path}: pressure/depth", "decreasing values", "non-decreasing")
    stroke = model_stroke(model.depth)
    if d[-1] > stroke * (1 + STROKE_TOL):
        # a longer run than the model knows: use the part inside the trained stroke
        keep = d <= stroke * (1 + STROKE_TOL)
        d, p = d[keep], p[keep]
    mean, covered = interval_means(d, p, model.depth)
    if smooth:
        mean = smooth_valid(mean, covered)
    mean = np.where(covered, np.maximum(mean, 0.0), np.nan)
    dist = None
    if len(rec.breakage["peak_load"]) > 0:
        dist = bin_events(rec.breakage["peak_load"], rec.breakage["diameter"],
                          model.load_edges, model.diameter_edges)
    t = Target(depth=np.asarray(model.depth, float), pressure=mean, valid=covered,
               distribution=dist, source=f"run file {path} (preset {rec.preset or '-'}, "
                                         f"seed {rec.seed})")
    return attach_distribution(t, model)


# ---------------------------------------------------------------------- CSV files
def _parse_column(name: str) -> tuple[str, str] | None:
    m = re.fullmatch(r"\s*(depth|pressure|sigma)\s*(?:_|\[|\()\s*([^\])\s]+)\s*[\])]?\s*",
                     name, flags=re.IGNORECASE)
    return (m.group(1).lower(), m.group(2)) if m else None


def read_curve_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read a CSV curve with declared units -> (depth [m], pressure [Pa], sigma [Pa] or None).

    Raises :class:`ConfigError` for a missing or unit-less header, unknown units or columns,
    non-numeric, NaN or infinite values, fewer than 2 rows, depth that is negative or not
    strictly increasing, negative pressure and non-positive sigma.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError("--target", str(path), "an existing CSV or run file")
    try:  # utf-8-sig: a byte-order mark (spreadsheet exports) is not part of the header
        with open(path, newline="", encoding="utf-8-sig") as f:
            rows = [r for r in csv.reader(line for line in f
                                          if line.strip() and not line.lstrip().startswith("#"))]
    except UnicodeDecodeError as err:
        raise ConfigError("--target", str(path), f"a UTF-8 text CSV (byte {err.start} is "
                          f"{err.object[err.start:err.start + 1]!r})") from None
    except csv.Error as err:
        raise ConfigError("--target", str(path), f"a readable CSV ({err})") from None
    if not rows:
        raise ConfigError(f"{path}: header", "empty file", _HEADER)
    header, body = rows[0], rows[1:]
    if len(header) == 1:
        for sep, name in ((";", "semicolons"), ("\t", "tabs"), ("|", "bars")):
            if sep in header[0]:
                raise ConfigError(f"{path}: header", header[0],
                                  f"comma-separated columns (this file uses {name}): "
                                  f"{_HEADER}")
    cols: dict[str, tuple[int, float]] = {}
    for i, name in enumerate(header):
        parsed = _parse_column(name)
        if parsed is None:
            raise ConfigError(f"{path}: header", ",".join(header),
                              f"columns with units: {_HEADER}")
        kind, unit = parsed
        table = DEPTH_UNITS if kind == "depth" else PRESSURE_UNITS
        key = unit if kind == "depth" else unit.lower()
        if key not in table:
            allowed = "m, mm, um" if kind == "depth" else "Pa, kPa, MPa, GPa"
            raise ConfigError(f"{path}: column '{name}'", unit, f"a unit among {allowed}")
        if kind in cols:
            raise ConfigError(f"{path}: header", ",".join(header), f"one '{kind}' column")
        cols[kind] = (i, table[key])
    for need in ("depth", "pressure"):
        if need not in cols:
            raise ConfigError(f"{path}: header", ",".join(header), _HEADER)
    if len(body) < 2:
        raise ConfigError(f"{path}: rows", len(body), ">= 2 data rows")
    data = {}
    for kind, (i, factor) in cols.items():
        vals = []
        for r, row in enumerate(body):
            try:
                vals.append(float(row[i]))
            except (IndexError, ValueError):
                raise ConfigError(f"{path}: row {r + 2} column '{header[i]}'",
                                  row[i] if i < len(row) else "<missing>", "a number") from None
        v = np.array(vals) * factor
        bad = ~np.isfinite(v)
        if bad.any():
            r = int(np.argmax(bad))
            raise ConfigError(f"{path}: row {r + 2} column '{header[i]}'", body[r][i],
                              "a finite number (no NaN or inf)")
        data[kind] = v
    depth, pressure, sigma = data["depth"], data["pressure"], data.get("sigma")
    step = np.diff(depth)
    if np.any(step <= 0):
        r = int(np.argmax(step <= 0)) + 1
        raise ConfigError(f"{path}: row {r + 2} column '{header[cols['depth'][0]]}'",
                          body[r][cols["depth"][0]], "depth strictly increasing row to row")
    if depth[0] < 0:
        raise ConfigError(f"{path}: row 2 column '{header[cols['depth'][0]]}'",
                          body[0][cols["depth"][0]], ">= 0 (displacement from h0)")
    if np.any(pressure < 0):
        r = int(np.argmax(pressure < 0))
        raise ConfigError(f"{path}: row {r + 2} column '{header[cols['pressure'][0]]}'",
                          body[r][cols["pressure"][0]], ">= 0 (compressive pressure)")
    if sigma is not None and np.any(sigma <= 0):
        r = int(np.argmax(sigma <= 0))
        raise ConfigError(f"{path}: row {r + 2} column '{header[cols['sigma'][0]]}'",
                          body[r][cols["sigma"][0]], "> 0 (one standard deviation)")
    return depth, pressure, sigma


def resample_curve(depth, pressure, sigma, model_depth, source: str = "curve") -> Target:
    """A curve with its own depths -> :class:`Target` on the model grid (linear
    interpolation at the model depths inside the curve's range); raises if the curve
    leaves ``[0, stroke]`` of the model."""
    depth = np.asarray(depth, float)
    md = np.asarray(model_depth, float)
    stroke = model_stroke(md)
    if depth[-1] > stroke * (1 + STROKE_TOL) or depth[0] < 0:
        bad = depth[-1] if depth[-1] > stroke else depth[0]
        raise ConfigError(f"{source}: depth", f"{bad:.6g} m",
                          f"[0, {stroke:.6g}] m (the stroke the model was trained on)")
    valid = (md >= depth[0] - 1e-15) & (md <= depth[-1] + 1e-15)
    if valid.sum() < 2:
        raise ConfigError(f"{source}: depth", f"[{depth[0]:.4g}, {depth[-1]:.4g}] m",
                          f"a range covering at least 2 model depths (spacing "
                          f"{md[1] - md[0]:.4g} m)")
    p = np.full(len(md), np.nan)
    p[valid] = np.interp(md[valid], depth, pressure)
    s = None
    if sigma is not None:
        s = np.full(len(md), np.nan)
        s[valid] = np.interp(md[valid], depth, sigma)
    return Target(depth=md, pressure=p, valid=valid, sigma=s, source=source)


def target_from_csv(path: str | Path, model) -> Target:
    """Target from a CSV curve with declared units (see the module docstring)."""
    depth, pressure, sigma = read_curve_csv(path)
    return resample_curve(depth, pressure, sigma, model.depth, source=f"CSV {path}")


def write_curve_csv(path: str | Path, depth, pressure, sigma=None) -> Path:
    """Write a curve in the SI spelling of the convention (``depth_m,pressure_Pa[,sigma_Pa]``),
    atomically."""
    from calendaring import atomic_path

    path = Path(path)
    cols = [np.asarray(depth, float), np.asarray(pressure, float)]
    head = "depth_m,pressure_Pa"
    if sigma is not None:
        cols.append(np.asarray(sigma, float))
        head += ",sigma_Pa"
    with atomic_path(path) as tmp:
        np.savetxt(tmp, np.column_stack(cols), delimiter=",", header=head, comments="",
                   fmt="%.10g")
    return path


def load_target(path: str | Path, model, centroids_si=None) -> Target:
    """A run file (``.h5``/``.hdf5``) or a CSV curve -> :class:`Target`; ``centroids_si`` =
    (load [N], diameter [m]) overrides or supplies the target centroids."""
    path = Path(path)
    if path.suffix.lower() in (".h5", ".hdf5"):
        t = target_from_run(path, model)
    else:
        t = target_from_csv(path, model)
    if centroids_si is not None:
        c = np.asarray(centroids_si, float)
        if c.shape != (2,) or not np.all(np.isfinite(c)) or np.any(c <= 0):
            raise ConfigError("--centroids", centroids_si, "LOAD_N,DIAMETER_M, both > 0")
        t.centroids = c
    return t


__all__ = ["DEPTH_UNITS", "PRESSURE_UNITS", "Target", "attach_distribution", "bin_centres",
           "interval_means", "is_log_axis", "load_target", "model_stroke", "read_curve_csv",
           "resample_curve", "target_from_csv", "target_from_run", "write_curve_csv"]
