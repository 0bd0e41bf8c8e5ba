"""Command line: ``analysis sobol | trends | microstructure | compare``.

Each command writes a JSON report (SI units, units named in keys) and PNGs into an output
folder; long work prints progress on stderr. Exit codes: 0 success, 2 bad input (a message
naming the key, the value and what is allowed; nothing written), 1 anything else.

    analysis sobol model.pt --n 2**14 --dataset dataset.h5 --out-dir sobol/
    analysis trends model.pt --at RESULT.json --out-dir trends/
    analysis microstructure runs/quick.h5 --snapshots 0,4 --voxels-per-diameter 5
    analysis compare --preset quick --out-dir studies/ --studies r0r1,psd
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from calendaring import (
    EXIT_OK,
    EXIT_UNSTABLE,
    PRESETS,
    ConfigError,
    ContractParser,
    input_file,
    output_path,
    run_cli,
)


def parse_power_of_two(text: str) -> int:
    """``"16384"``, ``"2**14"`` or ``"2^14"`` -> 16384 (must be a power of two >= 2)."""
    from analysis.sensitivity import check_power_of_two

    t = str(text).strip()
    m = re.fullmatch(r"2\s*(?:\*\*|\^)\s*(\d{1,2})", t)
    if m:
        return check_power_of_two(2 ** int(m.group(1)))
    if not re.fullmatch(r"\d{1,10}", t):
        raise ConfigError("--n", text, "a power of two, written 4096, 2**12 or 2^12")
    return check_power_of_two(int(t))


def _parser() -> argparse.ArgumentParser:
    ap = ContractParser(prog="analysis", description=__doc__.split("\n\n")[0],
                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True, parser_class=ContractParser)

    s = sub.add_parser("sobol", help="Sobol indices of the four key outputs on a surrogate")
    s.add_argument("model", help="surrogate checkpoint (MODEL.pt)")
    s.add_argument("--n", default="2**14", help="base sample size N, a power of two "
                   "(evaluations: N (k + 2)); the convergence table doubles up to it")
    s.add_argument("--n-min", default="256", help="first N of the convergence table")
    s.add_argument("--seed", type=int, default=0, help="seed of the design and the bootstrap")
    s.add_argument("--tol", type=float, default=0.05, help="CI half-width for convergence")
    s.add_argument("--spread-n", default=None, help="N per ensemble member (default N/4)")
    s.add_argument("--dataset", help="dataset HDF5 for the given-data cross-check")
    s.add_argument("--given-method", choices=("rbd_fast", "delta"), default="rbd_fast",
                   help="given-data estimator (delta is much slower)")
    s.add_argument("--reference", help="an earlier sobol.json (e.g. of the other cell) to "
                   "compare the rankings with")
    s.add_argument("--out-dir", help="output folder (default: <model>_sobol next to it)")
    s.add_argument("--quiet", action="store_true", help="no progress lines")

    t = sub.add_parser("trends", help="one-at-a-time parameter trends (Fig. 11)")
    t.add_argument("model", help="surrogate checkpoint (MODEL.pt)")
    t.add_argument("--at", help="JSON with a top-level \"parameters\" {name: physical value} "
                   "or [{name, value}] (e.g. an `inverse calibrate` RESULT.json) to hold the "
                   "others at; default mid-range")
    t.add_argument("--points", type=int, default=41, help="points per sweep")
    t.add_argument("--out-dir", help="output folder (default: <model>_trends next to it)")
    t.add_argument("--quiet", action="store_true")

    m = sub.add_parser("microstructure", help="porosity, tortuosity and D_eff of snapshots")
    m.add_argument("run_file", help="run file (RUN.h5)")
    m.add_argument("--snapshots", help="comma-separated snapshot indices (default: all)")
    m.add_argument("--resolution", default="converge", choices=("converge", "two-point"),
                   help="converge: partial-volume voxels refined until tau changes by less "
                   "than --refine-tol between levels (default); two-point: one resolution, "
                   "a coarser one and the linear extrapolation")
    m.add_argument("--refine-tol", type=float, help="relative tau change that ends the "
                   "refinement (default 0.02)")
    m.add_argument("--max-voxels", type=float, help="largest voxel count of a refinement "
                   "level (default 4e7)")
    m.add_argument("--max-levels", type=int, help="most refinement levels (default 5)")
    m.add_argument("--voxels-per-diameter", type=float, help="voxels across the smallest "
                   "particle diameter: the first level (default 3) or the two-point "
                   "resolution (default 4)")
    m.add_argument("--supersample", type=int, help="partial-volume sub-voxels per axis "
                   "(default 3 for converge, 1 = binary for two-point)")
    m.add_argument("--cb-phase", action="store_true", help="carbon black as its own "
                   "(conducting) phase")
    m.add_argument("--device", default="cpu", help="torch device for TauFactor")
    m.add_argument("--tol", type=float, default=1e-3, help="TauFactor tolerance")
    m.add_argument("--no-second-resolution", action="store_true",
                   help="skip the convergence check at a second resolution")
    m.add_argument("--no-render", action="store_true", help="skip the pyvista renders")
    m.add_argument("--out-dir", help="output folder (default: <run>_microstructure)")
    m.add_argument("--quiet", action="store_true")

    c = sub.add_parser("compare", help="R0/R1 and PSD studies (Figs. 12, 13; Table 5)")
    c.add_argument("--preset", required=True, choices=PRESETS,
                   help="calendaring preset of every run")
    c.add_argument("--out-dir", required=True, help="output folder (runs under runs/)")
    c.add_argument("--studies", default="r0r1,psd", help="comma-separated: r0r1, psd")
    c.add_argument("--seed", type=int, default=0, help="the one seed of every run")
    c.add_argument("--seeds", type=int, nargs="+",
                   help="several seeds: each in DIR/seed-<s>/, then their statistics and "
                        "the paper's claims in DIR/seeds.json (instead of --seed)")
    c.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for every run (repeatable)")
    c.add_argument("--jobs", type=int, default=1, help="runs at the same time")
    c.add_argument("--timeout", type=float, help="seconds allowed per run")
    c.add_argument("--no-microstructure", action="store_true",
                   help="skip porosity / tortuosity / D_eff")
    c.add_argument("--voxels-per-diameter", type=float, help="microstructure resolution")
    c.add_argument("--initial-transport", choices=("all", "R1", "none"), default="all",
                   help="whose snapshot nearest 0 um is analysed besides the final one: "
                        "every run's (default), R1's only (R0 shares its packing), none")
    c.add_argument("--device", default="cpu", help="torch device for TauFactor")
    c.add_argument("--no-run", action="store_true",
                   help="report only what is on disk (kept records and analyses, e.g. after "
                        "scripts/sweep-keep.sh --restore): no DEM run, no new analysis")
    c.add_argument("--quiet", action="store_true")
    return ap


def _check_model(path: str) -> None:
    if not Path(path).is_file():
        raise ConfigError("MODEL", str(path), "an existing surrogate checkpoint file (.pt)")


def _load_model(path: str):
    p = Path(path)
    try:
        import surrogate
        load = surrogate.load
    except (ImportError, AttributeError) as err:
        raise RuntimeError(f"the surrogate package cannot load models here ({err})") from None
    return load(p)


def _out_dir(arg: str | None, src: str, suffix: str) -> Path:
    if arg:
        out = Path(arg)
    else:
        p = Path(src)
        out = p.with_name(f"{p.stem}_{suffix}")
    return output_path(out, "--out-dir", folder=True)


def cmd_sobol(args) -> int:
    from analysis.sensitivity import check_power_of_two, sobol_study

    n = parse_power_of_two(args.n)
    n_min = parse_power_of_two(args.n_min)
    if n_min > n:
        raise ConfigError("--n-min", n_min, f"<= --n = {n}")
    spread = parse_power_of_two(args.spread_n) if args.spread_n else None
    if not 0 < args.tol < 1:
        raise ConfigError("--tol", args.tol, "in (0, 1)")
    ds = None
    if args.dataset:
        from calendaring import read_dataset

        ds = read_dataset(args.dataset)
    check_power_of_two(n)
    _check_model(args.model)
    reference = None
    if args.reference:
        ref_path = input_file(args.reference, "--reference")
        try:
            reference = json.loads(ref_path.read_text())
            reference["sobol"]["indices"]
        except (ValueError, KeyError, TypeError):
            raise ConfigError("--reference", str(args.reference),
                              "a sobol.json written by 'analysis sobol'") from None
        reference["path"] = str(ref_path)
    out = _out_dir(args.out_dir, args.model, "sobol")
    m = _load_model(args.model)
    if ds is not None and ds.space.names != m.space.names:
        raise ConfigError("--dataset", str(args.dataset),
                          f"a dataset with the model's parameters {m.space.names}")
    res = sobol_study(m, out, n=n, n_min=n_min, seed=args.seed, tol=args.tol, dataset=ds,
                      given_method=args.given_method, spread_n=spread,
                      progress=not args.quiet, reference=reference)
    _print_sobol(res)
    print(f"wrote {out / 'sobol.json'}")
    return EXIT_OK


def _print_sobol(res: dict) -> None:
    s = res["sobol"]
    names = [p["symbol"] for p in res["parameters"]]
    print(f"Sobol indices at N = {s['n']} ({s['n_evaluations']} evaluations), converged at "
          f"N = {res['converged_at_n']}")
    print("output              " + " ".join(f"{n:>8s}" for n in names))
    for o, d in s["indices"].items():
        for key in ("S1", "ST"):
            print(f"{o[:17]:17s} {key} " + " ".join(f"{v:8.3f}" for v in d[key]))
    pc = res["paper_claims"]
    print(f"paper (Fig. 10): d0 and phi the two largest ST in {pc['dominant_holds_in']}")
    for o, c in pc["outputs"].items():
        neg = ", ".join(f"{n} {v['verdict']} (ST {v['ST']:.3f} +- {v['ST_conf']:.3f})"
                        for n, v in c["negligible"].items())
        print(f"  {o}: ranking {' > '.join(c['ranking_by_ST'][:3])} ...; {neg}")
    for o, c in res.get("given_data_check", {}).items():
        if "agree" in c:
            print(f"given data, {o}: top two S1 {c['given_data_top2_S1']} against the "
                  f"surrogate's {c['surrogate_top2_S1']}: {'agree' if c['agree'] else 'differ'}")
    for o, c in res.get("reference", {}).get("comparison", {}).items():
        print(f"against the reference, {o}: Kendall tau {c['kendall_tau_ST']:.2f}, top two "
              f"{c['top2']} vs {c['reference_top2']}, ST differ beyond the CIs: "
              f"{sorted(c['differ']) or 'none'}")


def cmd_trends(args) -> int:
    from analysis.trends import held_point, trends_study

    if args.points < 2:
        raise ConfigError("--points", args.points, "an integer >= 2")
    _check_model(args.model)
    out = _out_dir(args.out_dir, args.model, "trends")
    m = _load_model(args.model)
    held_point(m.space, args.at)  # validate before any work
    res = trends_study(m, out, at=args.at, n_points=args.points, progress=not args.quiet)
    print(f"held at {json.dumps(res['at_physical'])}")
    print(f"wrote {out / 'trends.json'}")
    return EXIT_OK


def _parse_snapshots(text: str | None, n: int) -> list[int] | None:
    if text is None:
        return None
    try:
        idx = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ConfigError("--snapshots", text, "comma-separated integers") from None
    bad = [i for i in idx if not 0 <= i < n]
    if not idx or bad:
        raise ConfigError("--snapshots", text, f"indices in [0, {n - 1}]")
    return idx


def cmd_microstructure(args) -> int:
    from analysis.plots import atomic_write_json
    from calendaring import read_run

    rec = read_run(args.run_file)
    snaps = _parse_snapshots(args.snapshots, len(rec.snapshots))
    if not rec.snapshots:
        raise ConfigError("RUN", args.run_file, "a run file with snapshots")
    if args.supersample is not None and args.supersample < 1:
        raise ConfigError("--supersample", args.supersample, "an integer >= 1")
    if args.refine_tol is not None and not 0 < args.refine_tol < 1:
        raise ConfigError("--refine-tol", args.refine_tol, "in (0, 1)")
    if args.max_voxels is not None and not 1 <= args.max_voxels < float("inf"):
        raise ConfigError("--max-voxels", args.max_voxels, ">= 1 (finite)")
    if args.max_levels is not None and args.max_levels < 2:
        raise ConfigError("--max-levels", args.max_levels, "an integer >= 2")
    if args.voxels_per_diameter is not None and args.voxels_per_diameter <= 0:
        raise ConfigError("--voxels-per-diameter", args.voxels_per_diameter, "> 0")
    if not 0 < args.tol < 1:
        raise ConfigError("--tol", args.tol, "in (0, 1)")
    out = _out_dir(args.out_dir, args.run_file, "microstructure")
    from analysis.microstructure import analyse_run, plot_microstructure

    # options not given keep analyse_run's defaults (analysis.microstructure.REFINE_*)
    kw = {k: v for k in ("voxels_per_diameter", "refine_tol", "max_voxels", "max_levels")
          if (v := getattr(args, k)) is not None}
    res = analyse_run(rec.path, snapshots=snaps, supersample=args.supersample,
                      cb_phase=args.cb_phase, device=args.device, tol=args.tol,
                      second_resolution=not args.no_second_resolution,
                      progress=not args.quiet, resolution=args.resolution, **kw)
    report = {"run_file": str(rec.path), "result": res.to_json(), "figures": [],
              "render_errors": []}
    out.mkdir(parents=True, exist_ok=True)
    report["figures"] += [Path(p).name for p in plot_microstructure({rec.path.stem: res}, out)]
    if not args.no_render:
        try:
            from analysis.render import render_bonds, render_particles
        except ImportError as err:
            report["render_errors"].append(f"analysis.render unavailable: {err}")
        else:
            chosen = snaps if snaps is not None else [0, len(rec.snapshots) - 1]
            for k in sorted(set(chosen)):
                for fn, what in ((render_particles, "particles"), (render_bonds, "bonds")):
                    png = out / f"{rec.path.stem}_snap{k}_{what}.png"
                    try:
                        fn(rec.path, k, png)
                        report["figures"].append(png.name)
                    except Exception as err:  # a render problem does not lose the numbers
                        report["render_errors"].append(f"{what} snapshot {k}: "
                                                       f"{type(err).__name__}: {err}")
    atomic_write_json(out / "microstructure.json", report)
    from analysis.microstructure import format_table, microstructure_table

    depths = [s.depth for s in res.snapshots]
    table = format_table(microstructure_table({rec.path.stem: res}, depths=depths))
    tmp = out / ".microstructure.md.tmp"
    tmp.write_text(table + "\n")
    tmp.replace(out / "microstructure.md")
    print(table)
    for e in report["render_errors"]:
        print(f"warning: {e}", file=sys.stderr)
    print(f"wrote {out / 'microstructure.json'}, microstructure.md and "
          f"{len(report['figures'])} figures")
    return EXIT_OK


def cmd_compare(args) -> int:
    from analysis.compare import STUDIES, compare

    studies = [s.strip() for s in args.studies.split(",") if s.strip()]
    if not studies or any(s not in STUDIES for s in studies):
        raise ConfigError("--studies", args.studies,
                          f"a comma-separated subset of {','.join(STUDIES)}")
    if args.jobs < 1:
        raise ConfigError("--jobs", args.jobs, "an integer >= 1")
    if args.timeout is not None and args.timeout <= 0:
        raise ConfigError("--timeout", args.timeout, "> 0 s")
    out = _out_dir(args.out_dir, args.out_dir, "")
    micro_kw = {"device": args.device}
    if args.voxels_per_diameter is not None:
        if args.voxels_per_diameter <= 0:
            raise ConfigError("--voxels-per-diameter", args.voxels_per_diameter, "> 0")
        micro_kw["voxels_per_diameter"] = args.voxels_per_diameter
    kw = dict(preset=args.preset, studies=studies, extra_sets=args.set, jobs=args.jobs,
              micro=not args.no_microstructure, micro_kw=micro_kw, timeout=args.timeout,
              progress=not args.quiet, initial=args.initial_transport, run=not args.no_run)
    if args.seeds:
        from analysis.compare import compare_seeds

        pooled = compare_seeds(out, args.seeds, **kw)
        print(format_seeds(pooled))
        for s, names in pooled["missing"].items():
            print(f"seed {s}: not on disk, not run (--no-run): {', '.join(names)}")
        print(f"wrote {out / 'seeds.json'} and {pooled['figure']}")
        return EXIT_UNSTABLE if pooled["failures"] else EXIT_OK
    rep = compare(out, seed=args.seed, **kw)
    for st in rep["runs"]:
        print(f"{st['name']:3s} {st['status']:7s} {st['description']}")
    for name, mic in (rep.get("microstructure") or {}).items():
        if "error" in mic:
            print(f"{name:3s} microstructure: {mic['error']}")
        for r in mic.get("table", []):
            tau = "-" if r["tortuosity"] is None else f"{r['tortuosity']:.3f}"
            dep = float("nan") if r["depth_m"] is None else r["depth_m"] * 1e6
            por = float("nan") if r["porosity"] is None else 100 * r["porosity"]
            de = "-" if r["D_eff"] is None else f"{r['D_eff']:.4f}"
            print(f"{name:3s} depth {dep:5.2f} um: porosity {por:5.1f} %, tortuosity "
                  f"{tau}, D_eff {de}")
    if "r0r1" in rep:
        d = rep["r0r1"]
        print(f"R0/R1 identical up to depth {d['identical_until_depth_m']} m; first breakage "
              f"at {d['first_breakage_depth_m']} m")
    print(f"wrote {out / 'compare.json'}")
    return EXIT_UNSTABLE if rep["failures"] else EXIT_OK  # 3: some runs stopped (listed)


def format_seeds(pooled: dict) -> str:
    """The final transport figures per case (mean +- sd over seeds) and the claims."""
    lines = [f"seeds {pooled['seeds']}: final depth, mean +- sd over seeds"]
    for c, st in pooled["cases"].items():
        cells = []
        for k, f, unit in (("final_porosity", 100, " %"), ("final_tortuosity", 1, ""),
                           ("final_D_eff", 1, ""), ("breakage_events", 1, " events")):
            v = st.get(k) or {}
            if v.get("mean") is None:
                continue
            sd = f" +- {f * v['sd']:.3g}" if v.get("sd") is not None else ""
            cells.append(f"{k.replace('final_', '')} {f * v['mean']:.4g}{sd}{unit}")
        lines.append(f"{c:3s} " + ", ".join(cells))
    for cl in pooled["claims"]:
        rel, paper = cl["relative_change"], cl["paper_relative_change"]
        rel_s = f"{100 * rel:+.1f} %" if rel is not None else "-"
        paper_s = f"{100 * paper:+.1f} %" if paper is not None else "-"
        res = cl.get("resolution")
        res_s = ""
        if res:
            steps = "/".join(f"{100 * r:+.1f}" for r in res["relative_difference"])
            vpd = "/".join(f"{v:g}" for v in res["voxels_per_diameter"])
            res_s = (f"; {steps} % at {vpd} voxels per diameter, "
                     f"{'converged' if res['converged'] else 'not converged'} (ratio "
                     f"{100 * res['ratio_change']:.2g} % between the finest two")
            if res.get("below_seed_scatter") is not None:
                res_s += (", below" if res["below_seed_scatter"] else ", above") + \
                    " the seed scatter"
            if res.get("extrapolated") is not None:
                res_s += f"; extrapolated {100 * res['extrapolated']:+.1f} %"
            res_s += ")"
        lines.append(f"{cl['claim']}: {cl['verdict']} (here {rel_s}, paper {paper_s}{res_s})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``analysis`` command."""
    from analysis.render import RenderError
    from calendaring import DatasetError, RunFileError, __version__

    bad: tuple[type[BaseException], ...] = (DatasetError, RunFileError, RenderError)
    try:
        from surrogate.checkpoint import CheckpointError

        bad = (*bad, CheckpointError)
    except ImportError:
        pass

    def handle() -> int:
        args = _parser().parse_args(argv)
        return {"sobol": cmd_sobol, "trends": cmd_trends, "microstructure": cmd_microstructure,
                "compare": cmd_compare}[args.command](args)

    return run_cli("analysis", handle, bad, __version__)


if __name__ == "__main__":
    sys.exit(main())
