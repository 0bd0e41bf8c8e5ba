"""HDF5 run files: the one schema, its writer and its reader (host-only; no Taichi).

Other packages and users read runs only through :func:`read_run`, which returns a typed
:class:`RunRecord` and rejects corrupt, truncated or foreign files with :class:`RunFileError`.
Every dataset carries a ``unit`` attribute (SI; ``"1"`` for counts and ratios) and a
``description``. Schema version 2:

Root attributes: ``format`` = "calendaring-run", ``schema_version``, ``software_version``,
``source_commit`` (the git commit of the code that ran it, ``+dirty`` with local changes,
empty outside a checkout; optional: files written before it lack it), ``config``
(canonical JSON of the full configuration), ``config_hash``, ``seed``, ``preset``,
``created`` (UTC ISO 8601), ``cell_x``, ``cell_y``, ``thickness``, ``stroke`` (m),
``breakage_model`` (``"tavares_ufrj"`` or ``"none"`` for the no-breakage control),
``info`` (JSON: build report, time steps, plate speed, bond count, pool capacity, breakage
event count, springback, wall time; ``stages``: wall seconds and steps of each stage).

=============================  ======  ==================================================
dataset                        unit    content
=============================  ======  ==================================================
pressure/step                  1       time step of the sample (end of its block)
pressure/time                  s       time since the start of calendering
pressure/depth                 m       calendering displacement from h0 (increasing)
pressure/value                 Pa      top-plate pressure (normal force / cell area)
pressure/bottom                Pa      bottom-plate pressure
unloading/depth, value, bottom m, Pa   the same while the plate lifts (empty if no unload)
series/<name>                  see     one row per ``output.record_spacing`` of travel:
                               SERIES  step, time, depth, top/bottom pressure (means over
                                       the row's steps), porosity, coordination, largest
                                       overlap ratio, inertial number, bond counts, live
                                       particles, breakage events so far
energy/<term>                  J       energy ledger at the series rows (``breakage``: stored
                                       energy removed by particle replacements)
breakage/parent_id             1       one row per breakage event: id of the broken particle
breakage/diameter              m       its diameter
breakage/peak_load             N       the largest total contact normal force (sum over its
                                       contacts of |F_n|, paper Fig. 7) it sustained over its
                                       life before breaking
breakage/stressing_energy      J/kg    specific stressing energy E_k at breakage
breakage/fracture_energy       J/kg    its (damaged) fracture energy E'_f at breakage
breakage/e50                   J/kg    median fracture energy E50 at its size (Eq. 33)
breakage/t10                   1       breakage index t10 (fraction, Eq. 39)
breakage/n_fragments           1       fragments that replaced it
breakage/first_fragment_id     1       their ids are first_fragment_id + 0 .. n - 1
breakage/step, time, depth     1, s, m step, time since calendering began, plate depth
breakage/fragments/id          1       one row per fragment: its id
breakage/fragments/diameter    m       its diameter
breakage/fragments/event       1       its event row in breakage/
snapshots/<k>/position         m       particle centres (n, 3)
snapshots/<k>/radius           m
snapshots/<k>/material         1       0 = AM, 1 = CB (index into the config materials)
snapshots/<k>/id               1       stable particle id
snapshots/<k>/velocity         m/s
snapshots/<k>/normal_force     N       total contact normal force on the particle
snapshots/<k>/n_contacts       1       touching contacts (particles and plates)
snapshots/<k>/parent_id        1       id of the particle it broke from (-1: original)
snapshots/<k>/fracture_energy  J/kg    current (damaged) fracture energy (0 if unbreakable)
snapshots/<k>/peak_load        N       largest total contact normal force so far
snapshots/<k>/bonds/*          -       id_a, id_b (1), state (1: 0 intact, 1 failed in
                                       tension, 2 failed in shear, 3 removed), normal_force
                                       (N, compression positive), radius (m)
=============================  ======  ==================================================

Each ``snapshots/<k>`` group has attributes ``depth`` (m), ``step``, ``time`` (s), ``z_top``,
``z_bottom`` (m), ``top_pressure`` (Pa) and ``label``; ``k`` = 0, 1, ... in depth order.

Checkpoints (``format`` = "calendaring-checkpoint") use a generic tree layout private to
:mod:`calendaring.process.run`.

See also: :mod:`calendaring.data.digest` (the ~30 kB digest of a finished run),
:mod:`calendaring.process.plots` (figures of a run record), :mod:`calendaring.data.dataset`.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from calendaring._version import __version__, source_commit
from calendaring.core.config import (
    SimConfig,
    config_hash,
    config_json,
    config_text_hash,
    load_config_dict,
)
from calendaring.core.fileio import write_h5

FORMAT = "calendaring-run"
CHECKPOINT_FORMAT = "calendaring-checkpoint"
SCHEMA_VERSION = 2

SERIES_UNITS = {"step": "1", "time": "s", "depth": "m", "top_pressure": "Pa",
                "bottom_pressure": "Pa", "porosity": "1", "coordination": "1",
                "max_overlap_ratio": "1", "inertial_number": "1", "bonds_intact": "1",
                "bonds_failed_normal": "1", "bonds_failed_shear": "1", "bonds_removed": "1",
                "particles": "1", "breakage_events": "1"}
SERIES_DESCRIPTIONS = {
    "step": "time step at the end of the row", "time": "time since calendering started",
    "depth": "calendering displacement from h0", "top_pressure": "mean top-plate pressure",
    "bottom_pressure": "mean bottom-plate pressure",
    "porosity": "1 - sphere volume / (cell area x plate gap)",
    "coordination": "2 x touching particle pairs / particles",
    "max_overlap_ratio": "largest overlap / smaller radius",
    "inertial_number": "(v/h) d sqrt(rho/P), NaN while P = 0",
    "bonds_intact": "intact bonds", "bonds_failed_normal": "bonds failed in tension",
    "bonds_failed_shear": "bonds failed in shear",
    "bonds_removed": "bonds removed with a broken particle",
    "particles": "live particles (originals and fragments)",
    "breakage_events": "breakage events since calendering began"}
PRESSURE = {"step": ("1", "time step of the sample"),
            "time": ("s", "time since the start of calendering"),
            "depth": ("m", "calendering displacement from h0 (increasing)"),
            "value": ("Pa", "top-plate pressure"), "bottom": ("Pa", "bottom-plate pressure")}
UNLOADING = {k: PRESSURE[k] for k in ("depth", "value", "bottom")}
SNAPSHOT = {"position": ("m", "particle centres"), "radius": ("m", "particle radii"),
            "material": ("1", "material index: 0 = AM, 1 = CB"),
            "id": ("1", "stable particle id"), "velocity": ("m/s", "particle velocities"),
            "normal_force": ("N", "total contact normal force on the particle"),
            "n_contacts": ("1", "touching contacts (particles and plates)"),
            "parent_id": ("1", "id of the particle it broke from (-1 for originals)"),
            "fracture_energy": ("J/kg", "current (damaged) fracture energy"),
            "peak_load": ("N", "largest total contact normal force so far")}
BREAKAGE = {
    "parent_id": ("1", "id of the broken particle"),
    "diameter": ("m", "diameter of the broken particle"),
    "peak_load": ("N", "largest total contact normal force (sum over contacts of |F_n|) the "
                       "particle sustained over its life before breaking"),
    "stressing_energy": ("J/kg", "specific stressing energy E_k at breakage"),
    "fracture_energy": ("J/kg", "damaged fracture energy E'_f at breakage"),
    "e50": ("J/kg", "median fracture energy E50 at the parent size (Eq. 33)"),
    "t10": ("1", "breakage index t10 as a fraction (Eq. 39)"),
    "n_fragments": ("1", "number of fragments"),
    "first_fragment_id": ("1", "fragment ids are first_fragment_id + 0 .. n_fragments - 1"),
    "step": ("1", "time step of the breakage"),
    "time": ("s", "time since calendering began"),
    "depth": ("m", "calendering displacement from h0 at breakage")}
FRAGMENTS = {"id": ("1", "fragment id"), "diameter": ("m", "fragment diameter"),
             "event": ("1", "row of the breakage event in breakage/")}
BONDS = {"id_a": ("1", "id of the first particle"), "id_b": ("1", "id of the second particle"),
         "state": ("1", "0 intact, 1 failed in tension, 2 failed in shear, 3 removed"),
         "normal_force": ("N", "bond normal force, compression positive"),
         "radius": ("m", "bond disk radius")}
SNAPSHOT_ATTRS = ("depth", "step", "time", "z_top", "z_bottom", "top_pressure", "label")


class RunFileError(ValueError):
    """A run or checkpoint file that cannot be used (names the file and the reason)."""

    def __init__(self, path: str | Path, reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{path}: {reason}")


@dataclass
class RunState:
    """Host-side progress of a run (saved in checkpoints)."""

    stage: int = 0  # index into run.STAGES
    stage_step: int = 0  # steps done in the current stage
    stage_steps: int = 0  # steps of the current stage (an upper bound if it may stop early)
    params: dict = field(default_factory=dict)  # per-stage numbers fixed on entry
    info: dict = field(default_factory=dict)  # build report, dt, speeds, counts ...
    series: list = field(default_factory=list)  # rows of run.SERIES
    energy: list = field(default_factory=list)  # rows of energy terms (same rows as series)
    energy_keys: list = field(default_factory=list)
    trace: list = field(default_factory=list)  # per-step (step, z_top, f_bottom, f_top) blocks
    unload_trace: list = field(default_factory=list)
    snapshots: list = field(default_factory=list)  # dicts of arrays + attrs
    breakage: list = field(default_factory=list)  # rows of run.BREAKAGE_COLUMNS
    fragment_diameters: list = field(default_factory=list)  # per event row, [m]
    next_snapshot: int = 0
    wall: float = 0.0  # wall seconds spent so far (over resumes)


# ---------------------------------------------------------------------- writing

def _dataset(g: h5py.Group, name: str, data, unit: str, description: str) -> None:
    arr = np.asarray(data)
    kwargs = {"compression": "gzip", "compression_opts": 4} if arr.size > 4096 else {}
    ds = g.create_dataset(name, data=arr, **kwargs)
    ds.attrs["unit"] = unit
    ds.attrs["description"] = description


def _json(value: Any) -> str:
    return json.dumps(value, sort_keys=True, default=_json_default)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


def write_run(path: str | Path, data: dict) -> Path:
    """Write a run file atomically (temporary name, then rename). ``data`` keys: config
    (SimConfig), preset, seed, info (dict), pressure, unloading, series, energy (dicts of
    arrays), snapshots (list of {"data", "attrs", "bonds"})."""
    cfg: SimConfig = data["config"]

    def fill(f: h5py.File) -> None:
        a = f.attrs
        a["format"] = FORMAT
        a["schema_version"] = SCHEMA_VERSION
        a["software_version"] = __version__
        a["source_commit"] = source_commit()
        a["config"] = config_json(cfg)
        a["config_hash"] = config_hash(cfg)
        a["seed"] = int(data["seed"])
        a["preset"] = data.get("preset", "")
        a["created"] = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
        a["cell_x"] = cfg.domain.cell_x
        a["cell_y"] = cfg.domain.cell_y
        a["thickness"] = cfg.electrode.thickness
        a["stroke"] = cfg.protocol.stroke
        a["breakage_model"] = data["breakage_model"]
        a["info"] = _json(data["info"])
        for group, spec in (("pressure", PRESSURE), ("unloading", UNLOADING)):
            g = f.create_group(group)
            for k, (unit, desc) in spec.items():
                _dataset(g, k, np.asarray(data[group][k], float if k != "step" else np.int64),
                         unit, desc)
        g = f.create_group("series")
        for k, unit in SERIES_UNITS.items():
            _dataset(g, k, data["series"][k], unit, SERIES_DESCRIPTIONS[k])
        g = f.create_group("breakage")
        for k, (unit, desc) in BREAKAGE.items():
            _dataset(g, k, data["breakage"][k], unit, desc)
        fr = g.create_group("fragments")
        for k, (unit, desc) in FRAGMENTS.items():
            _dataset(fr, k, data["breakage"]["fragments"][k], unit, desc)
        g = f.create_group("energy")
        for k, v in data["energy"].items():
            _dataset(g, k, v, "J", f"energy ledger term {k}")
        g = f.create_group("snapshots")
        for k, snap in enumerate(data["snapshots"]):
            s = g.create_group(str(k))
            for name, (unit, desc) in SNAPSHOT.items():
                _dataset(s, name, snap["data"][name], unit, desc)
            for name in SNAPSHOT_ATTRS:
                s.attrs[name] = snap["attrs"][name]
            if snap.get("bonds") is not None:
                b = s.create_group("bonds")
                for name, (unit, desc) in BONDS.items():
                    _dataset(b, name, snap["bonds"][name], unit, desc)

    return write_h5(Path(path), fill)


# ---------------------------------------------------------------------- reading
@dataclass(frozen=True)
class Snapshot:
    """Particle state at one calendering depth (SI)."""

    index: int
    label: str
    depth: float  # [m]
    step: int
    time: float  # [s]
    z_top: float  # [m]
    z_bottom: float  # [m]
    top_pressure: float  # [Pa]
    position: np.ndarray  # (n, 3) [m]
    radius: np.ndarray  # [m]
    material: np.ndarray
    id: np.ndarray
    velocity: np.ndarray  # [m/s]
    normal_force: np.ndarray  # [N]
    n_contacts: np.ndarray
    parent_id: np.ndarray
    fracture_energy: np.ndarray  # [J/kg]
    peak_load: np.ndarray  # [N]
    bonds: dict | None  # id_a, id_b, state, normal_force [N], radius [m]

    def porosity(self, cell_x: float, cell_y: float) -> float:
        """1 - sphere volume / (cell area x plate gap) [-]."""
        vol = float(np.sum(4.0 / 3.0 * np.pi * self.radius**3))
        return 1.0 - vol / (cell_x * cell_y * (self.z_top - self.z_bottom))


@dataclass(frozen=True)
class RunRecord:
    """A run file, validated and loaded into memory (SI units)."""

    path: Path
    schema_version: int
    software_version: str
    config: SimConfig
    config_json: str
    seed: int
    preset: str
    created: str
    cell_x: float  # [m]
    cell_y: float  # [m]
    thickness: float  # h0 [m]
    stroke: float  # [m]
    breakage_model: str
    info: dict
    pressure: dict[str, np.ndarray]  # step, time [s], depth [m], value [Pa], bottom [Pa]
    unloading: dict[str, np.ndarray]
    series: dict[str, np.ndarray]
    energy: dict[str, np.ndarray]
    snapshots: list[Snapshot]
    breakage: dict[str, np.ndarray]  # BREAKAGE columns, plus "fragments": FRAGMENTS columns
    source_commit: str = ""  # git commit of the code that ran it ("" unrecorded)

    def snapshot_near(self, depth: float) -> Snapshot:
        """The snapshot whose depth is closest to ``depth`` [m]."""
        if not self.snapshots:
            raise LookupError(f"{self.path}: no snapshots")
        return min(self.snapshots, key=lambda s: abs(s.depth - depth))

    def pressure_at(self, depth: float) -> float:
        """Top-plate pressure [Pa] interpolated at a calendering depth [m]."""
        d, p = self.pressure["depth"], self.pressure["value"]
        if len(d) == 0 or depth < d[0] - 1e-12 or depth > d[-1] + 1e-12:
            raise ValueError(f"depth {depth} m outside the recorded range")
        return float(np.interp(depth, d, p))


def _read_group(f: h5py.File, path: Path, group: str, spec: dict) -> dict[str, np.ndarray]:
    """Datasets ``spec`` (name -> unit, or (unit, description)) of ``group``, checked."""
    if group not in f:
        raise RunFileError(path, f"missing group '{group}'")
    out = {}
    lengths = set()
    for name, unit in spec.items():
        unit = unit[0] if isinstance(unit, tuple) else unit
        key = f"{group}/{name}"
        if key not in f:
            raise RunFileError(path, f"missing dataset '{key}'")
        ds = f[key]
        if ds.attrs.get("unit") != unit:
            raise RunFileError(path, f"dataset '{key}' has unit {ds.attrs.get('unit')!r}, "
                                     f"expected {unit!r}")
        try:
            out[name] = ds[()]
        except Exception as err:  # truncated or corrupt chunk
            raise RunFileError(path, f"cannot read '{key}' ({err})") from None
        lengths.add(len(out[name]))
    if len(lengths) > 1:
        raise RunFileError(path, f"datasets of '{group}' have different lengths {sorted(lengths)}")
    return out


def read_run(path: str | Path) -> RunRecord:
    """Open and validate a run file; raises :class:`RunFileError` on anything unexpected."""
    path = Path(path)
    if not path.is_file():
        raise RunFileError(path, "no such file")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise RunFileError(path, f"not a readable HDF5 file (truncated or corrupt?): {err}") \
            from None
    with f:
        a = f.attrs
        if a.get("format") != FORMAT:
            raise RunFileError(path, f"not a calendaring run file (format = "
                                     f"{a.get('format')!r}, expected {FORMAT!r})")
        version = int(a.get("schema_version", -1))
        if version != SCHEMA_VERSION:
            raise RunFileError(path, f"schema_version {version} is not supported "
                                     f"(this reader knows {SCHEMA_VERSION})")
        try:
            cfg = load_config_dict(json.loads(a["config"]))
            info = json.loads(a["info"])
            cfg_text = str(a["config"])
            scalars = {k: a[k] for k in ("seed", "preset", "created", "cell_x", "cell_y",
                                         "thickness", "stroke", "breakage_model",
                                         "software_version", "config_hash")}
            commit = str(a.get("source_commit", ""))  # absent in files written before it
        except Exception as err:
            raise RunFileError(path, f"bad root attributes ({err})") from None
        if config_text_hash(cfg_text) != scalars["config_hash"]:
            raise RunFileError(path, "config does not match config_hash (edited or corrupt)")
        pressure = _read_group(f, path, "pressure", PRESSURE)
        unloading = _read_group(f, path, "unloading", UNLOADING)
        series = _read_group(f, path, "series", SERIES_UNITS)
        breakage = _read_group(f, path, "breakage", BREAKAGE)
        breakage["fragments"] = _read_group(f, path, "breakage/fragments", FRAGMENTS)
        if "energy" not in f:
            raise RunFileError(path, "missing group 'energy'")
        energy = _read_group(f, path, "energy", dict.fromkeys(f["energy"], "J"))
        snaps = []
        if "snapshots" not in f:
            raise RunFileError(path, "missing group 'snapshots'")
        keys = sorted(f["snapshots"], key=int)
        for k in keys:
            g = f["snapshots"][k]
            arrays = _read_group(f, path, f"snapshots/{k}", SNAPSHOT)
            if arrays["position"].ndim != 2 or arrays["position"].shape[1:] != (3,):
                raise RunFileError(path, f"snapshots/{k}/position is not (n, 3)")
            bonds = None
            if "bonds" in g:
                bonds = _read_group(f, path, f"snapshots/{k}/bonds", BONDS)
            try:
                at = {n: g.attrs[n] for n in SNAPSHOT_ATTRS}
            except KeyError as err:
                raise RunFileError(path, f"snapshots/{k} lacks attribute {err}") from None
            snaps.append(Snapshot(index=int(k), label=str(at["label"]),
                                  depth=float(at["depth"]), step=int(at["step"]),
                                  time=float(at["time"]), z_top=float(at["z_top"]),
                                  z_bottom=float(at["z_bottom"]),
                                  top_pressure=float(at["top_pressure"]), bonds=bonds,
                                  **arrays))
    return RunRecord(path=path, schema_version=version,
                     software_version=str(scalars["software_version"]), config=cfg,
                     config_json=cfg_text, seed=int(scalars["seed"]),
                     preset=str(scalars["preset"]), created=str(scalars["created"]),
                     cell_x=float(scalars["cell_x"]), cell_y=float(scalars["cell_y"]),
                     thickness=float(scalars["thickness"]), stroke=float(scalars["stroke"]),
                     breakage_model=str(scalars["breakage_model"]), info=info,
                     pressure=pressure, unloading=unloading, series=series, energy=energy,
                     snapshots=snaps, breakage=breakage,
                     source_commit=commit)


# ---------------------------------------------------------------------- checkpoints
def _put(g: h5py.Group, key: str, value: Any) -> None:
    if isinstance(value, dict):
        sub = g.create_group(key)
        sub.attrs["__kind__"] = "dict"
        for k, v in value.items():
            _put(sub, str(k), v)
    elif isinstance(value, np.ndarray):
        g.create_dataset(key, data=value)
    elif isinstance(value, list) and value and all(
            isinstance(x, (dict, np.ndarray)) for x in value):
        sub = g.create_group(key)
        sub.attrs["__kind__"] = "list"
        for i, v in enumerate(value):
            _put(sub, str(i), v)
    else:
        text = _json(value)
        if len(text) > 32_000:  # beyond the HDF5 compact-attribute limit: a dataset
            ds = g.create_dataset(key, data=np.frombuffer(text.encode(), np.uint8))
            ds.attrs["__json__"] = 1
        else:
            g.attrs[key] = text


def _get_group(g: h5py.Group) -> Any:
    kind = g.attrs.get("__kind__", "dict")
    items = {k: json.loads(v) for k, v in g.attrs.items() if k != "__kind__"}
    for k in g:
        node = g[k]
        if isinstance(node, h5py.Group):
            items[k] = _get_group(node)
        elif "__json__" in node.attrs:
            items[k] = json.loads(node[()].tobytes().decode())
        else:
            items[k] = node[()]
    if kind == "list":
        return [items[str(i)] for i in range(len(items))]
    return items


def incomplete_stroke(final_depth: float, stroke: float, target_pressure: float) -> str:
    """Why a run that ended at ``final_depth`` [m] is not complete ("" if it is): it must
    cover the whole ``stroke`` unless it was servoed to a ``target_pressure`` > 0."""
    if final_depth < stroke * (1 - 1e-6) and target_pressure <= 0:
        return f"incomplete stroke ({final_depth} m)"
    return ""


def previous_checkpoint(path: str | Path) -> Path:
    """Where :func:`write_checkpoint` keeps the checkpoint before the newest one."""
    path = Path(path)
    return path.with_name(path.name + ".prev")


def write_checkpoint(path: str | Path, ck: dict) -> Path:
    """Write a checkpoint atomically: ``config``, ``config_hash``, ``run`` (RunState),
    ``rng`` (bit-generator state) and ``sim`` (Simulation.save_state()).

    The checkpoint it replaces is kept as :func:`previous_checkpoint`, so a checkpoint
    found cut short or corrupt still leaves one to resume from. A write that fails (a full
    disk) removes its temporary file and leaves both generations as they were; the error
    says so."""

    def fill(f: h5py.File) -> None:
        f.attrs["format"] = CHECKPOINT_FORMAT
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["config"] = ck["config"]
        f.attrs["config_hash"] = ck["config_hash"]
        _put(f, "run", dataclasses.asdict(ck["run"]))
        _put(f, "rng", ck["rng"])
        _put(f, "sim", ck["sim"])

    path = Path(path)
    try:
        return write_h5(path, fill, previous=previous_checkpoint(path))
    except OSError as err:
        raise OSError(err.errno, f"{err.strerror or err} while writing the checkpoint; the "
                      "checkpoints written before are intact: free space and rerun with "
                      "--resume", str(path)) from err


def read_checkpoint(path: str | Path) -> dict:
    """Read :func:`write_checkpoint` output; the run state comes back as a RunState."""
    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != CHECKPOINT_FORMAT:
                raise RunFileError(path, "not a calendaring checkpoint")
            run = _get_group(f["run"])
            out = {"config": str(f.attrs["config"]), "config_hash": str(f.attrs["config_hash"]),
                   "rng": _get_group(f["rng"]), "sim": _get_group(f["sim"])}
        for key in ("series", "energy", "trace", "unload_trace", "snapshots", "energy_keys",
                    "breakage", "fragment_diameters"):
            run[key] = list(run.get(key) or [])
        out["run"] = RunState(**run)
    except RunFileError:
        raise
    except OSError as err:
        raise RunFileError(path, f"unreadable checkpoint, cut short or corrupt ({err})") \
            from None
    except (KeyError, ValueError, TypeError, UnicodeDecodeError) as err:
        raise RunFileError(path, f"corrupt checkpoint ({type(err).__name__}: {err})") from None
    sim = out["sim"]
    if sim.get("bonds") is None:
        sim["bonds"] = None
    if sim.get("schedule") is None:
        sim["schedule"] = None
    return out
