"""Posterior-guided refinement on synthetic twins: does spending DEM runs near the posterior
narrow the intervals without losing the truth?

Each twin is a dataset row the surrogate never trained on (by default one replicate run of
each replicate group, at a seed neither the training runs nor the new runs use, so its bed
is unseen), whose true parameters are known. For each, ``inverse refine`` runs rounds of
``--batch`` DEM runs up to ``--budget`` (:mod:`inverse.refine`); round 0 is the one-shot
calibration with the initial surrogate. The report compares, per round, the 90 % interval
widths (unit range), the optimum's error and the coverage of the truths over the twins.

    python benchmarks/refine_twins.py run --model models/reference/ensemble.pt \\
        --dataset data/reference.h5 --out studies/refine --budget 12 --batch 4
    python benchmarks/refine_twins.py report --out studies/refine

``run`` is resumable (rerun it; each twin's refinement resumes where it stopped). ``report``
writes ``benchmarks/results/<name>.json``, ``.md`` and ``.png`` (``--name``, default
``refine_twins``) from the twins' ``refine.json`` and round records: the means over the twins
per round, and every twin's rounds. Each round's MCMC width error is kept beside it
(``width-se.json``), since the posterior samples it comes from are not kept.

A refinement can only narrow what the surrogate's error widens. ``recalibrate`` separates the
two: it calibrates every finished round's model again on its twin with the observation sigma
set to the dataset's own run-to-run floor (the square root of the replicate groups' mean
per-point variance in the model's normalisation, :func:`surrogate.evaluate.replicate_comparison`)
in place of the posterior's default (5 % of the pressure + 1 % of its maximum, about twice
that floor at 100 um), the round's model error unchanged. No DEM run; one calibration a round,
kept beside the round (``recalibration-floor.json``) so a rerun at the same sigma skips it:

    python benchmarks/refine_twins.py recalibrate --out studies/refine \
        --dataset data/reference.h5

``recalibrate --perfect`` bounds what any refinement could reach: the same floor sigma with no
surrogate error at all (model error 0, the ensemble's variance left out), as if the surrogate
were the DEM's mean curve itself; the target is still one run on one bed, so its bed-to-bed
scatter stays. Kept as ``recalibration-perfect.json``; the report gives both tables.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from calendaring import pressure_components, read_dataset, save_figure, write_json, write_text

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
# recalibration kind (file recalibration-<kind>.json) -> its key in the report's rounds
RECALIBRATIONS = {"floor": "floor_sigma", "perfect": "perfect_surrogate"}


def default_twins(ds) -> list[int]:
    """One replicate row per replicate group, seeds 1, 2, 3, ... (never the training seed)."""
    rows = []
    train_seeds = set(np.unique(ds.seed[ds.role == "train"]).tolist())
    for k, g in enumerate(sorted(set(ds.group[ds.role == "replicate"].tolist()))):
        cand = [i for i in np.nonzero((ds.role == "replicate") & (ds.group == g))[0]
                if ds.seed[i] not in train_seeds]
        if cand:
            rows.append(int(cand[min(k, len(cand) - 1)]))
    return rows


def cmd_run(args) -> int:
    from inverse.optimise import OptimiserConfig
    from inverse.posterior import PosteriorConfig
    from inverse.refine import RefineConfig, refine

    torch.set_num_threads(args.threads)  # a small network: one thread is fastest
    ds = read_dataset(args.dataset)
    rows = args.rows or default_twins(ds)
    out = Path(args.out)
    for n, row in enumerate(rows):
        print(f"[twins] twin {n + 1}/{len(rows)}: row {row} ({ds.run_id[row]})",
              file=sys.stderr, flush=True)
        refine(args.model, args.dataset, out / f"twin-row{row:04d}", target_row=row,
               cfg=RefineConfig(budget=args.budget, batch=args.batch, tol=args.tol,
                                seed=args.seed, workers=args.workers, epochs=args.epochs),
               optimiser=OptimiserConfig(seed=args.seed),
               posterior=PosteriorConfig(seed=args.seed, steps=args.steps, burn=args.burn),
               progress=True)
    return cmd_report(args)


def cmd_report(args) -> int:
    out = Path(args.out)
    folders = sorted(p.parent for p in out.glob("twin-row*/refine.json"))
    twins = [json.loads((f / "refine.json").read_text()) for f in folders]
    if not twins:
        print(f"no twin folders with refine.json under {out}", file=sys.stderr)
        return 2
    names = list(twins[0]["rounds"][0]["posterior"])
    recals = [recalibrations(folder, t) for folder, t in zip(folders, twins, strict=True)]
    twin_rows = [twin_table(folder, t, rc)
                 for folder, t, rc in zip(folders, twins, recals, strict=True)]
    n_rounds = min(len(t["rounds"]) for t in twins)
    per_round = []
    for r in range(n_rounds):
        recs = [t["rounds"][r] for t in twins]
        row = {"round": r, "runs_done_mean": float(np.mean([
            sum(t["rounds"][k]["runs_done"] for k in range(r + 1)) for t in twins])),
               "model_error_sigma_mean": float(np.mean([x["model_error_sigma"] for x in recs])),
               "mean_width_unit": float(np.mean([x["mean_width_unit"] for x in recs])),
               "width_unit": {n: float(np.mean([x["posterior"][n]["width_unit"] for x in recs]))
                              for n in names},
               "coverage": {n: float(np.mean([x["truth"][n]["inside_ci90"] for x in recs]))
                            for n in names},
               "abs_optimum_error_unit": {n: float(np.mean([
                   abs(x["truth"][n]["optimum_error_unit"]) for x in recs])) for n in names}}
        se = [twin_rows[k][r]["mean_width_se_unit"] for k in range(len(twins))]
        row["mean_width_se_unit"] = (float(np.sqrt(np.sum(np.square(se)))) / len(se)
                                     if None not in se else None)
        e = [x["error_before_training"]["pressure_rmse_normalised"] for x in recs
             if x.get("error_before_training")]
        row["out_of_sample_rmse_mean"] = float(np.mean(e)) if e else None
        for kind, key in RECALIBRATIONS.items():
            if not all(kind in rc[r] for rc in recals):
                continue
            fl = [rc[r][kind] for rc in recals]
            row[key] = {
                "observation_sigma_normalised": fl[0]["observation_sigma_normalised"],
                "model_error_sigma_mean": float(np.mean([x["model_error_sigma"] for x in fl])),
                "mean_width_unit": float(np.mean([x["mean_width_unit"] for x in fl])),
                "width_unit": {n: float(np.mean([x["posterior"][n]["width_unit"] for x in fl]))
                               for n in names},
                "coverage": {n: float(np.mean([x["truth"][n]["inside_ci90"] for x in fl]))
                             for n in names},
                "smallest_principal_sd_unit": float(np.mean([x["principal_sd_unit"][0]
                                                             for x in fl]))}
            if all("principal_sd_unit_default_sigma" in x for x in fl):
                row["smallest_principal_sd_unit"] = float(np.mean([
                    x["principal_sd_unit_default_sigma"][0] for x in fl]))
        per_round.append(row)
    rep = {"twins": [{"target": t["request"]["target"], "stop_reason": t["stop_reason"],
                      "runs_done": t["runs_done"], "rounds": len(t["rounds"]),
                      "per_round": rows} for t, rows in zip(twins, twin_rows, strict=True)],
           "model": twins[0]["request"]["model"], "dataset": twins[0]["request"]["dataset"],
           "config": twins[0]["request"]["config"], "per_round": per_round}
    ds_path = Path(rep["dataset"])
    if not ds_path.is_absolute() and not ds_path.exists():
        ds_path = ROOT / ds_path  # a path relative to the checkout that ran the twins
    pc = pressure_components(read_dataset(ds_path)) if ds_path.exists() else None
    rep["pressure_components"] = pc
    results = Path(args.results_dir)
    results.mkdir(parents=True, exist_ok=True)
    write_json(results / f"{args.name}.json", rep)
    lines = [f"# Refinement on {len(twins)} synthetic twins", "",
             "| round | runs (mean) | sigma | out-of-sample RMSE | mean 90 % width | "
             + " | ".join(names) + " |", "|" + "---|" * (5 + len(names))]
    for row in per_round:
        oos = f"{row['out_of_sample_rmse_mean']:.4f}" if row["out_of_sample_rmse_mean"] \
            else "-"
        cells = [f"{row['width_unit'][n]:.2f} ({100 * row['coverage'][n]:.0f} %)"
                 for n in names]
        se = row["mean_width_se_unit"]
        width = f"{row['mean_width_unit']:.3f}" + (f" +- {se:.3f}" if se is not None else "")
        lines.append(f"| {row['round']} | {row['runs_done_mean']:.0f} | "
                     f"{row['model_error_sigma_mean']:.4f} | {oos} | "
                     f"{width} | " + " | ".join(cells) + " |")
    lines += ["", f"Rounds 0-{n_rounds - 1}, the rounds every twin reached. Cells: mean 90 % "
              "interval width (unit range) over the twins, and in brackets the share of twins "
              "whose truth lies inside. The mean width's +- is its MCMC sampling error, "
              "estimated from four interleaved sets of walkers."]
    lines += ["", "Per twin, every round: the error of the round's new runs before training "
              "on them, and the posterior with the default observation sigma / at the "
              "run-to-run floor / as a perfect surrogate at that floor:", "",
              "| twin (row) | round | runs | failed | sigma | out-of-sample RMSE (MPa) | "
              "ensemble 2-sigma coverage | mean 90 % width | smallest principal sd | "
              "truths inside | optimum error |", "|" + "---|" * 11]
    for t, rows in zip(twins, twin_rows, strict=True):
        for x in rows:
            e = x["out_of_sample"]
            oos = (f"{e['pressure_rmse_normalised']:.4f} ({e['pressure_rmse_MPa']:.1f})"
                   if e else "-")
            cov = f"{e['ensemble_coverage_2sigma']:.2f}" if e else "-"
            se = x["mean_width_se_unit"]
            w = [f"{x['mean_width_unit']:.3f}" + (f" +- {se:.3f}" if se is not None else "")]
            sd = [_fmt(x["smallest_principal_sd_unit"])]
            inside = [f"{x['truths_inside']}"]
            for kind in RECALIBRATIONS:
                rc = x.get(kind)
                w.append(_fmt(rc and rc["mean_width_unit"]))
                sd.append(_fmt(rc and rc["smallest_principal_sd_unit"]))
                inside.append(f"{rc['truths_inside']}" if rc else "-")
            lines.append(f"| {t['request']['target']['row']} | {x['round']} | "
                         f"{x['runs_done_total']} | {x['runs_failed']} | "
                         f"{x['model_error_sigma']:.4f} | {oos} | {cov} | {' / '.join(w)} | "
                         f"{' / '.join(sd)} | {' / '.join(inside)} of {x['parameters']} | "
                         f"{x['abs_optimum_error_unit_mean']:.3f} |")
    lines += ["", "Runs: new DEM runs finished up to this round; sigma: the surrogate error in "
              "the round's likelihood (normalised); optimum error: the mean absolute error of "
              "the calibrated optimum over the parameters (unit range)."]
    titles = {"floor_sigma": "The same rounds' models with the observation sigma at the "
                             "run-to-run floor ({:.4f} normalised; `recalibrate`):",
              "perfect_surrogate": "A perfect surrogate at the same floor ({:.4f}; model error "
                                   "0, no ensemble variance; `recalibrate --perfect`): the "
                                   "narrowest any refinement could make the intervals:"}
    shown = False
    for key, title in titles.items():
        fl = [row for row in per_round if key in row]
        if not fl:
            continue
        shown = True
        lines += ["", title.format(fl[0][key]["observation_sigma_normalised"]), "",
                  "| round | model error sigma | smallest principal sd (default sigma / "
                  "this) | mean 90 % width | " + " | ".join(names) + " |",
                  "|" + "---|" * (4 + len(names))]
        for row in fl:
            f = row[key]
            cells = [f"{f['width_unit'][n]:.2f} ({100 * f['coverage'][n]:.0f} %)"
                     for n in names]
            sd0 = row.get("smallest_principal_sd_unit")
            sd = (f"{sd0:.3f}" if sd0 is not None else "-") + \
                f" / {f['smallest_principal_sd_unit']:.3f}"
            lines.append(f"| {row['round']} | {f['model_error_sigma_mean']:.4f} | {sd} | "
                         f"{f['mean_width_unit']:.3f} | " + " | ".join(cells) + " |")
    if shown:
        lines += ["", "Principal sd: the posterior's standard deviation along its best-pinned "
                  "axis (unit range; a uniform prior has 0.289 along every axis)."]
    if pc is not None:
        lines += ["", f"The dataset's pressure curves resolve {pc['resolved']} of "
                  f"{pc['tested']} principal components above the bed-to-bed scatter (Holm, "
                  f"alpha {pc['alpha']}; {pc['groups']} replicate groups): "
                  f"{100 * (pc['signal_share_resolved'] or 0):.1f} % of the parameter-driven "
                  "variance. Noise share (bed-to-bed / total variance) of components 1-"
                  f"{pc['tested']}: " + ", ".join(f"{c['noise_share']:.2f}"
                                                  for c in pc["components"]) + "."]
    plot_report(rep, results / f"{args.name}.png")
    lines += ["", f"Figure: `{args.name}.png`."]
    write_text(results / f"{args.name}.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


def _fmt(x, digits: int = 3) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def round_width_se(folder: Path, r: int, walkers: int) -> float | None:
    """The MCMC sampling error of round ``r``'s mean 90 % width, from the round's posterior
    samples, and kept beside the round (``width-se.json``: the samples themselves are not
    kept, so a report made later, elsewhere, still has it); None when neither is there."""
    rnd = folder / "rounds" / f"r{r:02d}"
    kept = rnd / "width-se.json"
    if (rnd / "posterior.npz").exists():
        se = width_standard_error(np.load(rnd / "posterior.npz")["samples_unit"], walkers)
        if not kept.exists() or json.loads(kept.read_text())["mean_width_se_unit"] != se:
            write_json(kept, {"mean_width_se_unit": se, "walkers": walkers, "groups": 4})
        return se
    return json.loads(kept.read_text())["mean_width_se_unit"] if kept.exists() else None


def recalibrations(folder: Path, state: dict) -> list[dict]:
    """Per round of one twin: ``{kind: recalibration-<kind>.json}`` for those that exist."""
    rounds = folder / "rounds"
    return [{kind: json.loads(path.read_text()) for kind in RECALIBRATIONS
             if (path := rounds / f"r{rec['round']:02d}" / f"recalibration-{kind}.json")
             .exists()} for rec in state["rounds"]]


def twin_table(folder: Path, state: dict, recals: list[dict]) -> list[dict]:
    """One twin's rounds, each with its recalibrations (``recalibrations``) where they
    exist."""
    walkers = int(state["request"]["posterior"]["walkers"])
    rows, total = [], 0
    for rec, found in zip(state["rounds"], recals, strict=True):
        r = rec["round"]
        total += rec["runs_done"]
        e = rec.get("error_before_training") or None
        x = {"round": r, "runs_done_total": total, "runs_failed": len(rec.get("failed") or []),
             "model_error_sigma": rec["model_error_sigma"],
             "out_of_sample": e and {k: e[k] for k in (
                 "n_runs", "pressure_rmse_normalised", "pressure_rmse_MPa",
                 "abs_error_MPa_at_stroke", "ensemble_coverage_2sigma") if k in e},
             "mean_width_unit": rec["mean_width_unit"],
             "mean_width_se_unit": round_width_se(folder, r, walkers),
             "smallest_principal_sd_unit": None, "parameters": len(rec["truth"]),
             "truths_inside": int(sum(v["inside_ci90"] for v in rec["truth"].values())),
             "abs_optimum_error_unit_mean": float(np.mean([
                 abs(v["optimum_error_unit"]) for v in rec["truth"].values()]))}
        for kind, rc in found.items():
            x[kind] = {"observation_sigma_normalised": rc["observation_sigma_normalised"],
                       "mean_width_unit": rc["mean_width_unit"],
                       "smallest_principal_sd_unit": rc["principal_sd_unit"][0],
                       "truths_inside": int(sum(v["inside_ci90"]
                                                for v in rc["truth"].values()))}
            if "principal_sd_unit_default_sigma" in rc:
                x["smallest_principal_sd_unit"] = rc["principal_sd_unit_default_sigma"][0]
        rows.append(x)
    return rows


def plot_report(rep: dict, path: Path) -> Path:
    """Per twin and round: the out-of-sample error of the new runs against the run-to-run
    floor, the mean 90 % width and the best-pinned axis's sd, each with the default
    observation sigma (solid), at the floor (dashed) and as a perfect surrogate (dotted)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8), constrained_layout=True)
    styles = {None: "-", "floor": "--", "perfect": ":"}
    floor = None
    for k, t in enumerate(rep["twins"]):
        rows, colour = t["per_round"], f"C{k}"
        label = f"twin row {t['target']['row']}"
        r = [x["round"] for x in rows]
        oos = [(x["round"], x["out_of_sample"]["pressure_rmse_normalised"]) for x in rows
               if x["out_of_sample"]]
        if oos:
            ax[0].plot(*zip(*oos, strict=True), "o-", color=colour, label=label)
        for kind, ls in styles.items():
            sel = [x for x in rows if kind is None or kind in x]
            rr = [x["round"] for x in sel]
            vals = [x[kind] if kind else x for x in sel]
            sd = [v["smallest_principal_sd_unit"] for v in vals]
            ax[1].plot(rr, [v["mean_width_unit"] for v in vals], ls, marker="o", color=colour,
                       label=label if kind is None else None)
            if any(v is not None for v in sd):
                ax[2].plot([a for a, v in zip(rr, sd, strict=True) if v is not None],
                           [v for v in sd if v is not None], ls, marker="o", color=colour)
            if kind == "floor" and kind in rows[0]:
                floor = rows[0][kind]["observation_sigma_normalised"]
        ax[0].plot(r[:1], [rows[0]["model_error_sigma"]], "s", color=colour, mfc="none")
    if floor is not None:
        ax[0].axhline(floor, color="k", lw=0.8, ls="--", label="run-to-run floor")
    for kind, ls in styles.items():
        ax[2].plot([], [], ls, color="k", label={None: "default sigma", "floor": "at the floor",
                                                 "perfect": "perfect surrogate"}[kind])
    ax[0].set(xlabel="round", ylabel="pressure RMSE (normalised)",
              title="surrogate error on the new runs\n(square: round 0's estimate)")
    ax[1].set(xlabel="round", ylabel="mean 90 % width (unit range)",
              title="interval width (prior 0.9)")
    ax[2].set(xlabel="round", ylabel="sd along the best-pinned axis (unit)",
              title="best-pinned combination")
    ax[0].legend(fontsize=8)
    ax[2].legend(fontsize=8)
    for a in ax:
        a.xaxis.get_major_locator().set_params(integer=True)
    return save_figure(fig, path)


def floor_sigma(model, ds) -> float:
    """The run-to-run floor as one normalised pressure sigma (replicate groups, ddof 1)."""
    from surrogate.evaluate import replicate_comparison

    rep = replicate_comparison(model, ds)
    if rep is None:
        raise SystemExit("the dataset has no replicate group of >= 2 runs: no floor to use")
    return float(np.sqrt(rep["pressure_mse_normalised_floor"]))


def width_standard_error(samples_unit: np.ndarray, walkers: int, groups: int = 4) -> float:
    """The MCMC sampling error of a posterior's mean 90 % width (unit range), estimated by
    splitting the walkers into ``groups`` interleaved sets (emcee's flat chain is ordered step
    by step, walker by walker) and taking the spread of their mean widths over
    ``sqrt(groups)``. The walkers of one ensemble move together, so this is an estimate, not a
    bound; it tells whether a change between rounds is larger than the sampling noise."""
    s = np.asarray(samples_unit, float)
    s = s.reshape(-1, walkers, s.shape[-1])

    def width(x):
        q = np.quantile(x.reshape(-1, x.shape[-1]), [0.05, 0.95], axis=0)
        return float(np.mean(q[1] - q[0]))

    w = [width(s[:, g::groups]) for g in range(groups)]
    return float(np.std(w, ddof=1) / np.sqrt(groups))


def principal_sd(samples_unit: np.ndarray) -> list[float]:
    """Standard deviations of the posterior along its principal axes (unit range, ascending):
    how many parameter combinations the data pin, whatever the marginal widths say (a uniform
    prior has 0.289 along every axis)."""
    s = np.asarray(samples_unit, float).reshape(-1, np.shape(samples_unit)[-1])
    return np.sqrt(np.clip(np.linalg.eigvalsh(np.cov(s.T)), 0.0, None)).tolist()


def cmd_recalibrate(args) -> int:
    from inverse.calibrate import calibrate_target
    from inverse.optimise import OptimiserConfig
    from inverse.posterior import PosteriorConfig, with_normalised_sigma
    from inverse.refine import _posterior_rows, _truth_rows
    from inverse.validate import row_target
    from surrogate.api import load

    torch.set_num_threads(args.threads)
    ds = read_dataset(args.dataset)
    out = Path(args.out)
    folders = sorted(p.parent for p in out.glob("twin-row*/refine.json"))
    if not folders:
        print(f"no twin folders with refine.json under {out}", file=sys.stderr)
        return 2
    sigma_n = args.sigma
    if sigma_n is not None and not sigma_n > 0:
        print(f"--sigma {sigma_n}: must be > 0 (normalised units)", file=sys.stderr)
        return 2
    if sigma_n is None:  # the floor in the initial model's normalisation
        first = json.loads((folders[0] / "refine.json").read_text())
        sigma_n = floor_sigma(load(first["request"]["model"]), ds)
        print(f"[twins] observation sigma = the run-to-run floor, {sigma_n:.4f} normalised",
              file=sys.stderr, flush=True)
    kind = "perfect" if args.perfect else "floor"
    for folder in folders:
        state = json.loads((folder / "refine.json").read_text())
        req = state["request"]
        for rec in state["rounds"]:
            r = rec["round"]
            path = folder / "rounds" / f"r{r:02d}" / f"recalibration-{kind}.json"
            if path.exists() and np.isclose(json.loads(path.read_text())[
                    "observation_sigma_normalised"], sigma_n, rtol=1e-9, atol=0.0):
                continue  # done at this sigma (another sigma is recalibrated again)
            model_error = 0.0 if args.perfect else rec["model_error_sigma"]
            model_path = Path(rec["model"])
            if r > 0 and not model_path.exists():  # the folder moved: the round's own copy
                model_path = folder / "rounds" / f"r{r:02d}" / "model.pt"
            model = load(model_path)
            row = int(req["target"]["row"])
            target = with_normalised_sigma(
                model, row_target(model, ds, row, req["use_distribution"]), sigma_n)
            post = PosteriorConfig(**{
                k: v for k, v in {**req["posterior"], "model_error_sigma": model_error,
                                  "use_model_variance": not args.perfect and req[
                                      "posterior"].get("use_model_variance", True)}.items()
                if k in PosteriorConfig.__dataclass_fields__})
            oc = calibrate_target(model, target, optimiser=OptimiserConfig(**{
                k: v for k, v in req["optimiser"].items()
                if k in OptimiserConfig.__dataclass_fields__}),
                fix=req["fix"] or None, posterior=post, identifiability=False,
                progress=False)
            summary = oc.result["posterior"]["parameters"]
            u = np.asarray(oc.result["parameters_unit"], float)
            rows = _posterior_rows(summary)
            res = {"round": r, "model": str(model_path), "row": row,
                   "observation_sigma_normalised": sigma_n, "kind": kind,
                   "model_error_sigma": model_error,
                   "use_model_variance": post.use_model_variance,
                   "posterior": rows,
                   "posterior_diagnostics": {k: oc.result["posterior"]["diagnostics"][k]
                                             for k in ("acceptance_mean", "long_enough")},
                   "truth": _truth_rows(model.space, np.asarray(ds.params[row], float), u,
                                        summary),
                   "mean_width_unit": float(np.mean([x["width_unit"]
                                                     for x in rows.values()])),
                   "principal_sd_unit": principal_sd(oc.posterior.samples_unit)}
            npz = path.with_name("posterior.npz")  # the round's own posterior (default sigma)
            if npz.exists():
                res["principal_sd_unit_default_sigma"] = principal_sd(
                    np.load(npz)["samples_unit"])
            write_json(path, res)
            print(f"[twins] {folder.name} round {r} ({kind}): mean 90 % width "
                  f"{res['mean_width_unit']:.3f} (default sigma {rec['mean_width_unit']:.3f})"
                  f", truth inside {sum(t['inside_ci90'] for t in res['truth'].values())}/"
                  f"{len(res['truth'])}", file=sys.stderr, flush=True)
    return cmd_report(args)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run")
    r.add_argument("--model", required=True)
    r.add_argument("--dataset", required=True)
    r.add_argument("--out", required=True)
    r.add_argument("--rows", type=int, nargs="+", help="twin rows (default: one replicate "
                                                       "run per group at an unseen seed)")
    r.add_argument("--budget", type=int, default=12)
    r.add_argument("--batch", type=int, default=4)
    r.add_argument("--tol", type=float, default=0.02)
    r.add_argument("--epochs", type=int, default=None)
    r.add_argument("--steps", type=int, default=3000)
    r.add_argument("--burn", type=int, default=1000)
    r.add_argument("--workers", type=int, default=1)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    p = sub.add_parser("report")
    p.add_argument("--out", required=True)
    c = sub.add_parser("recalibrate", help="every finished round again, with the observation "
                                           "sigma at the run-to-run floor (no DEM run)")
    c.add_argument("--out", required=True)
    c.add_argument("--dataset", required=True)
    c.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    c.add_argument("--sigma", type=float, default=None,
                   help="the observation sigma, normalised (default: the dataset's "
                        "run-to-run floor)")
    c.add_argument("--perfect", action="store_true",
                   help="as if the surrogate were perfect (model error 0, no ensemble "
                        "variance): the narrowest intervals any refinement could reach")
    for q in (r, p, c):
        q.add_argument("--name", default="refine_twins",
                       help="the report's file name (.json, .md)")
        q.add_argument("--results-dir", default=str(RESULTS),
                       help="where the report goes (default benchmarks/results)")
    args = ap.parse_args(argv)
    return {"run": cmd_run, "report": cmd_report,
            "recalibrate": cmd_recalibrate}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
