"""Scale study: how the sweep-preset run's noise, bias and cost depend on the cell size and
the plate speed, to choose the production cell of the reference dataset.

``run`` drives one resumable sweep per case (``calendaring sweep --design reference
--replicates K --role replicate``: the Table 4 parameters, seeds S .. S+K-1, one thread a
run): cells of ``--cells`` micrometres at the sweep preset's plate speed, and at the
largest cell the inertial numbers of ``--inertial`` (5e-3, then the paper's 1e-3) with
``--speed-seeds`` seeds; the cheaper cases run first. Each case is a folder
``cell-<um>um`` or ``cell-<um>um-I<I>`` under ``--out``; rerunning the same command
resumes every case (finished runs are kept, runs in flight resume from their
checkpoints), so the study survives a stop.

``report`` reads the run files back (through ``calendaring.process.runfile.read_run``) and writes,
per case: runs done, wall seconds per run (one thread), particles at start and end,
breakage events per run, the top pressure at 5 / 10 / 15 / 19.5 um (mean and sd over
seeds), the replicate variance of the 196-point curve in normalised units (resampled and
smoothed as ``calendaring dataset`` does, then normalised with the reference dataset's
stored cube-root range, one scale for every case, ``--reference``), the mean pairwise KL
between the seeds' 30 x 30 breakage histograms (the reference dataset's bin edges), the
cost of information (variance x CPU seconds per run: lower is better), and the bias of
each case against the largest cell at the sweep speed (the difference of the mean
pressures in units of their combined standard error, and the KL of the pooled
histograms against the largest cell's pairwise KL).

    python benchmarks/scale_study.py run --out studies/scale --workers 2
    python benchmarks/scale_study.py report --out studies/scale

Writes JSON (default benchmarks/results/scale_study.json) and a Markdown table beside it.

Every finished run is also kept as a compact archive, ``--archive`` (default
benchmarks/results/scale_runs/<case>/<run>.npz: the raw pressure record, the breakage
events' loads and diameters, the counts and wall seconds, and the run file's software
version; the invocations' commits go to ``provenance.json`` beside them), so
the study's evidence lives in the repository and survives the loss of the study folder:
``report`` pools the archive with the folder's run files (one entry per case and seed),
and ``run`` skips a case whose seeds are all archived.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
REFERENCE = HERE.parent / "data" / "reference.h5"
DEPTHS_UM = (5.0, 10.0, 15.0, 19.5)


def cases(cells: list[float], inertial: list[float], seeds: int, speed_seeds: int,
          speed_cells: list[float] | None = None) -> list[dict]:
    """The study's cases: every cell at the preset's speed, then each of ``speed_cells``
    (default: the largest cell) at each inertial number of ``inertial``."""
    out = [{"name": f"cell-{c:g}um", "cell_um": c, "inertial": None, "seeds": seeds}
           for c in cells]
    for c in speed_cells or [max(cells)]:
        out += [{"name": f"cell-{c:g}um-I{i:g}", "cell_um": c, "inertial": i,
                 "seeds": speed_seeds} for i in inertial]
    return out


def sweep_command(case: dict, folder: Path, seed: int, workers: int, preset: str = "sweep",
                  threads: int = 1) -> list[str]:
    side = f"{case['cell_um'] * 1e-6:.6g}"
    cmd = [sys.executable, "-m", "calendaring.cli", "sweep", "--preset", preset,
           "--design", "reference", "--n", "1", "--replicates", str(case["seeds"]),
           "--role", "replicate", "--seed", str(seed), "--threads-per-run", str(threads),
           "--workers", str(workers), "--out", str(folder),
           "--set", f"domain.cell_x={side}", "--set", f"domain.cell_y={side}"]
    if case["inertial"] is not None:
        cmd += ["--set", f"protocol.inertial_number={case['inertial']:g}"]
    return cmd


def cmd_run(args) -> int:
    from bench_dem import _software  # this folder is on sys.path when run as a script

    from calendaring import write_json

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    todo = cases(args.cells, args.inertial, args.seeds, args.speed_seeds, args.speed_cells)
    prov_path = out / "provenance.json"
    prov = json.loads(prov_path.read_text()) if prov_path.exists() else {"invocations": []}
    prov["invocations"].append({"date": time.strftime("%Y-%m-%d %H:%M:%S"),
                                "argv": sys.argv, **_software()})
    write_json(prov_path, prov)
    for k, case in enumerate(todo):
        folder = out / case["name"]
        want = set(range(args.seed, args.seed + case["seeds"]))
        have = {r["seed"] for r in _archived(Path(args.archive) / case["name"])}
        if want <= have:
            print(f"[scale] case {k + 1}/{len(todo)}: {case['name']}: seeds "
                  f"{sorted(want)} archived, skipped", flush=True)
            continue
        print(f"[scale] case {k + 1}/{len(todo)}: {case['name']} ({case['seeds']} seeds) "
              f"-> {folder}", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.run(sweep_command(case, folder, args.seed, args.workers,
                                          args.preset, args.threads_per_run)).returncode
        print(f"[scale] {case['name']}: sweep exit {rc} after "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
        n = archive(folder, Path(args.archive) / case["name"])
        _record_invocations(Path(args.archive) / "provenance.json", prov["invocations"])
        print(f"[scale] {case['name']}: {n} runs archived", flush=True)
        if rc not in (0, 3):  # 3: some runs failed (recorded in the manifest); go on
            return rc
    return 0


def _record_invocations(path: Path, invocations: list[dict]) -> None:
    """Add the invocations not yet listed to the archive's provenance (studies running side
    by side into one archive each keep theirs)."""
    from calendaring import write_json

    prov = json.loads(path.read_text()) if path.exists() else {"invocations": []}
    seen = {json.dumps(i, sort_keys=True) for i in prov["invocations"]}
    prov["invocations"] += [i for i in invocations if json.dumps(i, sort_keys=True) not in seen]
    write_json(path, prov)


# ---------------------------------------------------------------------- report
def _num(v):
    return None if v is None else float(v)


def _runs(folder: Path) -> list[dict]:
    """The finished runs of one case: curve, histogram inputs, counts, wall seconds."""
    from calendaring import RunFileError, read_manifest, read_run

    manifest = read_manifest(folder) if (folder / "manifest.json").exists() else {}
    walls = {Path(e.file).name: e.wall_time for e in manifest.values()
             if getattr(e, "status", "") == "done"}
    out = []
    for path in sorted((folder / "runs").glob("*.h5")):
        try:
            rec = read_run(path)
        except RunFileError:
            continue  # in flight or cut short: not a finished run
        out.append({"name": path.stem, "seed": int(rec.seed),
                    "software_version": rec.software_version, "depth": rec.pressure["depth"],
                    "pressure": rec.pressure["value"], "stroke": rec.stroke,
                    "load": np.asarray(rec.breakage["peak_load"]),
                    "diameter": np.asarray(rec.breakage["diameter"]),
                    "events": len(rec.breakage["parent_id"]),
                    "particles_start": int(rec.info["n_particles"]),
                    "particles_end": int(rec.series["particles"][-1]),
                    "threads": int(rec.config.numerics.threads),
                    "wall_s": _num(walls.get(path.name, rec.info.get("wall_seconds")))})
    return out


_ARRAYS = ("depth", "pressure", "load", "diameter")


def archive(folder: Path, dest: Path) -> int:
    """Write each finished run of ``folder`` not yet in ``dest`` as ``<run>.npz``; returns
    how many runs ``dest`` now holds."""
    if folder.is_dir():
        dest.mkdir(parents=True, exist_ok=True)
        for r in _runs(folder):
            path = dest / f"{r['name']}.npz"
            if path.exists():
                continue
            tmp = path.with_suffix(".tmp.npz")
            meta = {k: v for k, v in r.items() if k not in _ARRAYS}
            np.savez_compressed(tmp, **{k: np.asarray(r[k]) for k in _ARRAYS},
                                meta=np.array(json.dumps(meta)))
            tmp.replace(path)
    return len(_archive_files(dest))


def _archive_files(dest: Path) -> list[Path]:
    """The archived runs of one case (a write cut short leaves only a ``.tmp.npz``)."""
    return [p for p in sorted(dest.glob("*.npz")) if not p.name.endswith(".tmp.npz")]


def _archived(dest: Path) -> list[dict]:
    out = []
    for path in _archive_files(dest):
        with np.load(path) as z:
            out.append({**json.loads(str(z["meta"])), **{k: z[k] for k in _ARRAYS}})
    return out


def pooled(folder: Path, dest: Path) -> list[dict]:
    """The case's finished runs, one per seed: the folder's run files, then the archive's."""
    runs = {}
    for r in _archived(dest) + (_runs(folder) if folder.is_dir() else []):
        runs[int(r["seed"])] = r
    return [runs[k] for k in sorted(runs)]


def summarise(runs: list[dict], ref) -> dict:
    """Statistics of one case's runs (see the module docstring)."""
    from calendaring import bin_events, kl_divergence, resample_pressure, smooth

    n = len(runs)
    curves = []
    for r in runs:
        mid, p = resample_pressure(r["depth"], r["pressure"], r["stroke"], len(ref.depth))
        curves.append(np.maximum(smooth(p), 0.0))
    curves = np.array(curves)
    depth_um = mid * 1e6
    at = {}
    for d in DEPTHS_UM:
        j = int(np.argmin(np.abs(depth_um - d)))
        col = curves[:, j]
        at[f"{d:g}um"] = {"mean_MPa": float(col.mean() / 1e6),
                          "sd_MPa": float(col.std(ddof=1) / 1e6) if n > 1 else None}
    x = ref.normalise_pressure(curves)
    var = float(x.var(axis=0, ddof=1).mean()) if n > 1 else None
    hists = np.array([bin_events(r["load"], r["diameter"], ref.load_edges, ref.diameter_edges)
                      for r in runs])
    has = [k for k in range(n) if runs[k]["events"] > 0]
    pair = [float(kl_divergence(hists[a], hists[b])) for i, a in enumerate(has)
            for b in has[i + 1:]]
    walls = [r["wall_s"] for r in runs if r["wall_s"]]
    threads = sorted({int(r.get("threads", 1)) for r in runs})
    wall = float(np.mean(walls)) if walls else None
    return {
        "runs": n, "seeds": [int(r["seed"]) for r in runs],
        "wall_s_per_run": wall, "threads_per_run": threads,
        "particles_start": float(np.mean([r["particles_start"] for r in runs])),
        "particles_end": float(np.mean([r["particles_end"] for r in runs])),
        "events_mean": float(np.mean([r["events"] for r in runs])),
        "events_sd": float(np.std([r["events"] for r in runs], ddof=1)) if n > 1 else None,
        "pressure": at, "pressure_var_normalised": var,
        "kl_pairwise": float(np.mean(pair)) if pair else None,
        "variance_x_cpu_s": var * wall if var is not None and wall else None,
        "_curves": curves, "_depth_um": depth_um,
        "_hist": hists[has].mean(axis=0) if has else None}


def bias(case: dict, base: dict) -> dict:
    """Mean-curve and histogram differences of ``case`` against ``base``: z = |mean
    difference| / combined standard error per depth where both have two runs or more, else
    against the base's seed standard deviation alone (one run's difference in base sds).
    Also over the stroke past its first 10 %: there the plate-speed comparison is free of
    the plate's first impact on the bed (a dynamic load of a few MPa whose seed scatter is
    tiny, so its z is large at any speed difference), and the mean relative difference of
    the mean curves."""
    from calendaring import kl_divergence

    out = {}
    a, b = case["_curves"], base["_curves"]
    if len(b) > 1:
        va = a.var(axis=0, ddof=1) / len(a) if len(a) > 1 else b.var(axis=0, ddof=1)
        se = np.sqrt(va + b.var(axis=0, ddof=1) / len(b))
        z = np.abs(a.mean(axis=0) - b.mean(axis=0)) / np.where(se > 0, se, np.inf)
        out["pressure_z_max"] = float(z.max())
        out["pressure_z_mean"] = float(z.mean())
        out["points_beyond_2se"] = float(np.mean(z > 2.0))
        out["depth_um_at_z_max"] = float(case["_depth_um"][int(z.argmax())])
        past = case["_depth_um"] > 0.1 * case["_depth_um"][-1]
        out["pressure_z_max_past_10pct"] = float(z[past].max())
        out["pressure_z_mean_past_10pct"] = float(z[past].mean())
        ma, mb = a.mean(axis=0)[past], b.mean(axis=0)[past]
        out["mean_curve_rel_diff_past_10pct"] = float(np.mean(np.abs(ma - mb) / mb))
    if case["_hist"] is not None and base["_hist"] is not None:
        out["kl_pooled_vs_base"] = float(kl_divergence(case["_hist"], base["_hist"]))
        out["kl_base_pairwise"] = base["kl_pairwise"]
    return out


def markdown(rows: list[dict]) -> str:
    head = ("| case | runs | wall s/run | particles | events | P 5 / 10 / 15 / 19.5 um [MPa] "
            "| var (normalised) | KL pairwise | var x CPU s | against | bias z max (at um) "
            "| z max / mean past 10 % | rel. diff past 10 % | KL pooled |")
    lines = [head, "|" + "---|" * 14]
    for r in rows:
        s = r["summary"]

        def f(v, fmt):
            return format(v, fmt) if v is not None else "-"
        p = " / ".join(f"{v['mean_MPa']:.1f} +- {f(v['sd_MPa'], '.1f')}"
                       for v in s["pressure"].values())
        b = r.get("bias", {})
        t = s.get("threads_per_run", [1])
        thr = "" if t == [1] else f" ({'/'.join(map(str, t))} threads)"
        lines.append(
            f"| {r['name']} | {s['runs']} | {f(s['wall_s_per_run'], '.0f')}{thr} | "
            f"{s['particles_start']:.0f} -> {s['particles_end']:.0f} | "
            f"{s['events_mean']:.0f} +- {f(s['events_sd'], '.0f')} | {p} | "
            f"{f(s['pressure_var_normalised'], '.2e')} | {f(s['kl_pairwise'], '.3f')} | "
            f"{f(s['variance_x_cpu_s'], '.3g')} | {b.get('against', '-')} | "
            f"{f(b.get('pressure_z_max'), '.2f')} ({f(b.get('depth_um_at_z_max'), '.1f')}) | "
            f"{f(b.get('pressure_z_max_past_10pct'), '.1f')} / "
            f"{f(b.get('pressure_z_mean_past_10pct'), '.1f')} | "
            f"{f(b.get('mean_curve_rel_diff_past_10pct'), '.1%')} | "
            f"{f(b.get('kl_pooled_vs_base'), '.3f')} |")
    return "\n".join(lines) + "\n"


def cmd_report(args) -> int:
    from calendaring import read_dataset, write_json

    ref = read_dataset(args.reference)
    out = Path(args.out)
    rows = []
    for case in cases(args.cells, args.inertial, args.seeds, args.speed_seeds,
                      args.speed_cells):
        runs = pooled(out / case["name"], Path(args.archive) / case["name"])
        if runs:
            rows.append({**case, "summary": summarise(runs, ref)})
    if not rows:
        print(f"[scale] no finished runs under {out}", file=sys.stderr)
        return 2
    sweep_speed = [r for r in rows if r["inertial"] is None]
    base = max(sweep_speed, key=lambda r: r["cell_um"]) if sweep_speed else None
    by_cell = {r["cell_um"]: r for r in sweep_speed}
    for r in rows:
        # a cell against the largest; a plate speed against its own cell at the sweep speed
        ref_row = base if r["inertial"] is None else by_cell.get(r["cell_um"])
        if ref_row is not None and r is not ref_row:
            r["bias"] = {"against": ref_row["name"],
                         **bias(r["summary"], ref_row["summary"])}
    for r in rows:
        for k in ("_curves", "_depth_um", "_hist"):
            r["summary"].pop(k)
    prov = out / "provenance.json"
    if not prov.exists():  # a report of the archive alone: the archive's invocations
        prov = Path(args.archive) / "provenance.json"
    result = {"benchmark": "scale_study", "reference": str(args.reference),
              "provenance": json.loads(prov.read_text()) if prov.exists() else None,
              "base_case": base["name"] if base else None, "cases": rows,
              "date": time.strftime("%Y-%m-%d %H:%M:%S")}
    path = write_json(Path(args.json), result)
    table = markdown(rows)
    Path(args.json).with_suffix(".md").write_text(table)
    print(table)
    print(f"[scale] wrote {path}", file=sys.stderr)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("run", "report"):
        p = sub.add_parser(name)
        p.add_argument("--out", required=True, help="study folder (one sweep per case)")
        p.add_argument("--cells", type=float, nargs="+", default=[30.0, 50.0, 70.0, 100.0],
                       help="cell sides [um]")
        p.add_argument("--inertial", type=float, nargs="*", default=[5e-3, 1e-3],
                       help="inertial numbers also run at the largest cell")
        p.add_argument("--seeds", type=int, default=3, help="seeds per cell")
        p.add_argument("--speed-seeds", type=int, default=2,
                       help="seeds per extra plate speed")
        p.add_argument("--speed-cells", type=float, nargs="*",
                       help="cells [um] run at the extra plate speeds (default: the largest)")
        p.add_argument("--archive", default=str(RESULTS / "scale_runs"),
                       help="folder of the compact per-run archive (kept in the repository)")
    run = sub.choices["run"]
    run.add_argument("--seed", type=int, default=0, help="first seed")
    run.add_argument("--workers", type=int, default=2)
    run.add_argument("--threads-per-run", type=int, default=1,
                     help="CPU threads of each run (the report lists them per case)")
    run.add_argument("--preset", default="sweep",
                     help="preset of the runs (another one only to try the script out)")
    rep = sub.choices["report"]
    rep.add_argument("--reference", default=str(REFERENCE),
                     help="dataset whose normalisation and histogram edges are used")
    rep.add_argument("--json", default=str(RESULTS / "scale_study.json"))
    args = ap.parse_args(argv)
    return {"run": cmd_run, "report": cmd_report}[args.cmd](args)


if __name__ == "__main__":
    raise SystemExit(main())
