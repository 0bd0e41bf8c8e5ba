"""A calendering run: build the electrode, bond it, calender it, record, checkpoint, write.

Stages (each a segment of time steps; ``build.*`` and ``protocol.*`` set them):

1. ``settle``: spheres inserted at random in the domain fall under the amplified body force
   ``build.settle_acceleration`` with the initial velocity ``-build.settle_velocity`` for
   ``build.settle_time_factor`` x the free-fall time over the domain height.
2. ``precompact``: real gravity; the top plate drops to just above the bed and moves down
   at ``build.plate_speed`` to the coating thickness ``h0``.
3. ``relax``: the plate is held at ``h0`` for ``build.relax_time``.
   Stages 1-3 use the coarse step ``build.timestep_fraction``; a run started from a packing
   file skips stage 1.
4. ``calender``: the time step becomes ``numerics.timestep_fraction`` x the Rayleigh time,
   bonds are created (spec 4.1), and the plate moves down ``protocol.stroke`` at the plate
   speed (``protocol.plate_speed``, or from the inertial number, see :func:`plate_speed`),
   or until the top pressure reaches ``protocol.target_pressure``.
5. ``unload`` (optional): the plate moves back up until it loses contact (springback).

Records: every step the plate forces (``pressure/``), every ``output.record_spacing`` of
plate travel a row of ``series/`` (porosity, coordination, bonds, energy, inertial number),
and a snapshot of the particles at each ``protocol.snapshot_depths``. Checkpoints go to a
separate file every ``output.checkpoint_interval`` wall seconds; ``resume=True`` continues
from it and gives the uninterrupted result (bit-identical on one CPU thread). The run file
is written at the end under a temporary name and renamed, so a killed run never leaves a
file that looks complete. File layout: :mod:`calendaring.process.runfile`.

See also: :mod:`calendaring.engine.simulation` (the engine each stage drives),
:mod:`calendaring.process.electrode` (recipe and insertion), :mod:`calendaring.process.packing`.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

from calendaring.core.config import SimConfig, config_hash, config_json
from calendaring.core.errors import ConfigError
from calendaring.core.units import to_mpa, to_um
from calendaring.process import runfile
from calendaring.process.electrode import diameter_bounds, random_insertion, recipe
from calendaring.process.runfile import RunState

STAGES = ("settle", "precompact", "relax", "calender", "unload")
SERIES = ("step", "time", "depth", "top_pressure", "bottom_pressure", "porosity",
          "coordination", "max_overlap_ratio", "inertial_number", "bonds_intact",
          "bonds_failed_normal", "bonds_failed_shear", "bonds_removed", "particles",
          "breakage_events")
# one row per breakage event (RunState.breakage), columns in this order
BREAKAGE_COLUMNS = ("parent_id", "diameter", "peak_load", "stressing_energy",
                    "fracture_energy", "e50", "t10", "n_fragments", "first_fragment_id", "step",
                    "time", "depth")


def plate_speed(cfg: SimConfig, diameter: np.ndarray, density: np.ndarray) -> float:
    """Calendering plate speed [m/s].

    ``protocol.plate_speed`` if set, else the speed giving the inertial number
    ``I = (v / h0) d sqrt(rho / P_ref)`` = ``protocol.inertial_number`` at the reference
    pressure ``protocol.reference_pressure``, with ``d`` and ``rho`` the mass-weighted mean
    diameter and (density-scaled) solid density of the particles.
    """
    pr = cfg.protocol
    if pr.plate_speed > 0:
        return pr.plate_speed
    d, rho = mean_grain(diameter, density)
    h0 = cfg.electrode.thickness
    return pr.inertial_number * h0 / (d * math.sqrt(rho / pr.reference_pressure))


def settle_fall_time(cfg: SimConfig) -> float:
    """Time [s] a sphere takes to fall the domain height from ``build.settle_velocity``
    under ``build.settle_acceleration`` (at that speed if the acceleration is 0); the
    settle stage lasts ``build.settle_time_factor`` times this."""
    a, v0, h = cfg.build.settle_acceleration, cfg.build.settle_velocity, cfg.domain.height
    return (-v0 + math.sqrt(v0 * v0 + 2 * a * h)) / a if a > 0 else h / max(v0, 1e-9)


def mean_grain(diameter: np.ndarray, density: np.ndarray) -> tuple[float, float]:
    """Mass-weighted mean diameter [m] and density [kg/m^3] of a set of spheres."""
    m = density * diameter**3
    return float(np.sum(m * diameter) / m.sum()), float(np.sum(m * density) / m.sum())


def _min_radius(cfg: SimConfig) -> dict[str, float]:
    """Smallest radius each sized material can have [m] (enters the time step)."""
    return {name: 0.5 * diameter_bounds(size)[0] for name, size in cfg.electrode.sizes.items()
            if name in cfg.materials}


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


class Progress:
    """A log line with rate and ETA at most every ``every`` seconds."""

    def __init__(self, label: str, total: int, enabled: bool = True, every: float = 5.0,
                 unit: str = "steps"):
        self.label, self.total, self.enabled, self.every = label, max(1, total), enabled, every
        self.unit = unit
        self.t0 = time.perf_counter()
        self.last = -1e9
        self.start_done = None

    def update(self, done: int, extra: str = "", force: bool = False) -> None:
        now = time.perf_counter()
        if self.start_done is None:
            self.start_done = done
            self.t0 = now
            self.last = now  # the first line comes once a rate can be measured
        if not self.enabled or (now - self.last < self.every and not force):
            return
        self.last = now
        el = now - self.t0
        rate = (done - self.start_done) / el if el > 0 else 0.0
        eta = (self.total - done) / rate if rate > 0 else float("nan")
        eta_s = f"{eta:7.0f} s" if math.isfinite(eta) else "      ? s"
        rate_s = f"{rate:7.0f}" if rate >= 1 or rate == 0 else f"{rate:7.4f}"
        _log(f"[{self.label:10s}] {100 * done / self.total:5.1f} % {done}/{self.total} "
             f"{self.unit} {rate_s} {self.unit}/s ETA {eta_s} {extra}")


class CalenderRun:
    """One calendering run from a configuration to an HDF5 run file.

    Args:
        cfg: configuration (checked with :meth:`SimConfig.check_run`).
        out: run-file path (``.h5``).
        checkpoint: checkpoint path (default ``<out>.ckpt``).
        progress: print progress lines to stderr.
        preset: name of the preset the config came from (recorded).
    """

    def __init__(self, cfg: SimConfig, out: str | Path, checkpoint: str | Path | None = None,
                 progress: bool = True, preset: str = "") -> None:
        self.cfg = cfg.check_run()
        self.out = Path(out)
        self.checkpoint = Path(checkpoint) if checkpoint else self.out.with_name(
            self.out.name + ".ckpt")
        self.progress = progress
        self.preset = preset
        self.sim = None
        self.rs = RunState()
        self.rng = np.random.default_rng(cfg.numerics.seed)
        self._last_ckpt = time.perf_counter()
        self._phase0: dict = {}  # phase records of the run before this process

    # ------------------------------------------------------------------ entry point
    def execute(self, resume: bool | str = False) -> Path:
        """Run to the end (or continue from the checkpoint) and write the run file.

        ``resume``: False starts afresh; True continues from the newest usable checkpoint
        (``<out>.ckpt``, else the one before it, ``<out>.ckpt.prev``) and raises if none is
        usable; ``"auto"`` does the same but starts afresh when none is (sweeps)."""
        t0 = time.perf_counter()
        try:
            if not (resume and self._resume(strict=resume != "auto")):
                self._start()
            self._phase0 = {k: dict(v) for k, v in self.rs.info.get("phases", {}).items()}
            booked = sum(self.sim.phase_seconds.values())  # rebuilds and steps of the set-up
            self._add_phase("setup", time.perf_counter() - t0 - booked)
            wall0 = self.rs.wall
            while self.rs.stage < len(STAGES):
                self._run_stage(t0, wall0)
            self.rs.wall = wall0 + time.perf_counter() - t0
            self.rs.info["phases"] = self._phase_totals()
            try:
                path = self._write()
            except OSError as err:
                raise OSError(err.errno, f"{err.strerror or err} while writing the run file; "
                              "the last checkpoint is kept: free space and rerun with "
                              "--resume", str(self.out)) from err
            for ck in (self.checkpoint, runfile.previous_checkpoint(self.checkpoint)):
                ck.unlink(missing_ok=True)
            return path
        finally:
            if self.sim is not None:
                self.sim.destroy()
                self.sim = None

    # ------------------------------------------------------------------ set-up
    def _start(self) -> None:
        from calendaring.engine.simulation import Simulation
        from calendaring.process.packing import read_csv, read_lammps_data

        cfg, rs = self.cfg, self.rs
        names = cfg.material_names
        area = cfg.domain.cell_x * cfg.domain.cell_y
        if cfg.electrode.packing:
            path = Path(cfg.electrode.packing)
            reader = read_csv if path.suffix.lower() == ".csv" else read_lammps_data
            pk = reader(path)
            if (abs(pk.cell_x - cfg.domain.cell_x) > 1e-12
                    or abs(pk.cell_y - cfg.domain.cell_y) > 1e-12):
                raise ConfigError("electrode.packing", str(path),
                                  f"a packing whose cell ({pk.cell_x}, {pk.cell_y}) m matches "
                                  "domain.cell_x/cell_y")
            pos, rad, mat = pk.position - [0, 0, pk.z_bottom], pk.radius, pk.material
            if mat.max() >= len(names):
                raise ConfigError("electrode.packing", str(path),
                                  f"material indices < {len(names)}")
            rs.info["build"] = {"source": str(path), "counts": {
                n: int(np.sum(mat == k)) for k, n in enumerate(names)}}
            rs.info["build"]["porosity_at_thickness"] = 1.0 - float(
                np.sum(4 / 3 * math.pi * rad**3)) / (area * cfg.electrode.thickness)
            first = "precompact"
        else:
            rec = recipe(cfg, self.rng)
            pos, rad, mat = random_insertion(rec.diameter, rec.material, cfg.domain.cell_x,
                                             cfg.domain.cell_y, cfg.domain.height, self.rng,
                                             cfg.build.max_insert_tries)
            rs.info["build"] = {"source": "random insertion", **rec.summary()}
            first = "settle"
        b = rs.info["build"]
        _log(f"electrode: {', '.join(f'{v} {k}' for k, v in b['counts'].items())} particles, "
             f"porosity at {to_um(cfg.electrode.thickness):.1f} um = "
             f"{100 * b['porosity_at_thickness']:.2f} %")
        capacity = pool_capacity(cfg, rad, mat)
        rs.info["pool_capacity"] = capacity
        self.sim = sim = Simulation(cfg, capacity=capacity, min_radius=_min_radius(cfg))
        vel = np.zeros((len(rad), 3))
        if first == "settle":
            vel[:, 2] = -cfg.build.settle_velocity
        sim.add_particles(pos, rad, mat, velocity=vel, order="space")
        rho = np.array([cfg.materials[n].density for n in names])[mat]
        sim.prime()  # dt = numerics.timestep_fraction x the smallest Rayleigh time
        dt_run = sim.dt
        dt_build = dt_run * cfg.build.timestep_fraction / cfg.numerics.timestep_fraction
        d_mean, rho_mean = mean_grain(2 * rad, rho * cfg.numerics.density_scaling)
        rs.info.update({
            "dt": dt_run, "dt_build": dt_build, "plate_speed": plate_speed(cfg, 2 * rad, rho),
            "mean_diameter": d_mean, "mean_density": rho_mean,
            "solid_volume": float(np.sum(4 / 3 * math.pi * rad**3)),
            "n_particles": len(rad), "config_hash": config_hash(cfg),
        })
        sim.change_timestep(dt_build)
        sim.breakage_active = False  # breakage starts with calendering
        sim.check_interval = 1  # coarse steps and fast plates: check the skin every step
        rs.stage = STAGES.index(first)
        self._enter_stage()

    def checkpoints(self) -> list[Path]:
        """The checkpoint files on disk, newest first."""
        return [p for p in (self.checkpoint, runfile.previous_checkpoint(self.checkpoint))
                if p.exists()]

    def _resume(self, strict: bool = True) -> bool:
        """Load the newest usable checkpoint; a cut-short, corrupt or foreign one is
        refused with a line on stderr and the one before it tried. Returns False (not
        strict) or raises (strict) when none is usable."""
        from calendaring.engine.simulation import Simulation

        refused = []
        ck = None
        for path in self.checkpoints():
            try:
                ck = runfile.read_checkpoint(path)
            except runfile.RunFileError as err:
                refused.append(f"{path}: {err}")
                _log(f"checkpoint refused: {err}")
                continue
            if ck["config_hash"] != config_hash(self.cfg):
                why = (f"{path}: written by another configuration (hash "
                       f"{ck['config_hash'][:12]} != {config_hash(self.cfg)[:12]})")
                refused.append(why)
                _log(f"checkpoint refused: {why}")
                ck = None
                continue
            if path != self.checkpoint:
                _log(f"resuming from the previous checkpoint {path}")
            break
        if ck is None:
            if strict:
                raise ConfigError("--resume", str(self.checkpoint),
                                  "a usable checkpoint of this configuration ("
                                  + ("; ".join(refused) if refused else "there is none") + ")")
            if refused:
                _log("no usable checkpoint: starting afresh")
            return False
        self.rs = ck["run"]
        self.rng.bit_generator.state = ck["rng"]
        st = ck["sim"]
        self.sim = Simulation(self.cfg, capacity=int(self.rs.info["pool_capacity"]),
                              min_radius=_min_radius(self.cfg))
        self.sim.load_state(st)
        _log(f"resumed from {path} at stage {STAGES[self.rs.stage]}, "
             f"step {self.sim.step_count}")
        return True

    # ------------------------------------------------------------------ stages
    def _enter_stage(self) -> None:
        """Fix the parameters of the stage ``rs.stage`` from the current state."""
        cfg, rs, sim = self.cfg, self.rs, self.sim
        name = STAGES[rs.stage]
        rs.stage_step = 0
        h0 = sim.z_bottom + cfg.electrode.thickness
        if name == "settle":
            a, t_fall = cfg.build.settle_acceleration, settle_fall_time(cfg)
            rs.stage_steps = max(1, math.ceil(cfg.build.settle_time_factor * t_fall / sim.dt))
            rs.params = {"gravity": a, "t_fall": t_fall}
            sim.gravity = a
            sim.set_top_plate(velocity=0.0)
        elif name == "precompact":
            sim.gravity = cfg.domain.gravity
            arr = sim.state()
            bed_top = float(np.max(arr["position"][:, 2] + arr["radius"]))
            z0 = max(min(sim.z_top, bed_top + 0.01 * cfg.electrode.thickness), h0)
            travel = z0 - h0
            n = max(1, math.ceil(travel / (cfg.build.plate_speed * sim.dt)))
            rs.stage_steps = n
            rs.params = {"z_start": z0}
            sim.set_top_plate(z=z0)
            sim.set_top_plate_history([0.0, n * sim.dt], [z0, h0])
            rs.info["bed_top_after_settling"] = bed_top
        elif name == "relax":
            sim.gravity = cfg.domain.gravity
            sim.set_top_plate(z=h0, velocity=0.0)
            rs.stage_steps = max(1, math.ceil(cfg.build.relax_time / sim.dt))
            rs.params = {}
        elif name == "calender":
            sim.gravity = cfg.domain.gravity
            sim.change_timestep(rs.info["dt"])
            sim.check_interval = cfg.numerics.rebuild_check_interval
            sim.set_top_plate(z=h0, velocity=0.0)
            n_bonds = sim.create_bonds() if cfg.bonds.enabled else 0
            sim.start_breakage()  # the build stages are breakage-free
            rs.info["bonds_created"] = n_bonds
            rs.info["calender_step0"] = sim.step_count
            rs.info["bed_after_build"] = self._bed_report()
            v = rs.info["plate_speed"]
            n = max(1, math.ceil(cfg.protocol.stroke / (v * sim.dt)))
            rs.stage_steps = n
            rs.params = {"h0": h0, "t0": sim.time, "speed": v}
            sim.set_top_plate_history([0.0, n * sim.dt], [h0, h0 - cfg.protocol.stroke])
            sim.take_trace()
            rs.next_snapshot = 0
            self._record_series()
            _log(f"calendering: {n_bonds} bonds, dt = {sim.dt:.4g} s, plate speed "
                 f"{v:.4g} m/s, {n} steps")
        elif name == "unload":
            if not cfg.protocol.unload:
                rs.stage += 1
                return
            v = cfg.protocol.unload_speed or rs.info["plate_speed"]
            z_min = sim.z_top
            n = max(1, math.ceil((h0 - z_min) / (v * sim.dt)))
            rs.stage_steps = n
            rs.params = {"h0": h0, "z_min": z_min, "speed": v}
            sim.set_top_plate_history([0.0, n * sim.dt], [z_min, z_min + n * v * sim.dt])
            sim.take_trace()

    def _chunk(self) -> int:
        """Steps to the next record / snapshot boundary of the current stage."""
        rs, name = self.rs, STAGES[self.rs.stage]
        left = rs.stage_steps - rs.stage_step
        if name == "calender":
            v, dt = rs.params["speed"], self.sim.dt
            k = max(1, round(self.cfg.output.record_spacing / (v * dt)))
            nxt = self._next_snapshot_step()
            if nxt is not None and nxt > rs.stage_step:
                k = min(k, nxt - rs.stage_step)
            return max(1, min(k, left))
        if name == "unload":
            k = max(1, round(self.cfg.output.record_spacing / (rs.params["speed"] * self.sim.dt)))
            return max(1, min(k, left))
        return max(1, min(2000, left))

    def _next_snapshot_step(self) -> int | None:
        depths = sorted(self.cfg.protocol.snapshot_depths)
        rs = self.rs
        if rs.next_snapshot >= len(depths):
            return None
        return round(depths[rs.next_snapshot] / self.cfg.protocol.stroke * rs.stage_steps)

    def _run_stage(self, t0: float, wall0: float) -> None:
        rs, sim, cfg = self.rs, self.sim, self.cfg
        name = STAGES[rs.stage]
        bar = Progress(name, rs.stage_steps, self.progress)
        # wall seconds and steps per stage, over resumes (the run file's info.stages)
        stages = rs.info.setdefault("stages", {})
        rec = stages.setdefault(name, {"wall_seconds": 0.0, "steps": 0})
        wall_in, t_in = rec["wall_seconds"], time.perf_counter()
        if name == "calender":
            self._snapshots_due()
        while rs.stage_step < rs.stage_steps:
            k = self._chunk()
            sim.run(k)
            rs.stage_step += k
            extra = f"plate {to_um(sim.z_top - sim.z_bottom):7.3f} um"
            stop = False
            if name == "calender":
                with sim.phase("records"):
                    row = self._record_series()
                    self._snapshots_due()
                extra += f" P {to_mpa(row[SERIES.index('top_pressure')]):9.3f} MPa"
                if sim.breakage_on:
                    extra += f" breakages {len(rs.breakage)}"
                tp = cfg.protocol.target_pressure
                if tp > 0 and row[SERIES.index("top_pressure")] >= tp:
                    stop = True
            elif name == "unload":
                block = sim.take_trace()
                rs.unload_trace.append(block)
                if len(block) and np.all(block[:, 3] <= 0.0):
                    stop = True
            bar.update(rs.stage_step, extra)
            rec["wall_seconds"] = wall_in + time.perf_counter() - t_in
            rec["steps"] = rs.stage_step
            if stop:
                break
            rs.wall = wall0 + time.perf_counter() - t0
            self._maybe_checkpoint()
        bar.update(rs.stage_step, f"plate {to_um(sim.z_top - sim.z_bottom):7.3f} um", force=True)
        if name == "calender":
            self._finish_calender()
        elif name == "unload":
            rs.info["unload"] = self._springback()
        rs.stage += 1
        if rs.stage < len(STAGES):
            self._enter_stage()

    def _finish_calender(self) -> None:
        rs, sim = self.rs, self.sim
        if sim._plate_schedule is not None:  # a pressure target stopped the plate early
            sim.set_top_plate(velocity=0.0)
        depth = rs.params["h0"] - sim.z_top
        if not rs.snapshots or abs(rs.snapshots[-1]["attrs"]["depth"] - depth) > 1e-12:
            self._snapshot("final")
        rs.info["final_depth"] = depth
        rs.info["calender_steps"] = rs.stage_step

    def _springback(self) -> dict:
        rs = self.rs
        tr = np.concatenate(rs.unload_trace) if rs.unload_trace else np.zeros((0, 4))
        z_min = rs.params["z_min"]
        h_min = z_min - self.sim.z_bottom
        free = np.nonzero(tr[:, 3] <= 0.0)[0] if len(tr) else np.zeros(0, int)
        if free.size == 0:
            return {"released": False, "h_min": h_min}
        h_rel = tr[free[0], 1] - self.sim.z_bottom
        return {"released": True, "h_min": h_min, "h_release": float(h_rel),
                "springback": float((h_rel - h_min) / h_min)}

    # ------------------------------------------------------------------ records
    def _bed_report(self) -> dict:
        s = self.sim.state()
        h = self.sim.z_top - self.sim.z_bottom
        vol = float(np.sum(4 / 3 * math.pi * s["radius"] ** 3))
        area = self.sim.cell_area
        return {"thickness": h, "porosity": 1 - vol / (area * h),
                "bed_top": float(np.max(s["position"][:, 2] + s["radius"])),
                "kinetic_energy": float(0.5 * np.sum(s["mass"] * np.sum(s["velocity"] ** 2, 1)))}

    def _record_series(self) -> list:
        rs, sim = self.rs, self.sim
        block = sim.take_trace()
        if len(block):
            rs.trace.append(block)
        area = sim.cell_area
        h = sim.z_top - sim.z_bottom
        if len(block):
            top = float(np.mean(block[:, 3])) / area
            bottom = float(-np.mean(block[:, 2])) / area
        else:
            f_bottom, f_top = sim.plate_forces()
            top, bottom = float(f_top[2]) / area, float(-f_bottom[2]) / area
        radius = sim.pool.radius.to_numpy()[: sim.pool.slots_used]
        alive = sim.pool.alive.to_numpy()[: sim.pool.slots_used] == 1
        vol = float(np.sum(4 / 3 * math.pi * radius[alive] ** 3))
        n_alive = int(np.count_nonzero(alive))
        n_touch, worst = sim.contact_stats()
        self._take_breakage()
        v = rs.params["speed"]
        inertial = (v / h * rs.info["mean_diameter"] * math.sqrt(rs.info["mean_density"] / top)
                    if top > 0 else float("nan"))
        counts = sim.bonds.counts() if sim.bonds is not None else dict.fromkeys(
            ("intact", "failed_normal", "failed_shear", "removed"), 0)
        row = [sim.step_count, sim.time - rs.params["t0"], rs.params["h0"] - sim.z_top, top,
               bottom, 1 - vol / (area * h), 2.0 * n_touch / max(1, n_alive), worst, inertial,
               counts["intact"], counts["failed_normal"], counts["failed_shear"],
               counts["removed"], n_alive, len(rs.breakage)]
        rs.series.append(row)
        energy = sim.energy()
        if not rs.energy_keys:
            rs.energy_keys = list(energy)
        rs.energy.append([energy[k] for k in rs.energy_keys])
        return row

    def _take_breakage(self) -> None:
        """Move the engine's breakage records into the run state (one row per event)."""
        rs = self.rs
        for rec in self.sim.take_breakage():
            depth = self.sim.z_bottom + self.cfg.electrode.thickness - rec["z_top"]
            t = (rec["step"] - rs.info["calender_step0"]) * rs.info["dt"]
            for k in range(len(rec["parent_id"])):
                rs.breakage.append([int(rec["parent_id"][k]), float(rec["diameter"][k]),
                                    float(rec["peak"][k]), float(rec["energy"][k]),
                                    float(rec["fracture"][k]), float(rec["e50"][k]),
                                    float(rec["t10"][k]), int(rec["nfrag"][k]),
                                    int(rec["first_id"][k]), int(rec["step"]), float(t),
                                    float(depth)])
                rs.fragment_diameters.append([float(x) for x in rec["fragment_diameters"][k]])

    def _snapshots_due(self) -> None:
        rs = self.rs
        while True:
            nxt = self._next_snapshot_step()
            if nxt is None or nxt > rs.stage_step:
                return
            self._snapshot(str(len(rs.snapshots)))
            rs.next_snapshot += 1

    def _snapshot(self, label: str) -> None:
        rs, sim = self.rs, self.sim
        s = sim.state()
        data = {"position": s["position"], "radius": s["radius"], "material": s["material"],
                "id": s["id"], "velocity": s["velocity"], "normal_force": s["normal_force_sum"],
                "n_contacts": s["n_contacts"], "parent_id": s["parent_id"],
                "fracture_energy": s["fracture_energy"], "peak_load": s["peak_load"]}
        _f_bottom, f_top = sim.plate_forces()
        attrs = {"depth": rs.params["h0"] - sim.z_top, "step": sim.step_count,
                 "time": sim.time - rs.params["t0"], "z_top": sim.z_top,
                 "z_bottom": sim.z_bottom, "top_pressure": float(f_top[2]) / sim.cell_area,
                 "label": label}
        bonds = None
        if sim.bonds is not None and self.cfg.output.snapshot_bonds:
            b = sim.bonds.to_numpy()
            bonds = {"id_a": b["id_a"], "id_b": b["id_b"], "state": b["state"],
                     "normal_force": b["f_n"], "radius": b["radius"]}
        rs.snapshots.append({"data": data, "attrs": attrs, "bonds": bonds})

    # ------------------------------------------------------------------ files
    def _maybe_checkpoint(self) -> None:
        every = self.cfg.output.checkpoint_interval
        if every <= 0 or time.perf_counter() - self._last_ckpt < every:
            return
        with self.sim.phase("checkpoint"):
            self._take_breakage()
            self.rs.info["phases"] = self._phase_totals()
            runfile.write_checkpoint(self.checkpoint, {
                "config": config_json(self.cfg), "config_hash": config_hash(self.cfg),
                "run": self.rs, "rng": self.rng.bit_generator.state,
                "sim": self.sim.save_state()})
        self._last_ckpt = time.perf_counter()

    def _add_phase(self, name: str, seconds: float) -> None:
        """Book host seconds outside the engine's own phases (the set-up)."""
        e = self._phase0.setdefault(name, {"seconds": 0.0, "calls": 0})
        e["seconds"] += seconds
        e["calls"] += 1

    def _phase_totals(self) -> dict:
        """Wall seconds and calls per phase over the whole run, resumes included (the run
        file's ``info.phases``; see :meth:`Simulation.phase`)."""
        out = {k: dict(v) for k, v in self._phase0.items()}
        for k, sec in self.sim.phase_seconds.items():
            e = out.setdefault(k, {"seconds": 0.0, "calls": 0})
            e["seconds"] += sec
            e["calls"] += self.sim.phase_calls[k]
        return out

    def _write(self) -> Path:
        rs, cfg = self.rs, self.cfg
        trace = np.concatenate(rs.trace) if rs.trace else np.zeros((0, 4))
        area = cfg.domain.cell_x * cfg.domain.cell_y
        h0 = self.sim.z_bottom + cfg.electrode.thickness
        stride = cfg.output.pressure_stride
        pressure = _block_mean(trace, stride)
        unload = np.concatenate(rs.unload_trace) if rs.unload_trace else np.zeros((0, 4))
        unload = _block_mean(unload, stride)
        info = dict(rs.info)
        info["wall_seconds"] = rs.wall
        self._take_breakage()
        rows = np.array(rs.breakage, float).reshape(-1, len(BREAKAGE_COLUMNS))
        brk = {k: rows[:, i] for i, k in enumerate(BREAKAGE_COLUMNS)}
        for k in ("parent_id", "n_fragments", "first_fragment_id", "step"):  # exact in f64
            brk[k] = brk[k].astype(np.int64)
        n_frag = brk["n_fragments"]
        brk["fragments"] = {
            "id": np.concatenate([f + np.arange(n, dtype=np.int64) for f, n in
                                  zip(brk["first_fragment_id"], n_frag, strict=True)]
                                 or [np.zeros(0, np.int64)]),
            "diameter": np.array([d for ds in rs.fragment_diameters for d in ds], float),
            "event": np.repeat(np.arange(len(n_frag), dtype=np.int64), n_frag)}
        info["breakage_events"] = len(rs.breakage)
        return runfile.write_run(self.out, {
            "config": cfg, "preset": self.preset, "seed": cfg.numerics.seed, "info": info,
            "breakage_model": "tavares_ufrj" if self.sim.breakage_on else "none",
            "breakage": brk,
            "pressure": {"step": pressure[:, 0], "depth": h0 - pressure[:, 1],
                         "value": pressure[:, 3] / area, "bottom": -pressure[:, 2] / area,
                         "time": (pressure[:, 0] - rs.info["calender_step0"]) * rs.info["dt"]},
            "unloading": {"depth": h0 - unload[:, 1], "value": unload[:, 3] / area,
                          "bottom": -unload[:, 2] / area},
            "series": {k: np.array([r[i] for r in rs.series], float)
                       for i, k in enumerate(SERIES)},
            "energy": {k: np.array([r[i] for r in rs.energy], float)
                       for i, k in enumerate(rs.energy_keys)},
            "snapshots": rs.snapshots,
        })


def build_packing(cfg: SimConfig, path: str | Path, progress: bool = True) -> Path:
    """Insert and settle the bed of ``cfg`` (the ``settle`` stage alone) and write it as a
    packing CSV, atomically.

    Runs whose ``electrode.packing`` is this file skip the settling and start with the
    pre-compaction, so a sweep settles one bed per seed instead of one per run. The build
    stages are breakage-free, so the bed does not depend on the ``[breakage]`` parameters.
    """
    from calendaring.process.packing import Packing, write_csv

    cfg = cfg.check_run()
    if cfg.electrode.packing:
        raise ConfigError("electrode.packing", cfg.electrode.packing,
                          "empty: build_packing settles a new bed")
    runner = CalenderRun(cfg, Path(path).with_suffix(".h5"), progress=progress)
    try:
        runner._start()
        runner._run_stage(time.perf_counter(), 0.0)  # settle; only positions the plate after
        sim = runner.sim
        a = sim.state()
        pk = Packing(position=a["position"], radius=a["radius"], material=a["material"],
                     ids=a["id"], cell_x=cfg.domain.cell_x, cell_y=cfg.domain.cell_y,
                     z_bottom=sim.z_bottom, z_top=sim.z_bottom + cfg.domain.height)
        return write_csv(path, pk, cfg.material_names)
    finally:
        if runner.sim is not None:
            runner.sim.destroy()
            runner.sim = None
        runner.checkpoint.unlink(missing_ok=True)  # a settle-only checkpoint is of no use


def pool_capacity(cfg: SimConfig, radius: np.ndarray, material: np.ndarray) -> int:
    """Particle slots for a run: the particles, plus every fragment that can ever exist
    when breakage is on (``breakage.pool_capacity``, or the worst case of
    :func:`calendaring.engine.breakage.worst_case_slots`)."""
    from calendaring.engine.breakage import breakable_mask, breakage_enabled, worst_case_slots

    n = len(radius)
    if not breakage_enabled(cfg):
        return n
    if cfg.breakage.pool_capacity:
        if cfg.breakage.pool_capacity < n:
            raise ConfigError("breakage.pool_capacity", cfg.breakage.pool_capacity,
                              f"0 (worst case) or >= the {n} particles of the bed")
        return cfg.breakage.pool_capacity
    return worst_case_slots(2 * np.asarray(radius), breakable_mask(cfg)[np.asarray(material)],
                            cfg.breakage)


def _block_mean(trace: np.ndarray, stride: int) -> np.ndarray:
    """Means over consecutive blocks of ``stride`` rows (the last block may be shorter)."""
    if stride <= 1 or len(trace) == 0:
        return trace
    n = len(trace)
    idx = np.arange(0, n, stride)
    sums = np.add.reduceat(trace, idx, axis=0)
    counts = np.diff(np.append(idx, n))[:, None]
    out = sums / counts
    out[:, 0] = trace[np.minimum(idx + counts[:, 0] - 1, n - 1), 0]  # step of the block end
    return out


def run(cfg: SimConfig, out: str | Path, resume: bool = False, progress: bool = True,
        preset: str = "") -> Path:
    """Run a calendering simulation and write ``out``; see :class:`CalenderRun`."""
    return CalenderRun(cfg, out, progress=progress, preset=preset).execute(resume=resume)


__all__ = ["BREAKAGE_COLUMNS", "SERIES", "STAGES", "CalenderRun", "Progress", "build_packing",
           "mean_grain",
           "plate_speed", "pool_capacity", "run"]
