"""Validation against truth: calibrate on dataset rows whose parameters are known.

For each held-out row (role ``holdout`` by default, never used in training, or an explicit
list of rows) the row's smoothed pressure curve and its breakage histogram become the target;
the surrogate is calibrated (two-phase optimiser, then the posterior) and compared with the
row's true parameters. Reported per parameter: the recovery error of the optimum and of the
posterior mean (unit-cube and physical, mean absolute and RMS), and the coverage of the 90 %
credible intervals (the fraction of rows whose truth lies inside). With ``identifiability``
each row also gets the slice loss profiles at its optimum
(:func:`inverse.identifiability.loss_profiles`). A parameter is constrained by a row when
its profile there is not flat and its posterior 90 % interval spans at most
``CONSTRAINED_WIDTH`` of the prior's (the uniform prior's 90 % interval is 0.9 of the unit
range); it is called identifiable when at least half of the rows constrain it. (The slice
profiles alone are lenient: at 30 um they rise by more than a tenth of the best loss for
every parameter, the truncation ratio included, whose posterior keeps the prior's width.)

Goals: d0 and phi inside their 90 % intervals in at least 80 % of the rows (``goal_met``),
and the same for every identifiable parameter (``identifiable_goal_met``).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from calendaring import ConfigError
from inverse.calibrate import calibrate_target
from inverse.optimise import OptimiserConfig
from inverse.posterior import PosteriorConfig
from inverse.report import write_json
from inverse.targets import Target, attach_distribution, resample_curve

PARTIAL = "validation.partial.json"
PRIOR_CI90_WIDTH = 0.9  # the uniform prior's 90 % interval on the unit range
CONSTRAINED_WIDTH = 0.8  # a row constrains a parameter: interval <= 0.8 x the prior's
IDENTIFIABLE_RULE = (f"constrained (slice profile not flat and 90 % interval <= "
                     f"{CONSTRAINED_WIDTH} x the prior's) in >= 50 % of the rows")
COVERAGE_GOAL = 0.8  # issue 7: d0 and phi inside their 90 % intervals >= 80 % of the time
KEY_PARAMETERS = ("d0", "phi")


def row_target(model, ds, i: int, use_distribution: bool = True) -> Target:
    """Dataset row ``i`` as a target on the model's depths."""
    md = np.asarray(model.depth, float)
    if len(ds.depth) == len(md) and np.allclose(ds.depth, md, rtol=1e-6, atol=1e-12):
        t = Target(depth=md, pressure=np.asarray(ds.pressure[i], float),
                   valid=np.ones(len(md), bool), source=f"dataset row {i}")
    else:
        t = resample_curve(ds.depth, ds.pressure[i], None, md, source=f"dataset row {i}")
    shape = (len(model.load_edges) - 1, len(model.diameter_edges) - 1)
    if (use_distribution and ds.n_events[i] > 0 and ds.histogram[i].shape == shape
            and np.allclose(ds.load_edges, model.load_edges, rtol=1e-6)
            and np.allclose(ds.diameter_edges, model.diameter_edges, rtol=1e-6)):
        t.distribution = np.asarray(ds.histogram[i], float)
        attach_distribution(t, model)
    return t


def trained_on(model, ds, i: int) -> bool:
    """Whether dataset row ``i`` (an index, checked against ``ds``) is one of the runs in
    the model's training split (matched by run id)."""
    if not 0 <= int(i) < len(ds):
        raise ConfigError("--target-row", int(i), f"a row index in [0, {len(ds) - 1}]")
    trained = {str(x) for part in model.info.get("split", {}).values() for x in part}
    return str(ds.run_id[int(i)]) in trained


def select_rows(ds, rows=None, roles=("holdout",)) -> np.ndarray:
    """Rows to validate on: explicit indices, else those with one of ``roles``."""
    if rows is not None:
        idx = np.asarray(list(rows), int)
        if len(idx) == 0 or idx.min() < 0 or idx.max() >= len(ds):
            raise ConfigError("--rows", list(map(int, idx)), f"indices in [0, {len(ds) - 1}]")
        return idx
    idx = np.nonzero(np.isin(ds.role, roles))[0]
    if len(idx) == 0:
        raise ConfigError("dataset roles", sorted(set(map(str, ds.role))),
                          f"rows with role in {list(roles)} (or pass --rows)")
    return idx


def validate_row(model, ds, i: int, optimiser: OptimiserConfig, posterior: PosteriorConfig,
                 use_distribution: bool = True, fix=None, identifiability: bool = True) -> dict:
    """Calibrate dataset row ``i`` and compare with its truth: the record :func:`validate`
    keeps per row (a function of the row and the settings only, so rows can be spread over
    processes)."""
    space = model.space
    target = row_target(model, ds, int(i), use_distribution)
    oc = calibrate_target(model, target, optimiser=optimiser, posterior=posterior,
                          identifiability=identifiability, fix=fix)
    truth = np.asarray(ds.params[i], float)
    tu = space.to_unit(truth)
    rec = {"row": int(i), "run_id": str(ds.run_id[i]), "fit": oc.result["fit"],
           "loss": oc.result["loss"]["total"], "parameters": {}}
    if identifiability:
        rec["flat"] = list(oc.result["identifiability"]["profiles"]["flat"])
    fixed = set(fix or {})
    for j, p in enumerate(oc.result["parameters"]):
        name = p["name"]
        if name in fixed:
            continue
        s = oc.posterior.summary[name]
        rec["parameters"][name] = {
            "truth": float(truth[j]), "truth_unit": float(tu[j]),
            "optimum": p["value"], "optimum_unit": p["value_unit"],
            "posterior_mean": s["mean"], "posterior_mean_unit": s["mean_unit"],
            "ci90": s["ci90"], "ci90_unit": s["ci90_unit"],
            "inside_ci90": bool(s["ci90_unit"][0] <= tu[j] <= s["ci90_unit"][1])}
    return rec


_WORKER: dict = {}


def _worker_init(model, ds, threads: int) -> None:
    import torch

    torch.set_num_threads(threads)
    _WORKER.update(model=model, ds=ds)


def _worker_row(i: int, kw: dict) -> dict:
    return validate_row(_WORKER["model"], _WORKER["ds"], i, **kw)


def _rows_in_parallel(model, ds, pending: list[int], kw: dict, jobs: int):
    """Yield the records of ``pending`` rows as worker processes finish them (spawned, each
    with the model and the dataset and the parent's torch thread count)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    import torch

    try:
        with ProcessPoolExecutor(max_workers=min(jobs, len(pending)),
                                 mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_worker_init,
                                 initargs=(model, ds, torch.get_num_threads())) as pool:
            futures = [pool.submit(_worker_row, int(i), kw) for i in pending]
            try:
                for f in as_completed(futures):
                    yield f.result()
            except BaseException:
                for f in futures:
                    f.cancel()
                raise
    except BrokenProcessPool as err:
        raise RuntimeError(
            f"validate: a worker process of --jobs {jobs} died before returning its row. The "
            "usual causes: validate(..., jobs > 1) called from a script without an "
            "'if __name__ == \"__main__\":' guard (each spawned worker re-runs the script), "
            "or a worker killed for memory. Guard the script, or use jobs=1; rows finished "
            "so far are kept in the checkpoint.") from err


def validate(model, ds, rows=None, roles=("holdout",), optimiser: OptimiserConfig | None = None,
             posterior: PosteriorConfig | None = None, use_distribution: bool = True,
             fix=None, identifiability: bool = True, progress: bool = True,
             done: dict[int, dict] | None = None, on_row=None, jobs: int = 1) -> dict:
    """Calibrate each selected row and score recovery and interval coverage.

    Returns a JSON-ready dict: ``rows`` (per row: truth, optimum, posterior mean and 90 %
    interval per parameter, inside flags, fit error, the parameters with flat profiles),
    ``per_parameter`` (mean absolute / RMS error in unit and physical values, coverage, the
    fraction of rows where it is identifiable), ``key_coverage`` and ``goal_met``,
    ``identifiable`` with ``identifiable_coverage`` and ``identifiable_goal_met``.

    ``done``: records of rows already calibrated with the same settings (reused, not rerun);
    ``on_row(record)`` is called after each new row (:func:`validate_to_dir` checkpoints).
    ``jobs`` > 1 calibrates that many rows at once in worker processes; each record depends
    on its row and the settings only, so the report is the same for any ``jobs``.
    """
    space = model.space
    if list(ds.space.names) != list(space.names):
        raise ConfigError("dataset parameters", ds.space.names, f"the model's {space.names}")
    if not (isinstance(jobs, int) and jobs >= 1):
        raise ConfigError("--jobs", jobs, "an integer >= 1")
    optimiser = optimiser or OptimiserConfig()
    posterior = posterior or PosteriorConfig()
    idx = select_rows(ds, rows, roles)
    t0 = time.perf_counter()
    fixed = set(fix or {})
    done = dict(done or {})
    kw = {"optimiser": optimiser, "posterior": posterior, "use_distribution": use_distribution,
          "fix": fix, "identifiability": identifiability}
    pending = [int(i) for i in idx if int(i) not in done]
    if jobs > 1 and len(pending) > 1:
        records = _rows_in_parallel(model, ds, pending, kw, jobs)
    else:
        records = (validate_row(model, ds, i, **kw) for i in pending)
    for n, rec in enumerate(records):
        done[rec["row"]] = rec
        if on_row is not None:
            on_row(rec)
        if progress:
            el = time.perf_counter() - t0
            eta = el / (n + 1) * (len(pending) - n - 1)
            inside = sum(v["inside_ci90"] for v in rec["parameters"].values())
            print(f"validate: row {rec['row']} ({n + 1}/{len(pending)} to calibrate), "
                  f"{inside}/{len(rec['parameters'])} truths inside 90 % CI, elapsed {el:.0f} s,"
                  f" ETA {eta:.0f} s", file=sys.stderr, flush=True)
    out_rows = [done[int(i)] for i in idx]
    per = {}
    for name in space.names:
        if name in fixed:
            continue
        r = [x["parameters"][name] for x in out_rows]
        eo = np.array([x["optimum_unit"] - x["truth_unit"] for x in r])
        em = np.array([x["posterior_mean_unit"] - x["truth_unit"] for x in r])
        ep = np.array([x["optimum"] - x["truth"] for x in r])
        per[name] = {"unit": space[name].unit, "mae_unit_optimum": float(np.abs(eo).mean()),
                     "rmse_unit_optimum": float(np.sqrt(np.mean(eo**2))),
                     "mae_unit_posterior_mean": float(np.abs(em).mean()),
                     "mae_physical_optimum": float(np.abs(ep).mean()),
                     "coverage_ci90": float(np.mean([x["inside_ci90"] for x in r])),
                     "mean_ci90_width_unit": float(np.mean([x["ci90_unit"][1] -
                                                            x["ci90_unit"][0] for x in r]))}
    if identifiability:
        for name, frac in identifiable_fractions(out_rows, list(per)).items():
            per[name].update(frac)
    key = {k: per[k]["coverage_ci90"] for k in KEY_PARAMETERS if k in per}
    out = {"rows": out_rows, "n_rows": len(out_rows), "per_parameter": per,
           "key_coverage": key, "goal": f"coverage >= {COVERAGE_GOAL} for {KEY_PARAMETERS}",
           "goal_met": bool(key and all(v >= COVERAGE_GOAL for v in key.values()))}
    if identifiability:
        ident = [k for k, v in per.items() if v["identifiable_fraction"] >= 0.5]
        cov = {k: per[k]["coverage_ci90"] for k in ident}
        out.update({"identifiable": ident, "identifiable_coverage": cov,
                    "identifiable_rule": IDENTIFIABLE_RULE,
                    "identifiable_goal_met": bool(all(v >= COVERAGE_GOAL
                                                      for v in cov.values()))})
    return out | {"optimiser": optimiser.to_json(), "posterior": posterior.to_json(),
                  "seconds": time.perf_counter() - t0}


def identifiable_fractions(rows: list[dict], names: list[str]) -> dict[str, dict]:
    """Per parameter, the fraction of ``rows`` (validation records) whose slice profile is
    not flat (``profile_fraction``), whose 90 % interval is at most ``CONSTRAINED_WIDTH``
    of the prior's (``narrow_fraction``) and where both hold (``identifiable_fraction``)."""
    out = {}
    for name in names:
        flat = np.array([name in x["flat"] for x in rows])
        w = np.array([x["parameters"][name]["ci90_unit"][1] - x["parameters"][name]["ci90_unit"][0]
                      for x in rows])
        narrow = w <= CONSTRAINED_WIDTH * PRIOR_CI90_WIDTH
        out[name] = {"profile_fraction": float(np.mean(~flat)),
                     "narrow_fraction": float(np.mean(narrow)),
                     "identifiable_fraction": float(np.mean(~flat & narrow))}
    return out


def plot_validation(report: dict, path, space):
    """Truth against optimum with the 90 % intervals, one panel per parameter."""
    import matplotlib.pyplot as plt

    names = list(report["per_parameter"])
    cols = 4
    rows = int(np.ceil(len(names) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.0 * rows), squeeze=False)
    for ax, name in zip(axes.flat, names, strict=False):
        r = [x["parameters"][name] for x in report["rows"]]
        t = np.array([x["truth_unit"] for x in r])
        m = np.array([x["posterior_mean_unit"] for x in r])
        lo = np.array([x["ci90_unit"][0] for x in r])
        hi = np.array([x["ci90_unit"][1] for x in r])
        ax.errorbar(t, m, yerr=[m - lo, hi - m], fmt="o", ms=3, lw=0.8)
        ax.plot([0, 1], [0, 1], "k--", lw=0.6)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        cov = report["per_parameter"][name]["coverage_ci90"]
        ax.set_title(f"{space[name].symbol}: coverage {100 * cov:.0f} %", fontsize=9)
        ax.set_xlabel("truth (unit)", fontsize=8)
        ax.set_ylabel("posterior mean, 90 % CI", fontsize=8)
    for ax in list(axes.flat)[len(names):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _request(model, ds, kw: dict) -> dict:
    """What makes a row's record reusable: the model's weights (a retrained model with the
    same weights counts as the same, so a checkpoint survives retraining on a fresh
    machine), the dataset and the settings."""
    from surrogate.checkpoint import checkpoint_fingerprint

    path = model.info.get("path") if hasattr(model, "info") else None
    settings = {k: (v.to_json() if hasattr(v, "to_json") else v) for k, v in kw.items()
                if k not in ("progress", "rows", "roles", "jobs")}
    req = {"model_fingerprint": checkpoint_fingerprint(path) if path and Path(path).is_file()
           else None, "dataset_fingerprint": ds.fingerprint, "settings": settings}
    return json.loads(json.dumps(req, default=str))


def validate_to_dir(model, ds, out_dir, **kw) -> dict:
    """:func:`validate`, then ``validation.json`` and ``validation.png`` in ``out_dir``.

    Resumable: each calibrated row is appended to ``validation.partial.json``; a rerun with
    the same model weights (:func:`surrogate.checkpoint.checkpoint_fingerprint`: a model
    retrained identically counts), dataset and settings reuses those rows (other settings
    start afresh). The partial file goes once ``validation.json`` is written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    partial = out_dir / PARTIAL
    request = _request(model, ds, kw)
    done: dict[int, dict] = {}
    if partial.is_file():
        old = json.loads(partial.read_text())
        if old.get("request") == request:
            done = {int(r["row"]): r for r in old.get("rows", [])}
        elif kw.get("progress", True):
            print(f"validate: {partial} holds other settings; starting afresh",
                  file=sys.stderr, flush=True)
    rows = list(done.values())

    def keep(rec: dict) -> None:
        rows.append(rec)
        write_json(partial, {"request": request, "rows": rows})

    rep = validate(model, ds, done=done, on_row=keep, **kw)
    rep["resumed_rows"] = len(done)
    rep["plot"] = str(plot_validation(rep, out_dir / "validation.png", model.space))
    write_json(out_dir / "validation.json", rep)
    partial.unlink(missing_ok=True)
    return rep


__all__ = ["CONSTRAINED_WIDTH", "COVERAGE_GOAL", "KEY_PARAMETERS", "PRIOR_CI90_WIDTH",
           "identifiable_fractions", "plot_validation", "row_target", "select_rows",
           "trained_on", "validate", "validate_row", "validate_to_dir"]
