"""Command line: ``inverse calibrate | verify | validate | refine``.

Exit codes: 0 success, 2 bad input (nothing written), 1 anything else.

    inverse calibrate --model model.pt --target curve.csv --out result.json
    inverse calibrate --model model.pt --target run.h5 --out result.json --posterior \\
        --fix damage_constant=5.549 --fix truncation_ratio=89.928
    inverse calibrate --model model.pt --target curve.csv --out result.json --multistart 64
    inverse verify result.json --preset quick --seeds 3 --draws 4
    inverse validate --model model.pt --dataset dataset.h5 --out validation/
    inverse refine --model model.pt --target curve.csv --dataset dataset.h5 --budget 24 \\
        --batch 4 --out refine/

Target CSV: a header with units, ``depth_um,pressure_MPa[,sigma_MPa]`` or
``depth_m,pressure_Pa[,sigma_Pa]`` (see :mod:`inverse.targets`). Parameter values in ``--fix``
are SI (percent for alpha_percentage and truncation_ratio), names as in ``[breakage]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from calendaring import (
    EXIT_OK,
    PRESETS,
    ConfigError,
    ContractParser,
    input_file,
    integer,
    output_path,
    run_cli,
)


def _parser() -> argparse.ArgumentParser:
    from inverse.optimise import DEFAULT_ITERATIONS, DEFAULT_MULTISTART, DEFAULT_RESTARTS
    from inverse.posterior import PosteriorConfig

    pc = PosteriorConfig()
    ap = ContractParser(prog="inverse", description=__doc__.split("\n\n")[0],
                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True, parser_class=ContractParser)
    c = sub.add_parser("calibrate", help="infer the breakage parameters from a pressure curve")
    c.add_argument("--model", required=True, help="surrogate checkpoint (MODEL.pt)")
    tg = c.add_mutually_exclusive_group(required=True)
    tg.add_argument("--target", help="CURVE.csv (units in the header) or RUN.h5")
    tg.add_argument("--target-row", type=integer(0),
                    help="a row of --dataset as the target (its smoothed curve and breakage "
                         "histogram; its true parameters are reported beside the result)")
    c.add_argument("--dataset", help="DATASET.h5 for --target-row")
    c.add_argument("--out", required=True, help="result JSON to write")
    c.add_argument("--restarts", type=int, default=None,
                   help=f"Sobol-started restarts (default {DEFAULT_RESTARTS}; "
                        f"{DEFAULT_MULTISTART} with --multistart)")
    c.add_argument("--iterations", type=int, default=DEFAULT_ITERATIONS,
                   help="iterations per restart: 30 %% Adam, 70 %% L-BFGS")
    c.add_argument("--multistart", action="store_true",
                   help="many restarts, batched, with the optima clustered")
    c.add_argument("--posterior", action="store_true", help="sample the posterior (emcee)")
    c.add_argument("--walkers", type=int, default=pc.walkers)
    c.add_argument("--steps", type=int, default=pc.steps, help="MCMC steps per walker")
    c.add_argument("--burn", type=int, default=pc.burn, help="MCMC burn-in steps")
    c.add_argument("--model-error", type=float, default=pc.model_error_sigma,
                   help="surrogate error sigma in normalised pressure units, added to the "
                        "likelihood variance (e.g. the model's held-out RMSE)")
    c.add_argument("--correlation-length", type=float, default=None,
                   help="points per independent residual in the likelihood (default: the "
                        "Savitzky-Golay filter's noise correlation length, 7.5; 1: treat "
                        "the points as independent)")
    c.add_argument("--sigma-rel", type=float, default=pc.sigma_rel,
                   help="default observation sigma, relative part (without a sigma column)")
    c.add_argument("--fix", action="append", default=[], metavar="NAME=VALUE",
                   help="hold a parameter at a physical value (SI); repeatable")
    c.add_argument("--centroids", metavar="LOAD_N,DIAMETER_M",
                   help="target breakage centroid (peak load [N], parent diameter [m])")
    c.add_argument("--profiles", choices=("slice", "optimised", "none"), default="slice",
                   help="loss profiles along each parameter (identifiability report)")
    c.add_argument("--seed", type=int, default=0, help="Sobol scrambling and MCMC seed")
    c.add_argument("--threads", type=integer(1), default=1,
                   help="torch CPU threads (default 1: fastest for this small network)")
    c.add_argument("--no-plots", action="store_true", help="write no PNGs")
    c.add_argument("--quiet", action="store_true", help="no progress output")
    v = sub.add_parser("verify", help="run the DEM at the calibrated parameters")
    v.add_argument("result", help="RESULT.json from `inverse calibrate`")
    v.add_argument("--preset", choices=PRESETS, default="quick")
    v.add_argument("--seeds", type=int, default=1, help="DEM seeds at the optimum")
    v.add_argument("--draws", type=int, default=0, help="posterior draws to run (one seed)")
    v.add_argument("--first-seed", type=int, default=0)
    v.add_argument("--out-dir", help="folder for runs, verify.json and verify.png "
                                     "(default: RESULT_verify/)")
    a = sub.add_parser("validate", help="calibrate held-out dataset rows with known parameters")
    a.add_argument("--model", required=True)
    a.add_argument("--dataset", required=True, help="DATASET.h5 (calendaring dataset)")
    a.add_argument("--out", required=True, help="output folder")
    a.add_argument("--rows", type=int, nargs="+", help="row indices (default: role holdout)")
    a.add_argument("--restarts", type=int, default=DEFAULT_RESTARTS)
    a.add_argument("--iterations", type=int, default=DEFAULT_ITERATIONS)
    a.add_argument("--steps", type=int, default=pc.steps)
    a.add_argument("--burn", type=int, default=pc.burn)
    a.add_argument("--walkers", type=int, default=pc.walkers)
    a.add_argument("--model-error", type=float, default=pc.model_error_sigma,
                   help="surrogate error sigma in normalised pressure units, added to the "
                        "likelihood variance (e.g. the model's held-out RMSE)")
    a.add_argument("--correlation-length", type=float, default=None,
                   help="points per independent residual in the likelihood (default: the "
                        "Savitzky-Golay filter's noise correlation length, 7.5; 1: treat "
                        "the points as independent)")
    a.add_argument("--sigma-rel", type=float, default=pc.sigma_rel)
    a.add_argument("--fix", action="append", default=[], metavar="NAME=VALUE")
    a.add_argument("--no-distribution", action="store_true",
                   help="calibrate on the pressure curve only (no centroid term)")
    a.add_argument("--no-identifiability", action="store_true",
                   help="skip the per-row loss profiles (and the coverage goal over the "
                        "identifiable parameters)")
    a.add_argument("--seed", type=int, default=0)
    a.add_argument("--threads", type=integer(1), default=1,
                   help="torch CPU threads (per job)")
    a.add_argument("--jobs", type=integer(1), default=1,
                   help="rows calibrated at once in worker processes (the report does not "
                        "depend on it; e.g. the number of cores with --threads 1)")
    a.add_argument("--quiet", action="store_true")
    f = sub.add_parser("refine", help="spend new DEM runs near the posterior: select, "
                                      "run, retrain, recalibrate (resumable)")
    f.add_argument("--model", required=True, help="the initial surrogate (MODEL.pt)")
    g = f.add_mutually_exclusive_group(required=True)
    g.add_argument("--target", help="CURVE.csv (units in the header) or RUN.h5")
    g.add_argument("--target-row", type=integer(0),
                   help="a dataset row the model never trained on (a synthetic twin whose "
                        "truth is known)")
    f.add_argument("--dataset", required=True,
                   help="DATASET.h5 the model was trained on; its problem is the DEM's")
    f.add_argument("--budget", type=integer(1), required=True, help="DEM runs in all")
    f.add_argument("--batch", type=integer(1), required=True, help="DEM runs per round")
    f.add_argument("--out", required=True, help="output folder (rerun to resume)")
    f.add_argument("--tol", type=float, default=0.05,
                   help="stop when no 90 %% interval end moves more than this fraction of "
                        "the unit range between rounds (default 0.05)")
    f.add_argument("--dem-seed", type=integer(0),
                   help="one seed (bed) for every new DEM run (default: each run a bed of "
                        "its own, on seeds the dataset never used)")
    f.add_argument("--epochs", type=integer(1),
                   help="retraining epochs (default: the initial model's)")
    f.add_argument("--refine-weight", type=integer(1), default=1,
                   help="copies of each new run in the training split (default 1)")
    f.add_argument("--candidates", type=integer(1), default=4000,
                   help="posterior samples the selection chooses among")
    f.add_argument("--workers", type=integer(0), default=0,
                   help="DEM runs at a time (0: one per core)")
    f.add_argument("--threads-per-run", type=integer(1), default=1)
    f.add_argument("--scheduler", help="address of a running Dask scheduler")
    f.add_argument("--timeout", type=float, help="seconds per DEM run attempt")
    f.add_argument("--restarts", type=int, default=DEFAULT_RESTARTS)
    f.add_argument("--iterations", type=int, default=DEFAULT_ITERATIONS)
    f.add_argument("--walkers", type=int, default=pc.walkers)
    f.add_argument("--steps", type=int, default=pc.steps)
    f.add_argument("--burn", type=int, default=pc.burn)
    f.add_argument("--model-error", type=float, default=0.0,
                   help="surrogate error sigma of round 0, normalised units (default 0: "
                        "the model's recorded held-out RMSE); later rounds use the error "
                        "measured on the new runs")
    f.add_argument("--correlation-length", type=float, default=None)
    f.add_argument("--sigma-rel", type=float, default=pc.sigma_rel)
    f.add_argument("--fix", action="append", default=[], metavar="NAME=VALUE")
    f.add_argument("--no-distribution", action="store_true",
                   help="with --target-row: calibrate on the pressure curve only")
    f.add_argument("--seed", type=int, default=0, help="selection, optimiser and MCMC seed")
    f.add_argument("--threads", type=integer(1), default=1, help="torch CPU threads")
    f.add_argument("--quiet", action="store_true")
    return ap


def parse_fix(items: list[str]) -> dict[str, float]:
    """``["name=value", ...]`` -> ``{name: float}`` (names checked later against the space)."""
    out = {}
    for s in items:
        if "=" not in s:
            raise ConfigError("--fix", s, "NAME=VALUE, e.g. damage_constant=5.549")
        k, v = s.split("=", 1)
        try:
            out[k.strip()] = float(v)
        except ValueError:
            raise ConfigError(f"--fix {k.strip()}", v, "a number (SI units)") from None
    return out


def _centroids(s: str | None):
    if not s:
        return None
    try:
        vals = [float(x) for x in s.split(",")]
    except ValueError:
        raise ConfigError("--centroids", s, "LOAD_N,DIAMETER_M (two numbers, SI)") from None
    if len(vals) != 2:
        raise ConfigError("--centroids", s, "LOAD_N,DIAMETER_M (two numbers, SI)")
    return vals


def _row_target(args, model):
    """``--target-row`` of ``--dataset``: the row's target and its true parameters."""
    from calendaring import read_dataset
    from inverse.validate import row_target, trained_on

    if not args.dataset:
        raise ConfigError("--dataset", None, "a DATASET.h5 with --target-row")
    if args.centroids:
        raise ConfigError("--centroids", args.centroids, "not with --target-row (the row's "
                          "own histogram gives them)")
    ds = read_dataset(input_file(args.dataset, "--dataset"))
    if list(ds.space.names) != list(model.space.names):
        raise ConfigError("--dataset", args.dataset, f"the model's parameters "
                          f"{model.space.names}")
    i = int(args.target_row)
    if trained_on(model, ds, i):
        print(f"warning: row {i} ({ds.run_id[i]}) is one the model trained on",
              file=sys.stderr)
    target = row_target(model, ds, i)
    truth = {"row": i, "run_id": str(ds.run_id[i]), "role": str(ds.role[i]),
             "seed": int(ds.seed[i]), "parameters": ds.space.as_dict(ds.params[i]),
             "parameters_unit": ds.unit_params[i].tolist()}
    return target, truth


def _load_model(path: str):
    p = Path(path)
    if not p.is_file():
        raise ConfigError("--model", path, "an existing surrogate checkpoint file")
    import surrogate

    return surrogate.load(p)


def cmd_calibrate(args) -> int:
    from dataclasses import replace

    from inverse.calibrate import calibrate_target
    from inverse.optimise import DEFAULT_MULTISTART, DEFAULT_RESTARTS, OptimiserConfig
    from inverse.posterior import PosteriorConfig
    from inverse.report import format_table4, write_json
    from inverse.targets import load_target

    out = output_path(args.out, "--out", suffixes=(".json",), overwrite=True)
    fix = parse_fix(args.fix)
    restarts = args.restarts or (DEFAULT_MULTISTART if args.multistart else DEFAULT_RESTARTS)
    opt = OptimiserConfig(iterations=args.iterations, restarts=restarts, seed=args.seed,
                          batch=True if args.multistart else None)
    post = PosteriorConfig(walkers=args.walkers, steps=args.steps, burn=args.burn,
                           seed=args.seed, sigma_rel=args.sigma_rel,
                           model_error_sigma=args.model_error,
                           correlation_length=args.correlation_length) if args.posterior else None
    model = _load_model(args.model)
    model.space.check(fix)
    truth = None
    if args.target_row is not None:
        target, truth = _row_target(args, model)
    else:
        if args.dataset:
            raise ConfigError("--dataset", args.dataset, "given only with --target-row")
        target = load_target(args.target, model, _centroids(args.centroids))
    progress = not args.quiet
    if progress:
        print(f"target: {target.source}, {target.n_valid} of {len(target.depth)} model depths"
              f"{', with centroid' if target.centroids is not None else ''}", file=sys.stderr)
    oc = calibrate_target(model, target, optimiser=replace(opt), fix=fix,
                          posterior=post, identifiability=args.profiles != "none",
                          profile_mode=args.profiles if args.profiles != "none" else "slice",
                          progress=progress, model_path=args.model)
    res = oc.result
    if truth is not None:
        res["truth"] = truth
    if not args.no_plots:
        stem = out.with_suffix("")
        out.parent.mkdir(parents=True, exist_ok=True)
        plots = {}
        if "identifiability" in res:
            from inverse.identifiability import plot_identifiability

            plots["identifiability"] = str(plot_identifiability(
                res["identifiability"], f"{stem}_identifiability.png",
                {p.name: p.symbol for p in model.space}))
        if oc.posterior is not None:
            from inverse.posterior import observation_sigma, plot_predictive, plot_trace

            plots["predictive"] = str(plot_predictive(
                target, res["posterior"]["predictive"], f"{stem}_predictive.png",
                best_pressure=res["prediction"]["pressure_Pa"],
                sigma_pa=observation_sigma(target, post)))
            plots["trace"] = str(plot_trace(oc.posterior, f"{stem}_trace.png",
                                            {p.name: p.symbol for p in model.space}))
        res["plots"] = plots
    write_json(out, res)
    print(format_table4(res))
    if truth is not None:
        print(f"truth ({truth['role']} row {truth['row']}, {truth['run_id']}): "
              + ", ".join(f"{k} {v:.4g}" for k, v in truth["parameters"].items()))
    print(f"wrote {out}")
    return EXIT_OK


def cmd_verify(args) -> int:
    from inverse.verify import verify

    if args.out_dir:
        output_path(args.out_dir, "--out-dir", folder=True)
    rep = verify(args.result, preset=args.preset, seeds=args.seeds, draws=args.draws,
                 out_dir=args.out_dir, first_seed=args.first_seed)
    e = rep["optimum_mean_error"]
    for c in rep["curves"]:
        ce = c["error"]
        if ce["rmse_Pa"] is not None:
            print(f"{c['kind']:>8s} seed {c['seed']}: RMSE {ce['rmse_Pa'] / 1e6:.4g} MPa "
                  f"({100 * ce['relative_rmse']:.1f} %) over {ce['points']} points")
    if e and e.get("rmse_Pa") is not None:
        print(f"mean of {rep['seeds']} DEM run(s) at the optimum vs target: RMSE "
              f"{e['rmse_Pa'] / 1e6:.4g} MPa ({100 * e['relative_rmse']:.1f} %), max |error| "
              f"{e['max_abs_Pa'] / 1e6:.4g} MPa over {e['points']} points")
    print(f"wrote {Path(rep['plot']).parent / 'verify.json'} and {rep['plot']}")
    return EXIT_OK


def _settings(args) -> dict:
    """The optimiser and posterior settings of ``validate`` and ``refine`` (one seed)."""
    from inverse.optimise import OptimiserConfig
    from inverse.posterior import PosteriorConfig

    return {"optimiser": OptimiserConfig(iterations=args.iterations, restarts=args.restarts,
                                         seed=args.seed),
            "posterior": PosteriorConfig(walkers=args.walkers, steps=args.steps,
                                         burn=args.burn, seed=args.seed,
                                         sigma_rel=args.sigma_rel,
                                         model_error_sigma=args.model_error,
                                         correlation_length=args.correlation_length)}


def cmd_validate(args) -> int:
    from calendaring import read_dataset
    from inverse.validate import validate_to_dir

    output_path(args.out, "--out", folder=True)
    model = _load_model(args.model)
    ds = read_dataset(args.dataset)
    fix = parse_fix(args.fix)
    model.space.check(fix)
    rep = validate_to_dir(model, ds, args.out, rows=args.rows, **_settings(args),
                          use_distribution=not args.no_distribution, fix=fix or None,
                          identifiability=not args.no_identifiability,
                          progress=not args.quiet, jobs=args.jobs)
    ident = "identifiable" in rep
    print(f"{'parameter':<18s}{'MAE (unit)':>11s}{'coverage 90 %':>15s}{'CI width':>10s}"
          + (f"{'identifiable':>14s}" if ident else ""))
    for name, p in rep["per_parameter"].items():
        print(f"{name:<18s}{p['mae_unit_optimum']:>11.3f}{100 * p['coverage_ci90']:>14.0f}%"
              f"{p['mean_ci90_width_unit']:>10.3f}"
              + (f"{100 * p['identifiable_fraction']:>13.0f}%" if ident else ""))
    print(f"{rep['n_rows']} rows ({rep['resumed_rows']} resumed); key coverage "
          f"{rep['key_coverage']}; goal {'met' if rep['goal_met'] else 'not met'} "
          f"({rep['goal']})")
    if ident:
        print(f"identifiable ({rep['identifiable_rule']}): {rep['identifiable']}; coverage "
              f"goal over them {'met' if rep['identifiable_goal_met'] else 'not met'}")
    print(f"wrote {Path(args.out) / 'validation.json'}")
    return EXIT_OK


def cmd_refine(args) -> int:
    from inverse.refine import RefineConfig, refine

    output_path(args.out, "--out", folder=True)
    input_file(args.dataset, "--dataset", (".h5", ".hdf5"))
    input_file(args.model, "--model")
    cfg = RefineConfig(budget=args.budget, batch=args.batch, tol=args.tol,
                       dem_seed=args.dem_seed, candidates=args.candidates, epochs=args.epochs,
                       refine_weight=args.refine_weight, seed=args.seed, workers=args.workers,
                       threads_per_run=args.threads_per_run, scheduler=args.scheduler,
                       timeout=args.timeout)
    state = refine(
        args.model, args.dataset, args.out, target=args.target, target_row=args.target_row,
        cfg=cfg, fix=parse_fix(args.fix), use_distribution=not args.no_distribution,
        **_settings(args), progress=not args.quiet)
    print(format_refinement(state))
    print(f"wrote {Path(args.out) / 'refine.json'} and {state.get('plot', '')}")
    return EXIT_OK


def format_refinement(state: dict) -> str:
    """A table of the rounds: runs, surrogate error, mean 90 % width and, per parameter, the
    interval width (unit range; '*' where a known truth lies outside)."""
    rounds = state["rounds"]
    names = list(rounds[0]["posterior"])
    head = f"{'round':>5s}{'runs':>6s}{'sigma':>8s}{'oos rmse':>9s}{'width':>7s}  " + \
        "".join(f"{n[:9]:>10s}" for n in names)
    lines = [head]
    for r in rounds:
        e = r.get("error_before_training") or {}
        oos = f"{e['pressure_rmse_normalised']:.4f}" if e else "-"
        cells = []
        for n in names:
            w = r["posterior"][n]["width_unit"]
            t = r["truth"].get(n)
            cells.append(f"{w:>9.3f}{'*' if t and not t['inside_ci90'] else ' '}")
        lines.append(f"{r['round']:>5d}{r['runs_done']:>6d}{r['model_error_sigma']:>8.4f}"
                     f"{oos:>9s}{r['mean_width_unit']:>7.3f}  " + "".join(cells))
    lines.append(f"{state['status']}: {state['stop_reason']} ({state['runs_done']} runs "
                 f"done of {state['runs_spent']} planned)")
    return "\n".join(lines)


def main(argv=None) -> int:
    """Entry point of the ``inverse`` console script; returns the exit code."""
    from calendaring import DatasetError, RunFileError, __version__

    bad = [DatasetError, RunFileError]
    try:
        from surrogate.checkpoint import CheckpointError

        bad.append(CheckpointError)
    except ImportError:  # surrogate not installed: no checkpoint errors to catch
        pass

    def handle() -> int:
        args = _parser().parse_args(argv)
        if getattr(args, "threads", None) is not None:
            import torch

            torch.set_num_threads(args.threads)
        return {"calibrate": cmd_calibrate, "verify": cmd_verify,
                "validate": cmd_validate, "refine": cmd_refine}[args.command](args)

    return run_cli("inverse", handle, tuple(bad), __version__)


if __name__ == "__main__":
    sys.exit(main())
