"""Training datasets: many run files consolidated into one HDF5 file for the surrogate.

:func:`build_dataset` turns a folder of run files (a sweep) into a :class:`Dataset`;
:func:`write_dataset` / :func:`read_dataset` store and load it. Per run (paper section 2.3):

1. the calendering pressure resampled onto ``n_points`` (196) equally spaced depths over the
   stroke: the mean pressure over each of ``n_points`` equal depth intervals, at the interval
   midpoints (an exact mean of the recorded trace, whatever its sampling);
2. Savitzky-Golay smoothing (polynomial order 3, window 17 by default, as in the paper);
3. cube-root transform and min-max normalisation with global statistics stored in the file;
4. the breakage events binned into a 30 x 30 histogram of peak load (rows, axis 0) against
   parent diameter (columns, axis 1) with fixed global edges stored in the file, normalised to
   probabilities (Eq. 43; a run without events has an all-zero histogram and ``n_events = 0``);
5. the eight parameters in physical units and scaled to ``[0, 1]`` by the stored bounds.

Every transform is invertible with the stored metadata (:meth:`Dataset.pressure_from_normalised`).
Run files that are corrupt, incomplete, without breakage or from another problem are listed in
``skipped`` with the reason and never stop the build.

Schema (``format`` = "calendaring-dataset", ``schema_version`` 1); every dataset has ``unit``
and ``description`` attributes:

==============================  ======  ============================================
dataset                         unit    content
==============================  ======  ============================================
parameters/physical             mixed   (n, 8) values; ``units`` attribute per column
parameters/unit                 1       (n, 8) the same scaled to [0, 1]
pressure/depth                  m       (196,) depth of each point (interval midpoints)
pressure/raw                    Pa      (n, 196) interval means of the top-plate pressure
pressure/smoothed               Pa      (n, 196) after Savitzky-Golay smoothing
pressure/normalised             1       (n, 196) (cbrt(smoothed) - cbrt_min) / (cbrt_max -
                                        cbrt_min); attributes cbrt_min, cbrt_max [Pa^(1/3)]
distribution/histogram          1       (n, 30, 30) probabilities, [load bin, diameter bin]
distribution/load_edges         N       (31,) peak-load bin edges
distribution/diameter_edges     m       (31,) parent-diameter bin edges
distribution/n_events           1       (n,) breakage events binned
runs/run_id, role, file         -       (n,) strings; role: train | replicate | holdout
                                        | refine (added by ``inverse refine``)
runs/design_index, seed, group  1       (n,); group: replicate group (same parameters), -1
runs/wall_time                  s       (n,) wall time of the run
==============================  ======  ============================================

Root attributes: ``parameter_space`` (JSON, :meth:`ParameterSpace.to_json`), ``stroke`` (m),
``savgol_window``, ``savgol_order``, ``load_scale``, ``base_config`` (JSON of the first run's
configuration), ``fingerprint`` (SHA-256 of the arrays), ``skipped`` (JSON list of
[file, reason]), ``provenance`` (JSON), ``noise_floor`` (JSON, :func:`noise_floor`).

See also: :mod:`calendaring.data.digest` (the per-run digests it can be built from),
:mod:`calendaring.data.curves` (resampling and smoothing), :mod:`calendaring.process.runfile`.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import json
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

import h5py
import numpy as np

from calendaring._version import __version__
from calendaring.core.errors import ConfigError
from calendaring.core.fileio import write_h5
from calendaring.data.curves import resample_pressure, smooth
from calendaring.data.params import PAPER_SPACE, ParameterSpace

FORMAT = "calendaring-dataset"
SCHEMA_VERSION = 1
ROLES = ("train", "replicate", "holdout", "refine")
KL_FLOOR = 1e-8


class DatasetError(ValueError):
    """A dataset file that cannot be used (names the file and the reason)."""

    def __init__(self, path: str | Path, reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{path}: {reason}")


@dataclass
class Dataset:
    """A consolidated training set (SI units; see the module docstring for each field)."""

    space: ParameterSpace
    params: np.ndarray  # (n, 8) physical
    depth: np.ndarray  # (196,) m
    pressure_raw: np.ndarray  # (n, 196) Pa
    pressure: np.ndarray  # (n, 196) Pa, smoothed
    histogram: np.ndarray  # (n, 30, 30) probabilities [load, diameter]
    load_edges: np.ndarray  # (31,) N
    diameter_edges: np.ndarray  # (31,) m
    n_events: np.ndarray  # (n,)
    run_id: np.ndarray  # (n,) str
    role: np.ndarray  # (n,) str
    design_index: np.ndarray  # (n,) int
    seed: np.ndarray  # (n,) int
    group: np.ndarray  # (n,) int, -1 if not a replicate
    wall_time: np.ndarray  # (n,) s
    stroke: float  # m
    cbrt_min: float = 0.0  # Pa^(1/3)
    cbrt_max: float = 1.0  # Pa^(1/3)
    savgol_window: int = 17
    savgol_order: int = 3
    load_scale: str = "log"
    files: np.ndarray | None = None  # (n,) str
    base_config: str = "{}"
    skipped: list = field(default_factory=list)
    provenance: dict = field(default_factory=dict)
    path: Path | None = None

    def __post_init__(self) -> None:
        n = len(self.params)
        for name in ("pressure_raw", "pressure", "histogram", "n_events", "run_id", "role",
                     "design_index", "seed", "group", "wall_time"):
            if len(getattr(self, name)) != n:
                raise DatasetError(self.path or "<memory>", f"'{name}' has "
                                   f"{len(getattr(self, name))} rows, expected {n}")
        if self.files is None:
            self.files = np.array([""] * n)

    # ------------------------------------------------------------------ views
    def __len__(self) -> int:
        return len(self.params)

    @property
    def unit_params(self) -> np.ndarray:
        """Parameters scaled to [0, 1] by the stored bounds."""
        return self.space.to_unit(self.params)

    @property
    def pressure_normalised(self) -> np.ndarray:
        return self.normalise_pressure(self.pressure)

    def normalise_pressure(self, p) -> np.ndarray:
        """Pa -> normalised cube-root units (the paper's training target)."""
        return (np.cbrt(np.asarray(p, dtype=float)) - self.cbrt_min) / (
            self.cbrt_max - self.cbrt_min)

    def pressure_from_normalised(self, x) -> np.ndarray:
        """Normalised cube-root units -> Pa (inverse of :meth:`normalise_pressure`)."""
        c = np.asarray(x, dtype=float) * (self.cbrt_max - self.cbrt_min) + self.cbrt_min
        return c**3

    @property
    def load_centres(self) -> np.ndarray:
        return bin_centres(self.load_edges, self.load_scale)

    @property
    def diameter_centres(self) -> np.ndarray:
        return bin_centres(self.diameter_edges, "linear")

    def subset(self, mask) -> Dataset:
        """Rows selected by a boolean mask or an index array (metadata shared)."""
        idx = np.arange(len(self))[mask]
        arrays = {k: getattr(self, k)[idx] for k in (
            "params", "pressure_raw", "pressure", "histogram", "n_events", "run_id", "role",
            "design_index", "seed", "group", "wall_time", "files")}
        return replace(self, **arrays)

    def by_role(self, *roles: str) -> Dataset:
        for r in roles:
            if r not in ROLES:
                raise ConfigError("role", r, f"one of {ROLES}")
        return self.subset(np.isin(self.role, roles))

    @property
    def fingerprint(self) -> str:
        """SHA-256 over the parameters, pressures, histograms and edges."""
        h = hashlib.sha256()
        for a in (self.params, self.depth, self.pressure, self.histogram, self.load_edges,
                  self.diameter_edges):
            h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
        return h.hexdigest()


# ---------------------------------------------------------------------- transforms
def histogram_edges(loads: Iterable[np.ndarray], diameters: Iterable[np.ndarray],
                    bins: int = 30, load_scale: str = "log",
                    load_range: tuple[float, float] | None = None,
                    diameter_range: tuple[float, float] | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Global bin edges over all runs' events (or the given ranges)."""
    if load_scale not in ("log", "linear"):
        raise ConfigError("load_scale", load_scale, "'log' or 'linear'")
    loads = [np.asarray(x, float) for x in loads]
    diameters = [np.asarray(x, float) for x in diameters]
    all_l = np.concatenate(loads) if loads else np.zeros(0)
    all_d = np.concatenate(diameters) if diameters else np.zeros(0)
    if load_range is None:
        pos = all_l[all_l > 0]
        if pos.size == 0:
            raise ValueError("no breakage events with a positive peak load in any run")
        load_range = (float(pos.min()), float(pos.max()))
    if diameter_range is None:
        if all_d.size == 0:
            raise ValueError("no breakage events in any run")
        diameter_range = (float(all_d.min()), float(all_d.max()))
    lo, hi = load_range
    if not (0 < lo < hi) if load_scale == "log" else not (lo < hi):
        raise ConfigError("load_range", load_range, "lower < upper (> 0 for a log scale)")
    if not (0 <= diameter_range[0] < diameter_range[1]):
        raise ConfigError("diameter_range", diameter_range, "0 <= lower < upper [m]")
    if load_scale == "log":
        le = np.geomspace(lo, hi, bins + 1)
    else:
        le = np.linspace(lo, hi, bins + 1)
    de = np.linspace(diameter_range[0], diameter_range[1], bins + 1)
    return le, de


def bin_centres(edges: np.ndarray, scale: str = "linear") -> np.ndarray:
    """Bin centres of ``edges``: geometric on a log axis, arithmetic otherwise."""
    e = np.asarray(edges, float)
    return np.sqrt(e[:-1] * e[1:]) if scale == "log" else 0.5 * (e[:-1] + e[1:])


def bin_events(load, diameter, load_edges, diameter_edges) -> np.ndarray:
    """Probability histogram [load bin, diameter bin] (Eq. 43); values outside the edges
    are clipped into the end bins; all zeros when there is no event."""
    load = np.clip(np.asarray(load, float), load_edges[0], load_edges[-1])
    diameter = np.clip(np.asarray(diameter, float), diameter_edges[0], diameter_edges[-1])
    h, _, _ = np.histogram2d(load, diameter, bins=[load_edges, diameter_edges])
    total = h.sum()
    return h / total if total > 0 else h


def centroids(hist: np.ndarray, load_centres: np.ndarray, diameter_centres: np.ndarray,
              log_load: bool = True) -> np.ndarray:
    """Probability-weighted centroid (load [N], diameter [m]) of histograms ``(..., L, D)``;
    the load centroid is geometric for a log axis. NaN for an empty histogram."""
    h = np.asarray(hist, float)
    w = h.sum(axis=(-1, -2))
    with np.errstate(invalid="ignore", divide="ignore"):
        pl = h.sum(axis=-1) @ (np.log(load_centres) if log_load else load_centres) / w
        pd = h.sum(axis=-2) @ diameter_centres / w
    return np.stack([np.exp(pl) if log_load else pl, pd], axis=-1)


def kl_divergence(p, q, floor: float = KL_FLOOR) -> np.ndarray:
    """KL(p || q) over the last two axes with the paper's 1e-8 floor on both."""
    p = np.asarray(p, float) + floor
    q = np.asarray(q, float) + floor
    p = p / p.sum(axis=(-1, -2), keepdims=True)
    q = q / q.sum(axis=(-1, -2), keepdims=True)
    return np.sum(p * np.log(p / q), axis=(-1, -2))


def sampled_kl_floor(counts: np.ndarray, n_sim: int = 200, seed: int = 0) -> dict:
    """What the KL floor of one replicate group would read, and what a perfect model would
    score, if each run's events were drawn independently from one distribution.

    The group's pooled histogram stands in for the true distribution q. Each simulated group
    draws every run's event count from q (multinomial); ``floor_like`` is the mean
    KL(run || pooled simulated group), as :func:`noise_floor` computes its floor, and
    ``perfect`` the mean KL(run || q), the score of a model that predicts q exactly. The
    pooled histogram includes the run itself, so ``floor_like < perfect``: a prediction of
    the true distribution scores ``perfect / floor_like`` times the floor.

    Args:
        counts: ``(runs, L, D)`` event counts of one group (runs with events only).
        n_sim: simulated groups.
        seed: NumPy seed.
    """
    counts = np.asarray(counts)
    n = counts.reshape(len(counts), -1).sum(axis=1).astype(int)
    if len(counts) < 2 or np.any(n < 1):
        raise ConfigError("replicate counts", f"{len(counts)} runs, events {n.tolist()}",
                          ">= 2 runs, each with >= 1 event")
    q = counts.sum(axis=0).astype(float)
    q /= q.sum()
    rng = np.random.default_rng(seed)
    floor_like, perfect = [], []
    for _ in range(int(n_sim)):
        sims = np.stack([rng.multinomial(k, q.ravel()).reshape(q.shape) for k in n])
        hist = sims / n[:, None, None]
        pooled = sims.sum(axis=0) / n.sum()
        floor_like.append(float(np.mean(kl_divergence(hist, pooled))))
        perfect.append(float(np.mean(kl_divergence(hist, q))))
    fl, pf = float(np.mean(floor_like)), float(np.mean(perfect))
    return {"floor_like": fl, "perfect": pf, "ratio": pf / fl if fl > 0 else float("nan"),
            "n_sim": int(n_sim)}


def perfect_model_kl(q: np.ndarray, n_events: int, n_sim: int = 200, seed: int = 0) -> float:
    """Mean KL(sample || q) of ``n_events`` events drawn independently from ``q``: what a
    model predicting the true distribution ``q`` scores against a histogram of that many
    events (the least KL a model can be expected to reach on such a target).

    Args:
        q: ``(L, D)`` probabilities (normalised here).
        n_events: events in the target histogram (>= 1).
        n_sim: simulated histograms.
        seed: NumPy seed.
    """
    q = np.asarray(q, float)
    if not (q.ndim == 2 and np.all(q >= 0) and q.sum() > 0):
        raise ConfigError("q", f"shape {q.shape}", "a non-negative (L, D) histogram, not all 0")
    if int(n_events) < 1:
        raise ConfigError("n_events", n_events, "an integer >= 1")
    q = q / q.sum()
    rng = np.random.default_rng(seed)
    sims = rng.multinomial(int(n_events), q.ravel(), size=int(n_sim)).reshape(-1, *q.shape)
    return float(np.mean(kl_divergence(sims / int(n_events), q)))


def seed_means(ds: Dataset, role: str = "holdout", min_runs: int = 2) -> Dataset:
    """One row per replicate group of ``role`` with ``>= min_runs`` runs: the seed mean.

    A single chaotic run is not a test target; the mean over the seeds of one parameter set
    is. Pressure (raw and smoothed): the mean over the group's runs [Pa]. Histogram: the
    events of all runs pooled (each run's probabilities weighted by its event count);
    ``n_events``: their sum; ``wall_time``: the sum; ``seed``: the number of runs averaged
    (the runs themselves stay in ``ds``); ``run_id``: ``mean:<first run id>+<k-1>``. The
    normalisation, edges and metadata are those of ``ds``.
    """
    if role not in ROLES:
        raise ConfigError("role", role, f"one of {ROLES}")
    mine = ds.role == role
    groups = [g for g in sorted({int(g) for g in ds.group[mine & (ds.group >= 0)]})
              if np.sum((ds.group == g) & mine) >= min_runs]
    rows = []
    for g in groups:
        idx = np.nonzero((ds.group == g) & mine)[0]
        w = ds.n_events[idx].astype(float)
        pooled = np.tensordot(w, ds.histogram[idx], axes=1)
        total = pooled.sum()
        rows.append({"first": idx[0], "pressure_raw": ds.pressure_raw[idx].mean(axis=0),
                     "pressure": ds.pressure[idx].mean(axis=0),
                     "histogram": pooled / total if total > 0 else pooled,
                     "n_events": int(w.sum()), "seed": len(idx),
                     "run_id": f"mean:{ds.run_id[idx[0]]}+{len(idx) - 1}",
                     "wall_time": float(ds.wall_time[idx].sum())})
    out = ds.subset(np.array([r["first"] for r in rows], dtype=int))
    if not rows:
        return out
    return replace(out, **{k: np.array([r[k] for r in rows]) for k in (
        "pressure_raw", "pressure", "histogram", "n_events", "seed", "run_id", "wall_time")})


def noise_floor(ds: Dataset, kl_simulations: int = 200) -> dict:
    """Run-to-run noise at repeated parameters (replicate groups with >= 2 runs).

    Pressure: the mean over groups of the per-point replicate variance (normalised units,
    the unit of the surrogate's MSE: the MSE a perfect mean predictor would still score
    against one replicate, times n/(n-1)) and the relative spread in Pa at 25/50/75/100 %
    of the stroke. Distribution: the mean KL of each replicate's histogram to its group's
    pooled histogram, and the mean pairwise KL between replicates.

    The KL floor is optimistic: the pooled histogram contains the replicate itself.
    ``kl_perfect_model_ratio`` (:func:`sampled_kl_floor`, ``kl_simulations`` simulated
    groups per group; 0 skips it) is how many times that floor a model predicting the true
    distribution would score if events were independent draws: the least ratio a
    model can be expected to reach.
    """
    groups = sorted(set(int(g) for g in ds.group if g >= 0))
    out = {"groups": [], "pressure_mse_normalised": None, "kl_to_group_mean": None,
           "kl_pairwise": None, "kl_perfect_model_ratio": None}
    x = ds.pressure_normalised
    mses, kls, pair, ratios = [], [], [], []
    for g in groups:
        idx = np.nonzero(ds.group == g)[0]
        if len(idx) < 2:
            continue
        var = x[idx].var(axis=0, ddof=1).mean()
        mses.append(var)
        has = idx[ds.n_events[idx] > 0]
        pooled = ds.histogram[has].sum(axis=0) if len(has) else None
        k_mean = float(np.mean(kl_divergence(ds.histogram[has], pooled / pooled.sum()))) \
            if len(has) >= 2 else float("nan")
        pk = [float(kl_divergence(ds.histogram[a], ds.histogram[b]))
              for i, a in enumerate(has) for b in has[i + 1:]]
        pk_mean = float(np.mean(pk)) if pk else float("nan")
        kls.append(k_mean)
        pair.append(pk_mean)
        sim = None
        if kl_simulations and len(has) >= 2:
            raw = ds.histogram[has] * ds.n_events[has][:, None, None]
            counts = np.rint(raw).astype(int)
            # only histograms of counted events (not, e.g., smooth synthetic ones)
            if np.allclose(raw, counts, atol=1e-6) and np.all(counts.sum(axis=(1, 2)) > 0):
                sim = sampled_kl_floor(counts, kl_simulations, seed=g)
                ratios.append(sim["ratio"])
        p = ds.pressure[idx]
        rel = {}
        for frac in (0.25, 0.5, 0.75, 1.0):
            j = min(len(ds.depth) - 1, round(frac * len(ds.depth)) - 1)
            m = p[:, j].mean()
            rel[f"{int(frac * 100)}%"] = float(p[:, j].std(ddof=1) / m) if m > 0 else None
        out["groups"].append({
            "group": g, "runs": len(idx), "params": ds.space.as_dict(ds.params[idx[0]]),
            "pressure_var_normalised": float(var), "pressure_rel_std": rel,
            "events_mean": float(ds.n_events[idx].mean()), "kl_to_group_mean": k_mean,
            "kl_pairwise": pk_mean, "kl_sampled": sim})
    if mses:
        out["pressure_mse_normalised"] = float(np.mean(mses))
        out["kl_to_group_mean"] = float(np.nanmean(kls)) if np.any(np.isfinite(kls)) else None
        out["kl_pairwise"] = float(np.nanmean(pair)) if np.any(np.isfinite(pair)) else None
        out["kl_perfect_model_ratio"] = float(np.mean(ratios)) if ratios else None
    return out


# ---------------------------------------------------------------------- file I/O
def _put(g, name, data, unit, description, **attrs):
    arr = np.asarray(data)
    if arr.dtype.kind == "U":
        arr = arr.astype(h5py.string_dtype())
    kw = {"compression": "gzip", "compression_opts": 4} if arr.size > 4096 else {}
    ds = g.create_dataset(name, data=arr, **kw)
    ds.attrs["unit"] = unit
    ds.attrs["description"] = description
    for k, v in attrs.items():
        ds.attrs[k] = v


def write_dataset(path: str | Path, ds: Dataset) -> Path:
    """Write ``ds`` atomically (:func:`calendaring.core.fileio.write_h5`: temporary name,
    flushed to disk, then renamed)."""
    path = Path(path)
    if path.suffix.lower() not in (".h5", ".hdf5"):
        raise ConfigError("--out", str(path), "a path ending in .h5 or .hdf5")

    def fill(f):
        a = f.attrs
        a["format"] = FORMAT
        a["schema_version"] = SCHEMA_VERSION
        a["software_version"] = __version__
        a["created"] = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
        a["parameter_space"] = json.dumps(ds.space.to_json())
        a["stroke"] = ds.stroke
        a["savgol_window"] = ds.savgol_window
        a["savgol_order"] = ds.savgol_order
        a["load_scale"] = ds.load_scale
        a["base_config"] = ds.base_config
        a["fingerprint"] = ds.fingerprint
        a["skipped"] = json.dumps(ds.skipped)
        a["provenance"] = json.dumps(ds.provenance, default=str)
        a["noise_floor"] = json.dumps(noise_floor(ds))
        g = f.create_group("parameters")
        _put(g, "physical", ds.params, "mixed", "the eight breakage parameters",
             units=json.dumps(ds.space.units), names=json.dumps(ds.space.names))
        _put(g, "unit", ds.unit_params, "1", "parameters scaled to [0, 1] by the bounds")
        g = f.create_group("pressure")
        _put(g, "depth", ds.depth, "m", "depth of each point (interval midpoints)")
        _put(g, "raw", ds.pressure_raw, "Pa", "interval means of the top-plate pressure")
        _put(g, "smoothed", ds.pressure, "Pa", "Savitzky-Golay smoothed pressure")
        _put(g, "normalised", ds.pressure_normalised, "1",
             "(cbrt(smoothed) - cbrt_min) / (cbrt_max - cbrt_min)",
             cbrt_min=ds.cbrt_min, cbrt_max=ds.cbrt_max)
        g = f.create_group("distribution")
        _put(g, "histogram", ds.histogram, "1",
             "breakage probability per [peak-load bin, parent-diameter bin]")
        _put(g, "load_edges", ds.load_edges, "N", "peak-load bin edges")
        _put(g, "diameter_edges", ds.diameter_edges, "m", "parent-diameter bin edges")
        _put(g, "n_events", ds.n_events, "1", "breakage events binned")
        g = f.create_group("runs")
        _put(g, "run_id", ds.run_id, "-", "sweep run id")
        _put(g, "role", ds.role, "-", "train | replicate | holdout | refine")
        _put(g, "file", ds.files, "-", "run file name")
        _put(g, "design_index", ds.design_index, "1", "row of the design")
        _put(g, "seed", ds.seed, "1", "random seed of the run")
        _put(g, "group", ds.group, "1", "replicate group (-1: none)")
        _put(g, "wall_time", ds.wall_time, "s", "wall time of the run")

    return write_h5(path, fill)


_EXPECTED = {"parameters/physical": "mixed", "parameters/unit": "1", "pressure/depth": "m",
             "pressure/raw": "Pa", "pressure/smoothed": "Pa", "pressure/normalised": "1",
             "distribution/histogram": "1", "distribution/load_edges": "N",
             "distribution/diameter_edges": "m", "distribution/n_events": "1",
             "runs/run_id": "-", "runs/role": "-", "runs/file": "-", "runs/design_index": "1",
             "runs/seed": "1", "runs/group": "1", "runs/wall_time": "s"}


def read_dataset(path: str | Path) -> Dataset:
    """Open and validate a dataset file; raises :class:`DatasetError` naming what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "no such file")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise DatasetError(path, f"not a readable HDF5 file: {err}") from None
    with f:
        a = f.attrs
        if a.get("format") != FORMAT:
            raise DatasetError(path, f"not a calendaring dataset (format = {a.get('format')!r}, "
                                     f"expected {FORMAT!r}); build one with `calendaring "
                                     "dataset RUNS/ --out DATASET.h5`")
        if int(a.get("schema_version", -1)) != SCHEMA_VERSION:
            raise DatasetError(path, f"schema_version {a.get('schema_version')} is not "
                                     f"supported (this reader knows {SCHEMA_VERSION})")
        arr = {}
        for key, unit in _EXPECTED.items():
            if key not in f:
                raise DatasetError(path, f"missing dataset '{key}'")
            if f[key].attrs.get("unit") != unit:
                raise DatasetError(path, f"dataset '{key}' has unit "
                                         f"{f[key].attrs.get('unit')!r}, expected {unit!r}")
            v = f[key][()]
            if v.dtype.kind in "OS":
                v = np.array([s.decode() if isinstance(s, bytes) else str(s) for s in v])
            arr[key] = v
        norm = f["pressure/normalised"].attrs
        try:
            space = ParameterSpace.from_json(json.loads(a["parameter_space"]))
            ds = Dataset(
                space=space, params=arr["parameters/physical"], depth=arr["pressure/depth"],
                pressure_raw=arr["pressure/raw"], pressure=arr["pressure/smoothed"],
                histogram=arr["distribution/histogram"],
                load_edges=arr["distribution/load_edges"],
                diameter_edges=arr["distribution/diameter_edges"],
                n_events=arr["distribution/n_events"], run_id=arr["runs/run_id"],
                role=arr["runs/role"], design_index=arr["runs/design_index"],
                seed=arr["runs/seed"], group=arr["runs/group"],
                wall_time=arr["runs/wall_time"], files=arr["runs/file"],
                stroke=float(a["stroke"]), cbrt_min=float(norm["cbrt_min"]),
                cbrt_max=float(norm["cbrt_max"]), savgol_window=int(a["savgol_window"]),
                savgol_order=int(a["savgol_order"]), load_scale=str(a["load_scale"]),
                base_config=str(a["base_config"]), skipped=json.loads(a["skipped"]),
                provenance=json.loads(a["provenance"]), path=path)
        except DatasetError:
            raise
        except Exception as err:
            raise DatasetError(path, f"bad attributes or shapes ({err})") from None
    if ds.params.shape[1:] != (len(ds.space),):
        raise DatasetError(path, f"parameters/physical has shape {ds.params.shape}, expected "
                                 f"(n, {len(ds.space)})")
    if ds.pressure.shape[1:] != ds.depth.shape:
        raise DatasetError(path, "pressure rows do not match pressure/depth")
    nb = (len(ds.load_edges) - 1, len(ds.diameter_edges) - 1)
    if ds.histogram.shape[1:] != nb:
        raise DatasetError(path, f"histograms of shape {ds.histogram.shape[1:]} do not match "
                                 f"the edges {nb}")
    return ds


# ---------------------------------------------------------------------- building
def _problem_key(cfg) -> str:
    """What must agree between runs of one dataset: the configuration without the breakage
    parameters, the seed and the packing path."""
    from calendaring.core.config import config_hash_excluding

    return config_hash_excluding(cfg, (*(f"breakage.{n}" for n in PAPER_SPACE.names),
                                       "numerics.seed", "electrode.packing"))


@dataclass
class _Source:
    """What the dataset takes from one run: its run file or, without one, its digest."""

    name: str
    kind: str  # "run file" or "digest"
    config: object
    preset: str
    seed: int
    breakage_model: str
    stroke: float
    final_depth: float
    wall_seconds: float
    peak_load: np.ndarray
    diameter: np.ndarray
    pressure_means: object  # n_points -> interval means [Pa]
    source_commit: str  # git commit of the code that ran it ("" unrecorded)

    @classmethod
    def open(cls, run: Path, digest: Path) -> _Source:
        from calendaring.data.digest import read_digest
        from calendaring.process.runfile import RunFileError, read_run

        try:
            rec = read_run(run)
        except RunFileError as err:
            if not digest.exists():
                raise
            try:
                dg = read_digest(digest)
            except RunFileError as err2:
                raise RunFileError(run, f"{err.reason}; digest: {err2.reason}") from None
            return cls(name=run.stem, kind="digest", config=dg.config, preset=dg.preset,
                       seed=dg.seed,
                       breakage_model=dg.breakage_model, stroke=dg.stroke,
                       final_depth=dg.final_depth, wall_seconds=dg.wall_seconds,
                       peak_load=dg.peak_load, diameter=dg.diameter,
                       pressure_means=lambda n: dg.pressure_means(n)[1],
                       source_commit=dg.source_commit)
        return cls(name=run.stem, kind="run file", config=rec.config, preset=rec.preset,
                   seed=rec.seed,
                   breakage_model=rec.breakage_model, stroke=rec.stroke,
                   final_depth=float(rec.info.get("final_depth", 0.0)),
                   wall_seconds=float(rec.info.get("wall_seconds", 0.0)),
                   peak_load=rec.breakage["peak_load"], diameter=rec.breakage["diameter"],
                   pressure_means=lambda n: resample_pressure(
                       rec.pressure["depth"], rec.pressure["value"], rec.stroke, n)[1],
                   source_commit=rec.source_commit)


def _read_rows(folder: Path, n_points: int, space: ParameterSpace, progress: bool,
               names: Iterable[str] | None = None, key0: str | None = None
               ) -> tuple[list[dict], list, object]:
    """Read the runs of a sweep ``folder`` (``names``, default all) as dataset rows: a
    run file, or its digest when the file is not usable. Returns (rows, skipped, first
    record). A run of another problem than ``key0`` (default: the first usable run's) is
    skipped with the reason."""
    from calendaring.data.digest import digest_path, run_files_dir
    from calendaring.process.runfile import RunFileError

    run_dir = run_files_dir(folder)
    if names is None:
        names = sorted({p.stem for p in run_dir.glob("*.h5")}
                       | {p.stem for p in (folder / "digests").glob("*.h5")})
    names = list(names)
    manifest = {}
    if (folder / "manifest.json").exists():
        from calendaring.data.sweep import read_manifest

        manifest = read_manifest(folder)
    rows, skipped, rec0 = [], [], None
    t0 = time.perf_counter()
    for k, name in enumerate(names):
        path = run_dir / f"{name}.h5"
        try:
            rec = _Source.open(path, digest_path(folder, name))
        except RunFileError as err:
            skipped.append([path.name, err.reason])
            continue
        why = None
        if rec.breakage_model == "none":
            why = "a no-breakage run"
        elif rec.final_depth < rec.stroke * (1 - 1e-6):
            why = f"incomplete stroke ({rec.final_depth:.4g} of {rec.stroke:.4g} m)"
        else:
            key = _problem_key(rec.config)
            if key0 is None:
                key0, rec0 = key, rec
            elif key != key0:
                ref = f"{rec0.name}.h5" if rec0 is not None else "the dataset"
                why = f"a different problem from {ref} (configuration differs " \
                      "beyond the breakage parameters, seed and packing)"
        if why is None:
            try:
                p = rec.pressure_means(n_points)
            except ValueError as err:
                why = f"unusable pressure trace: {err}"
        if why:
            skipped.append([path.name, why])
            continue
        rec0 = rec0 or rec
        e = manifest.get(name)
        rows.append({
            "params": [float(getattr(rec.config.breakage, n)) for n in space.names],
            "raw": p, "load": rec.peak_load, "diameter": rec.diameter,
            "run_id": name, "file": path.name, "role": e.role if e else "train",
            "design_index": e.index if e else -1, "seed": rec.seed,
            "group": e.group if e else "", "wall": rec.wall_seconds, "kind": rec.kind,
            "stroke": rec.stroke, "commit": rec.source_commit})
        if progress and (k == len(names) - 1 or k % 25 == 0):
            print(f"[dataset] {k + 1}/{len(names)} runs read "
                  f"({time.perf_counter() - t0:.0f} s)",
                  file=sys.stderr, flush=True)
    if rows:
        params = np.array([r["params"] for r in rows])
        tol = 1e-9 * (space.upper - space.lower)
        bad = [r["run_id"] for r, x in zip(rows, params, strict=True)
               if np.any(x < space.lower - tol) or np.any(x > space.upper + tol)]
        if bad:
            raise DatasetError(folder, f"runs with parameters outside the space bounds: "
                                       f"{bad[:5]}")
    return rows, skipped, rec0


def build_dataset(folder: str | Path, *, n_points: int = 196, savgol_window: int = 17,
                  savgol_order: int = 3, bins: int = 30, load_scale: str = "log",
                  load_range: tuple[float, float] | None = None,
                  diameter_range: tuple[float, float] | None = None,
                  space: ParameterSpace = PAPER_SPACE, progress: bool = True,
                  command: str = "", notes: dict[str, str] | None = None) -> Dataset:
    """Consolidate the run files of a sweep folder (``runs/*.h5``, or ``*.h5`` directly in
    ``folder``) into a :class:`Dataset`; a run without a usable run file is taken from its
    digest ``digests/<run>.h5`` (:mod:`calendaring.data.digest`) when there is one. Roles and
    replicate groups come from the sweep's manifest when there is one (otherwise every run
    is ``train``). Corrupt, incomplete, no-breakage or foreign runs are listed in
    ``skipped`` with the reason. The provenance counts the runs per source commit (the git
    commit each run file or digest records, ``"unrecorded"`` where it has none) and keeps
    ``notes`` (free text by key, e.g. what the files cannot say about how they were made).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError("RUNS", str(folder), "an existing folder of run files")
    if n_points < savgol_window:
        raise ConfigError("n_points", n_points, f">= savgol_window = {savgol_window}")
    if bins < 2:
        raise ConfigError("bins", bins, ">= 2")
    smooth(np.zeros(savgol_window + 1), savgol_window, savgol_order)  # validates the window
    rows, skipped, rec0 = _read_rows(folder, n_points, space, progress)
    if not rows:
        raise DatasetError(folder, f"no usable run files ({len(skipped)} skipped: "
                                   f"{skipped[:3]})")
    le, de = histogram_edges([r["load"] for r in rows], [r["diameter"] for r in rows], bins,
                             load_scale, load_range, diameter_range)
    raw = np.stack([r["raw"] for r in rows])
    sm = smooth(raw, savgol_window, savgol_order)
    c = np.cbrt(sm)
    edges = np.linspace(0.0, float(rec0.stroke), n_points + 1)
    from calendaring.core.config import config_json

    n_names = len(rows) + len(skipped)
    return Dataset(
        space=space, depth=0.5 * (edges[1:] + edges[:-1]), pressure_raw=raw,
        pressure=sm, load_edges=le, diameter_edges=de, stroke=float(rec0.stroke),
        cbrt_min=float(c.min()), cbrt_max=float(c.max()), savgol_window=savgol_window,
        savgol_order=savgol_order, load_scale=load_scale,
        base_config=config_json(rec0.config), skipped=skipped,
        **_row_arrays(rows, le, de),
        provenance={"runs_folder": str(folder.resolve()), "command": command,
                    "software_version": __version__, "built": datetime.datetime.now(
                        datetime.UTC).isoformat(timespec="seconds"),
                    "run_files": n_names, "used": len(rows), "skipped": len(skipped),
                    "from_digests": sum(r["kind"] == "digest" for r in rows),
                    "preset": rec0.preset, "source_commits": commit_counts(rows),
                    **({"notes": dict(notes)} if notes else {}),
                    "group_names": sorted({r["group"] for r in rows if r["group"]})})


def commit_counts(rows: list[dict]) -> dict[str, int]:
    """Runs per source commit of rows of :func:`_read_rows`, most runs first; runs that
    record none count as ``"unrecorded"``."""
    counts: dict[str, int] = {}
    for r in rows:
        key = r["commit"] or "unrecorded"
        counts[key] = counts.get(key, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def _row_arrays(rows: list[dict], load_edges, diameter_edges,
                group_names: list[str] | None = None) -> dict:
    """The per-row arrays of a :class:`Dataset` from rows of :func:`_read_rows`; replicate
    groups are numbered in the order of ``group_names`` (new names appended, sorted)."""
    names = list(group_names or [])
    names += sorted({r["group"] for r in rows if r["group"]} - set(names))
    gid = {g: i for i, g in enumerate(names)}
    return {
        "params": np.array([r["params"] for r in rows], float),
        "histogram": np.stack([bin_events(r["load"], r["diameter"], load_edges,
                                          diameter_edges) for r in rows]),
        "n_events": np.array([len(r["load"]) for r in rows]),
        "run_id": np.array([r["run_id"] for r in rows]),
        "role": np.array([r["role"] for r in rows]),
        "design_index": np.array([r["design_index"] for r in rows]),
        "seed": np.array([r["seed"] for r in rows]),
        "group": np.array([gid.get(r["group"], -1) for r in rows]),
        "wall_time": np.array([r["wall"] for r in rows]),
        "files": np.array([r["file"] for r in rows])}


def dataset_config(ds: Dataset):
    """The :class:`~calendaring.core.config.SimConfig` of the dataset's problem (its first
    run's configuration read with today's defaults for keys added since), with the packing
    path cleared and breakage on (every row is a breakage run): the base of new runs of the
    same problem (:func:`append_runs`)."""
    from calendaring.core.config import load_config_dict, with_overrides

    try:
        cfg = load_config_dict(json.loads(ds.base_config))
    except (ValueError, TypeError) as err:
        raise DatasetError(ds.path or "<memory>", f"unusable base_config ({err})") from None
    return with_overrides(cfg, {"electrode.packing": "", "breakage.enabled": True})


def append_runs(ds: Dataset, folder: str | Path, names: Iterable[str] | None = None,
                role: str | None = None, progress: bool = False) -> Dataset:
    """``ds`` with the runs of the sweep ``folder`` (``names``, default all) appended as new
    rows, processed exactly as ``ds`` was: the same depths, smoothing, bin edges (events
    outside them fall into the end bins, as :func:`bin_events` does) and parameter space.
    ``role`` replaces the manifest's role of the new rows. The normalisation statistics
    (``cbrt_min``/``cbrt_max``) are recomputed over all rows.

    Raises:
        DatasetError: a run of another problem than ``ds`` (the configuration beyond the
            breakage parameters, the seed and the packing differs), another stroke, a run
            id already in ``ds``, or no usable run.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError("RUNS", str(folder), "an existing folder of run files")
    if role is not None and role not in ROLES:
        raise ConfigError("role", role, f"one of {ROLES}")
    key0 = _problem_key(dataset_config(ds))
    rows, skipped, _ = _read_rows(folder, len(ds.depth), ds.space, progress, names, key0)
    foreign = [s for s in skipped if "different problem" in s[1]]
    if foreign:
        raise DatasetError(folder, f"{len(foreign)} run(s) of another problem than the "
                                   f"dataset, e.g. {foreign[0][0]}: {foreign[0][1]}")
    if not rows:
        raise DatasetError(folder, f"no usable runs to append ({len(skipped)} skipped: "
                                   f"{skipped[:3]})")
    stroke = [r["run_id"] for r in rows if abs(r["stroke"] - ds.stroke) > 1e-9 * ds.stroke]
    if stroke:
        raise DatasetError(folder, f"runs with another stroke than the dataset's "
                                   f"{ds.stroke:.4g} m: {stroke[:3]}")
    dup = sorted(set(ds.run_id) & {r["run_id"] for r in rows})
    if dup:
        raise DatasetError(folder, f"runs already in the dataset: {dup[:3]}")
    if role is not None:
        for r in rows:
            r["role"] = role
    old_groups = list(ds.provenance.get("group_names", []))
    groups = old_groups + sorted({r["group"] for r in rows if r["group"]} - set(old_groups))
    new = _row_arrays(rows, ds.load_edges, ds.diameter_edges, groups)
    raw = np.stack([r["raw"] for r in rows])
    new["pressure_raw"] = raw
    new["pressure"] = smooth(raw, ds.savgol_window, ds.savgol_order)
    old = {k: getattr(ds, k) for k in new}
    merged = {k: np.concatenate([np.asarray(old[k]), np.asarray(v)]) for k, v in new.items()}
    c = np.cbrt(merged["pressure"])
    prov = dict(ds.provenance)
    prov.setdefault("appended", []).append({
        "runs_folder": str(folder.resolve()), "rows": len(rows), "skipped": len(skipped),
        "role": role or "from the manifest", "source_commits": commit_counts(rows),
        "at": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")})
    prov["group_names"] = groups
    return replace(ds, **merged, cbrt_min=float(c.min()), cbrt_max=float(c.max()),
                   skipped=list(ds.skipped) + skipped, provenance=prov, path=None)


def provenance_report(folder: str | Path, ds: Dataset) -> dict:
    """What a committed dataset needs beside it: how it was made (command, software version,
    designs and their largest |r|), the sweep's wall times and run counts per role (from the
    manifest), breakage events per run, the replicate noise floors and how many components
    of the pressure curves stand above them (:func:`pressure_components`)."""
    folder = Path(folder)
    rep = {"dataset_fingerprint": ds.fingerprint, **ds.provenance}
    designs = {}
    for p in sorted((folder / "designs").glob("*.json")):
        with contextlib.suppress(ValueError, KeyError, OSError):
            designs[p.stem] = json.loads(p.read_text())["max_abs_r"]
    rep["designs_max_abs_r"] = designs
    if (folder / "manifest.json").exists():
        from calendaring.data.sweep import read_manifest

        runs = read_manifest(folder)
        by_role = {}
        for e in runs.values():
            r = by_role.setdefault(e.role, {"done": 0, "failed": 0, "pending": 0,
                                            "running": 0, "wall_seconds": []})
            r[e.status] += 1
            if e.status == "done" and e.wall_time:
                r["wall_seconds"].append(e.wall_time)
        for r in by_role.values():
            w = r.pop("wall_seconds")
            r["wall_seconds_per_run_mean"] = float(np.mean(w)) if w else None
            r["wall_seconds_total"] = float(np.sum(w)) if w else None
        rep["sweep"] = by_role
        failed = [[e.run_id, e.error.splitlines()[0] if e.error else ""]
                  for e in runs.values() if e.status == "failed"]
        rep["failed_runs"] = failed
    ev = ds.n_events
    rep["events_per_run"] = {"mean": float(ev.mean()), "min": int(ev.min()),
                             "max": int(ev.max()), "runs_without_events": int(np.sum(ev == 0))}
    rep["rows_by_role"] = {r: int(np.sum(ds.role == r)) for r in sorted(set(ds.role))}
    rep["noise_floor"] = noise_floor(ds)
    rep["pressure_components"] = pressure_components(ds)
    return rep


def pressure_components(ds: Dataset, n_components: int = 10, alpha: float = 0.05
                        ) -> dict | None:
    """How many independent numbers a pressure curve carries above the bed-to-bed scatter.

    The curves (normalised cube-root units) are split into principal components over all
    rows. For each component, its variance over the rows is set against the pooled variance
    of its scores within the replicate groups (the same parameters on other beds: pure
    scatter, ``dof = sum (n_g - 1)``). A component whose scores vary no more than the
    scatter carries no information on the parameters: with ``ratio = variance /
    bed_to_bed`` approximately ``F(n - 1, dof)`` under that null, ``p = F.sf(ratio)`` and
    Holm's step-down procedure at ``alpha`` over the ``n_components`` tested marks the
    resolved ones. ``signal_variance = max(variance - bed_to_bed, 0)``;
    ``signal_share_resolved`` is the resolved components' share of the summed signal.

    The number resolved bounds how many parameter combinations one measured curve can pin
    down, whatever the calibration or the surrogate: a calibration of 8 parameters from a
    curve that resolves 2 components is a ridge in 6 directions. Components are ordered by
    variance, so the test is a screen, not an exact count (a component chosen for its large
    variance has its ratio inflated slightly). None without a replicate group of >= 2 runs.
    """
    from scipy.stats import f as f_dist

    if not 0 < alpha < 1:
        raise ConfigError("alpha", alpha, "(0, 1)")
    if int(n_components) < 1:
        raise ConfigError("n_components", n_components, "an integer >= 1")
    groups = [np.nonzero(ds.group == g)[0] for g in sorted(set(int(g) for g in ds.group
                                                                if g >= 0))]
    groups = [idx for idx in groups if len(idx) >= 2]
    if not groups:
        return None
    x = ds.pressure_normalised
    k = int(min(n_components, len(x) - 1, x.shape[1]))
    _, _, vt = np.linalg.svd(x - x.mean(axis=0), full_matrices=False)
    scores = (x - x.mean(axis=0)) @ vt[:k].T
    dof = int(sum(len(idx) - 1 for idx in groups))
    within = sum(((scores[idx] - scores[idx].mean(axis=0)) ** 2).sum(axis=0)
                 for idx in groups) / dof
    total = scores.var(axis=0, ddof=1)
    ratio = total / np.maximum(within, np.finfo(float).tiny)
    pval = f_dist.sf(ratio, len(x) - 1, dof)
    resolved = np.zeros(k, bool)
    for rank, j in enumerate(np.argsort(pval)):  # Holm: step down until one fails
        if pval[j] > alpha / (k - rank):
            break
        resolved[j] = True
    signal = np.clip(total - within, 0.0, None)
    comps = [{"index": j + 1, "variance": float(total[j]), "bed_to_bed_variance": float(
        within[j]), "signal_variance": float(signal[j]), "noise_share": float(
        within[j] / total[j]) if total[j] > 0 else None, "f_ratio": float(ratio[j]),
              "p_value": float(pval[j]), "resolved": bool(resolved[j])} for j in range(k)]
    return {"rows": len(x), "groups": len(groups), "dof_bed_to_bed": dof, "alpha": alpha,
            "tested": k, "resolved": int(resolved.sum()),
            "resolved_components": [c["index"] for c in comps if c["resolved"]],
            "signal_share_resolved": float(signal[resolved].sum() / signal.sum())
            if signal.sum() > 0 else None,
            "components": comps, "units": "normalised cube-root pressure, squared"}


# ---------------------------------------------------------------------- synthetic data
def synthetic_response(u: np.ndarray, depth: np.ndarray, stroke: float,
                       load_edges: np.ndarray, diameter_edges: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """The analytic stand-in of :func:`synthetic_dataset` at unit parameters ``u`` (n, 8):
    pressure ``(n, len(depth))`` [Pa] and histograms ``(n, L, D)`` (not physics)."""
    u = np.atleast_2d(np.asarray(u, float))
    z = np.asarray(depth, float)
    p0 = 2e6 * (1 + u[:, 1] + 0.5 * u[:, 2] ** 2 + 0.2 * np.sin(3 * u[:, 3]))
    k = 3.0 + 1.5 * u[:, 3] - 0.8 * u[:, 4] + 0.3 * u[:, 0] * u[:, 5]
    p = p0[:, None] * np.expm1(k[:, None] * z[None, :] / stroke)
    le, de = np.asarray(load_edges, float), np.asarray(diameter_edges, float)
    lc, dc = np.log(np.sqrt(le[:-1] * le[1:])), 0.5 * (de[:-1] + de[1:])
    lo, hi = np.log(le[0]), np.log(le[-1])
    mu_l = lo + (hi - lo) * (0.3 + 0.4 * u[:, 2] * u[:, 1])
    mu_d = 6e-6 + 6e-6 * u[:, 3]
    h = np.exp(-0.5 * ((lc[None, :, None] - mu_l[:, None, None]) / 0.8) ** 2
               - 0.5 * ((dc[None, None, :] - mu_d[:, None, None]) / 2e-6) ** 2)
    return p, h / h.sum(axis=(1, 2), keepdims=True)


def synthetic_dataset(n: int = 64, seed: int = 0, n_points: int = 196, bins: int = 30,
                      space: ParameterSpace = PAPER_SPACE, replicate_groups: int = 0,
                      replicates: int = 0, noise: float = 0.0, stroke: float = 19.5e-6
                      ) -> Dataset:
    """A smooth analytic stand-in for a sweep, for tests and examples (not physics).

    Pressure: ``P(z) = P0 (exp(k z / stroke) - 1)`` with ``P0`` and ``k`` smooth functions of
    the unit parameters; histogram: a Gaussian blob whose centre moves with the parameters.
    ``noise`` adds relative multiplicative noise to replicates' pressures.
    """
    rng = np.random.default_rng(seed)
    u = rng.random((n, len(space)))
    role = np.array(["train"] * n, dtype=object)
    group = -np.ones(n, dtype=int)
    if replicate_groups and replicates:
        base = rng.random((replicate_groups, len(space)))
        u = np.vstack([u, np.repeat(base, replicates, axis=0)])
        role = np.concatenate([role, ["replicate"] * (replicate_groups * replicates)])
        group = np.concatenate([group, np.repeat(np.arange(replicate_groups), replicates)])
    m = len(u)
    edges = np.linspace(0, stroke, n_points + 1)
    z = 0.5 * (edges[1:] + edges[:-1])
    le = np.geomspace(1e-3, 1.0, bins + 1)
    de = np.linspace(4e-6, 16e-6, bins + 1)
    p, h = synthetic_response(u, z, stroke, le, de)
    if noise:
        p = p * (1 + noise * rng.standard_normal((m, 1)))
    x = space.from_unit(u)
    c = np.cbrt(p)
    return Dataset(space=space, params=x, depth=z, pressure_raw=p, pressure=p, histogram=h,
                   load_edges=le, diameter_edges=de, n_events=np.full(m, 500),
                   run_id=np.array([f"syn-{i:04d}" for i in range(m)]), role=role.astype(str),
                   design_index=np.arange(m), seed=np.full(m, seed), group=group,
                   wall_time=np.zeros(m), stroke=stroke, cbrt_min=float(c.min()),
                   cbrt_max=float(c.max()), provenance={"synthetic": True, "seed": seed})


__all__ = ["FORMAT", "KL_FLOOR", "ROLES", "SCHEMA_VERSION", "Dataset", "DatasetError",
           "append_runs", "bin_centres", "bin_events", "build_dataset", "centroids",
           "dataset_config", "histogram_edges",
           "kl_divergence", "noise_floor", "perfect_model_kl", "pressure_components",
           "provenance_report",
           "read_dataset", "resample_pressure", "sampled_kl_floor", "seed_means", "smooth",
           "synthetic_dataset", "synthetic_response", "write_dataset"]
