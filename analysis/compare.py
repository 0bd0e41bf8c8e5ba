"""The paper's comparison studies (sections 3.4, 3.5; Figs. 12, 13; Table 5) at small scale.

Studies (each a set of ``calendaring run`` subprocesses from one preset and one seed):

- ``r0r1``: breakage (R1) against the no-breakage control (R0, ``--no-breakage``): the same
  configuration, packing and seed, so the two pressure traces are identical up to the first
  breakage event; the report gives the depth where they part and the difference after.
- ``psd``: the particle-size robustness set of Table 5 against the baseline R1: C1-C4 (same
  mean, standard deviation 1.08-1.59 um) and R4, R5 (larger mean and spread). The Table 5
  mean and standard deviation set the AM normal distribution (``electrode.sizes.AM.mean`` /
  ``.std``); it is truncated at the same number of standard deviations below and above the
  mean as the preset's baseline distribution (paper 2.1: N(7.74, 1.35) um in [4.94, 10.69]
  um, i.e. -2.07 and +2.19 sigma). The AM mass fraction, coating density and thickness are
  unchanged, so the AM mass and volume are the same in every run (as in the paper); the
  realised diameter statistics of every run are reported next to Table 5's.

For each run: the pressure-depth curve (Figs. 12 b/d, 13 a), breakage counts and, through
:func:`analysis.microstructure.analyse_run`, porosity, tortuosity and D_eff at the snapshots
nearest 0 and 19.5 um (or the end of a shorter stroke).

Run files go to ``<out_dir>/runs/<name>.h5``. A run whose file exists and reads back is not
run again (resume); a crashed run with a checkpoint continues from it; failures are recorded
in the report and do not stop the other runs. ``compare.json`` and the PNGs are written
atomically. Each case's microstructure is analysed as soon as its run ends.

Beside each run file, ``<name>.record.h5`` keeps what the report needs of the run (its
summary, the raw pressure trace, the initial AM diameters, a digest of the initial
packing; a few tens of kB) and ``<name>.microstructure.json`` the analysis. A case whose
run file is gone (a fresh machine) but whose record and analysis are there, made for the
same preset, seed and settings, is not run again (status ``kept``): a study of many hours
survives a lost machine case by case once those two files are kept
(``scripts/sweep-keep.sh``).

    analysis compare --preset quick --out-dir studies/ --studies r0r1,psd
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calendaring import PRESETS, ConfigError, format_override

STUDIES = ("r0r1", "psd")
INITIAL_CHOICES = ("all", "R1", "none")
PAPER_FINAL_DEPTH = 19.5e-6
"""The paper's largest calendering depth [m] (Table 5 runs, Fig. 13)."""

TABLE5 = {
    # name: (mean, std, D10, D50, D90) of the AM diameter [m], paper Table 5 (um there)
    "R1": (7.743e-6, 1.349e-6, 5.902e-6, 7.746e-6, 9.563e-6),
    "C1": (7.774e-6, 1.081e-6, 6.317e-6, 7.787e-6, 9.220e-6),
    "C2": (7.696e-6, 1.419e-6, 5.749e-6, 7.637e-6, 9.708e-6),
    "C3": (7.752e-6, 1.506e-6, 5.653e-6, 7.758e-6, 9.845e-6),
    "C4": (7.767e-6, 1.589e-6, 5.528e-6, 7.765e-6, 9.958e-6),
    "R4": (9.920e-6, 1.670e-6, 7.645e-6, 9.951e-6, 12.105e-6),
    "R5": (11.854e-6, 2.061e-6, 9.080e-6, 11.847e-6, 14.599e-6),
}
PSD_CASES = ("C1", "C2", "C3", "C4", "R4", "R5")
AM_KEY = "electrode.sizes.AM"


@dataclass
class Case:
    """One run of a study: its name, the studies it belongs to and its CLI arguments."""

    name: str
    studies: list[str]
    description: str
    no_breakage: bool = False
    sets: dict[str, object] = field(default_factory=dict)


def _baseline_am(preset: str):
    from calendaring import load_preset

    cfg = load_preset(preset)
    am = cfg.electrode.sizes.get("AM")
    if am is None:
        raise ConfigError(f"preset {preset}: electrode.sizes.AM", None,
                          "an AM size distribution (the PSD study varies it)")
    return am


def truncation_sigmas(preset: str) -> tuple[float, float]:
    """(lower, upper) truncation of the preset's AM normal distribution in standard
    deviations from the mean (used for every PSD case)."""
    am = _baseline_am(preset)
    if am.distribution != "normal" or am.std <= 0:
        raise ConfigError(f"{AM_KEY}.distribution", am.distribution,
                          "'normal' in the preset for the PSD study")
    lo, hi = am.bounds
    return (am.mean - lo) / am.std, (hi - am.mean) / am.std


def _fit_cell(preset: str, sets: dict, extra_sets: Sequence[str] = ()) -> dict:
    """``sets`` plus a larger square cell when the preset's periodic cell is too small for
    the case's largest AM diameter (the minimum-image check of ``SimConfig.check_run``);
    the cell grows in 1 um steps until the configuration passes. Same coating per area."""
    from calendaring import load_preset, parse_override, with_overrides

    base = load_preset(preset)
    over = dict(parse_override(s) for s in extra_sets)
    over.update(sets)
    cell = max(base.domain.cell_x, base.domain.cell_y)
    for _ in range(200):
        try:
            with_overrides(base, over).check_run()
            return {**sets, **{k: v for k, v in over.items() if k.startswith("domain.cell_")
                               and k not in dict(parse_override(x) for x in extra_sets)}}
        except ConfigError as err:
            if not str(err.key).startswith("domain.cell_"):
                raise ConfigError(f"{err.key} (PSD case)", err.value, err.allowed) from None
        cell = (math.floor(cell * 1e6 + 1e-6) + 1) * 1e-6
        over["domain.cell_x"] = over["domain.cell_y"] = cell
    raise ConfigError("domain.cell_x", cell, "a cell that fits the AM size distribution")


def plan(studies: Sequence[str], preset: str, extra_sets: Sequence[str] = ()) -> list[Case]:
    """The runs of the requested studies (R1 shared), in run order. ``extra_sets`` (applied
    to every run) only matter here for fitting the cell of the PSD cases."""
    studies = list(studies)
    bad = [s for s in studies if s not in STUDIES]
    if bad or not studies:
        raise ConfigError("--studies", ",".join(studies), f"a comma-separated subset of "
                          f"{','.join(STUDIES)}")
    if preset not in PRESETS:
        raise ConfigError("--preset", preset, f"one of {PRESETS}")
    cases = [Case("R1", list(studies), "breakage, the preset's AM size distribution")]
    if "r0r1" in studies:
        cases.append(Case("R0", ["r0r1"], "no breakage (control), same packing and seed",
                          no_breakage=True))
    if "psd" in studies:
        zlo, zhi = truncation_sigmas(preset)
        for name in PSD_CASES:
            mean, std = TABLE5[name][:2]
            sets = _fit_cell(preset, {f"{AM_KEY}.distribution": "normal",
                                      f"{AM_KEY}.mean": mean, f"{AM_KEY}.std": std,
                                      f"{AM_KEY}.min": mean - zlo * std,
                                      f"{AM_KEY}.max": mean + zhi * std}, extra_sets)
            desc = f"AM normal mean {mean * 1e6:.3f} um, std {std * 1e6:.3f} um (Table 5)"
            if "domain.cell_x" in sets:
                desc += (f"; cell enlarged to {sets['domain.cell_x'] * 1e6:.0f} um to fit the "
                         "largest AM diameter")
            cases.append(Case(name, ["psd"], desc, sets=sets))
    return cases


def _check_overrides(preset: str, extra_sets: Sequence[str]) -> None:
    """Bad ``--set`` overrides are bad input (ConfigError), not failed runs."""
    from calendaring import load_preset, parse_override, with_overrides

    over = dict(parse_override(str(x)) for x in extra_sets)
    if over:
        with_overrides(load_preset(preset), over).check_run()


def run_command(case: Case, out: Path, preset: str, seed: int,
                extra_sets: Sequence[str] = (), resume: bool = False) -> list[str]:
    """The ``calendaring run`` command line of one case. Runs use one CPU thread: runs are
    bit-reproducible only on one thread (atomic force sums), so R0 and R1 then share their
    packing bit for bit, and ``--jobs`` runs several at once."""
    cmd = [sys.executable, "-m", "calendaring.cli", "run", "--preset", preset, "--out",
           str(out), "--seed", str(int(seed)), "--threads", "1"]
    if case.no_breakage:
        cmd.append("--no-breakage")
    for s in extra_sets:
        cmd += ["--set", s]
    for k, v in case.sets.items():
        cmd += ["--set", format_override(k, v)]
    if resume:
        cmd.append("--resume")
    elif out.exists():
        cmd.append("--overwrite")
    return cmd


def _readable(path: Path) -> bool:
    from calendaring import RunFileError, read_run

    try:
        read_run(path)
    except (RunFileError, OSError, ValueError):
        return False
    return True


def execute(case: Case, out: Path, preset: str, seed: int, extra_sets: Sequence[str] = (),
            timeout: float | None = None, progress: bool = True,
            lock: threading.Lock | None = None) -> dict:
    """Run one case unless its run file exists and reads back; returns its status record
    (``status``: ``done`` | ``exists`` | ``failed``; ``returncode`` and the last lines of its
    output on failure)."""
    lock = lock or threading.Lock()
    if out.exists() and _readable(out):
        return {"name": case.name, "status": "exists", "file": str(out)}
    ckpt = out.with_name(out.name + ".ckpt")
    cmd = run_command(case, out, preset, seed, extra_sets, resume=ckpt.exists())
    out.parent.mkdir(parents=True, exist_ok=True)
    tail: deque[str] = deque(maxlen=30)
    t0 = time.perf_counter()
    env = dict(os.environ)
    try:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, env=env)
    except OSError as err:
        return {"name": case.name, "status": "failed", "returncode": None,
                "error": str(err), "command": cmd}
    assert proc.stdout is not None
    killed = threading.Event()

    def kill():
        killed.set()
        proc.kill()

    timer = threading.Timer(timeout, kill) if timeout else None
    if timer:
        timer.start()
    try:
        for line in proc.stdout:
            line = line.rstrip()
            tail.append(line)
            if progress and line:
                with lock:
                    print(f"[{case.name}] {line}", file=sys.stderr, flush=True)
        rc = proc.wait()
    finally:
        if timer:
            timer.cancel()
    timed_out = killed.is_set()
    wall = time.perf_counter() - t0
    if rc == 0 and not timed_out and _readable(out):
        return {"name": case.name, "status": "done", "file": str(out), "wall_time_s": wall}
    for tmp in out.parent.glob(f".{out.name}.tmp-*"):  # left by a killed writer
        tmp.unlink(missing_ok=True)
    return {"name": case.name, "status": "failed", "returncode": rc, "timed_out": timed_out,
            "wall_time_s": wall, "output_tail": list(tail), "command": cmd}


# ---------------------------------------------------------------------- case records
RECORD_VERSION = 1


def case_key(case: Case, preset: str, seed: int, extra_sets: Sequence[str] = ()) -> dict:
    """What makes a case's run: a kept record is reused only for the same key."""
    return {"version": RECORD_VERSION, "case": case.name, "preset": preset,
            "seed": int(seed), "no_breakage": bool(case.no_breakage),
            "sets": [format_override(k, v) for k, v in sorted(case.sets.items())],
            "extra_sets": [str(x) for x in extra_sets]}


def _packing_sha256(rec) -> str | None:
    """Digest of the initial packing (positions, radii, materials of snapshot 0): equal
    digests mean bitwise-equal packings."""
    import hashlib

    if not rec.snapshots:
        return None
    sn = rec.snapshots[0]
    h = hashlib.sha256()
    for a in (sn.position, sn.radius, sn.material):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _initial_am_diameters(rec) -> np.ndarray:
    if not rec.snapshots or "AM" not in rec.config.material_names:
        return np.zeros(0)
    sn = rec.snapshots[0]
    return 2 * sn.radius[sn.material == rec.config.material_names.index("AM")]


def run_view(rec) -> dict:
    """What the report takes from one run (a ``RunRecord``): its summary, the raw pressure
    trace, the initial AM diameters, the packing digest, the snapshots to analyse and the
    identity of the run file (config hash, creation time) that keys the analysis cache."""
    return {"path": str(rec.path), "summary": run_summary(rec),
            "pressure": {k: np.asarray(rec.pressure[k]) for k in ("step", "depth", "value")},
            "am_diameters": _initial_am_diameters(rec),
            "packing_sha256": _packing_sha256(rec), "targets": target_snapshots(rec),
            "config_hash": rec.info.get("config_hash"), "created": rec.created}


def write_case_record(path: Path, view: dict, key: dict) -> Path:
    """Keep a :func:`run_view` of a finished run in a small HDF5 file, atomically
    (:func:`calendaring.write_h5`). Every dataset carries its unit."""
    import json

    from calendaring import json_safe, write_h5

    def fill(f):
        f.attrs["kind"] = "analysis.compare case record"
        f.attrs["key"] = json.dumps(key, sort_keys=True)
        meta = {k: view[k] for k in ("path", "summary", "packing_sha256", "targets",
                                     "config_hash", "created")}
        f.attrs["view"] = json.dumps(json_safe(meta))
        for name, unit in (("step", "1"), ("depth", "m"), ("value", "Pa")):
            d = f.create_dataset(f"pressure/{name}", data=view["pressure"][name],
                                 compression="gzip", shuffle=True)
            d.attrs["unit"] = unit
        d = f.create_dataset("am_diameter", data=view["am_diameters"], compression="gzip",
                             shuffle=True)
        d.attrs["unit"] = "m"

    return write_h5(path, fill)


def read_case_record(path: Path, key: dict) -> dict | None:
    """The kept :func:`run_view` of a case, or None when the record is missing, unreadable
    or made for another key (preset, seed, settings)."""
    import json

    import h5py

    try:
        with h5py.File(path, "r") as f:
            if json.loads(f.attrs["key"]) != json.loads(json.dumps(key, sort_keys=True)):
                return None
            view = json.loads(f.attrs["view"])
            view["pressure"] = {k: f[f"pressure/{k}"][()] for k in ("step", "depth", "value")}
            view["am_diameters"] = f["am_diameter"][()]
    except (OSError, KeyError, ValueError):
        return None
    return view


# ---------------------------------------------------------------------- report
def _first_divergence(a: dict, b: dict) -> dict:
    """Where two pressure traces (``RunRecord.pressure``) stop being identical."""
    n = min(len(a["value"]), len(b["value"]))
    same = (a["step"][:n] == b["step"][:n]) & (a["value"][:n] == b["value"][:n])
    diff = np.nonzero(~same)[0]
    k = int(diff[0]) if len(diff) else n
    out = {"identical_samples": k, "compared_samples": n,
           "identical_until_depth_m": float(a["depth"][k - 1]) if k > 0 else None,
           "first_difference_depth_m": float(a["depth"][k]) if k < n else None}
    return out


def _curve(rec, max_points: int = 400) -> dict:
    d, p = rec.pressure["depth"], rec.pressure["value"]
    if len(d) > max_points:  # interval means on an even depth grid (exact for the trace)
        from calendaring import resample_pressure

        try:
            d, p = resample_pressure(d, p, float(d[-1]), max_points)
        except ValueError:
            idx = np.linspace(0, len(d) - 1, max_points).astype(int)
            d, p = d[idx], p[idx]
    return {"depth_m": np.asarray(d).tolist(), "pressure_Pa": np.asarray(p).tolist()}


def _am_stats(rec) -> dict:
    if not rec.snapshots:
        return {}
    sn = rec.snapshots[0]
    names = rec.config.material_names
    if "AM" not in names:
        return {}
    dia = 2 * sn.radius[sn.material == names.index("AM")]
    if len(dia) == 0:
        return {}
    q = np.percentile(dia, [10, 50, 90])
    return {"n": len(dia), "mean_m": float(dia.mean()),
            "std_m": float(dia.std(ddof=1)) if len(dia) > 1 else 0.0,
            "D10_m": float(q[0]), "D50_m": float(q[1]), "D90_m": float(q[2])}


def run_summary(rec) -> dict:
    """Key figures of one run for the report (SI)."""
    p = rec.pressure["value"]
    ev = rec.breakage.get("depth", np.zeros(0))
    return {"file": str(rec.path), "breakage_model": rec.breakage_model, "seed": rec.seed,
            "stroke_m": rec.stroke, "final_depth_m": rec.info.get("final_depth"),
            "peak_pressure_Pa": float(p.max()) if len(p) else None,
            "final_pressure_Pa": float(p[-1]) if len(p) else None,
            "breakage_events": len(ev),
            "first_breakage_depth_m": float(np.min(ev)) if len(ev) else None,
            "particles_final": len(rec.snapshots[-1].radius) if rec.snapshots else None,
            "am_diameter_at_start": _am_stats(rec),
            "snapshots": [{"index": s.index, "depth_m": s.depth} for s in rec.snapshots],
            "wall_seconds": rec.info.get("wall_seconds"), "curve": _curve(rec)}


def target_snapshots(rec, depths: Sequence[float] | None = None) -> list[int]:
    """Snapshot indices nearest 0 and 19.5 um (clipped to the run's stroke), unique."""
    depths = depths if depths is not None else (0.0, min(PAPER_FINAL_DEPTH, rec.stroke))
    idx = []
    for d in depths:
        k = rec.snapshot_near(d).index
        if k not in idx:
            idx.append(k)
    return idx


def _micro_rows(js) -> list[dict]:
    """Porosity / tortuosity / D_eff rows from ``MicrostructureResult.to_json()``."""
    snaps = js.get("snapshots", js) if isinstance(js, dict) else js
    if isinstance(snaps, dict):
        snaps = list(snaps.values())
    rows = []
    for s in snaps if isinstance(snaps, list) else []:
        if not isinstance(s, dict):
            continue
        rows.append({
            "snapshot": s.get("snapshot", s.get("index")),
            "depth_m": s.get("depth_m", s.get("depth")),
            "porosity": s.get("voxel_porosity", s.get("porosity")),
            "particle_porosity": s.get("particle_porosity"),
            "tortuosity": s.get("tortuosity"),
            "tortuosity_reason": s.get("tortuosity_reason"),
            "D_eff": s.get("D_eff"),
            "voxel_size_m": s.get("voxel_size_m"),
            "extrapolated": {k: (s.get("extrapolated") or {}).get(k)
                             for k in ("voxel_porosity", "tortuosity", "D_eff")}})
    return rows


def microstructure(run_file: Path, snapshots: list[int], **kw) -> dict:
    """:func:`analysis.microstructure.analyse_run` at the given snapshots; an error record
    (not an exception) when the module is missing or the analysis fails."""
    try:
        from analysis.microstructure import analyse_run
    except ImportError as err:
        return {"error": f"analysis.microstructure unavailable: {err}"}
    try:
        res = analyse_run(run_file, snapshots=snapshots, **kw)
        js = res.to_json()
    except Exception as err:  # recorded in the report; other runs go on
        return {"error": f"{type(err).__name__}: {err}"}
    return {"snapshots_analysed": snapshots, "table": _micro_rows(js), "result": js}


def _read_json(path: Path):
    import json

    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


# ---------------------------------------------------------------------- plots
def plot_micro_table(tables: dict[str, list[dict]], path: Path) -> Path:
    """Porosity, tortuosity and D_eff against depth for several runs (Fig. 13 b-d) from the
    microstructure table rows (primary resolution; open markers: extrapolated)."""
    import matplotlib.pyplot as plt

    from analysis.plots import save_figure

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    panels = (("porosity", "voxel porosity [%]", 100.0), ("tortuosity", "tortuosity [-]", 1.0),
              ("D_eff", "relative D_eff [-]", 1.0))
    for k, (name, rows) in enumerate(tables.items()):
        d = np.array([np.nan if r["depth_m"] is None else r["depth_m"] for r in rows]) * 1e6
        for ax, (key, label, f) in zip(axes, panels, strict=True):
            y = np.array([np.nan if r.get(key) is None else r[key] for r in rows], float)
            ax.plot(d, y * f, "o-", color=f"C{k}", label=name)
            ex = np.array([np.nan if (r.get("extrapolated") or {}).get(
                "voxel_porosity" if key == "porosity" else key) is None else
                r["extrapolated"]["voxel_porosity" if key == "porosity" else key]
                for r in rows], float)
            if np.isfinite(ex).any():
                ax.plot(d, ex * f, "o:", mfc="none", color=f"C{k}")
            ax.set_xlabel("calendering depth [um]")
            ax.set_ylabel(label)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_pressure(curves: dict[str, dict], path: Path, title: str) -> Path:
    """Pressure-depth curves of several runs (um / MPa)."""
    import matplotlib.pyplot as plt

    from analysis.plots import save_figure

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for name, c in curves.items():
        ax.plot(np.asarray(c["depth"]) * 1e6, np.asarray(c["pressure"]) * 1e-6, lw=1.2,
                label=name)
    ax.set_xlabel("calendering depth [um]")
    ax.set_ylabel("pressure [MPa]")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_psd(diams: dict[str, np.ndarray], path: Path, title: str) -> Path:
    """AM diameter distributions at the start of several runs (Fig. 12 a/c)."""
    import matplotlib.pyplot as plt

    from analysis.plots import save_figure

    fig, ax = plt.subplots(figsize=(5.5, 4))
    allv = np.concatenate([v for v in diams.values() if len(v)]) * 1e6
    bins = np.linspace(allv.min(), allv.max(), 16) if len(allv) else 10
    for name, v in diams.items():
        ax.hist(np.asarray(v) * 1e6, bins=bins, density=True, histtype="step", lw=1.3,
                label=f"{name} ({len(v)})")
    ax.set_xlabel("AM diameter [um]")
    ax.set_ylabel("probability density [1/um]")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


# ---------------------------------------------------------------------- study
def compare(out_dir: str | Path, preset: str = "quick", studies: Sequence[str] = STUDIES,
            seed: int = 0, extra_sets: Sequence[str] = (), jobs: int = 1,
            micro: bool = True, micro_kw: dict | None = None, timeout: float | None = None,
            progress: bool = True, initial: str = "all", run: bool = True) -> dict:
    """Run (or resume) the studies and write ``compare.json`` and PNGs into ``out_dir``.

    Args:
        out_dir: output folder (run files under ``runs/``).
        preset: ``calendaring`` preset of every run.
        studies: subset of :data:`STUDIES`.
        seed: the one seed of every run (same packing for R0 and R1).
        extra_sets: ``KEY=VALUE`` overrides applied to every run (e.g. a shorter stroke).
        jobs: runs at the same time (each a subprocess).
        micro: analyse the microstructure at the snapshots nearest 0 and 19.5 um.
        micro_kw: keyword arguments of ``analyse_run`` (device, voxels_per_diameter, ...).
        timeout: seconds allowed per run (None: no limit).
        initial: whose snapshot nearest 0 um is analysed too: ``"all"`` the runs',
            ``"R1"`` the baseline's only (R0 starts from R1's packing; the paper's claims
            are about the final state), ``"none"``. At the representative volume a
            snapshot costs minutes, so this halves the study.
        run: False reports only what is on disk (kept records with their analyses, or run
            files whose analysis is cached): no DEM run and no microstructure solve; a case
            without both is listed under ``missing``.

    Returns:
        The report (also in ``compare.json``): ``runs`` (status of each), ``failures``,
        per study the run summaries, the R0/R1 divergence, the PSD table and the
        microstructure tables.
    """
    from analysis.plots import atomic_write_json
    from calendaring import read_run

    if int(jobs) < 1:
        raise ConfigError("--jobs", jobs, "an integer >= 1")
    if initial not in INITIAL_CHOICES:
        raise ConfigError("--initial-transport", initial, f"one of {INITIAL_CHOICES}")
    for s in extra_sets:
        if "=" not in str(s):
            raise ConfigError("--set", s, "the form KEY=VALUE")
    cases = plan(studies, preset, extra_sets)
    _check_overrides(preset, extra_sets)
    out_dir = Path(out_dir)
    runs_dir = out_dir / "runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    lock = threading.Lock()
    t0 = time.perf_counter()
    if progress:
        print(f"compare: {len(cases)} runs ({', '.join(c.name for c in cases)}), preset "
              f"{preset}, seed {seed}, {jobs} at a time", file=sys.stderr, flush=True)
    mk = dict(micro_kw or {})
    mk.setdefault("device", "cpu")
    # in the cache key: a cache of the former two-point default is not reused
    mk.setdefault("resolution", "converge")
    mk.pop("progress", None)

    def micro_key(name, view):
        snaps = view["targets"]
        if initial == "none" or (initial == "R1" and name != "R1"):
            snaps = snaps[1:] or snaps  # the final one (a run of one snapshot keeps it)
        return {"snapshots": snaps, "settings": {k: mk[k] for k in sorted(mk)},
                "run_config_hash": view["config_hash"], "created": view["created"]}

    def cached_micro(name, view):
        old = _read_json(runs_dir / f"{name}.microstructure.json")
        if old is not None and old.get("key") == micro_key(name, view) \
                and "error" not in old["value"]:
            return {**old["value"], "cached": True}
        return None

    def go(case):
        out = runs_dir / f"{case.name}.h5"
        key = case_key(case, preset, seed, extra_sets)
        view = st = val = None
        if not (out.exists() and _readable(out)):
            kept = read_case_record(runs_dir / f"{case.name}.record.h5", key)
            if kept is not None and micro:
                val = cached_micro(case.name, kept)
            if kept is not None and (not micro or val is not None):
                view, st = kept, {"name": case.name, "status": "kept",
                                  "file": str(runs_dir / f"{case.name}.record.h5")}
        if st is None and not run:  # only what is on disk: no DEM run, no new analysis
            if out.exists() and _readable(out):
                v = run_view(read_run(out))
                c = cached_micro(case.name, v) if micro else None
                if not micro or c is not None:
                    view, val = v, c
                    st = {"name": case.name, "status": "exists", "file": str(out)}
            if st is None:
                return {"name": case.name, "status": "missing"}, None, None
        if st is None:
            st = execute(case, out, preset, seed, extra_sets, timeout, progress, lock)
        if progress:
            with lock:
                print(f"compare: {case.name} {st['status']} "
                      f"({time.perf_counter() - t0:.0f} s elapsed)", file=sys.stderr,
                      flush=True)
        if st["status"] == "failed":
            return st, None, None
        if view is None:
            view = run_view(read_run(st["file"]))
            have = read_case_record(runs_dir / f"{case.name}.record.h5", key)
            if have is None or have["created"] != view["created"]:  # kept files stay put
                write_case_record(runs_dir / f"{case.name}.record.h5", view, key)
        if not micro:
            return st, view, None
        if val is None:
            val = cached_micro(case.name, view)
        if val is None:
            mkey = micro_key(case.name, view)
            if progress:
                with lock:
                    print(f"compare: microstructure of {case.name} at snapshots "
                          f"{mkey['snapshots']}", file=sys.stderr, flush=True)
            val = microstructure(Path(view["path"]), mkey["snapshots"], progress=progress,
                                 **mk)
            if "error" not in val:
                atomic_write_json(runs_dir / f"{case.name}.microstructure.json",
                                  {"key": mkey, "value": val})
        return st, view, val

    with ThreadPoolExecutor(max_workers=int(jobs)) as pool:
        results = list(pool.map(go, cases))
    statuses = [st for st, _, _ in results]
    ok = {st["name"]: view for st, view, _ in results if view is not None}
    report = {"preset": preset, "seed": seed, "studies": list(studies), "initial": initial,
              "extra_sets": list(extra_sets),
              "units": "SI (m, Pa, N); tortuosity, D_eff (relative) and porosity dimensionless",
              "runs": [{**st, "description": c.description, "studies": c.studies,
                        "sets": c.sets, "no_breakage": c.no_breakage}
                       for st, c in zip(statuses, cases, strict=True)],
              "failures": [st for st in statuses if st["status"] == "failed"],
              "missing": [st["name"] for st in statuses if st["status"] == "missing"],
              "summaries": {n: v["summary"] for n, v in ok.items()}}
    figures = []
    if micro:
        report["microstructure"] = {st["name"]: val for st, view, val in results
                                    if view is not None}
        have = {n: v["table"] for n, v in report["microstructure"].items() if v.get("table")}
        if have:
            figures.append(plot_micro_table(have, out_dir / "fig13bcd_microstructure.png"))

    if "r0r1" in studies and "R0" in ok and "R1" in ok:
        r0, r1 = ok["R0"], ok["R1"]
        div = _first_divergence(r1["pressure"], r0["pressure"])
        s1 = report["summaries"]["R1"]
        div["first_breakage_depth_m"] = s1["first_breakage_depth_m"]
        div["final_pressure_ratio_R1_over_R0"] = (
            s1["final_pressure_Pa"] / report["summaries"]["R0"]["final_pressure_Pa"]
            if report["summaries"]["R0"]["final_pressure_Pa"] else None)
        div["same_initial_packing"] = bool(r0["packing_sha256"] is not None
                                           and r0["packing_sha256"] == r1["packing_sha256"])
        report["r0r1"] = div
        figures.append(plot_pressure(
            {"R0 (no breakage)": _raw(r0), "R1 (breakage)": _raw(r1)},
            out_dir / "r0r1_pressure.png", f"R0 vs R1, preset {preset}, seed {seed}"))
    if "psd" in studies:
        table = {}
        for name in ("R1", *PSD_CASES):
            t = TABLE5[name]
            row = {"table5": dict(zip(("mean_m", "std_m", "D10_m", "D50_m", "D90_m"), t,
                                      strict=True))}
            if name in ok:
                row["realised"] = report["summaries"][name]["am_diameter_at_start"]
            table[name] = row
        report["psd"] = table
        groups = [("fig12b_psd_std_pressure.png", "R1, C1-C4: AM size spread (Fig. 12b)",
                   ("R1", "C1", "C2", "C3", "C4")),
                  ("fig12d_psd_mean_pressure.png", "R1, R4, R5: AM mean size (Fig. 12d)",
                   ("R1", "R4", "R5"))]
        for fname, title, names in groups:
            have = [n for n in names if n in ok]
            if have:
                figures.append(plot_pressure({n: _raw(ok[n]) for n in have}, out_dir / fname,
                                             title))
                figures.append(plot_psd({n: _am_diameters(ok[n]) for n in have},
                                        out_dir / fname.replace("pressure", "distribution")
                                        .replace("12b", "12a").replace("12d", "12c"),
                                        title.replace("(Fig. 12b)", "(Fig. 12a)")
                                        .replace("(Fig. 12d)", "(Fig. 12c)")))
    fig13 = [n for n in ("R0", "R1", "R4", "R5") if n in ok]
    if len(fig13) > 1:
        figures.append(plot_pressure({n: _raw(ok[n]) for n in fig13},
                                     out_dir / "fig13a_pressure.png",
                                     "Pressure-depth curves (Fig. 13a)"))
    report["figures"] = [p.name for p in figures]
    report["wall_time_s"] = time.perf_counter() - t0
    atomic_write_json(out_dir / "compare.json", report)
    if progress:
        print(f"compare: wrote {out_dir / 'compare.json'} ({len(report['failures'])} "
              f"failed runs)", file=sys.stderr, flush=True)
    return report


# ---------------------------------------------------------------------- seeds
PAPER_FINAL = {
    # name: (tortuosity, relative D_eff) at 19.5 um, paper section 3.5 (Fig. 13)
    "R0": (2.2846, 0.1033), "R1": (1.8976, 0.1590), "R4": (1.8996, 0.1664),
    "R5": (1.8728, 0.1760)}
"""The paper's tortuosity and D_eff at the final depth [-] (its one run per case)."""
CLAIMS = (
    # (claim, case, baseline, metric, the paper's sign of case - baseline)
    ("breakage lowers tortuosity at 19.5 um", "R1", "R0", "tortuosity", -1),
    ("breakage raises D_eff at 19.5 um", "R1", "R0", "D_eff", +1),
    ("larger particles (R4) lower tortuosity at 19.5 um", "R4", "R1", "tortuosity", -1),
    ("larger particles (R4) raise D_eff at 19.5 um", "R4", "R1", "D_eff", +1),
    ("larger particles (R5) lower tortuosity at 19.5 um", "R5", "R1", "tortuosity", -1),
    ("larger particles (R5) raise D_eff at 19.5 um", "R5", "R1", "D_eff", +1),
)
SEED_METRICS = ("final_pressure_Pa", "peak_pressure_Pa", "breakage_events")
MICRO_METRICS = ("porosity", "tortuosity", "D_eff")


def _stats(values) -> dict:
    """Mean, sample standard deviation (ddof 1), standard error and a two-sided 95 %
    Student-t interval of the mean over seeds (None where fewer than two values)."""
    from scipy import stats

    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], float)
    out = {"n": len(v), "values": v.tolist(), "mean": float(v.mean()) if len(v) else None}
    if len(v) >= 2:
        sd = float(v.std(ddof=1))
        se = sd / np.sqrt(len(v))
        h = float(stats.t.ppf(0.975, len(v) - 1)) * se
        out.update(sd=sd, se=se, ci95=[out["mean"] - h, out["mean"] + h])
    else:
        out.update(sd=None, se=None, ci95=None)
    return out


def seed_metrics(report: dict) -> dict[str, dict[str, float | None]]:
    """Per case of one seed's report: pressure, events, and porosity / tortuosity / D_eff
    at the first and the last analysed depth (``initial_*``, ``final_*``; ``initial_*``
    None when only one depth was analysed)."""
    out = {}
    for name, s in (report.get("summaries") or {}).items():
        row = {k: s.get(k) for k in SEED_METRICS}
        table = ((report.get("microstructure") or {}).get(name) or {}).get("table") or []
        rows = sorted((r for r in table if r.get("depth_m") is not None),
                      key=lambda r: r["depth_m"])
        for tag, r in (("initial", rows[0] if len(rows) >= 2 else None),
                       ("final", rows[-1] if rows else None)):
            for k in MICRO_METRICS:
                row[f"{tag}_{k}"] = None if r is None else r.get(k)
        out[name] = row
    return out


def final_levels(report: dict, case: str) -> tuple[dict[float, dict], float | None]:
    """The refinement levels of a case's deepest analysed snapshot in one seed's report,
    ``{voxels per diameter (2 decimals): {"tortuosity", "D_eff"}}``, and the refinement's
    tolerance; no levels when the analysis kept none (``--resolution two-point``, an error
    record)."""
    res = ((report.get("microstructure") or {}).get(case) or {}).get("result") or {}
    snaps = [s for s in res.get("snapshots") or []
             if isinstance(s, dict) and s.get("depth_m") is not None]
    if not snaps:
        return {}, None
    ref = max(snaps, key=lambda s: s["depth_m"]).get("refinement") or {}
    tol = ref.get("refine_tol", (res.get("settings") or {}).get("refine_tol"))
    return ({round(float(lv["voxels_per_diameter"]), 2):
             {"tortuosity": lv.get("tortuosity"), "D_eff": lv.get("D_eff")}
             for lv in ref.get("levels") or [] if lv.get("voxels_per_diameter")}, tol)


def resolution_check(reports: dict[int, dict], case: str, base: str, metric: str) -> dict | None:
    """How the relative difference ``case / base - 1`` of a final-depth metric moves with the
    voxel size: per refinement level that every seed analysing both cases analysed for
    both (a seed without them, e.g. one not run yet, is left out), the seeds' mean of the
    paired relative difference; its change between the two finest levels (``last_change``)
    and of the ratio ``case / base`` (``ratio_change``); from three levels whose changes
    shrink with one sign, their Richardson limit (``extrapolated``,
    :func:`analysis.microstructure._richardson`, as for tau). ``remaining`` is what
    resolution may still change: the distance to that limit, the last change when only two
    levels exist, None when the changes do not shrink. ``converged`` when the remaining
    change of the ratio is below the refinement's own tolerance (the criterion tau itself is
    held to), and ``below_seed_scatter`` when the last change is smaller than the half-width
    of the seeds' 95 % interval of the relative difference at the finest level. A difference
    can converge long before either value does: the resolution error of a compressed bed is
    local and nearly the same factor in both cases (benchmarks/README, the converged
    microstructure of one 100 um snapshot). None when fewer than two common levels."""
    from analysis.microstructure import _richardson

    per_seed, tols = [], []
    for s in sorted(reports):
        (a, ta), (b, tb) = final_levels(reports[s], case), final_levels(reports[s], base)
        if not (a and b):  # a seed without both analyses (not run yet): not in the check
            continue
        per_seed.append({v: a[v][metric] / b[v][metric] - 1 for v in a.keys() & b.keys()
                         if a[v].get(metric) and b[v].get(metric)})
        tols += [t for t in (ta, tb) if t is not None]
    common = sorted(set.intersection(*(set(p) for p in per_seed))) if per_seed else []
    if len(common) < 2:
        return None
    rel = {v: [p[v] for p in per_seed] for v in common}
    mean = [float(np.mean(rel[v])) for v in common]
    ratio_change = abs((1 + mean[-1]) / (1 + mean[-2]) - 1)
    tol = min(tols) if tols else 0.02
    # what resolution may still change: the Richardson limit when three levels show the
    # changes shrinking with one sign (none left when the last step changed nothing), the
    # last change from two levels, unknown (not converged) when the changes do not shrink
    extrapolated, remaining = None, abs(mean[-1] - mean[-2])
    if len(mean) >= 3 and remaining > 0:
        extrapolated = _richardson(mean, [1.0 / v for v in common])["tortuosity_richardson"]
        remaining = None if extrapolated is None else abs(extrapolated - mean[-1])
    elif len(mean) >= 3:
        extrapolated = mean[-1]
    finest = _stats(rel[common[-1]])
    half = None if finest["ci95"] is None else (finest["ci95"][1] - finest["ci95"][0]) / 2
    converged = remaining is not None and remaining / (1 + mean[-1]) < tol
    return {"voxels_per_diameter": common, "relative_difference": mean,
            "last_change": mean[-1] - mean[-2], "extrapolated": extrapolated,
            "remaining": remaining, "ratio_change": ratio_change,
            "tolerance": tol, "converged": bool(converged),
            "seed_ci95_half_width": half,
            "below_seed_scatter": None if half is None else bool(abs(mean[-1] - mean[-2]) < half)}


def pool_seeds(reports: dict[int, dict]) -> dict:
    """Seed statistics of several :func:`compare` reports (one per seed, same studies):
    per case and metric the mean, sd and 95 % interval over seeds; per case against its
    baseline (R1, and R1 against R0) the paired differences by seed (same seed: R0 and R1
    share their packing) with their interval and the relative change; and each claim of
    the paper (:data:`CLAIMS`) as ``holds`` (the 95 % interval of the difference excludes 0
    on the paper's side), ``opposite`` (it excludes 0 on the other side) or ``not
    resolved``, next to the paper's own change and the difference's dependence on the voxel
    size (:func:`resolution_check`)."""
    per_seed = {int(k): seed_metrics(r) for k, r in reports.items()}
    cases = sorted({c for m in per_seed.values() for c in m})
    metrics = sorted({k for m in per_seed.values() for row in m.values() for k in row})
    cases_out = {c: {k: _stats([per_seed[s].get(c, {}).get(k) for s in sorted(per_seed)])
                     for k in metrics} for c in cases}
    diffs = {}
    for c in cases:
        base = "R0" if c == "R1" else "R1"
        if c == base or base not in cases:
            continue
        d = {}
        for k in metrics:
            pairs = [(per_seed[s][c].get(k), per_seed[s][base].get(k)) for s in sorted(per_seed)
                     if c in per_seed[s] and base in per_seed[s]]
            pairs = [(a, b) for a, b in pairs if a is not None and b is not None]
            st = _stats([a - b for a, b in pairs])
            mb = float(np.mean([b for _, b in pairs])) if pairs else None
            st["relative"] = st["mean"] / mb if pairs and mb else None
            d[k] = st
        diffs[f"{c}-{base}"] = d
    claims = []
    for text, c, base, metric, sign in CLAIMS:
        key = f"{c}-{base}"
        st = diffs.get(key, {}).get(f"final_{metric}")
        paper = None
        if c in PAPER_FINAL and base in PAPER_FINAL:
            j = 0 if metric == "tortuosity" else 1
            paper = PAPER_FINAL[c][j] / PAPER_FINAL[base][j] - 1
        if st is None or st["n"] == 0:
            verdict = "not measured"
        elif st["ci95"] is None:
            verdict = "one seed: not resolved"
        elif min(sign * st["ci95"][0], sign * st["ci95"][1]) > 0:
            verdict = "holds"
        elif max(sign * st["ci95"][0], sign * st["ci95"][1]) < 0:
            verdict = "opposite"
        else:
            verdict = "not resolved (the 95 % interval holds 0)"
        claims.append({"claim": text, "difference": key, "metric": f"final_{metric}",
                       "verdict": verdict, "relative_change": None if st is None else
                       st.get("relative"), "paper_relative_change": paper,
                       "difference_stats": st,
                       "resolution": resolution_check(reports, c, base, metric)})
    return {"seeds": sorted(per_seed), "per_seed": per_seed, "cases": cases_out,
            "differences": diffs, "claims": claims,
            "paper_final": {k: {"tortuosity": v[0], "D_eff": v[1]}
                            for k, v in PAPER_FINAL.items()},
            "notes": "sd: sample standard deviation over seeds (ddof 1); ci95: two-sided "
                     "Student-t interval of the mean; differences are paired by seed"}


def compare_seeds(out_dir: str | Path, seeds: Sequence[int], **kw) -> dict:
    """:func:`compare` once per seed (``out_dir/seed-<s>/``, each resumable), then
    :func:`pool_seeds` into ``out_dir/seeds.json`` and a figure of the final tortuosity and
    D_eff per case (mean and sd over seeds, the paper's values as crosses)."""
    from analysis.plots import atomic_write_json

    seeds = [int(x) for x in seeds]
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise ConfigError("--seeds", seeds, "distinct seeds >= 0")
    out_dir = Path(out_dir)
    reports = {s: compare(out_dir / f"seed-{s}", seed=s, **kw) for s in seeds}
    pooled = pool_seeds(reports)
    pooled["failures"] = {s: r["failures"] for s, r in reports.items() if r["failures"]}
    pooled["missing"] = {s: r["missing"] for s, r in reports.items() if r.get("missing")}
    pooled["figure"] = str(plot_seeds(pooled, out_dir / "seeds_final_transport.png"))
    atomic_write_json(out_dir / "seeds.json", pooled)
    return pooled


def plot_seeds(pooled: dict, path: Path) -> Path:
    """Final tortuosity and D_eff per case: mean with sd bars over seeds, each seed a dot,
    the paper's value a cross."""
    import matplotlib.pyplot as plt

    from analysis.plots import save_figure

    cases = [c for c in ("R0", "R1", "C1", "C2", "C3", "C4", "R4", "R5")
             if c in pooled["cases"]]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, metric, j in ((axes[0], "tortuosity", 0), (axes[1], "D_eff", 1)):
        for x, c in enumerate(cases):
            st = pooled["cases"][c][f"final_{metric}"]
            if st["n"]:
                ax.plot([x] * st["n"], st["values"], ".", color="0.6")
                ax.errorbar(x, st["mean"], yerr=st["sd"] or 0, fmt="o", color="C0",
                            capsize=3)
            if c in PAPER_FINAL:
                ax.plot(x, PAPER_FINAL[c][j], "x", color="C3", ms=8)
        ax.set_xticks(range(len(cases)), cases)
        ax.set_ylabel(f"{metric} at the final depth [-]")
    axes[0].set_title(f"mean +- sd over seeds {pooled['seeds']} (x: the paper)", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


def _raw(view) -> dict:
    return {"depth": view["pressure"]["depth"], "pressure": view["pressure"]["value"]}


def _am_diameters(view) -> np.ndarray:
    return view["am_diameters"]


__all__ = ["CLAIMS", "INITIAL_CHOICES", "PAPER_FINAL", "PSD_CASES", "STUDIES", "TABLE5", "Case",
           "case_key", "compare", "compare_seeds", "execute", "final_levels", "plan",
           "plot_seeds", "pool_seeds", "read_case_record", "resolution_check", "run_command",
           "run_summary", "run_view", "seed_metrics", "target_snapshots", "truncation_sigmas",
           "write_case_record"]
