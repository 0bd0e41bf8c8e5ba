"""Command line: ``calendaring run | inspect | plot | export``.

Exit codes (the contract of :mod:`calendaring.core.cli_contract`, shared by the four programs):
0 success, 2 bad input (one line naming the key, the value and what is allowed; nothing
written), 3 the simulation stopped on a guard (diagnostic printed; the last checkpoint is
kept), 1 an internal error (a bug: traceback and a line saying so), 130 interrupted.

    calendaring run --preset quick --out runs/quick.h5
    calendaring run my.toml --set protocol.stroke=10e-6 --out runs/a.h5 --seed 3
    calendaring run --preset paper --out runs/paper.h5 --resume     # after a crash
    calendaring inspect runs/quick.h5
    calendaring plot runs/quick.h5
    calendaring export runs/quick.h5 --snapshot 4 --vtk
    calendaring pack --preset quick --seed 0 --out bed.csv      # settle a bed only
    calendaring sweep --design lhs --n 280 --preset sweep --out RUNS/
    calendaring dataset RUNS/ --out data/dataset.h5
    calendaring digest RUNS/                  # digests of run files made without them

See also: :mod:`calendaring.core.cli_contract` (exit codes and argument checks),
:mod:`calendaring.process.run` (``run``), :mod:`calendaring.data.sweep` (``sweep``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from calendaring.core.cli_contract import (
    EXIT_OK,
    ContractParser,
    input_file,
    input_folder,
    integer,
    output_path,
    real,
    run_cli,
)
from calendaring.core.config import (
    ARCHES,
    CONFIG_SUFFIXES,
    PRESETS,
    SEED_MAX,
    THREADS_MAX,
    load_config,
    load_preset,
    parse_override,
    with_overrides,
)
from calendaring.core.errors import ConfigError
from calendaring.core.units import to_mpa, to_um
from calendaring.process.preflight import DEFAULT_MAX_HOURS


def _parser() -> argparse.ArgumentParser:
    ap = ContractParser(prog="calendaring", description=__doc__.split("\n\n")[0],
                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True, parser_class=ContractParser)
    r = sub.add_parser("run", help="run a calendering simulation into an HDF5 run file")
    _config_args(r)
    r.add_argument("--out", required=True, help="run file to write (.h5)")
    r.add_argument("--resume", action="store_true",
                   help="continue from <out>.ckpt (or <out>.ckpt.prev if that one is cut "
                        "short or corrupt)")
    r.add_argument("--restart-if-unusable", action="store_true",
                   help="with --resume: start afresh when no checkpoint is usable (sweeps)")
    r.add_argument("--no-breakage", action="store_true",
                   help="the no-breakage control (paper R0): breakage.enabled = false, "
                        "same packing and seed")
    r.add_argument("--overwrite", action="store_true", help="replace an existing run file")
    i = sub.add_parser("inspect", help="print a summary of a run file")
    i.add_argument("run_file")
    i.add_argument("--json", action="store_true", help="machine-readable summary")
    p = sub.add_parser("plot", help="pressure-depth and microstructure PNGs of a run file")
    p.add_argument("run_file")
    p.add_argument("--out-dir", help="folder for the PNGs (default: next to the run file)")
    e = sub.add_parser("export", help="write one snapshot as VTK, LAMMPS data or CSV")
    e.add_argument("run_file")
    e.add_argument("--snapshot", type=integer(0), required=True, help="snapshot index k")
    fmt = e.add_mutually_exclusive_group(required=True)
    fmt.add_argument("--vtk", action="store_true", help="ParaView .vtp (needs pyvista)")
    fmt.add_argument("--lammps", action="store_true", help="LAMMPS data, atom_style granular")
    fmt.add_argument("--csv", action="store_true", help="calendaring packing CSV")
    e.add_argument("--out", help="output path (default: <run>_snap<k>.<ext>)")
    k = sub.add_parser("pack", help="insert and settle a bed only, and write it as a packing "
                                    "CSV (runs start from it with electrode.packing)")
    _config_args(k)
    k.add_argument("--out", required=True, help="packing CSV to write")
    k.add_argument("--overwrite", action="store_true", help="replace an existing file")
    s = sub.add_parser("sweep", help="many runs over a design of the 8 breakage parameters, "
                                     "as Dask tasks (resumable)",
                       description=_sweep_doc(),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("config", nargs="?", help="configuration TOML (or use --preset)")
    s.add_argument("--preset", choices=PRESETS, help="a configuration shipped with the package")
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value for every run; repeatable")
    s.add_argument("--design", default="lhs",
                   help="lhs | sobol | reference | centre | DESIGN.csv (default lhs)")
    s.add_argument("--n", type=integer(1, 10**7), default=1, help="design points (default 1)")
    s.add_argument("--seed", type=integer(0, SEED_MAX), default=0,
                   help="run seed (bed and fracture energies); replicates use seed+1, ...")
    s.add_argument("--seed-per-row", action="store_true",
                   help="each design row its own seed (seed + row x replicates + replicate): "
                        "every run on a bed of its own")
    s.add_argument("--beds", type=integer(1, 10**6),
                   help="the rows take turns over this many seeds (seed + (row mod K) x "
                        "replicates + replicate): K settled beds for the whole design")
    s.add_argument("--design-seed", type=integer(0, SEED_MAX),
                   help="seed of the design (default --seed)")
    s.add_argument("--replicates", type=integer(1, 10**6), default=1,
                   help="seeds per design point")
    s.add_argument("--role", default="train", help="train | replicate | holdout | refine")
    s.add_argument("--out", required=True, help="sweep folder (created; reused to resume)")
    s.add_argument("--scheduler", help="address of a running Dask scheduler "
                                       "(default: a LocalCluster on this machine)")
    s.add_argument("--workers", type=integer(0, THREADS_MAX), default=0,
                   help="LocalCluster workers (default: cores / threads per run)")
    s.add_argument("--threads-per-run", type=integer(1, THREADS_MAX), default=1,
                   help="CPU threads of each run")
    s.add_argument("--max-attempts", type=integer(1, 100), default=2,
                   help="tries per run (default 2)")
    s.add_argument("--timeout", type=real(0, lo_open=True, unit="s"),
                   help="seconds per run attempt (default none)")
    s.add_argument("--gpu", action="store_true",
                   help="each run needs one 'GPU' worker resource (workers started with "
                        "--resources GPU=1); set numerics.arch with --set")
    s.add_argument("--quiet", action="store_true", help="no progress lines")
    g = sub.add_parser("digest", help="write the digest (what a dataset needs, ~30 kB) of "
                                      "every finished run file of a sweep folder that lacks "
                                      "one")
    g.add_argument("runs", help="sweep folder")
    g.add_argument("--overwrite", action="store_true", help="rewrite existing digests")
    d = sub.add_parser("dataset", help="consolidate a sweep's run files (or their digests) "
                                       "into a training dataset file")
    d.add_argument("runs", help="sweep folder (or a folder of run files)")
    d.add_argument("--out", required=True, help="dataset file to write (.h5)")
    d.add_argument("--points", type=integer(2, 10**6), default=196,
                   help="pressure points (default 196)")
    d.add_argument("--savgol-window", type=integer(1, 10**6), default=17,
                   help="Savitzky-Golay window")
    d.add_argument("--savgol-order", type=integer(0, 100), default=3,
                   help="Savitzky-Golay order")
    d.add_argument("--bins", type=integer(2, 10**4), default=30,
                   help="histogram bins per axis")
    d.add_argument("--load-scale", choices=("log", "linear"), default="log",
                   help="peak-load axis of the histogram (default log)")
    d.add_argument("--load-range", type=real(0, lo_open=True, unit="N"), nargs=2,
                   metavar=("MIN_N", "MAX_N"),
                   help="fixed peak-load edges [N] (default: the events' range)")
    d.add_argument("--diameter-range", type=real(0, lo_open=True, unit="m"), nargs=2,
                   metavar=("MIN_M", "MAX_M"),
                   help="fixed diameter edges [m] (default: the events' range)")
    d.add_argument("--note", action="append", default=[], metavar="KEY=TEXT",
                   help="a note kept in the provenance under notes.KEY, e.g. which commit "
                        "ran runs that predate the recording of source commits (repeatable)")
    d.add_argument("--overwrite", action="store_true", help="replace an existing file")
    d.add_argument("--quiet", action="store_true", help="no progress lines")
    return ap


def _sweep_doc() -> str:
    from calendaring.data import sweep

    return sweep.__doc__.split("Layout")[0]


def _config_args(r) -> None:
    r.add_argument("config", nargs="?", help="configuration TOML (or use --preset)")
    r.add_argument("--max-hours", type=real(0, lo_open=True, unit="h"),
                   default=DEFAULT_MAX_HOURS, help="refuse a run whose estimated wall time "
                   f"is longer (default {DEFAULT_MAX_HOURS:g} h; see "
                   "calendaring.process.preflight)")
    r.add_argument("--preset", choices=PRESETS, help="a configuration shipped with the package")
    r.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value (dotted key, TOML value); repeatable")
    r.add_argument("--arch", choices=[a for a in ARCHES if a != "auto"], help="Taichi backend")
    r.add_argument("--seed", type=integer(0, SEED_MAX), help="random seed (numerics.seed)")
    r.add_argument("--threads", type=integer(0, THREADS_MAX),
                   help="CPU threads (numerics.threads, 0 = all)")
    r.add_argument("--quiet", action="store_true", help="no progress lines")
    r.set_defaults(no_breakage=False, resume=False, restart_if_unusable=False)


def _run_config(args):
    if bool(args.config) == bool(args.preset):
        raise ConfigError("config", args.config or args.preset,
                          "exactly one of CONFIG.toml (or .json) or --preset NAME")
    cfg = (load_preset(args.preset) if args.preset
           else load_config(input_file(args.config, "config", CONFIG_SUFFIXES)))
    overrides = dict(parse_override(s) for s in args.set)
    if args.arch:
        overrides["numerics.arch"] = args.arch
    if args.seed is not None:
        overrides["numerics.seed"] = args.seed
    if args.threads is not None:
        overrides["numerics.threads"] = args.threads
    if args.no_breakage:
        overrides["breakage.enabled"] = False
    if overrides:
        cfg = with_overrides(cfg, overrides)
    return cfg.check_run()


def _preflight(cfg, args) -> None:
    """Refuse a run that would not fit the machine; print the estimate (stderr)."""
    from calendaring.process.preflight import check

    est = check(cfg, max_hours=args.max_hours)
    if not args.quiet:
        print(est.line(), file=sys.stderr, flush=True)


def cmd_run(args) -> int:
    cfg = _run_config(args)
    out = output_path(args.out, "--out", suffixes=(".h5", ".hdf5"),
                      overwrite=args.overwrite or args.resume)
    _preflight(cfg, args)
    from calendaring.process.run import CalenderRun

    runner = CalenderRun(cfg, out, progress=not args.quiet, preset=args.preset or "")
    if args.resume and not runner.checkpoints():
        raise ConfigError("--resume", str(runner.checkpoint), "an existing checkpoint file")
    resume = ("auto" if args.restart_if_unusable else True) if args.resume else False
    path = runner.execute(resume=resume)
    print(f"wrote {path}")
    return EXIT_OK


def cmd_pack(args) -> int:
    cfg = _run_config(args)
    out = output_path(args.out, "--out", suffixes=(".csv",), overwrite=args.overwrite)
    _preflight(cfg, args)
    from calendaring.process.run import build_packing

    print(f"wrote {build_packing(cfg, out, progress=not args.quiet)}")
    return EXIT_OK


def cmd_sweep(args) -> int:
    from calendaring.data.sweep import SweepOptions, summary, sweep

    if bool(args.config) == bool(args.preset):
        raise ConfigError("config", args.config or args.preset,
                          "exactly one of CONFIG.toml (or .json) or --preset NAME")
    if args.config:
        input_file(args.config, "config", CONFIG_SUFFIXES)
    out = output_path(args.out, "--out", folder=True)
    source = f"preset:{args.preset}" if args.preset else str(Path(args.config).resolve())
    opt = SweepOptions(source=source, out=out, design=args.design, n=args.n, seed=args.seed,
                       design_seed=args.design_seed, replicates=args.replicates,
                       seed_per_row=args.seed_per_row, beds=args.beds or 0,
                       role=args.role, overrides=dict(parse_override(s) for s in args.set),
                       workers=args.workers, threads_per_run=args.threads_per_run,
                       scheduler=args.scheduler, max_attempts=args.max_attempts,
                       timeout=args.timeout, gpu=args.gpu, progress=not args.quiet)
    runs = sweep(opt)
    s = summary(runs)
    print(json.dumps(s))
    failed = [e for e in runs.values() if e.status == "failed"]
    for e in failed:
        print(f"failed: {e.run_id} ({e.attempts} attempts): "
              f"{e.error.splitlines()[0] if e.error else ''}", file=sys.stderr)
    return EXIT_OK


def cmd_digest(args) -> int:
    from calendaring.data.digest import digest_path, run_files_dir, write_digest
    from calendaring.process.runfile import RunFileError, read_run

    folder = input_folder(args.runs, "RUNS")
    output_path(folder / "digests", "RUNS/digests", folder=True)
    wrote = kept = 0
    for path in sorted(run_files_dir(folder).glob("*.h5")):
        dest = digest_path(folder, path.stem)
        if dest.exists() and not args.overwrite:
            kept += 1
            continue
        try:
            rec = read_run(path)
        except RunFileError as err:
            print(f"skipped {path.name}: {err.reason}", file=sys.stderr)
            continue
        write_digest(dest, rec)
        wrote += 1
    print(f"wrote {wrote} digests under {folder / 'digests'} ({kept} already there)")
    return EXIT_OK


def cmd_dataset(args) -> int:
    from calendaring.data.dataset import build_dataset, write_dataset

    input_folder(args.runs, "RUNS")
    notes = {}
    for item in args.note:
        key, sep, text = item.partition("=")
        if not sep or not key.strip() or not text.strip():
            raise ConfigError("--note", item, "KEY=TEXT with a non-empty key and text")
        if key.strip() in notes:
            raise ConfigError("--note", item, f"one note per key ({key.strip()!r} repeated)")
        notes[key.strip()] = text.strip()
    out = output_path(args.out, "--out", suffixes=(".h5", ".hdf5"), overwrite=args.overwrite)
    ds = build_dataset(args.runs, n_points=args.points, savgol_window=args.savgol_window,
                       savgol_order=args.savgol_order, bins=args.bins,
                       load_scale=args.load_scale,
                       load_range=tuple(args.load_range) if args.load_range else None,
                       diameter_range=tuple(args.diameter_range) if args.diameter_range
                       else None, progress=not args.quiet,
                       command="calendaring dataset " + " ".join(sys.argv[2:]), notes=notes)
    write_dataset(out, ds)
    from calendaring.core.fileio import write_json
    from calendaring.data.dataset import noise_floor, pressure_components, provenance_report

    prov = write_json(out.with_name(out.stem + ".provenance.json"),
                      provenance_report(args.runs, ds))
    nf = noise_floor(ds)
    roles = {str(r): int(np.sum(ds.role == r)) for r in sorted(set(ds.role))}
    print(f"wrote {out} and {prov.name}: {len(ds)} runs {roles}, {len(ds.skipped)} skipped, "
          f"{int(ds.n_events.sum())} breakage events")
    for name, why in ds.skipped:
        print(f"skipped {name}: {why}", file=sys.stderr)
    if nf["pressure_mse_normalised"] is not None:
        print(f"replicate noise floor: pressure MSE {nf['pressure_mse_normalised']:.3g} "
              f"(normalised), KL to group mean {nf['kl_to_group_mean']:.3g}")
    pc = pressure_components(ds)
    if pc is not None:
        print(f"pressure curves: {pc['resolved']} of {pc['tested']} principal components "
              f"above the bed-to-bed scatter (Holm, alpha {pc['alpha']}), holding "
              f"{100 * (pc['signal_share_resolved'] or 0):.1f} % of the parameter-driven "
              f"variance: a calibration on one curve can pin at most that many parameter "
              f"combinations")
    return EXIT_OK


def summary(rec) -> dict:
    """Key figures of a run (SI)."""
    out = {"file": str(rec.path), "preset": rec.preset, "seed": rec.seed,
           "software_version": rec.software_version, "breakage_model": rec.breakage_model,
           "cell_x": rec.cell_x, "cell_y": rec.cell_y, "thickness": rec.thickness,
           "stroke": rec.stroke, **{k: rec.info.get(k) for k in (
               "dt", "plate_speed", "bonds_created", "final_depth", "wall_seconds")}}
    b = rec.info.get("build", {})
    out["counts"] = b.get("counts")
    out["porosity_at_thickness"] = b.get("porosity_at_thickness")
    d = rec.pressure["depth"]
    out["pressure_at"] = {f"{to_um(x):g} um": rec.pressure_at(x) for x in
                          (5e-6, 10e-6, 15e-6, rec.stroke)
                          if len(d) and d[0] - 1e-12 <= x <= d[-1] + 1e-12}
    out["peak_pressure"] = float(rec.pressure["value"].max()) if len(d) else None
    s = rec.series
    if len(s["depth"]):
        out["final_porosity"] = float(s["porosity"][-1])
        out["bonds_intact_final"] = int(s["bonds_intact"][-1])
        out["max_inertial_number_above_reference"] = _max_inertial(rec)
    out["snapshots"] = [{"index": sn.index, "label": sn.label, "depth": sn.depth,
                         "particles": len(sn.radius)} for sn in rec.snapshots]
    out["breakage_events"] = len(rec.breakage["parent_id"])
    out["fragments"] = len(rec.breakage["fragments"]["id"])
    if "unload" in rec.info:
        out["unload"] = rec.info["unload"]
    return out


def _max_inertial(rec) -> float | None:
    import numpy as np

    s = rec.series
    p_ref = rec.config.protocol.reference_pressure
    sel = s["top_pressure"] >= p_ref
    return float(np.nanmax(s["inertial_number"][sel])) if sel.any() else None


def cmd_inspect(args) -> int:
    from calendaring.process.runfile import read_run

    rec = read_run(args.run_file)
    s = summary(rec)
    if args.json:
        print(json.dumps(s, indent=2, default=str))
        return EXIT_OK
    print(f"{s['file']}  (preset {s['preset'] or '-'}, seed {s['seed']}, "
          f"calendaring {s['software_version']}, breakage: {s['breakage_model']})")
    print(f"cell {to_um(s['cell_x']):.1f} x {to_um(s['cell_y']):.1f} um, thickness "
          f"{to_um(s['thickness']):.2f} um, stroke {to_um(s['stroke']):.2f} um")
    if s["counts"]:
        print("particles: " + ", ".join(f"{v} {k}" for k, v in s["counts"].items())
              + f"; porosity at h0 {100 * s['porosity_at_thickness']:.2f} %")
    print(f"dt {s['dt']:.4g} s, plate speed {s['plate_speed']:.4g} m/s, "
          f"{s['bonds_created']} bonds created, wall time {s['wall_seconds']:.1f} s")
    for k, v in s["pressure_at"].items():
        print(f"  pressure at {k:>8s}: {to_mpa(v):10.4f} MPa")
    if s.get("final_porosity") is not None:
        print(f"final porosity {100 * s['final_porosity']:.2f} %, intact bonds "
              f"{s['bonds_intact_final']}, max inertial number (P >= P_ref) "
              f"{s['max_inertial_number_above_reference']}")
    if s["breakage_model"] != "none":
        print(f"breakage: {s['breakage_events']} events, {s['fragments']} fragments")
    for sn in s["snapshots"]:
        print(f"  snapshot {sn['index']} ({sn['label']}): depth {to_um(sn['depth']):.3f} um, "
              f"{sn['particles']} particles")
    if "unload" in s:
        print(f"unloading: {s['unload']}")
    return EXIT_OK


def cmd_plot(args) -> int:
    from calendaring.process.plots import plot_breakage, plot_microstructure, plot_pressure
    from calendaring.process.runfile import read_run

    rec = read_run(args.run_file)
    folder = Path(args.out_dir) if args.out_dir else rec.path.parent
    output_path(folder, "--out-dir", folder=True)
    folder.mkdir(parents=True, exist_ok=True)
    stem = rec.path.stem
    paths = [plot_pressure(rec, folder / f"{stem}_pressure.png"),
             plot_microstructure(rec, folder / f"{stem}_microstructure.png")]
    if rec.breakage_model != "none":
        paths.append(plot_breakage(rec, folder / f"{stem}_breakage.png"))
    for path in paths:
        print(f"wrote {path}")
    return EXIT_OK


def cmd_export(args) -> int:
    import numpy as np

    from calendaring.process.packing import Packing, write_csv, write_lammps_data, write_vtk
    from calendaring.process.runfile import read_run

    rec = read_run(args.run_file)
    if not 0 <= args.snapshot < len(rec.snapshots):
        raise ConfigError("--snapshot", args.snapshot,
                          f"an index in [0, {len(rec.snapshots) - 1}]")
    sn = rec.snapshots[args.snapshot]
    names = rec.config.material_names
    density = np.array([rec.config.materials[n].density for n in names])[sn.material]
    pk = Packing(position=sn.position, radius=sn.radius, material=sn.material, ids=sn.id + 1,
                 cell_x=rec.cell_x, cell_y=rec.cell_y, z_bottom=sn.z_bottom, z_top=sn.z_top,
                 density=density)
    ext = ".vtp" if args.vtk else ".data" if args.lammps else ".csv"
    out = Path(args.out) if args.out else rec.path.with_name(
        f"{rec.path.stem}_snap{args.snapshot}{ext}")
    output_path(out, "--out", suffixes=(ext,), overwrite=True)
    if args.vtk:
        paths = write_vtk(out, pk, point_data={"normal_force": sn.normal_force,
                                               "velocity": sn.velocity,
                                               "n_contacts": sn.n_contacts})
    elif args.lammps:
        paths = [write_lammps_data(out, pk)]
    else:
        paths = [write_csv(out, pk, material_names=names)]
    for path in paths:
        print(f"wrote {path}")
    return EXIT_OK


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``calendaring`` command.

    Exit codes: :mod:`calendaring.core.cli_contract`.
    """
    from calendaring._version import __version__
    from calendaring.data.dataset import DatasetError
    from calendaring.process.packing import PackingError
    from calendaring.process.runfile import RunFileError

    def handle() -> int:
        args = _parser().parse_args(argv)
        return {"run": cmd_run, "inspect": cmd_inspect, "plot": cmd_plot,
                "export": cmd_export, "pack": cmd_pack, "sweep": cmd_sweep,
                "dataset": cmd_dataset, "digest": cmd_digest}[args.command](args)

    return run_cli("calendaring", handle, (RunFileError, PackingError, DatasetError),
                   __version__)


if __name__ == "__main__":
    sys.exit(main())
