"""Run digests: what ``calendaring dataset`` needs of a finished run, in a few tens of kB.

A sweep writes ``digests/<run>.h5`` next to each finished ``runs/<run>.h5``. The digest holds
the run's configuration, seed, preset and software version, its stroke, final depth, wall
time and particle counts, the top-plate pressure as :data:`POINTS` exact interval means
over ``[0, stroke]`` (``calendaring.data.curves.resample_pressure`` of the recorded trace), and
every breakage event's peak load and parent diameter. A dataset built from the digests of a
sweep equals the one built from its run files for any ``--points`` that divides
:data:`POINTS` (the mean over an interval is the mean of its equal sub-interval means),
so a long sweep's evidence can live in the repository (a run file of the 100 um cell is
some MB, its digest about 30 kB) and survive the loss of the machine that ran it.

Layout (HDF5; every dataset has a ``unit`` attribute): root attributes ``format`` =
``calendaring-run-digest``, ``schema_version``, ``run``, ``software_version``,
``source_commit`` (the run file's; optional, absent in older digests), ``config``
(JSON), ``config_hash``, ``seed``, ``preset``, ``breakage_model``, ``stroke`` [m],
``final_depth`` [m], ``wall_seconds`` [s], ``n_particles``, ``particles_end``; datasets
``pressure_mean`` [Pa] (:data:`POINTS`), ``peak_load`` [N], ``diameter`` [m].

See also: :mod:`calendaring.process.runfile` (the run file a digest summarises),
:mod:`calendaring.data.dataset` (built from digests), :mod:`calendaring.data.sweep`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from calendaring.core.config import SimConfig, config_text_hash, load_config_dict
from calendaring.core.fileio import write_h5
from calendaring.data.curves import resample_pressure
from calendaring.process.runfile import RunFileError, RunRecord, incomplete_stroke

DIGEST_FORMAT = "calendaring-run-digest"
DIGEST_SCHEMA = 1
POINTS = 1960  # 10 x the paper's 196 points


@dataclass
class Digest:
    """A digest read back (SI units)."""

    path: Path
    run: str
    software_version: str
    config: SimConfig
    seed: int
    preset: str
    breakage_model: str
    stroke: float
    final_depth: float
    wall_seconds: float
    n_particles: int
    particles_end: int
    pressure_mean: np.ndarray  # [Pa], POINTS interval means over [0, stroke]
    peak_load: np.ndarray  # [N]
    diameter: np.ndarray  # [m]
    source_commit: str = ""  # git commit of the code that ran it ("" unrecorded)

    def pressure_means(self, n_points: int) -> tuple[np.ndarray, np.ndarray]:
        """(midpoint depths [m], mean pressure [Pa]) over ``n_points`` equal intervals;
        ``n_points`` must divide :data:`POINTS`."""
        if n_points < 1 or POINTS % n_points:
            raise ValueError(f"a digest holds {POINTS} interval means: the number of points "
                             f"must divide it, not {n_points}")
        means = self.pressure_mean.reshape(n_points, POINTS // n_points).mean(axis=1)
        edges = np.linspace(0.0, self.stroke, n_points + 1)
        return 0.5 * (edges[1:] + edges[:-1]), means


def run_files_dir(folder: str | Path) -> Path:
    """Where the run files of ``folder`` lie: a sweep folder keeps them under ``runs/``;
    any other folder is taken as a folder of run files itself."""
    folder = Path(folder)
    return folder / "runs" if (folder / "runs").is_dir() else folder


def digest_path(folder: str | Path, run: str) -> Path:
    """Where a sweep folder keeps the digest of run ``run`` (the run file's stem)."""
    return Path(folder) / "digests" / f"{run}.h5"


def write_digest(path: str | Path, rec: RunRecord) -> Path:
    """Write the digest of the run ``rec`` to ``path`` (atomically)."""
    _, means = resample_pressure(rec.pressure["depth"], rec.pressure["value"], rec.stroke,
                                 POINTS)

    def fill(f: h5py.File) -> None:
        a = f.attrs
        a["format"] = DIGEST_FORMAT
        a["schema_version"] = DIGEST_SCHEMA
        a["run"] = rec.path.stem
        a["software_version"] = rec.software_version
        a["source_commit"] = rec.source_commit
        a["config"] = rec.config_json
        a["config_hash"] = config_text_hash(rec.config_json)
        a["seed"] = int(rec.seed)
        a["preset"] = rec.preset
        a["breakage_model"] = rec.breakage_model
        a["stroke"] = float(rec.stroke)
        a["final_depth"] = float(rec.info.get("final_depth", 0.0))
        a["wall_seconds"] = float(rec.info.get("wall_seconds", 0.0))
        a["n_particles"] = int(rec.info.get("n_particles", 0))
        series = rec.series.get("particles", np.zeros(0))
        a["particles_end"] = int(series[-1]) if len(series) else 0
        for name, data, unit in (("pressure_mean", means, "Pa"),
                                 ("peak_load", rec.breakage["peak_load"], "N"),
                                 ("diameter", rec.breakage["diameter"], "m")):
            ds = f.create_dataset(name, data=np.asarray(data, float), compression="gzip",
                                  compression_opts=6, shuffle=True)
            ds.attrs["unit"] = unit

    return write_h5(Path(path), fill)


def read_digest(path: str | Path) -> Digest:
    """Open and validate a digest; raises :class:`RunFileError` naming what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise RunFileError(path, "no such file")
    try:
        with h5py.File(path, "r") as f:
            a = dict(f.attrs)
            if a.get("format") != DIGEST_FORMAT:
                raise RunFileError(path, f"not a calendaring run digest (format = "
                                         f"{a.get('format')!r})")
            if int(a.get("schema_version", -1)) != DIGEST_SCHEMA:
                raise RunFileError(path, f"digest schema_version {a.get('schema_version')} "
                                         f"is not {DIGEST_SCHEMA}")
            arrays = {}
            for name, unit in (("pressure_mean", "Pa"), ("peak_load", "N"),
                               ("diameter", "m")):
                if name not in f or f[name].attrs.get("unit") != unit:
                    raise RunFileError(path, f"dataset {name} [{unit}] missing")
                arrays[name] = np.asarray(f[name][()], float)
    except RunFileError:
        raise
    except OSError as err:
        raise RunFileError(path, f"not a readable HDF5 file (truncated or corrupt?): {err}") \
            from None
    try:
        cfg = load_config_dict(json.loads(str(a["config"])))
        if config_text_hash(a["config"]) != str(a["config_hash"]):
            raise RunFileError(path, "config does not match config_hash (edited or corrupt)")
        dg = Digest(path=path, run=str(a["run"]), software_version=str(a["software_version"]),
                    config=cfg, seed=int(a["seed"]), preset=str(a["preset"]),
                    breakage_model=str(a["breakage_model"]), stroke=float(a["stroke"]),
                    final_depth=float(a["final_depth"]),
                    wall_seconds=float(a["wall_seconds"]), n_particles=int(a["n_particles"]),
                    particles_end=int(a["particles_end"]),
                    source_commit=str(a.get("source_commit", "")), **arrays)
    except RunFileError:
        raise
    except (KeyError, ValueError, TypeError) as err:
        raise RunFileError(path, f"bad digest attributes ({type(err).__name__}: {err})") \
            from None
    if dg.pressure_mean.shape != (POINTS,) or dg.peak_load.shape != dg.diameter.shape:
        raise RunFileError(path, "digest arrays of the wrong shape")
    return dg


def digest_ok(path: str | Path) -> tuple[bool, str]:
    """Does ``path`` read back as the digest of a complete run (the whole stroke)?"""
    try:
        dg = read_digest(path)
    except RunFileError as err:
        return False, str(err)
    why = incomplete_stroke(dg.final_depth, dg.stroke, dg.config.protocol.target_pressure)
    return not why, why


__all__ = ["DIGEST_FORMAT", "POINTS", "Digest", "digest_ok", "digest_path", "read_digest",
           "run_files_dir", "write_digest"]
