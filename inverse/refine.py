"""Posterior-guided refinement: spend new DEM runs where the calibration needs them.

``inverse refine`` (:func:`refine`) calibrates a target with the surrogate, then repeats
rounds of

1. **select** ``batch`` points from the current posterior: a greedy farthest-point
   (maximin) selection among posterior samples, in coordinates scaled by the posterior's
   own standard deviation per parameter, away from every point already run; the first
   round starts at the calibrated optimum;
2. **run** them with the DEM through :func:`calendaring.data.sweep.sweep` (resumable, local
   workers or a Dask scheduler), with the dataset's own problem configuration
   (:func:`calendaring.data.dataset.dataset_config`), by default each run on a bed of its
   own (seeds the dataset never used: a measured curve's bed is unknown, so the error
   measured on them must include the bed-to-bed scatter), or all on one given seed;
3. **measure** the current surrogate's error on the new runs *before* they are trained on
   (the honest out-of-sample check near the posterior: :func:`surrogate.evaluate.model_metrics`);
4. **add** them to the dataset with role ``refine`` (:func:`calendaring.data.dataset.append_runs`)
   and **retrain** the surrogate from scratch with the initial model's training settings,
   architecture, member count and split of the original rows, the refine rows always in the
   training part (``refine_weight`` times);
5. **recalibrate** with the pooled out-of-sample error as the surrogate error of the
   likelihood (``model_error_sigma``, normalised pressure units: the root mean square over
   every refine run measured so far, each by the model before it was trained on it),

until ``budget`` runs are spent or the posterior stops changing (every free parameter's
90 % interval ends move by less than ``tol`` of the unit range between two rounds).

Everything lands in the output folder, each file written atomically; a killed refinement
resumes where it stopped by rerunning the same command (a finished step is never redone;
runs in flight resume from their checkpoints):

==============================  ==========================================================
``refine.json``                 the request, every finished round, the status and the stop
                                reason (rewritten after each step)
``base.json``                   the DEM configuration of every new run
``runs/``                       the sweep folder of the new runs (manifest, runs, digests)
``rounds/rNN/calibration.json`` round NN's calibration (:mod:`inverse.report` layout)
``rounds/rNN/posterior.npz``    its posterior samples (free unit coordinates)
``rounds/rNN/refine-rNN.csv``   the points selected in round NN (physical values)
``rounds/rNN/error.json``       the previous model's error on round NN's runs
``rounds/rNN/dataset.h5``       the dataset with every refine run up to round NN
``rounds/rNN/model.pt``         the surrogate retrained on it
``rounds/rNN/round.json``       the round's record (present once the round is complete)
``refine.png``                  90 % intervals per parameter and round (truth if known)
==============================  ==========================================================

A target may be a curve (CSV or run file, :func:`inverse.targets.load_target`) or a row of
the dataset that the surrogate never trained on (a synthetic twin: its true parameters are
known, so each round also records the optimum's error and whether the intervals cover the
truth).
"""

from __future__ import annotations

import datetime
import hashlib
import json
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from calendaring import ConfigError
from inverse.optimise import OptimiserConfig
from inverse.posterior import PosteriorConfig
from inverse.report import write_json

FORMAT = "calendaring-refine"
ROLE = "refine"


@dataclass(frozen=True)
class RefineConfig:
    """What a refinement spends and how it selects, runs and retrains."""

    budget: int  # DEM runs in all
    batch: int  # DEM runs per round
    tol: float = 0.05  # stop when no 90 % interval end moves more than this (unit range)
    dem_seed: int | None = None  # None: every new run on a bed of its own (see Refinement)
    candidates: int = 4000  # posterior samples the selection chooses among
    epochs: int | None = None  # retraining epochs (None: the initial model's)
    refine_weight: int = 1  # copies of each refine row in the training split
    seed: int = 0  # selection, optimiser and MCMC seed
    workers: int = 0  # sweep workers (0: one per core)
    threads_per_run: int = 1
    scheduler: str | None = None  # address of a Dask scheduler
    timeout: float | None = None  # s per DEM run attempt
    max_attempts: int = 2

    def __post_init__(self) -> None:
        for key, lo in (("budget", 1), ("batch", 1), ("candidates", 1), ("refine_weight", 1),
                        ("threads_per_run", 1), ("max_attempts", 1), ("workers", 0)):
            v = getattr(self, key)
            if not isinstance(v, int | np.integer) or v < lo:
                raise ConfigError(f"--{key.replace('_', '-')}", v, f"an integer >= {lo}")
        if self.batch > self.budget:
            raise ConfigError("--batch", self.batch, f"<= --budget ({self.budget})")
        if self.candidates < self.batch:
            raise ConfigError("--candidates", self.candidates, f">= --batch ({self.batch})")
        if not (0 < self.tol < 1):
            raise ConfigError("--tol", self.tol, "a fraction of the unit range in (0, 1)")
        if self.epochs is not None and (not isinstance(self.epochs, int) or self.epochs < 1):
            raise ConfigError("--epochs", self.epochs, "an integer >= 1")
        if self.dem_seed is not None and (not isinstance(self.dem_seed, int)
                                          or self.dem_seed < 0):
            raise ConfigError("--dem-seed", self.dem_seed, "an integer >= 0")
        if self.timeout is not None and not self.timeout > 0:
            raise ConfigError("--timeout", self.timeout, "> 0 s")


# ---------------------------------------------------------------------- selection
def select_points(samples: np.ndarray, k: int, chosen: np.ndarray | None = None,
                  first: np.ndarray | None = None, candidates: int = 4000,
                  seed: int = 0) -> tuple[np.ndarray, dict]:
    """``k`` spread-out points among posterior ``samples`` (S, m) (free unit coordinates).

    Greedy farthest-point selection in coordinates divided by the samples' standard
    deviation per column (so a tightly constrained parameter counts as much as a loose
    one): each pick is the candidate farthest from every point chosen so far, ``chosen``
    (earlier rounds' points) included. Without earlier points the first pick is ``first``
    (e.g. the optimum) or the candidate nearest the samples' median. Returns the points
    (k, m) and a description (scale, the smallest scaled distance between any two of the
    new and old points).
    """
    samples = np.atleast_2d(np.asarray(samples, float))
    if len(samples) < k:
        raise ConfigError("posterior samples", len(samples), f">= {k} (the batch)")
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(samples), size=min(len(samples), int(candidates)), replace=False)
    cand = samples[np.sort(pick)]
    scale = np.maximum(samples.std(axis=0, ddof=1), 1e-3)
    z = cand / scale
    old = np.zeros((0, samples.shape[1])) if chosen is None or len(chosen) == 0 \
        else np.atleast_2d(np.asarray(chosen, float)) / scale
    out: list[np.ndarray] = []
    dmin = np.full(len(z), np.inf)
    for p in old:
        dmin = np.minimum(dmin, np.linalg.norm(z - p, axis=1))
    if len(old) == 0:
        start = np.asarray(first, float) if first is not None else \
            cand[np.argmin(np.linalg.norm(z - np.median(z, axis=0), axis=1))]
        out.append(start)
        dmin = np.linalg.norm(z - start / scale, axis=1)
    while len(out) < k:
        j = int(np.argmax(dmin))
        out.append(cand[j])
        dmin = np.minimum(dmin, np.linalg.norm(z - z[j], axis=1))
    pts = np.array(out[:k])
    allz = np.concatenate([old, pts / scale])
    d = np.linalg.norm(allz[:, None, :] - allz[None, :, :], axis=-1)
    d[np.diag_indices_from(d)] = np.inf
    return pts, {"scale_unit": scale.tolist(), "candidates": len(cand),
                 "earlier_points": len(old),
                 "min_scaled_distance": float(d.min()) if len(allz) > 1 else None}


def interval_change(a: dict, b: dict) -> float:
    """Largest move of a 90 % interval end (unit range) between two posterior summaries
    ``{name: {"ci90_unit": [lo, hi]}}`` over the parameters both have."""
    moves = [max(abs(a[n]["ci90_unit"][0] - b[n]["ci90_unit"][0]),
                 abs(a[n]["ci90_unit"][1] - b[n]["ci90_unit"][1])) for n in a if n in b]
    return float(max(moves)) if moves else float("inf")


# ---------------------------------------------------------------------- surrogate
def initial_model_error(model) -> float:
    """The model's own held-out pressure RMSE (normalised units) as recorded at training
    (``info.metrics.test``), 0 if it has none."""
    try:
        mse = model.info["metrics"]["test"]["pressure"]["pressure_mse_normalised"]
        return float(np.sqrt(mse))
    except (KeyError, TypeError):
        return 0.0


def out_of_sample_error(model, ds, rows) -> dict:
    """The model's errors on dataset ``rows`` it has not trained on: the metrics of
    :func:`surrogate.evaluate.model_metrics` plus the pressure RMSE (normalised units) of
    each row."""
    from surrogate.evaluate import model_metrics

    rows = np.asarray(rows, int)
    pred = model.predict_unit(ds.unit_params[rows])
    out = model_metrics(model, ds, rows, pred)
    r = pred.pressure_normalised - model.normalise_pressure(ds.pressure[rows])
    out["rows"] = [{"run_id": str(ds.run_id[i]),
                    "pressure_rmse_normalised": float(np.sqrt(np.mean(e**2)))}
                   for i, e in zip(rows, r, strict=True)]
    out["pressure_sse_normalised"] = float(np.sum(np.mean(r**2, axis=1)))
    return out


def retrain(model, ds, epochs: int | None = None, refine_weight: int = 1,
            progress: bool = False):
    """The surrogate retrained from scratch on ``ds``: the initial model's training settings
    (:class:`~surrogate.train.TrainConfig` from its checkpoint), architecture and member
    count; the split of the original rows as the initial model's (same seed and roles),
    every ``refine`` row added to the training part ``refine_weight`` times."""
    from surrogate.api import SurrogateModel
    from surrogate.train import TrainConfig, make_split, train

    tc = TrainConfig.from_dict(model.info.get("train_config", {}))
    if epochs:
        tc = replace(tc, epochs=int(epochs))
    base_roles = tuple(r for r in tc.train_roles if r != ROLE) or ("train",)
    split = make_split(ds, replace(tc, train_roles=base_roles))
    ref = np.nonzero(ds.role == ROLE)[0]
    split["train"] = np.sort(np.concatenate([split["train"],
                                             np.repeat(ref, int(refine_weight))]))
    tc = replace(tc, train_roles=(*base_roles, ROLE))
    t0 = time.perf_counter()
    results = []
    for k in range(model.n_members):
        results.append(train(ds, replace(tc, member=k), model.config, progress=progress,
                             split=split, norm=results[0].normalisation if results else None))
    seconds = time.perf_counter() - t0
    new = SurrogateModel.from_training(results, ds, {
        "train_seconds_total": seconds,
        "refine": {"refine_rows": len(ref), "refine_weight": int(refine_weight),
                   "from_model": str(model.info.get("path", ""))}})
    return new, seconds


# ---------------------------------------------------------------------- the loop
def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def _log(msg: str, progress: bool) -> None:
    if progress:
        print(f"[refine] {msg}", file=sys.stderr, flush=True)


def _target_digest(target) -> str:
    h = hashlib.sha256()
    for a in (target.depth, target.pressure, target.valid):
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def _posterior_rows(summary: dict) -> dict:
    return {n: {"mean_unit": s["mean_unit"], "ci90_unit": s["ci90_unit"],
                "width_unit": s["ci90_unit"][1] - s["ci90_unit"][0],
                "mean": s["mean"], "ci90": s["ci90"], "unit": s["unit"]}
            for n, s in summary.items()}


def _truth_rows(space, truth: np.ndarray | None, u_opt: np.ndarray, summary: dict) -> dict:
    if truth is None:
        return {}
    tu = space.to_unit(np.asarray(truth, float)[None, :])[0]
    out = {}
    for n, s in summary.items():
        j = space.index(n)
        out[n] = {"truth": float(truth[j]), "truth_unit": float(tu[j]),
                  "optimum_error_unit": float(u_opt[j] - tu[j]),
                  "inside_ci90": bool(s["ci90_unit"][0] <= tu[j] <= s["ci90_unit"][1])}
    return out


class Refinement:
    """One refinement in its folder (see the module docstring); :meth:`run` does the rest.

    Torch runs on the caller's threads (the CLI sets one: fastest for this small network).

    Args:
        model_path: the initial surrogate checkpoint.
        dataset_path: the dataset it was trained on (its problem is the DEM's).
        out: the output folder (created; a folder of the same refinement resumes).
        target: a curve path (CSV or run file) or, with ``target_row``, None.
        target_row: a dataset row the model never trained on (a synthetic twin).
        cfg: budget, batch and the rest (:class:`RefineConfig`).
        optimiser, posterior: calibration settings; ``posterior.model_error_sigma`` is the
            surrogate error of round 0 (0: the model's recorded held-out RMSE).
        fix: ``{name: physical value}`` parameters held.
        use_distribution: with a twin, calibrate on its breakage centroid too.
        task, pack: replace :func:`calendaring.data.sweep.run_task` and
            :func:`~calendaring.data.sweep.pack_task` (same signatures; tests).
    """

    def __init__(self, model_path, dataset_path, out, target=None, target_row=None,
                 cfg: RefineConfig | None = None, optimiser: OptimiserConfig | None = None,
                 posterior: PosteriorConfig | None = None, fix: dict | None = None,
                 use_distribution: bool = True, progress: bool = True, task=None,
                 pack=None) -> None:
        import surrogate
        from calendaring import read_dataset

        if (target is None) == (target_row is None):
            raise ConfigError("--target", target, "exactly one of --target CURVE and "
                                                  "--target-row ROW")
        if cfg is None:
            raise ConfigError("refine", None, "a RefineConfig (budget and batch)")
        self.cfg = cfg
        self.out = Path(out)
        self.progress = progress
        self.task, self.pack = task, pack  # the sweep's DEM and packing tasks (tests)
        self.fix = dict(fix or {})
        self.optimiser = optimiser or OptimiserConfig(seed=cfg.seed)
        self.posterior = posterior or PosteriorConfig(seed=cfg.seed)
        self.model_path = Path(model_path)
        self.dataset_path = Path(dataset_path)
        self.model0 = surrogate.load(self.model_path)
        self.ds0 = read_dataset(self.dataset_path)
        m, d = self.model0, self.ds0
        if list(m.space.names) != list(d.space.names):
            raise ConfigError("--dataset parameters", d.space.names,
                              f"the model's {m.space.names}")
        if len(m.depth) != len(d.depth) or not np.allclose(m.depth, d.depth, rtol=1e-9):
            raise ConfigError("--dataset depths", f"{len(d.depth)} points",
                              f"the model's {len(m.depth)} depths (the dataset it was "
                              "trained on)")
        if not (np.allclose(m.load_edges, d.load_edges, rtol=1e-9)
                and np.allclose(m.diameter_edges, d.diameter_edges, rtol=1e-9)):
            raise ConfigError("--dataset bins", "histogram edges",
                              "the model's (the dataset it was trained on)")
        m.space.check(self.fix)
        self.truth = None
        if target_row is not None:
            from inverse.validate import row_target, trained_on

            i = int(target_row)
            if trained_on(m, d, i) or d.role[i] == "train":
                raise ConfigError("--target-row", i, "a row the model never trained on "
                                  f"(role holdout or replicate; row {i} is "
                                  f"{d.role[i]} {d.run_id[i]})")
            self.target = row_target(m, d, i, use_distribution)
            self.truth = np.asarray(d.params[i], float)
            self.target_desc = {"row": i, "run_id": str(d.run_id[i]),
                                "role": str(d.role[i]), "seed": int(d.seed[i])}
        else:
            from inverse.targets import load_target

            self.target = load_target(target, m)
            self.target_desc = {"path": str(target)}
        self.target_desc["digest"] = _target_digest(self.target)
        # the new runs' beds: by default each run its own, on seeds the dataset never used
        # (so the error measured on them includes the bed-to-bed scatter that a
        # measurement has), else all on the one given seed (one settled bed, cheaper)
        self.distinct_beds = cfg.dem_seed is None
        self.dem_seed = int(d.seed.max()) + 1 if self.distinct_beds else int(cfg.dem_seed)
        sigma0 = self.posterior.model_error_sigma or initial_model_error(m)
        self.sigma0 = float(sigma0)
        from surrogate.checkpoint import checkpoint_fingerprint

        self.request = {
            "model": str(self.model_path),
            # the weights, not the file: a model retrained identically resumes the folder
            "model_fingerprint": checkpoint_fingerprint(self.model_path),
            "dataset": str(self.dataset_path), "dataset_fingerprint": d.fingerprint,
            "target": self.target_desc, "config": asdict(cfg), "dem_seed": self.dem_seed,
            "distinct_beds": self.distinct_beds,
            "fix": self.fix, "use_distribution": bool(use_distribution),
            "optimiser": self.optimiser.to_json(),
            "posterior": {**self.posterior.to_json(), "model_error_sigma": self.sigma0}}

    # ------------------------------------------------------------------ files
    def rdir(self, r: int) -> Path:
        return self.out / "rounds" / f"r{r:02d}"

    def _state(self) -> dict:
        p = self.out / "refine.json"
        return json.loads(p.read_text()) if p.exists() else {}

    def _check_request(self, state: dict) -> None:
        """A folder holds one refinement: a resume must ask for the same thing (the
        execution settings of the sweep may change)."""
        old = state.get("request")
        if not old:
            return
        loose = {"workers", "scheduler", "timeout", "threads_per_run", "max_attempts",
                 "budget"}
        for key in sorted(set(old) | set(self.request)):
            a, b = old.get(key), self.request.get(key)
            if key == "config":
                a = {k: v for k, v in (a or {}).items() if k not in loose}
                b = {k: v for k, v in (b or {}).items() if k not in loose}
            if key in ("model", "dataset"):
                continue  # paths may move; their digests are compared
            if json.dumps(a, sort_keys=True, default=str) != \
                    json.dumps(b, sort_keys=True, default=str):
                raise ConfigError("--out", str(self.out),
                                  f"a new folder, or the same request to resume this "
                                  f"refinement ('{key}' was {a}, now {b})")

    def _write_state(self, rounds: list[dict], status: str, reason: str = "") -> None:
        write_json(self.out / "refine.json", {
            "format": FORMAT, "updated": _now(), "request": self.request, "status": status,
            "stop_reason": reason, "runs_spent": sum(r["runs_planned"] for r in rounds),
            "runs_done": sum(r["runs_done"] for r in rounds), "rounds": rounds})

    # ------------------------------------------------------------------ steps
    def _calibrate(self, model, sigma: float, r: int) -> tuple[dict, np.ndarray, np.ndarray]:
        """Round ``r``'s calibration (reused when on disk): (result, samples, free)."""
        from inverse.calibrate import calibrate_target

        d = self.rdir(r)
        path, npz = d / "calibration.json", d / "posterior.npz"
        if path.exists() and npz.exists():
            z = np.load(npz)
            return json.loads(path.read_text()), z["samples_unit"], z["free"]
        d.mkdir(parents=True, exist_ok=True)
        post = replace(self.posterior, model_error_sigma=float(sigma))
        oc = calibrate_target(model, self.target, optimiser=self.optimiser, fix=self.fix,
                              posterior=post, identifiability=False, progress=False)
        free = np.array([n in oc.posterior.names for n in model.space.names])
        tmp = npz.with_name(f".{npz.stem}.tmp.npz")
        np.savez(tmp, samples_unit=oc.posterior.samples_unit, free=free)
        tmp.replace(npz)
        write_json(path, oc.result)
        return oc.result, oc.posterior.samples_unit, free

    def _record(self, r: int, model_path: Path, sigma: float, cal: dict, extra: dict) -> dict:
        space = self.model0.space
        summary = cal["posterior"]["parameters"]
        u = np.asarray(cal["parameters_unit"], float)
        rec = {"round": r, "model": str(model_path), "model_error_sigma": float(sigma),
               "optimum_unit": u.tolist(),
               "optimum": space.from_unit(u[None, :])[0].tolist(),
               "fit": cal["fit"], "posterior": _posterior_rows(summary),
               "posterior_diagnostics": {k: cal["posterior"]["diagnostics"][k]
                                         for k in ("acceptance_mean", "long_enough")},
               "truth": _truth_rows(space, self.truth, u, summary), **extra}
        rec["mean_width_unit"] = float(np.mean([p["width_unit"]
                                                for p in rec["posterior"].values()]))
        return rec

    def _base_config(self) -> Path:
        from calendaring import config_json, dataset_config, write_text

        path = self.out / "base.json"
        if not path.exists():
            write_text(path, config_json(dataset_config(self.ds0)) + "\n")
        return path

    def _round(self, r: int, k: int, spent: int, prev: dict, ds_prev, model_prev,
               model_prev_path: Path, sq_errors: list[float]
               ) -> tuple[dict, object, object, Path]:
        """Round ``r`` >= 1 (each step reused when on disk); ``spent``: runs planned in the
        rounds before it."""
        import surrogate
        from calendaring import (
            SweepOptions,
            append_runs,
            read_dataset,
            read_design_csv,
            sweep,
            write_dataset,
            write_design_csv,
        )

        space = self.model0.space
        d = self.rdir(r)
        d.mkdir(parents=True, exist_ok=True)
        times = {}
        label = f"refine-r{r:02d}"
        csv = d / f"{label}.csv"
        # 1. select
        if not csv.exists():
            z = np.load(self.rdir(r - 1) / "posterior.npz")
            samples, free = z["samples_unit"], z["free"]
            u_prev = np.asarray(prev["optimum_unit"], float)
            done_u = space.to_unit(ds_prev.params[ds_prev.role == ROLE]) \
                if np.any(ds_prev.role == ROLE) else np.zeros((0, len(space)))
            pts, info = select_points(samples, k, chosen=done_u[:, free],
                                      first=u_prev[free], candidates=self.cfg.candidates,
                                      seed=self.cfg.seed + r)
            u = np.repeat(u_prev[None, :], k, axis=0)
            u[:, free] = pts
            x = space.from_unit(u)
            for name, v in self.fix.items():
                x[:, space.index(name)] = v
            write_json(d / "selection.json", {**info, "points_unit": u.tolist(),
                                              "free": [n for n, f in zip(space.names, free,
                                                                         strict=True) if f]})
            write_design_csv(csv, x, space)
        x = read_design_csv(csv, space)
        # 2. run
        t0 = time.perf_counter()
        seed = self.dem_seed + (spent if self.distinct_beds else 0)
        beds = (f"seeds {seed}-{seed + len(x) - 1}" if self.distinct_beds and len(x) > 1
                else f"seed {seed}")
        _log(f"round {r}: {len(x)} DEM runs ({beds}) in {self.out / 'runs'}", self.progress)
        runs = sweep(SweepOptions(
            source=str(self._base_config().resolve()), out=self.out / "runs", design=str(csv),
            n=len(x), seed=seed, seed_per_row=self.distinct_beds, role=ROLE,
            workers=self.cfg.workers,
            threads_per_run=self.cfg.threads_per_run, scheduler=self.cfg.scheduler,
            max_attempts=self.cfg.max_attempts, timeout=self.cfg.timeout,
            progress=self.progress), task=self.task, pack=self.pack)
        times["runs"] = time.perf_counter() - t0
        mine = sorted((e for e in runs.values() if e.design == label), key=lambda e: e.index)
        done = [e.run_id for e in mine if e.status == "done"]
        failed = [[e.run_id, e.error.splitlines()[0] if e.error else ""]
                  for e in mine if e.status != "done"]
        runs_rec = [{"run_id": e.run_id, "status": e.status, "wall_s": e.wall_time}
                    for e in mine]
        # 3.-4. add, measure, retrain
        dpath, mpath, epath = d / "dataset.h5", d / "model.pt", d / "error.json"
        if not done:
            ds, model, model_path, err = ds_prev, model_prev, model_prev_path, None
            _log(f"round {r}: no run finished ({len(failed)} failed); the model stays",
                 self.progress)
        else:
            if dpath.exists():
                ds = read_dataset(dpath)
            else:
                write_dataset(dpath, append_runs(ds_prev, self.out / "runs", names=done,
                                                 role=ROLE))
                ds = read_dataset(dpath)
            new_rows = np.nonzero(np.isin(ds.run_id, done))[0]
            if epath.exists():
                err = json.loads(epath.read_text())
            else:
                err = out_of_sample_error(model_prev, ds, new_rows)
                write_json(epath, err)
            if mpath.exists():
                model = surrogate.load(mpath)
            else:
                t0 = time.perf_counter()
                model, _ = retrain(model_prev, ds, self.cfg.epochs, self.cfg.refine_weight,
                                   progress=False)
                model.save(mpath)
                model = surrogate.load(mpath)
                times["retrain"] = time.perf_counter() - t0
            model_path = mpath
        if err is not None:
            sq_errors.extend(row["pressure_rmse_normalised"] ** 2 for row in err["rows"])
        sigma = float(np.sqrt(np.mean(sq_errors))) if sq_errors else \
            prev["model_error_sigma"]
        t0 = time.perf_counter()
        cal, _, _ = self._calibrate(model, sigma, r)
        times["calibrate"] = time.perf_counter() - t0
        summary_err = None
        if err is not None:
            p = err["pressure"]
            summary_err = {
                "n_runs": p["n_rows"],
                "pressure_rmse_normalised": float(np.sqrt(p["pressure_mse_normalised"])),
                "pressure_rmse_MPa": p["pressure_rmse_Pa"] / 1e6,
                "abs_error_MPa_at_stroke": {k: v["abs_error_Pa"] / 1e6
                                            for k, v in p["at_stroke"].items()},
                "kl_mean": err.get("distribution", {}).get("kl_mean"),
                "ensemble_coverage_2sigma": err.get("ensemble", {}).get("coverage_2sigma")}
        rec = self._record(r, model_path, sigma, cal, {
            "runs_planned": len(x), "runs_done": len(done), "runs": runs_rec,
            "failed": failed, "points": x.tolist(),
            "error_before_training": summary_err, "dataset_rows": len(ds),
            "interval_change_unit": interval_change(
                cal["posterior"]["parameters"],
                {n: {"ci90_unit": v["ci90_unit"]} for n, v in prev["posterior"].items()}),
            "seconds": times, "finished": _now()})
        write_json(d / "round.json", rec)
        return rec, ds, model, model_path

    # ------------------------------------------------------------------ driver
    def run(self) -> dict:
        """Run (or resume) the refinement; returns the final ``refine.json`` content."""
        import surrogate
        from calendaring import read_dataset, write_text

        self.out.mkdir(parents=True, exist_ok=True)
        state = self._state()
        self._check_request(state)
        self._base_config()
        write_text(self.out / "target.json", json.dumps(self.target.to_json()) + "\n")
        rounds: list[dict] = []
        r0 = self.rdir(0) / "round.json"
        if r0.exists():
            rec = json.loads(r0.read_text())
        else:
            _log(f"round 0: calibrating with the initial model (model error sigma "
                 f"{self.sigma0:.4g})", self.progress)
            t0 = time.perf_counter()
            cal, _, _ = self._calibrate(self.model0, self.sigma0, 0)
            rec = self._record(0, self.model_path, self.sigma0, cal, {
                "runs_planned": 0, "runs_done": 0, "seconds": {
                    "calibrate": time.perf_counter() - t0}, "finished": _now()})
            write_json(r0, rec)
        rounds.append(rec)
        self._write_state(rounds, "running")
        _log(self._line(rec), self.progress)
        ds, model, mpath = self.ds0, self.model0, self.model_path
        sq_errors: list[float] = []
        r = 0
        reason = ""
        while True:
            spent = sum(x["runs_planned"] for x in rounds)
            if r >= 1 and rounds[-1]["runs_done"] and \
                    rounds[-1]["interval_change_unit"] < self.cfg.tol:
                reason = (f"posterior stable: no 90 % interval end moved more than "
                          f"{self.cfg.tol} (unit range) in round {r}")
                break
            if spent >= self.cfg.budget:
                reason = f"budget spent ({spent} of {self.cfg.budget} runs)"
                break
            r += 1
            k = min(self.cfg.batch, self.cfg.budget - spent)
            path = self.rdir(r) / "round.json"
            if path.exists():  # a finished round: reload what the next one needs
                rec = json.loads(path.read_text())
                if (self.rdir(r) / "dataset.h5").exists():
                    ds = read_dataset(self.rdir(r) / "dataset.h5")
                    err = json.loads((self.rdir(r) / "error.json").read_text())
                    sq_errors.extend(x["pressure_rmse_normalised"] ** 2 for x in err["rows"])
                if (self.rdir(r) / "model.pt").exists():
                    mpath = self.rdir(r) / "model.pt"
                    model = surrogate.load(mpath)
            else:
                rec, ds, model, mpath = self._round(r, k, spent, rounds[-1], ds, model,
                                                    mpath, sq_errors)
            rounds.append(rec)
            self._write_state(rounds, "running")
            _log(self._line(rec), self.progress)
        self._write_state(rounds, "done", reason)
        _log(f"done: {reason}", self.progress)
        try:
            plot_refinement(rounds, self.model0.space, self.out / "refine.png")
        except Exception as err:  # a plot never loses the results
            _log(f"plot failed: {err}", self.progress)
        state = self._state()
        state["plot"] = str(self.out / "refine.png")
        write_json(self.out / "refine.json", state)
        return state

    def _line(self, rec: dict) -> str:
        w = rec["mean_width_unit"]
        s = (f"round {rec['round']}: {rec['runs_done']}/{rec['runs_planned']} runs, model "
             f"error sigma {rec['model_error_sigma']:.4f}, mean 90 % width {w:.3f} (unit)")
        if rec.get("error_before_training"):
            s += (f", out-of-sample RMSE "
                  f"{rec['error_before_training']['pressure_rmse_normalised']:.4f}")
        if rec["truth"]:
            inside = sum(v["inside_ci90"] for v in rec["truth"].values())
            s += f", truth inside {inside}/{len(rec['truth'])}"
        return s


def plot_refinement(rounds: list[dict], space, path) -> Path:
    """90 % interval (bar) and optimum (dot) of each free parameter per round, unit scale,
    with the truth (dashed) when known."""
    import matplotlib.pyplot as plt

    names = list(rounds[0]["posterior"])
    cols = 4
    rows = int(np.ceil(len(names) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.0 * cols, 2.6 * rows), squeeze=False)
    rr = np.array([x["round"] for x in rounds])
    for ax, name in zip(axes.flat, names, strict=False):
        lo = np.array([x["posterior"][name]["ci90_unit"][0] for x in rounds])
        hi = np.array([x["posterior"][name]["ci90_unit"][1] for x in rounds])
        opt = np.array([x["optimum_unit"][space.index(name)] for x in rounds])
        ax.vlines(rr, lo, hi, color="C0", lw=4, alpha=0.6)
        ax.plot(rr, opt, "o", color="C3", ms=3)
        t = rounds[0]["truth"].get(name)
        if t:
            ax.axhline(t["truth_unit"], color="k", ls="--", lw=0.8)
        ax.set_ylim(0, 1)
        ax.set_xticks(rr)
        ax.set_title(space[name].symbol, fontsize=9)
        ax.set_xlabel("round", fontsize=8)
    for ax in list(axes.flat)[len(names):]:
        ax.axis("off")
    known = " (dashed: the truth)" if rounds[0]["truth"] else ""
    fig.suptitle(f"90 % intervals (bars) and optimum (dots) per round{known}", fontsize=9)
    fig.tight_layout()
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
    return path


def refine(model_path, dataset_path, out, **kw) -> dict:
    """Build a :class:`Refinement` and run (or resume) it; returns ``refine.json``."""
    return Refinement(model_path, dataset_path, out, **kw).run()


__all__ = ["FORMAT", "ROLE", "RefineConfig", "Refinement", "initial_model_error",
           "interval_change", "out_of_sample_error", "plot_refinement", "refine", "retrain",
           "select_points"]
