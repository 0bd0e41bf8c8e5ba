"""DEM speed harness: our engine against LIGGGHTS on the same electrode, and the full model's
scaling, memory and start-up.

``versus``: one bed of the paper preset (our recipe: 1,461 AM + 3,704 CB spheres in the
100 x 100 um cell, inserted at random and pre-compacted by the top plate to the coating
thickness, untimed) is handed to both codes: to ours in memory, to LIGGGHTS as a
``read_data`` file. Both then run the same number of steps with the same time step (ours:
4 % of the smallest Rayleigh time) while the top plate moves down at the same speed, with
the contact law reduced to Hertz-Mindlin (no plasticity, no adhesion, no bonds, no
breakage, no gravity; friction, restitution and rolling friction of the paper). Reported:
steps/s, particle-steps/s, the ratio, contacts per particle, and both top-plate pressure
curves overlaid (PNG) with their agreement. Without a ``liggghts`` binary our figures are
reported alone.

``scaling``: the full model (EEPA with adhesion and plasticity, CB bonds, Tavares
breakage, energy ledger) of the paper preset: particle-steps/s at about 1k, 5k, 20k and
100k particles (the 5k bed tiled periodically 2 x 2 and 4 x 5 for the large ones), the
device memory per particle slot at the full pool capacity, and the first-compile and
cached start-up times of a fresh process.

``paper``: a whole calendering run of the paper preset (or ``--preset NAME``) as
``calendaring run`` does it, from random insertion through settling, pre-compaction,
relaxation, calendering with bonds and breakage, to unloading: wall time and steps/s of
each stage, as the run file records them. The paper preset takes of the order of an hour on
2 cores; ``--run-dir`` keeps the run file and its checkpoint, and a rerun resumes.

``overhead``: the Hertz-mode step on a one-particle bed, per thread count in a fresh
process: the per-step cost that does not grow with the bed (the kernel launch from Python,
the host's flag check and, above one thread, the thread pool's dispatch of each parallel
loop).

    python benchmarks/bench_dem.py versus --threads 2 --np 2
    python benchmarks/bench_dem.py scaling --threads 2
    python benchmarks/bench_dem.py paper --threads 2
    python benchmarks/bench_dem.py overhead --threads 1 2

On a GPU (``--arch cuda``; ``versus`` then runs ours alone, ``scaling`` takes ``1M``, the 5k
bed tiled 14 x 14):

    python benchmarks/bench_dem.py versus --arch cuda --liggghts off --repeat 1
    python benchmarks/bench_dem.py scaling --arch cuda --sizes 5k 100k 1M --particle-steps 5e8

Writes JSON (and the overlay PNG) to benchmarks/results/. Speed is measured here, never
asserted in tests.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
RESULTS = HERE / "results"
LOOP_RE = re.compile(r"Loop time of ([0-9.eE+-]+) on (\d+) procs for (\d+) steps with (\d+) atoms")


# ----------------------------------------------------------------------------- configs
def hertz_config(cfg, threads: int, skin: float | None = None):
    """``cfg`` reduced to Hertz-Mindlin: no plasticity, adhesion, pull-off, bonds, breakage,
    gravity or energy ledger; tangential stiffness 8 G* sqrt(R* delta). ``skin`` sets the
    Verlet skin [m] (default: the configuration's)."""
    from calendaring import with_overrides

    over = {"numerics.threads": threads, "numerics.track_energy": False,
            "numerics.skin": skin if skin is not None else cfg.numerics.skin,
            "breakage.enabled": False, "bonds.enabled": False, "domain.gravity": 0.0,
            "contact.tangential_stiffness_ratio": 1.0, "contact.damping_mode": "tangent_sqrt56"}
    for key in cfg.contact.pairs:
        over[f"contact.pairs.{key}.plasticity_ratio"] = 0.0
        over[f"contact.pairs.{key}.surface_energy"] = 0.0
        over[f"contact.pairs.{key}.pull_off_force"] = 0.0
    for key in cfg.contact.plate_pairs:
        over[f"contact.plate_pairs.{key}.plasticity_ratio"] = 0.0
        over[f"contact.plate_pairs.{key}.surface_energy"] = 0.0
        over[f"contact.plate_pairs.{key}.pull_off_force"] = 0.0
    return with_overrides(cfg, over)


def paper_bed(cfg, seed: int, cell_scale: float = 1.0, porosity: float = 0.33,
              hold_steps: int = 20000):
    """The paper preset's particles (our recipe) in a cell scaled by ``cell_scale`` per side,
    pre-compacted to ``porosity`` and held there for ``hold_steps`` steps. The coating
    thickness of the paper (porosity 0.42) is below jamming, so the bed carries no load
    at rest; 0.33 is about half-way through the paper's 19.5 um stroke, where the plate
    pressure is tens of MPa. Returns (pos, rad, mat, z_top, cfg)."""
    from bench_step import compact_bed

    from calendaring import recipe, with_overrides

    cfg = with_overrides(cfg, {"domain.cell_x": cfg.domain.cell_x * cell_scale,
                               "domain.cell_y": cfg.domain.cell_y * cell_scale})
    rng = np.random.default_rng(seed)
    rec = recipe(cfg, rng)
    pos, rad, mat, vel, z_top = compact_bed(cfg, rec.diameter, rec.material, porosity, rng,
                                            hold_steps=hold_steps)
    speed = np.linalg.norm(vel, axis=1)
    print(f"[bed] {len(rad)} spheres held under the plate: rms speed "
          f"{np.sqrt(np.mean(speed**2)):.3g} m/s, largest {speed.max():.3g} m/s", flush=True)
    return pos, rad, mat, z_top, cfg


# ----------------------------------------------------------------------------- ours
def our_timestep(cfg, pos, rad, mat) -> float:
    """Our time step for this bed [s] (what LIGGGHTS is given)."""
    from calendaring import Simulation

    sim = Simulation(cfg, capacity=len(rad))
    try:
        sim.add_particles(pos, rad, mat)
        return sim.compute_timestep()
    finally:
        sim.destroy()


def run_ours(cfg, pos, rad, mat, z_top, speed: float, steps: int, every: int = 100) -> dict:
    """Time ``steps`` steps of our engine from rest; top-plate force every ``every`` steps."""
    from calendaring import Simulation

    sim = Simulation(cfg, capacity=len(rad))
    try:
        sim.add_particles(pos, rad, mat, order="space")  # as calendering runs store a bed
        sim.set_top_plate(z=z_top, velocity=-speed)
        t0 = time.perf_counter()
        sim.prime()  # compile or load the kernels, first neighbour list and forces
        t_prime = time.perf_counter() - t0
        area = sim.cell_area
        rows = [(sim.step_count, sim.z_top, sim.top_pressure() * area)]
        sim.take_trace()
        # The multi-step launch kernel is compiled (or loaded from the kernel cache) at the
        # first run: the first steps run untimed, as LIGGGHTS' loop time leaves out its
        # set-up. (Each Simulation gets kernels of its own: the fields are part of their
        # signature, so the second Simulation of a process compiles them again; timed, that
        # took 2-3 s of a 20,000-step run.)
        warm = min(200, steps // 10)
        sim.run(warm)
        t0 = time.perf_counter()
        sim.run(steps - warm)
        wall = time.perf_counter() - t0
        timed = steps - warm
        # the engine's per-step plate record (step, z, bottom force, top force), every
        # ``every`` steps: the same numbers a callback would read, without stopping the
        # multi-step launches every ``every`` steps
        trace = sim.take_trace()
        keep = trace[:, 0] % every == 0
        rows += [tuple(r) for r in trace[keep][:, [0, 1, 3]]]
        n = sim.pool.n_alive()
        touching, _worst = sim.contact_stats()
        return {"code": "calendaring", "arch": sim.backend.arch,
                "threads": cfg.numerics.threads, "particles": n,
                "steps": steps, "timed_steps": timed, "wall_s": wall,
                "steps_per_s": timed / wall, "particle_steps_per_s": n * timed / wall,
                "dt_s": sim.dt, "prime_s": t_prime, "rebuilds": sim.n_rebuilds,
                "contacts_per_particle": 2.0 * touching / n,
                "force": np.array(rows, float)}
    finally:
        sim.destroy()


# ----------------------------------------------------------------------------- LIGGGHTS
LIGGGHTS_INPUT = """\
# written by benchmarks/bench_dem.py: the same bed, dt, plate speed and step count as ours
atom_style      granular
atom_modify     map array
boundary        p p f
newton          off
communicate     single vel yes
units           si
hard_particles  yes
processors      * * 1
read_data       bed.data
neighbor        {skin} bin
neigh_modify    delay 0
# types: 1 AM, 2 CB, 3 top plate, 4 bottom plate
fix m1 all property/global youngsModulus peratomtype {E}
fix m2 all property/global poissonsRatio peratomtype {nu}
fix m3 all property/global coefficientRestitution peratomtypepair 4 {e}
fix m4 all property/global coefficientFriction peratomtypepair 4 {mu}
fix m5 all property/global coefficientRollingFriction peratomtypepair 4 {mur}
pair_style gran model hertz tangential history rolling_friction cdt
pair_coeff * *
timestep {dt:.17g}
fix bottom  all mesh/surface/stress file plate_unit.stl type 4 scale {L:.17g} move 0. 0. {zb:.17g}
fix topwall all mesh/surface/stress file plate_unit.stl type 3 scale {L:.17g} move 0. 0. {zt:.17g}
fix walls   all wall/gran model hertz tangential history rolling_friction cdt &
            mesh n_meshes 2 meshes bottom topwall
fix integr all nve/sphere
variable ztop equal {zt:.17g}+f_topwall[9]
variable ftop equal f_topwall[3]
variable fbot equal f_bottom[3]
compute cpa all contact/atom
compute zc all reduce ave c_cpa
thermo_style custom step atoms ke c_zc cpu spcpu
thermo {thermo}
thermo_modify lost ignore norm no
fix ftop all ave/time {every} 1 {every} v_ztop v_ftop v_fbot file top_wall_force.txt
run 0
fix mv all move/mesh mesh topwall linear 0. 0. {v:.17g}
run {steps}
"""

STL = ("solid plate\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 1 1 0\n"
       "endloop\nendfacet\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 1 0\n"
       "vertex 0 1 0\nendloop\nendfacet\nendsolid plate\n")


def liggghts_files(folder: Path, cfg, pos, rad, mat, z_top: float, dt: float, speed: float,
                   steps: int, skin: float, every: int = 100) -> None:
    """The bed as ``bed.data`` (atom types 1 AM, 2 CB; 3 and 4 are the plates) and the
    input ``in.bench`` with every material and contact constant taken from ``cfg``."""
    from calendaring import Packing, write_lammps_data

    names = cfg.material_names
    if names != ["AM", "CB"]:
        raise SystemExit(f"versus expects the materials AM, CB; got {names}")
    s = cfg.numerics.density_scaling
    pk = Packing(position=pos, radius=rad, material=mat, ids=np.arange(1, len(rad) + 1),
                 cell_x=cfg.domain.cell_x, cell_y=cfg.domain.cell_y, z_bottom=0.0,
                 z_top=z_top + 2e-6)
    write_lammps_data(folder / "bed.data", pk, {i: s * cfg.materials[n].density
                                               for i, n in enumerate(names)}, atom_types=4)
    mats = [cfg.materials["AM"], cfg.materials["CB"], cfg.plates.top, cfg.plates.bottom]
    pair = {}
    for a in range(4):
        for b in range(4):
            if a < 2 and b < 2:
                p = cfg.pair(names[a], names[b])
            elif a < 2 or b < 2:
                p = cfg.contact.plate_pairs[names[min(a, b)]]
            else:
                p = None  # plate-plate: never in contact
            pair[a, b] = p

    def matrix(attr, default):
        return " ".join(f"{getattr(pair[a, b], attr) if pair[a, b] else default:.17g}"
                        for a in range(4) for b in range(4))

    if abs(cfg.domain.cell_x - cfg.domain.cell_y) > 1e-15:
        raise SystemExit("versus needs a square cell (one STL scale)")
    text = LIGGGHTS_INPUT.format(
        skin=skin, E=" ".join(f"{m.youngs_modulus:.17g}" for m in mats),
        nu=" ".join(f"{m.poisson_ratio:.17g}" for m in mats),
        e=matrix("restitution", 0.5), mu=matrix("friction", 0.0),
        mur=matrix("rolling_friction", 0.0), dt=dt, L=cfg.domain.cell_x, zb=0.0, zt=z_top,
        v=-speed, steps=steps, every=every, thermo=max(every, steps // 10))
    (folder / "in.bench").write_text(text)
    (folder / "plate_unit.stl").write_text(STL)


def run_liggghts(folder: Path, binary: str, nproc: int, steps: int) -> dict:
    """Run LIGGGHTS in ``folder`` (``mpirun -np nproc`` when nproc > 1); parse its timing."""
    cmd = [binary, "-in", "in.bench", "-echo", "none", "-log", "log.liggghts"]
    if nproc > 1:
        mpirun = shutil.which("mpirun")
        if mpirun is None:
            raise SystemExit("mpirun not found: install openmpi-bin or use --np 1")
        extra = ["--allow-run-as-root"] if os.geteuid() == 0 else []
        cmd = [mpirun, *extra, "--oversubscribe", "-np", str(nproc), *cmd]
    env = dict(os.environ, OMPI_MCA_btl_vader_single_copy_mechanism="none")
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=folder, capture_output=True, text=True, env=env)
    total = time.perf_counter() - t0
    (folder / "stdout.txt").write_text(proc.stdout + proc.stderr)
    loops = LOOP_RE.findall(proc.stdout)
    if proc.returncode != 0 or not loops:
        tail = "\n".join((proc.stdout + proc.stderr).splitlines()[-20:])
        raise SystemExit(f"LIGGGHTS failed (exit {proc.returncode}); last lines:\n{tail}")
    t, procs, n_steps, atoms = loops[-1]
    t, n_steps, atoms = float(t), int(n_steps), int(atoms)
    if n_steps != steps:
        raise SystemExit(f"LIGGGHTS ran {n_steps} steps, expected {steps}")
    zc = _last_thermo_column(proc.stdout, "zc")
    force = np.loadtxt(folder / "top_wall_force.txt", comments="#", ndmin=2)
    force = force[force[:, 0] > 0]  # step 0 is written before the mesh forces exist
    return {"code": "LIGGGHTS", "version": _liggghts_version(proc.stdout), "ranks": int(procs),
            "particles": atoms, "steps": n_steps, "wall_s": t, "steps_per_s": n_steps / t,
            "particle_steps_per_s": atoms * n_steps / t, "process_wall_s": total,
            "contacts_per_particle": zc,
            # ave/time rows: step, plate height, Fz on top plate, Fz on bottom plate
            "force": force[:, :3]}


def _last_thermo_column(stdout: str, name: str) -> float | None:
    header, value = None, None
    for line in stdout.splitlines():
        cols = line.split()
        if cols and cols[0] == "Step":
            header = cols
        elif header and len(cols) == len(header) and cols[0].isdigit():
            value = float(cols[header.index(name)]) if name in header else None
    return value


def _liggghts_version(stdout: str) -> str:
    m = re.search(r"LIGGGHTS \(([^)]*)\)", stdout)
    return m.group(1) if m else "unknown"


def compare_curves(ours: np.ndarray, peer: np.ndarray, area: float) -> dict:
    """Top-plate pressure agreement over the common plate travel: RMS and largest
    difference relative to the mean pressure, and the final pressures."""
    d_ours = ours[0, 1] - ours[:, 1]
    d_peer = peer[0, 1] - peer[:, 1] if len(peer) else d_ours
    p_ours = np.abs(ours[:, 2]) / area
    p_peer = np.abs(peer[:, 2]) / area
    hi = min(d_ours[-1], d_peer[-1])
    grid = np.linspace(0.0, hi, 50)
    a = np.interp(grid, d_ours, p_ours)
    b = np.interp(grid, d_peer, p_peer)
    scale = max(float(np.mean(np.abs(b))), 1e-30)
    return {"plate_travel_m": float(hi), "mean_pressure_liggghts_Pa": float(np.mean(b)),
            "mean_pressure_ours_Pa": float(np.mean(a)),
            "rms_difference_rel": float(np.sqrt(np.mean((a - b) ** 2)) / scale),
            "max_difference_rel": float(np.max(np.abs(a - b)) / scale),
            "final_pressure_ours_Pa": float(a[-1]), "final_pressure_liggghts_Pa": float(b[-1])}


def plot_versus(path: Path, ours: np.ndarray, peer: np.ndarray | None, area: float,
                title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from calendaring import save_figure

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot((ours[0, 1] - ours[:, 1]) * 1e9, np.abs(ours[:, 2]) / area / 1e6, label="calendaring")
    if peer is not None:
        ax.plot((peer[0, 1] - peer[:, 1]) * 1e9, np.abs(peer[:, 2]) / area / 1e6, "--",
                label="LIGGGHTS 3.8")
    ax.set_xlabel("top-plate travel [nm]")
    ax.set_ylabel("top-plate pressure [MPa]")
    ax.set_title(title, fontsize=9)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def _once(run, k: int, n: int, label: str) -> dict:
    out = run()
    print(f"[versus] {label}, run {k + 1}/{n}: {out['steps_per_s']:.0f} steps/s "
          f"({out['particle_steps_per_s']:.3g} particle-steps/s)", flush=True)
    return out


def _median_of(outs: list[dict]) -> dict:
    """The last result with the median rate over the runs and every run's rate."""
    out = dict(outs[-1])
    rates = [o["steps_per_s"] for o in outs]
    out["steps_per_s_runs"] = rates
    out["steps_per_s"] = float(np.median(rates))
    out["particle_steps_per_s"] = out["steps_per_s"] * out["particles"]
    return out


def repeat_median(run, n: int, label: str) -> dict:
    """Call ``run()`` (a dict with steps_per_s and particles) ``n`` times; the last result
    with the median rate over the runs (the machine is noisy) and every run's rate."""
    return _median_of([_once(run, k, n, label) for k in range(n)])


def interleaved(first, second, n: int, labels: tuple[str, str],
                pause: float = 0.0) -> tuple[dict, dict]:
    """``first()`` and ``second()`` in turn, ``n`` times each (a virtual machine's speed
    drifts over minutes: side by side, each pair of runs meets the same conditions), with
    ``pause`` seconds of idle before each run; each code's median, plus the per-pair
    ratios in the first's ``ratio_runs``."""
    a, b = [], []
    for k in range(n):
        time.sleep(pause)
        a.append(_once(first, k, n, labels[0]))
        time.sleep(pause)
        b.append(_once(second, k, n, labels[1]))
    out_a, out_b = _median_of(a), _median_of(b)
    out_a["ratio_runs"] = [x["steps_per_s"] / y["steps_per_s"] for x, y in zip(a, b,
                                                                            strict=True)]
    return out_a, out_b


def cmd_versus(args) -> dict:
    from calendaring import init_taichi, load_preset, with_overrides

    init_taichi(arch=args.arch, threads=args.threads)
    cfg = hertz_config(load_preset("paper"), args.threads)
    skin = args.skin if args.skin is not None else args.liggghts_skin
    t0 = time.perf_counter()
    bed = Path(args.bed) if args.bed else None
    if bed is not None and bed.exists():
        with np.load(bed) as z:
            pos, rad, mat, z_top = z["pos"], z["rad"], z["mat"], float(z["z_top"])
    else:
        pos, rad, mat, z_top, cfg = paper_bed(cfg, args.seed, porosity=args.porosity)
        if bed is not None:
            np.savez(bed, pos=pos, rad=rad, mat=mat, z_top=z_top)
    prep = time.perf_counter() - t0
    cfg = hertz_config(cfg, args.threads, skin)  # the same neighbour skin as LIGGGHTS'
    if args.arch != "cpu":
        cfg = with_overrides(cfg, {"numerics.arch": args.arch})
    if args.rolling_friction is not None:
        over = {f"contact.pairs.{k}.rolling_friction": args.rolling_friction
                for k in cfg.contact.pairs}
        over.update({f"contact.plate_pairs.{k}.rolling_friction": args.rolling_friction
                     for k in cfg.contact.plate_pairs})
        cfg = with_overrides(cfg, over)
    print(f"[versus] bed: {len(rad)} spheres ({int(np.sum(mat == 0))} AM, "
          f"{int(np.sum(mat == 1))} CB), plate at {z_top * 1e6:.2f} um, built in {prep:.0f} s",
          flush=True)
    ours_label = (f"calendaring on {args.threads} threads" if args.arch == "cpu"
                  else f"calendaring on {args.arch}")

    def ours_once() -> dict:
        return run_ours(cfg, pos, rad, mat, z_top, args.speed, args.steps)

    area = cfg.domain.cell_x * cfg.domain.cell_y
    binary = None if args.liggghts == "off" else (
        args.liggghts or shutil.which("liggghts") or shutil.which("lmp_serial"))
    peer = None
    result = {"benchmark": "bench_dem versus", "preset": "paper (Hertz-Mindlin reduction)",
              "speed_m_s": args.speed, "seed": args.seed, "bed_build_s": prep,
              "rolling_friction": args.rolling_friction}
    if binary is None:
        print("[versus] LIGGGHTS off or not found (Debian package 'liggghts'): our figures "
              "alone")
        ours = repeat_median(ours_once, args.repeat, ours_label)
        result["liggghts"] = None
    else:
        dt = our_timestep(cfg, pos, rad, mat)

        def liggghts_once() -> dict:
            folder = Path(tempfile.mkdtemp(prefix="bench-liggghts-"))
            try:
                liggghts_files(folder, cfg, pos, rad, mat, z_top, dt, args.speed,
                               args.steps, args.liggghts_skin)
                return run_liggghts(folder, binary, args.np, args.steps)
            finally:
                if args.keep:
                    print(f"[versus] LIGGGHTS files kept in {folder}")
                else:
                    shutil.rmtree(folder, ignore_errors=True)

        ours, peer = interleaved(ours_once, liggghts_once, args.repeat,
                                 (ours_label, f"LIGGGHTS on {args.np} MPI ranks"), args.pause)
        result["liggghts"] = {k: v for k, v in peer.items() if k != "force"}
        result["liggghts"]["skin_m"] = args.liggghts_skin
        result["ratio_steps_per_s"] = ours["steps_per_s"] / peer["steps_per_s"]
        result["ratio_median_of_pairs"] = float(np.median(ours["ratio_runs"]))
        result["agreement"] = compare_curves(ours["force"], peer["force"], area)
        if peer["particles"] != ours["particles"]:
            result["warning"] = (f"LIGGGHTS ended with {peer['particles']} atoms, ours with "
                                 f"{ours['particles']}")
    result["calendaring"] = {k: v for k, v in ours.items() if k != "force"}
    result["calendaring"]["skin_m"] = cfg.numerics.skin
    title = (f"{len(rad)} spheres, dt = {ours['dt_s']:.3g} s, plate {args.speed} m/s, "
             f"{args.steps} steps")
    plot_versus(Path(args.out).with_suffix(".png"), ours["force"],
                None if peer is None else peer["force"], area, title)
    return result


# ----------------------------------------------------------------------------- scaling
def field_bytes(obj) -> int:
    """Bytes of every Taichi field held as an attribute of ``obj`` (lists included)."""
    import taichi as ti

    size = {ti.f64: 8, ti.i64: 8, ti.u64: 8, ti.f32: 4, ti.i32: 4, ti.u32: 4, ti.i16: 2,
            ti.u16: 2, ti.i8: 1, ti.u8: 1}
    seen, total = set(), 0
    for v in vars(obj).values():
        for f in v if isinstance(v, (list, tuple)) else [v]:
            if isinstance(f, (ti.ScalarField, ti.MatrixField)) and id(f) not in seen:
                seen.add(id(f))
                per = f.n * f.m if isinstance(f, ti.MatrixField) else 1
                total += int(np.prod(f.shape)) * per * size[f.dtype]
    return total


def full_config(threads: int, arch: str = "cpu"):
    from calendaring import load_preset, with_overrides

    return with_overrides(load_preset("paper"), {"numerics.threads": threads,
                                                 "numerics.arch": arch})


def tile(pos, rad, mat, cfg, nx: int, ny: int):
    from calendaring import with_overrides

    lx, ly = cfg.domain.cell_x, cfg.domain.cell_y
    shifts = [(i * lx, j * ly, 0.0) for i in range(nx) for j in range(ny)]
    pos = np.concatenate([pos + np.array(s) for s in shifts])
    cfg = with_overrides(cfg, {"domain.cell_x": nx * lx, "domain.cell_y": ny * ly})
    return pos, np.tile(rad, nx * ny), np.tile(mat, nx * ny), cfg


def measure_full(cfg, pos, rad, mat, z_top, steps: int, speed: float) -> dict:
    """Full model from the compacted bed: bonds created, breakage live, ``steps`` timed."""
    from calendaring import Simulation, pool_capacity

    cap = pool_capacity(cfg, rad, mat)
    sim = Simulation(cfg, capacity=cap)
    try:
        sim.add_particles(pos, rad, mat, order="space")
        sim.set_top_plate(z=z_top, velocity=-speed)
        n_bonds = sim.create_bonds()
        sim.start_breakage()
        sim.run(50)  # warm-up
        t0 = time.perf_counter()
        sim.run(steps)
        wall = time.perf_counter() - t0
        n = sim.pool.n_alive()
        parts = {name: field_bytes(o) for name, o in (
            ("pool", sim.pool), ("pair_table", sim.table), ("grid", sim.grid),
            ("bonds", sim.bonds), ("kernels", sim.kernels), ("breakage", sim.breakage))
            if o is not None}
        mem = sum(parts.values())
        return {"particles": n, "pool_capacity": cap, "bonds": n_bonds, "steps": steps,
                "wall_s": wall, "steps_per_s": steps / wall,
                "particle_steps_per_s": n * steps / wall, "dt_s": sim.dt,
                "breakage_events": sim.n_breakage_events,
                "pairs": int(sim.table.n_pairs[None]), "pair_capacity": sim.table.capacity,
                "device_bytes": mem, "device_bytes_by_part": parts,
                "bytes_per_slot": mem / cap}
    finally:
        sim.destroy()


STARTUP = """
import time, sys
t0 = time.perf_counter()
sys.path.insert(0, {here!r})
from bench_dem import full_config
from calendaring.engine.simulation import Simulation
import numpy as np
cfg = full_config(1, {arch!r})
rng = np.random.default_rng(0)
pos = np.column_stack([rng.uniform(0, 1e-4, 40), rng.uniform(0, 1e-4, 40),
                       np.linspace(6e-6, 190e-6, 40)])
sim = Simulation(cfg, capacity=200)
sim.add_particles(pos, np.full(40, 2e-6), np.arange(40) % 2)
sim.create_bonds()
sim.start_breakage()
sim.run(2)
print("STARTUP", time.perf_counter() - t0)
"""


def startup_times(arch: str = "cpu") -> dict:
    """Seconds from a fresh interpreter to two steps of the full model: with an empty
    kernel cache (first compile), then again with that cache (cached start-up)."""
    cache = tempfile.mkdtemp(prefix="bench-kcache-")
    try:
        out = {}
        for key in ("first_compile_s", "cached_start_s"):
            code = STARTUP.format(here=str(HERE), arch=arch)
            proc = subprocess.run([sys.executable, "-c", code],
                                  capture_output=True, text=True,
                                  env=dict(os.environ, CALENDARING_KERNEL_CACHE=cache))
            m = re.search(r"STARTUP ([0-9.eE+-]+)", proc.stdout)
            if proc.returncode != 0 or not m:
                raise SystemExit(f"start-up probe failed:\n{proc.stdout}\n{proc.stderr}")
            out[key] = float(m.group(1))
        return out
    finally:
        shutil.rmtree(cache, ignore_errors=True)


def cached_bed(cfg, seed: int, cell_scale: float, folder: str | None):
    """:func:`paper_bed`, kept as NPZ in ``folder`` (when given) for reruns."""
    from calendaring import with_overrides

    path = Path(folder) / f"full-bed-s{seed}-x{cell_scale:.4f}.npz" if folder else None
    if path is not None and path.exists():
        with np.load(path) as z:
            c = with_overrides(cfg, {"domain.cell_x": float(z["cell"]),
                                     "domain.cell_y": float(z["cell"])})
            return z["pos"], z["rad"], z["mat"], float(z["z_top"]), c
    pos, rad, mat, z_top, c = paper_bed(cfg, seed, cell_scale)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, pos=pos, rad=rad, mat=mat, z_top=z_top, cell=c.domain.cell_x)
    return pos, rad, mat, z_top, c


TILES = {"20k": (2, 2), "100k": (4, 5), "1M": (14, 14)}  # tilings of the 5k bed


def cmd_scaling(args) -> dict:
    from calendaring import init_taichi

    result = {"benchmark": "bench_dem scaling", "preset": "paper (full model)",
              "arch": args.arch, "threads": args.threads, "speed_m_s": args.speed}
    if not args.skip_startup:
        result["startup"] = startup_times(args.arch)
        print(f"[scaling] start-up: {result['startup']}", flush=True)
    init_taichi(arch=args.arch, threads=args.threads)
    cfg = full_config(args.threads, args.arch)
    rows = []
    small = cached_bed(cfg, args.seed, np.sqrt(0.2), args.bed_dir)
    base = cached_bed(cfg, args.seed, 1.0, args.bed_dir)
    beds = {"1k": small, "5k": base}
    pos, rad, mat, z_top, c5 = base
    for label, (nx, ny) in TILES.items():
        if label in args.sizes:
            p, r, m, c = tile(pos, rad, mat, c5, nx, ny)
            beds[label] = (p, r, m, z_top, c)
    for label in args.sizes:
        p, r, m, zt, c = beds[label]
        steps = max(50, int(args.particle_steps / len(r)))
        row = measure_full(c, p, r, m, zt, steps, args.speed)
        row["label"] = label
        rows.append(row)
        print(f"[scaling] {label}: {row['particles']} particles, {row['steps_per_s']:.0f} "
              f"steps/s, {row['particle_steps_per_s']:.3g} particle-steps/s, "
              f"{row['bytes_per_slot']:.0f} B per slot", flush=True)
    result["rows"] = rows
    return result


def _software() -> dict:
    """Version and git commit of the calendaring package that ran."""
    import calendaring

    here = Path(calendaring.__file__).resolve().parent
    proc = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here,
                          capture_output=True, text=True)
    dirty = subprocess.run(["git", "status", "--porcelain", "--", "."], cwd=here,
                           capture_output=True, text=True).stdout.strip()
    return {"calendaring": getattr(calendaring, "__version__", "unknown"),
            "path": str(here), "commit": proc.stdout.strip() or None,
            "modified": bool(dirty)}


def overhead_once(threads: int, steps: int, repeat: int) -> dict:
    """Steps/s of the Hertz-mode step on a one-particle bed: what a step costs beyond its
    arithmetic (the kernel launch from Python, the host's flag check and, with more than
    one thread, the thread pool's dispatch of each parallel loop)."""
    from calendaring import Simulation, init_taichi, load_preset

    init_taichi(arch="cpu", threads=threads)
    cfg = hertz_config(load_preset("paper"), threads)
    sim = Simulation(cfg, capacity=8)
    try:
        sim.add_particles(np.array([[50e-6, 50e-6, 10e-6]]), np.array([4e-6]), np.array([0]))
        sim.set_top_plate(z=70e-6, velocity=0.0)
        sim.prime()
        sim.run(1000)
        rates = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            sim.run(steps)
            rates.append(steps / (time.perf_counter() - t0))
    finally:
        sim.destroy()
    best = max(rates)
    return {"threads": threads, "steps": steps, "steps_per_s_runs": rates,
            "steps_per_s_best": best, "us_per_step_best": 1e6 / best,
            "us_per_step_median": 1e6 / float(np.median(rates))}


def cmd_overhead(args) -> dict:
    """:func:`overhead_once` for each thread count, each in a fresh process (Taichi starts
    once per process)."""
    import subprocess

    rows = []
    for t in args.threads:
        out = subprocess.run(
            [sys.executable, __file__, "overhead-one", "--threads", str(t), "--steps",
             str(args.steps), "--repeat", str(args.repeat)],
            check=True, capture_output=True, text=True).stdout
        row = json.loads(out.strip().splitlines()[-1])
        print(f"[overhead] {t} thread(s): {row['us_per_step_best']:.1f} us per step "
              f"(best of {args.repeat})", flush=True)
        rows.append(row)
    return {"benchmark": "bench_dem overhead",
            "problem": "Hertz-mode step (paper preset reduced to Hertz-Mindlin) on one "
                       "particle: the per-step cost that does not scale with the bed",
            "rows": rows}


def cmd_paper(args) -> dict:
    """A whole calendering run of a preset as a user starts it (``calendaring run``): the
    electrode built from scratch (settling, pre-compaction, relaxation), calendered with
    bonds and breakage, unloaded; wall time and steps/s of each stage from the run file."""
    from calendaring import CalenderRun, load_preset, read_run, with_overrides

    cfg = with_overrides(load_preset(args.preset), {"numerics.threads": args.threads,
                                                    "numerics.arch": args.arch})
    folder = Path(args.run_dir) if args.run_dir else Path(tempfile.mkdtemp(prefix="bench-run-"))
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{args.preset}.h5"
    runner = CalenderRun(cfg, path, progress=True, preset=args.preset)
    resume = runner.checkpoint.exists()  # a run stopped part-way goes on from its checkpoint
    t0 = time.perf_counter()
    runner.execute(resume=resume)
    process_wall = time.perf_counter() - t0
    rec = read_run(path)
    info = rec.info
    stages = {name: {**st, "steps_per_s": st["steps"] / st["wall_seconds"]
                     if st["wall_seconds"] > 0 else None}
              for name, st in info.get("stages", {}).items()}
    bed = info.get("bed_after_build", {})
    snap = rec.snapshots[-1] if rec.snapshots else None
    result = {
        "benchmark": "bench_dem paper", "preset": args.preset, "arch": args.arch,
        "threads": args.threads, "resumed": resume,
        "wall_s": info["wall_seconds"], "process_wall_s": process_wall,
        "stages": stages,
        "particles_at_start": info.get("n_particles"),
        "particles_at_end": len(snap.radius) if snap is not None else None,
        "bonds": info.get("bonds_created"), "breakage_events": info.get("breakage_events"),
        "calender_steps": info.get("calender_steps"), "dt_s": info.get("dt"),
        "plate_speed_m_s": info.get("plate_speed"),
        "final_pressure_Pa": float(rec.pressure["value"][-1]) if len(rec.pressure["value"])
        else None,
        "bed_after_build": bed, "run_file": str(path) if args.run_dir else None,
    }
    if not args.run_dir:
        shutil.rmtree(folder, ignore_errors=True)
    cal = stages.get("calender", {})
    print(f"[paper] {args.preset}: {result['wall_s'] / 60:.1f} min in all; calendering "
          f"{cal.get('steps')} steps in {cal.get('wall_seconds', 0) / 60:.1f} min "
          f"({cal.get('steps_per_s') or 0:.0f} steps/s), {result['breakage_events']} "
          f"breakage events", flush=True)
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    v = sub.add_parser("versus", help="ours against LIGGGHTS on the same bed (Hertz-Mindlin)")
    v.add_argument("--steps", type=int, default=20000)
    v.add_argument("--speed", type=float, default=0.05, help="top-plate speed [m/s]")
    v.add_argument("--threads", type=int, default=2)
    v.add_argument("--arch", default="cpu", choices=["cpu", "cuda"],
                   help="our backend (LIGGGHTS runs on the CPU)")
    v.add_argument("--pause", type=float, default=0.0,
                   help="idle seconds before each run (lets the machine settle between "
                        "the two codes)")
    v.add_argument("--repeat", type=int, default=3,
                   help="runs of each code (medians reported: the machine is noisy)")
    v.add_argument("--np", type=int, default=2, help="LIGGGHTS MPI ranks")
    v.add_argument("--liggghts", default=None,
                   help="LIGGGHTS binary (default: on PATH); 'off' runs ours alone")
    v.add_argument("--liggghts-skin", type=float, default=0.6e-6,
                   help="LIGGGHTS neighbour skin [m] (the reference input's)")
    v.add_argument("--skin", type=float, default=None,
                   help="our Verlet skin [m] (default: the same as --liggghts-skin)")
    v.add_argument("--rolling-friction", type=float, default=None,
                   help="rolling friction of every pair in both codes (default: the paper's)")
    v.add_argument("--seed", type=int, default=0)
    v.add_argument("--porosity", type=float, default=0.33,
                   help="porosity of the loaded bed both codes start from")
    v.add_argument("--keep", action="store_true", help="keep the LIGGGHTS folder")
    v.add_argument("--bed", default=None,
                   help="NPZ of the compacted bed: loaded when it exists, else written")
    v.add_argument("--out", default=str(RESULTS / "bench_dem_versus.json"))
    s = sub.add_parser("scaling", help="full model: particle-steps/s, memory, start-up")
    s.add_argument("--threads", type=int, default=2)
    s.add_argument("--arch", default="cpu", choices=["cpu", "cuda"])
    s.add_argument("--sizes", nargs="+", default=["1k", "5k", "20k", "100k"],
                   choices=["1k", "5k", "20k", "100k", "1M"])
    s.add_argument("--particle-steps", type=float, default=2e7,
                   help="timed particle-steps per size")
    s.add_argument("--speed", type=float, default=0.05, help="top-plate speed [m/s]")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--skip-startup", action="store_true")
    s.add_argument("--bed-dir", default=None, help="keep the compacted beds here (NPZ)")
    s.add_argument("--out", default=str(RESULTS / "bench_dem_scaling.json"))
    o = sub.add_parser("overhead", help="per-step cost on a one-particle bed (launch, "
                       "dispatch)")
    o.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    o.add_argument("--steps", type=int, default=5000)
    o.add_argument("--repeat", type=int, default=5)
    o.add_argument("--out", default=str(RESULTS / "bench_dem_overhead.json"))
    w = sub.add_parser("paper", help="a whole calendering run of a preset: wall time per "
                       "stage")
    w.add_argument("--preset", default="paper")
    w.add_argument("--threads", type=int, default=2)
    w.add_argument("--arch", default="cpu", choices=["cpu", "cuda"])
    w.add_argument("--run-dir", default=None,
                   help="keep the run file (and its checkpoint) here; a rerun resumes a "
                        "stopped run (default: a temporary folder, removed)")
    w.add_argument("--out", default=None,
                   help="JSON path (default results/bench_dem_paper.json, or "
                        "bench_dem_paper_PRESET.json for another preset)")
    o1 = sub.add_parser("overhead-one", help=argparse.SUPPRESS)
    o1.add_argument("--threads", type=int, required=True)
    o1.add_argument("--steps", type=int, default=5000)
    o1.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    if args.cmd == "overhead-one":  # child of cmd_overhead: one JSON line on stdout
        print(json.dumps(overhead_once(args.threads, args.steps, args.repeat)))
        return 0
    if args.cmd == "paper" and args.out is None:
        tail = "" if args.preset == "paper" else f"_{args.preset}"
        args.out = str(RESULTS / f"bench_dem_paper{tail}.json")
    result = {"versus": cmd_versus, "scaling": cmd_scaling, "overhead": cmd_overhead,
              "paper": cmd_paper}[args.cmd](args)
    result.update({"software": _software(), "python": sys.version.split()[0],
                   "machine": platform.machine(),
                   "processor": platform.processor(), "cpus": os.cpu_count(),
                   "load_average": os.getloadavg(),
                   "date": time.strftime("%Y-%m-%d %H:%M:%S")})
    from calendaring import write_json

    write_json(Path(args.out), result)
    print(json.dumps(result, indent=2, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
