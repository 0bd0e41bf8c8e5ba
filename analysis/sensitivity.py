"""Global (Sobol) sensitivity of the key outputs to the breakage parameters (paper 3.3, Fig. 10).

Everything runs through one generic model interface, so the same code path is tested on the
Ishigami function (known indices) and used on the surrogate::

    model(u: np.ndarray (n, k) in [0, 1]) -> {output name: np.ndarray (n,)}

- :func:`sobol_indices`: Saltelli/Sobol' design with SALib (``sample.sobol``, N a power of
  two, no second-order terms) and ``analyze.sobol``: first-order ``S1`` and total ``ST``
  indices with bootstrap confidence-interval half-widths ``S1_conf`` / ``ST_conf``
  (Saltelli et al. 2010, doi:10.1016/j.cpc.2009.09.018; Jansen 1999 for ``ST``).
- :func:`sobol_convergence`: the same over N doubling. Scrambled Sobol' sequences with one
  seed are nested (the design at 2N starts with the design at N), so each level evaluates only
  the new rows. Stops when every CI half-width is below ``tol`` (0.05) and the ranking by
  ``ST`` is stable (see :func:`ranking_stable`).
- :func:`ensemble_spread`: indices of each ensemble member on the same design (epistemic
  spread of the surrogate); for a model without per-member access, the bootstrap spread of
  the indices, labelled as such.
- :func:`given_data_indices`: a surrogate-free cross-check on the raw dataset runs with
  SALib's given-data estimators (``analyze.delta``: Borgonovo 2007 delta moment-independent
  measure and a first-order index; or ``analyze.rbd_fast``, Tarantola et al. 2006).
- :func:`surrogate_model`: adapts a :mod:`surrogate` model (or one member) to the interface,
  with :func:`analysis.outputs.key_outputs` on its predictions.
- :func:`plot_sobol`, :func:`plot_convergence`: Fig. 10 bar charts and the convergence plot.
- :func:`paper_claims`, :func:`compare_to_reference`, :func:`given_data_check`: the paper's
  Fig. 10 reading (d0 and phi dominant, gamma and R_t negligible), another study's
  ranking (e.g. the other cell) and the raw runs' top two, checked on a result.
- :func:`sobol_study`: all of the above into an output folder (``analysis sobol``).
"""

from __future__ import annotations

import contextlib
import io
import math
import sys
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from analysis.outputs import LABELS, OUTPUTS, UNITS, key_outputs
from calendaring import ConfigError

Model = Callable[[np.ndarray], Mapping[str, np.ndarray]]

CI_TOL = 0.05
"""Largest allowed CI half-width of any index at convergence (field notes section 4)."""
CONF_LEVEL = 0.95
NUM_RESAMPLES = 100
BATCH_SIZE = 8192
GIVEN_DATA_METHODS = ("delta", "rbd_fast")
RBD_HARMONICS = 10
"""Harmonics M of the RBD-FAST estimator (SALib's default)."""


# ---------------------------------------------------------------------- helpers
def log(msg: str) -> None:
    """A progress line on stderr."""
    print(msg, file=sys.stderr, flush=True)


def check_power_of_two(n, key: str = "--n", lo: int = 2) -> int:
    """``n`` as an int if it is a power of two >= ``lo``; ConfigError otherwise."""
    try:
        v = int(n)
    except (TypeError, ValueError):
        raise ConfigError(key, n, f"a power of two >= {lo}") from None
    if v != n and not (isinstance(n, float) and n == v):
        raise ConfigError(key, n, f"a power of two >= {lo}")
    if v < lo or v & (v - 1):
        raise ConfigError(key, n, f"a power of two >= {lo} (e.g. 2**12 = 4096)")
    return v


def unit_problem(names: Sequence[str]) -> dict:
    """SALib problem over the unit cube ``[0, 1]^k`` with the given parameter names."""
    names = [str(n) for n in names]
    if not names or len(set(names)) != len(names):
        raise ConfigError("names", names, "one or more unique parameter names")
    return {"num_vars": len(names), "names": names, "bounds": [[0.0, 1.0]] * len(names)}


def evaluate(model: Model, u: np.ndarray, batch_size: int = BATCH_SIZE,
             progress: bool = False, desc: str = "model") -> dict[str, np.ndarray]:
    """``model`` on the rows of ``u`` in batches (bounded memory); outputs concatenated."""
    u = np.asarray(u, dtype=float)
    parts: dict[str, list[np.ndarray]] = {}
    n_batches = max(1, math.ceil(len(u) / batch_size))
    t0 = last = time.perf_counter()
    for b in range(n_batches):
        chunk = u[b * batch_size:(b + 1) * batch_size]
        out = model(chunk)
        for k, v in out.items():
            v = np.asarray(v, dtype=float).reshape(len(chunk))
            parts.setdefault(k, []).append(v)
        now = time.perf_counter()
        if progress and n_batches > 1 and (now - last > 5.0 or b == n_batches - 1):
            last = now
            el = now - t0
            eta = el / (b + 1) * (n_batches - b - 1)
            log(f"  {desc}: batch {b + 1}/{n_batches} ({(b + 1) * 100 // n_batches} %), "
                f"{el:.1f} s elapsed, ETA {eta:.1f} s")
    if not parts:
        raise ConfigError("model", "no outputs", "a callable returning {name: (n,) array}")
    return {k: np.concatenate(v) for k, v in parts.items()}


# ---------------------------------------------------------------------- Ishigami
def ishigami(u, a: float = 7.0, b: float = 0.1) -> dict[str, np.ndarray]:
    """Ishigami function (Ishigami & Homma 1990) of unit inputs ``(n, 3)`` mapped to
    ``[-pi, pi]^3``: ``y = sin x1 + a sin^2 x2 + b x3^4 sin x1``."""
    x = -np.pi + 2 * np.pi * np.asarray(u, dtype=float)
    return {"y": np.sin(x[:, 0]) + a * np.sin(x[:, 1]) ** 2
            + b * x[:, 2] ** 4 * np.sin(x[:, 0])}


def ishigami_indices(a: float = 7.0, b: float = 0.1) -> dict[str, np.ndarray]:
    """Analytic first-order and total Sobol indices of :func:`ishigami` (Sobol & Levitan 1999)."""
    pi4, pi8 = np.pi**4, np.pi**8
    v = a**2 / 8 + b * pi4 / 5 + b**2 * pi8 / 18 + 0.5
    v1 = 0.5 * (1 + b * pi4 / 5) ** 2
    v2 = a**2 / 8
    v13 = 8 * b**2 * pi8 / 225
    return {"S1": np.array([v1, v2, 0.0]) / v, "ST": np.array([v1 + v13, v2, v13]) / v}


# ---------------------------------------------------------------------- Sobol
@dataclass
class SobolResult:
    """First-order and total indices of every output, with CI half-widths (all unit 1).

    ``indices[output]`` has ``S1``, ``S1_conf``, ``ST``, ``ST_conf``: arrays ``(k,)`` in the
    order of ``names``. ``constant`` lists outputs without variance (indices reported 0).
    """

    names: list[str]
    n: int
    seed: int
    n_evaluations: int
    indices: dict[str, dict[str, np.ndarray]]
    conf_level: float = CONF_LEVEL
    constant: list[str] = field(default_factory=list)
    resamples: dict[str, dict[str, np.ndarray]] = field(default_factory=dict, repr=False)

    def max_conf(self, output: str | None = None) -> float:
        """Largest CI half-width of any S1/ST (of one output, or of all)."""
        outs = [output] if output else list(self.indices)
        return float(max(np.nanmax(np.r_[self.indices[o]["S1_conf"], self.indices[o]["ST_conf"]])
                         for o in outs))

    def ranking(self, output: str) -> list[str]:
        """Parameter names by decreasing total index."""
        st = self.indices[output]["ST"]
        return [self.names[i] for i in np.argsort(-st, kind="stable")]

    def to_json(self) -> dict:
        return {"method": "sobol (SALib sample.sobol / analyze.sobol, no second order)",
                "names": self.names, "n": self.n, "seed": self.seed,
                "n_evaluations": self.n_evaluations, "conf_level": self.conf_level,
                "unit": "1", "conf": "CI half-width (bootstrap)", "constant": self.constant,
                "indices": {o: {k: [float(x) for x in v] for k, v in d.items()}
                            for o, d in self.indices.items()},
                "ranking_by_ST": {o: self.ranking(o) for o in self.indices}}


def sobol_sample(names: Sequence[str], n: int, seed: int = 0) -> np.ndarray:
    """SALib Sobol' design ``(n (k + 2), k)`` on the unit cube (no second-order rows)."""
    from SALib.sample import sobol as sobol_sampler

    n = check_power_of_two(n)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # SALib's notes on sample sizes
        return sobol_sampler.sample(unit_problem(names), n, calc_second_order=False, seed=seed)


def analyze_outputs(names: Sequence[str], y: Mapping[str, np.ndarray], n: int, seed: int = 0,
                    num_resamples: int = NUM_RESAMPLES, conf_level: float = CONF_LEVEL,
                    keep_resamples: bool = False) -> SobolResult:
    """SALib ``analyze.sobol`` on every output of a design of base size ``n``."""
    from SALib.analyze import sobol as sobol_analyzer

    problem = unit_problem(names)
    k = len(names)
    indices, constant, resamples = {}, [], {}
    n_eval = 0
    for out, vals in y.items():
        vals = np.asarray(vals, dtype=float)
        n_eval = len(vals)
        if len(vals) != n * (k + 2):
            raise ConfigError(f"outputs.{out}", f"{len(vals)} values",
                              f"N (k + 2) = {n * (k + 2)} values of the Sobol design")
        if not np.all(np.isfinite(vals)):
            raise ConfigError(f"outputs.{out}", f"{int(np.sum(~np.isfinite(vals)))} "
                              "non-finite values", "finite model outputs on the whole cube")
        if np.ptp(vals) <= 1e-12 * max(1.0, float(np.abs(vals).max())):
            constant.append(out)
            z = np.zeros(k)
            indices[out] = {"S1": z, "S1_conf": z.copy(), "ST": z.copy(), "ST_conf": z.copy()}
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            r = sobol_analyzer.analyze(problem, vals, calc_second_order=False,
                                       num_resamples=num_resamples, conf_level=conf_level,
                                       seed=seed, keep_resamples=keep_resamples)
        indices[out] = {key: np.asarray(r[key], dtype=float)
                        for key in ("S1", "S1_conf", "ST", "ST_conf")}
        if keep_resamples:
            resamples[out] = {"S1": np.asarray(r["S1_conf_all"]),
                              "ST": np.asarray(r["ST_conf_all"])}
    return SobolResult(list(names), n, seed, n_eval, indices, conf_level, constant, resamples)


def sobol_indices(model: Model, names: Sequence[str], n: int, seed: int = 0,
                  num_resamples: int = NUM_RESAMPLES, conf_level: float = CONF_LEVEL,
                  batch_size: int = BATCH_SIZE, progress: bool = False,
                  keep_resamples: bool = False) -> SobolResult:
    """Sobol indices of every output of ``model`` over the unit cube of ``names``.

    Args:
        model: ``model(u (m, k)) -> {output: (m,)}``.
        names: the k parameter names (SALib problem names).
        n: base sample size, a power of two; the model is evaluated at ``n (k + 2)`` points.
        seed: seeds the scrambled Sobol' sequence and the bootstrap.
    """
    u = sobol_sample(names, n, seed)
    y = evaluate(model, u, batch_size=batch_size, progress=progress)
    return analyze_outputs(names, y, n, seed, num_resamples, conf_level, keep_resamples)


def ranking_stable(prev: SobolResult, new: SobolResult) -> bool:
    """True when the ranking by ST did not change between two levels, up to ties.

    A pair of parameters ordered differently at the two levels counts as tied (not a change)
    when their ``ST`` values at the new level differ by less than the sum of their CI
    half-widths; negligible parameters (gamma, R_t) would otherwise swap places forever.
    """
    for out in new.indices:
        if out not in prev.indices:
            return False
        a, b = prev.indices[out]["ST"], new.indices[out]["ST"]
        conf = new.indices[out]["ST_conf"]
        k = len(a)
        for i in range(k):
            for j in range(i + 1, k):
                if np.sign(a[i] - a[j]) != np.sign(b[i] - b[j]) and \
                        abs(b[i] - b[j]) >= conf[i] + conf[j]:
                    return False
    return True


def sobol_convergence(model: Model, names: Sequence[str], n_max: int, n_min: int = 256,
                      seed: int = 0, tol: float = CI_TOL, stop: bool = True,
                      num_resamples: int = NUM_RESAMPLES, batch_size: int = BATCH_SIZE,
                      progress: bool = False) -> tuple[list[dict], SobolResult]:
    """Indices at N = n_min, 2 n_min, ... up to n_max; returns (table rows, last result).

    Each row: ``n``, ``n_evaluations``, ``max_conf`` (largest CI half-width of all outputs),
    per output ``max_conf`` and ``ranking`` (by ST), ``ranking_stable`` (vs the previous
    level, :func:`ranking_stable`) and ``converged`` (all half-widths < ``tol`` and the
    ranking stable). With ``stop``, the loop ends at the first converged level.
    """
    n_max = check_power_of_two(n_max)
    n_min = min(check_power_of_two(n_min, "n_min"), n_max)
    k = len(names)
    u_all = sobol_sample(names, n_max, seed)  # nested: the design at n is u_all[:n (k + 2)]
    y: dict[str, np.ndarray] = {}
    rows, prev, res = [], None, None
    n = n_min
    t0 = time.perf_counter()
    while n <= n_max:
        m = n * (k + 2)
        done = len(next(iter(y.values()))) if y else 0
        new = evaluate(model, u_all[done:m], batch_size=batch_size, progress=progress,
                       desc=f"N = {n}")
        y = {o: np.concatenate([y.get(o, np.zeros(0)), v]) for o, v in new.items()}
        res = analyze_outputs(names, y, n, seed, num_resamples)
        stable = prev is not None and ranking_stable(prev, res)
        mc = res.max_conf()
        conv = bool(stable and mc < tol)
        rows.append({"n": n, "n_evaluations": m, "max_conf": mc,
                     "outputs": {o: {"max_conf": res.max_conf(o), "ranking": res.ranking(o)}
                                 for o in res.indices},
                     "ranking_stable": bool(stable), "converged": conv,
                     "elapsed_s": time.perf_counter() - t0})
        if progress:
            log(f"sobol N = {n:6d}: {m} evaluations, largest CI half-width {mc:.4f}, ranking "
                f"{'stable' if stable else 'changed' if prev else '-'}"
                f"{' -> converged' if conv else ''} ({time.perf_counter() - t0:.1f} s)")
        if conv and stop:
            break
        prev = res
        n *= 2
    return rows, res


# ---------------------------------------------------------------------- surrogate adapter
def surrogate_model(m, member=None, outputs_kw: Mapping | None = None) -> Model:
    """Wrap a :mod:`surrogate` model (``predict_unit``) as a unit-cube model of the four
    outputs; ``member`` is one member object of an ensemble (same interface) instead."""
    target = member if member is not None else m
    kw = dict(outputs_kw or {})
    if "log_load" not in kw and getattr(m, "load_scale", None) in ("log", "linear"):
        kw["log_load"] = m.load_scale == "log"

    fast = callable(getattr(target, "torch_forward", None)) and \
        callable(getattr(target, "pressure_from_normalised", None))

    def model(u: np.ndarray) -> dict[str, np.ndarray]:
        u = np.clip(u, 0.0, 1.0)
        if fast:
            # torch_forward skips predict()'s float64 copies and member spreads; the peak is
            # taken in normalised units (the map to Pa is increasing: same maximum)
            import torch

            with torch.no_grad():
                p_norm, dist, _ = target.torch_forward(torch.as_tensor(u, dtype=torch.float32))
            peak = target.pressure_from_normalised(
                p_norm.max(dim=1).values.double().numpy())  # (n,) Pa
            return key_outputs(peak[:, None], dist.numpy(), m.load_edges, m.diameter_edges,
                               **kw)
        pred = target.predict_unit(u)
        return key_outputs(pred.pressure, pred.distribution, m.load_edges,
                           m.diameter_edges, **kw)

    return model


def ensemble_single_pass(m, outputs_kw: Mapping | None = None) -> Model | None:
    """For an ensemble whose members are networks ``member(u) -> (p_norm, dist)`` (as in
    :class:`surrogate.api.SurrogateModel`): a model that runs every member once per row and
    returns the ensemble-mean outputs (mean normalised pressure and mean distribution, as
    ``torch_forward``) plus each member's own outputs under ``"member<k>/<output>"``.
    None when the model is not such an ensemble."""
    members = getattr(m, "members", None)
    if not getattr(m, "is_ensemble", False) or not isinstance(members, list | tuple) or \
            not all(callable(x) and not hasattr(x, "predict_unit") for x in members) or \
            not callable(getattr(m, "pressure_from_normalised", None)):
        return None
    kw = dict(outputs_kw or {})
    if "log_load" not in kw and getattr(m, "load_scale", None) in ("log", "linear"):
        kw["log_load"] = m.load_scale == "log"

    def outputs(p_norm, dist):
        peak = m.pressure_from_normalised(p_norm.max(dim=1).values.double().numpy())
        return key_outputs(peak[:, None], dist.numpy(), m.load_edges, m.diameter_edges, **kw)

    def model(u: np.ndarray) -> dict[str, np.ndarray]:
        import torch

        ut = torch.as_tensor(np.clip(u, 0.0, 1.0), dtype=torch.float32)
        with torch.no_grad():
            for x in members:
                x.eval()
            outs = [x(ut) for x in members]  # [(p_norm (n, 196), dist (n, L, D))]
            gp = getattr(m, "pressure_gp", None)
            if gp is not None:  # the pressure of every member is the GP branch's
                p_gp = gp(ut, variance=False)[0]
                outs = [(p_gp, d) for _, d in outs]
            res = outputs(torch.stack([o[0] for o in outs]).mean(0),
                          torch.stack([o[1] for o in outs]).mean(0))
            for k, (p, d) in enumerate(outs):
                res.update({f"member{k}/{o}": v for o, v in outputs(p, d).items()})
        return res

    return model


def member_models(m) -> list | None:
    """The members of an ensemble as objects with ``predict_unit``, or None if the model
    offers no per-member access (or is a single model)."""
    if not getattr(m, "is_ensemble", False):
        return None
    get = getattr(m, "member", None)
    n = getattr(m, "n_members", None)
    if isinstance(n, int) and callable(get):
        return [get(i) for i in range(n)]
    members = getattr(m, "members", None)
    if members is None or callable(members):
        return None
    try:
        members = list(members)
    except TypeError:
        return None
    if members and all(hasattr(x, "predict_unit") for x in members):
        return members
    # surrogate.SurrogateModel keeps its members as networks: wrap each one in a
    # single-member model of the same class (same normalisation, space and bins).
    try:
        return [type(m)([x], m.normalisation, m.space, m.depth, m.load_edges,
                        m.diameter_edges, getattr(m, "load_scale", "log")) for x in members]
    except Exception:
        return None


def spread_summary(per: Sequence[SobolResult]) -> dict:
    """Per-member indices -> mean, std (ddof 1), min, max and the members' values."""
    first = per[0]
    out = {"method": "per-member", "n_members": len(per), "n": first.n, "seed": first.seed,
           "names": list(first.names), "indices": {}}
    for o in first.indices:
        d = {}
        for key in ("S1", "ST"):
            v = np.array([r.indices[o][key] for r in per])  # (members, k)
            d[key] = {"mean": v.mean(0).tolist(),
                      "std": (v.std(0, ddof=1) if len(per) > 1 else np.zeros(v.shape[1]))
                      .tolist(), "min": v.min(0).tolist(), "max": v.max(0).tolist(),
                      "members": v.tolist()}
        out["indices"][o] = d
    return out


def ensemble_spread(m, names: Sequence[str], n: int, seed: int = 0,
                    num_resamples: int = NUM_RESAMPLES, batch_size: int = BATCH_SIZE,
                    progress: bool = False, models: Sequence[Model] | None = None,
                    fallback: Model | None = None) -> dict:
    """Spread of the indices over ensemble members (same design for every member).

    ``models`` gives the member models directly (tests); otherwise they come from
    :func:`member_models` of the surrogate ``m``. Without per-member access, the spread is the
    bootstrap spread (std over SALib's resamples) of the indices of ``fallback`` (or of the
    whole model), and ``method`` says so.
    """
    if models is None and m is not None:
        members = member_models(m)
        models = [surrogate_model(m, member=x) for x in members] if members else None
    if models:
        per = []
        for i, mod in enumerate(models):
            if progress:
                log(f"ensemble member {i + 1}/{len(models)}: N = {n}")
            per.append(sobol_indices(mod, names, n, seed, num_resamples, batch_size=batch_size))
        return spread_summary(per)
    model = fallback if fallback is not None else surrogate_model(m)
    if progress:
        log("ensemble spread: no per-member access; bootstrap spread of the indices instead")
    res = sobol_indices(model, names, n, seed, num_resamples, batch_size=batch_size,
                        keep_resamples=True)
    return bootstrap_spread(res)


def bootstrap_spread(res: SobolResult) -> dict:
    """The spread of indices over SALib's bootstrap resamples (``res`` from an analysis with
    ``keep_resamples=True``), for a model without members."""
    names, n, seed = res.names, res.n, res.seed
    num_resamples = len(next(iter(res.resamples.values()))["S1"]) if res.resamples else 0
    out = {"method": "bootstrap", "note": "the model gives no per-member predictions (or is "
           "a single model): std over bootstrap resamples of the Sobol design, i.e. the "
           "sampling spread of the indices, not the epistemic spread between members",
           "n_resamples": num_resamples, "n": n, "seed": seed, "names": list(names),
           "indices": {}}
    for o, d in res.indices.items():
        rs = res.resamples.get(o)
        out["indices"][o] = {key: {"mean": d[key].tolist(),
                                   "std": (rs[key].std(0, ddof=1).tolist() if rs
                                           else [0.0] * len(names))}
                             for key in ("S1", "ST")}
    return out


# ---------------------------------------------------------------------- given data
def given_data_indices(x_unit, y: Mapping[str, np.ndarray], names: Sequence[str],
                       method: str = "rbd_fast", seed: int = 0,
                       num_resamples: int = NUM_RESAMPLES) -> dict:
    """Sensitivity from given (not designed) samples: SALib ``delta`` or ``rbd_fast``.

    Args:
        x_unit: ``(m, k)`` inputs in the unit cube (e.g. the dataset's LHS design).
        y: ``{output: (m,)}``; rows with a non-finite value are dropped per output.
        method: ``"rbd_fast"`` (S1 with CI; about a second) or ``"delta"`` (delta and S1
            with CIs; SALib's delta bootstraps three variants and takes minutes).
    """
    if method not in GIVEN_DATA_METHODS:
        raise ConfigError("method", method, f"one of {GIVEN_DATA_METHODS}")
    x = np.clip(np.asarray(x_unit, dtype=float), 0.0, 1.0)
    problem = unit_problem(names)
    if x.ndim != 2 or x.shape[1] != len(names):
        raise ConfigError("x_unit", f"array of shape {x.shape}", f"(m, {len(names)})")
    out = {"method": method if method != "delta" else "delta (Borgonovo, raw bootstrap) and "
           "S1", "names": list(names), "seed": seed, "unit": "1", "indices": {}}
    for o, vals in y.items():
        vals = np.asarray(vals, dtype=float)
        ok = np.isfinite(vals)
        # rbd_fast's bootstrap halves the rows and its bias correction divides by
        # 1 - 2 M / rows: it needs more than 4 M rows (M = RBD_HARMONICS)
        need = 2 * len(names) + 2 if method == "delta" else 4 * RBD_HARMONICS + 2
        if ok.sum() < need:
            out["indices"][o] = {"error": f"{int(ok.sum())} usable rows (need at least "
                                          f"{need})", "rows": int(ok.sum())}
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if method == "delta":
                from SALib.analyze import delta

                np.random.seed(seed)  # noqa: NPY002 (SALib delta bootstraps with the legacy global RNG)
                with contextlib.redirect_stdout(io.StringIO()), \
                        contextlib.redirect_stderr(io.StringIO()):  # SALib's binning notes
                    r = delta.analyze(problem, x[ok], vals[ok], num_resamples=num_resamples,
                                      seed=seed)
                if "delta" not in r and "delta_raw" in r:  # SALib >= 1.5 names
                    r["delta"], r["delta_conf"] = r["delta_raw"], r["delta_raw_conf"]
                keys = ("delta", "delta_conf", "S1", "S1_conf")
            else:
                from SALib.analyze import rbd_fast

                r = rbd_fast.analyze(problem, x[ok], vals[ok], M=RBD_HARMONICS,
                                     num_resamples=num_resamples, seed=seed)
                keys = ("S1", "S1_conf")
        out["indices"][o] = {k: [float(v) for v in np.asarray(r[k])] for k in keys}
        out["indices"][o]["rows"] = int(ok.sum())
    return out


def dataset_given_data(ds, method: str = "rbd_fast", roles: Sequence[str] = ("train",),
                       seed: int = 0) -> dict:
    """:func:`given_data_indices` on a :class:`calendaring.data.dataset.Dataset`'s runs of
    ``roles`` (the raw DEM results: smoothed pressure and binned events, no surrogate)."""
    from analysis.outputs import outputs_of_dataset

    sub = ds.by_role(*roles)
    if len(sub) == 0:
        raise ConfigError("dataset", str(ds.path or "<memory>"),
                          f"runs with role in {list(roles)} (none found)")
    res = given_data_indices(sub.unit_params, outputs_of_dataset(sub), sub.space.names,
                             method, seed)
    res["rows_total"] = len(sub)
    res["roles"] = list(roles)
    res["dataset"] = str(ds.path) if ds.path else None
    return res


# ---------------------------------------------------------------------- against the paper
PAPER_FIG10 = {"dominant": ("d0", "phi"), "negligible": ("damage_constant", "truncation_ratio")}
"""The paper's reading of Fig. 10 (section 3.3): d0 and phi dominate the outputs; gamma and
the truncation ratio are negligible."""
NEGLIGIBLE_ST = 0.05
"""A total index whose whole 95 % interval lies below this is called negligible."""


def _ranking(names, st) -> list[str]:
    return [names[i] for i in np.argsort(-np.asarray(st, float), kind="stable")]


def paper_claims(sobol: Mapping) -> dict:
    """The paper's Fig. 10 claims checked on a ``SobolResult.to_json()`` dict, per output.

    ``dominant``: holds when d0 and phi are the two largest total indices. ``negligible``
    (gamma, truncation ratio): ``negligible`` when ``ST + ST_conf < NEGLIGIBLE_ST``, ``not
    negligible`` when ``ST - ST_conf > NEGLIGIBLE_ST``, else ``not resolved``.
    """
    names = list(sobol["names"])
    out = {"rule": f"dominant: {list(PAPER_FIG10['dominant'])} are the two largest ST; "
                   f"negligible: ST + CI half-width < {NEGLIGIBLE_ST}", "outputs": {}}
    held = 0
    for o, d in sobol["indices"].items():
        rank = _ranking(names, d["ST"])
        top2 = set(rank[:2]) == set(PAPER_FIG10["dominant"])
        held += top2
        neg = {}
        for name in PAPER_FIG10["negligible"]:
            if name not in names:
                continue
            j = names.index(name)
            st, c = float(d["ST"][j]), float(d["ST_conf"][j])
            neg[name] = {"ST": st, "ST_conf": c,
                         "verdict": "negligible" if st + c < NEGLIGIBLE_ST else
                         "not negligible" if st - c > NEGLIGIBLE_ST else "not resolved"}
        out["outputs"][o] = {"ranking_by_ST": rank,
                             "rank_of": {n: rank.index(n) + 1 for n in PAPER_FIG10["dominant"]
                                         if n in names},
                             "dominant_holds": bool(top2), "negligible": neg}
    out["dominant_holds_in"] = f"{held} of {len(out['outputs'])} outputs"
    return out


def compare_to_reference(sobol: Mapping, reference: Mapping) -> dict:
    """Two Sobol results (e.g. 100 um against 30 um) per output: Kendall's tau between the
    total indices, the top two of each, and the parameters whose ST differ by more than
    the combined CI half-width (``sqrt(c1^2 + c2^2)``)."""
    from scipy.stats import kendalltau

    names = list(sobol["names"])
    if list(reference["names"]) != names:
        raise ConfigError("reference parameters", reference["names"], f"the same as {names}")
    out = {}
    for o, d in sobol["indices"].items():
        r = reference["indices"].get(o)
        if r is None:
            continue
        st, rst = np.asarray(d["ST"], float), np.asarray(r["ST"], float)
        comb = np.hypot(np.asarray(d["ST_conf"], float), np.asarray(r["ST_conf"], float))
        tau = kendalltau(st, rst).statistic
        out[o] = {"kendall_tau_ST": float(tau), "top2": _ranking(names, st)[:2],
                  "reference_top2": _ranking(names, rst)[:2],
                  "same_top2": set(_ranking(names, st)[:2]) == set(_ranking(names, rst)[:2]),
                  "differ": {n: {"ST": float(st[j]), "reference_ST": float(rst[j]),
                                 "combined_conf": float(comb[j])}
                             for j, n in enumerate(names) if abs(st[j] - rst[j]) > comb[j]}}
    return out


def given_data_check(sobol: Mapping, given: Mapping) -> dict:
    """The surrogate's top two first-order indices against the given-data estimate from
    the raw runs (the same estimand, S1), per output."""
    names = list(sobol["names"])
    out = {}
    for o, d in sobol["indices"].items():
        g = given["indices"].get(o, {})
        if "S1" not in g:
            out[o] = {"error": g.get("error", "no given-data estimate")}
            continue
        top = _ranking(names, d["S1"])[:2]
        gtop = _ranking(names, g["S1"])[:2]
        out[o] = {"surrogate_top2_S1": top, "given_data_top2_S1": gtop,
                  "agree": set(top) == set(gtop),
                  "given_data_S1": {n: [g["S1"][names.index(n)], g["S1_conf"][names.index(n)]]
                                    for n in top},
                  "surrogate_S1": {n: [d["S1"][names.index(n)], d["S1_conf"][names.index(n)]]
                                   for n in top}}
    return out


# ---------------------------------------------------------------------- plots
def plot_sobol(result: SobolResult, path: str | Path, symbols: Sequence[str] | None = None,
               title: str = "") -> Path:
    """Fig. 10: one panel per output, S1 and ST bars with CI error bars (PNG, atomic)."""
    import matplotlib.pyplot as plt

    from analysis.plots import save_figure

    outs = list(result.indices)
    labels = list(symbols) if symbols else result.names
    ncol = 2 if len(outs) > 1 else 1
    nrow = math.ceil(len(outs) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(6.2 * ncol, 3.6 * nrow), squeeze=False)
    x = np.arange(len(labels))
    for ax, o, letter in zip(axes.flat, outs, "abcdefghij", strict=False):
        d = result.indices[o]
        ax.bar(x - 0.2, d["S1"], 0.4, yerr=d["S1_conf"], capsize=2, label="$S_1$",
               color="tab:blue")
        ax.bar(x + 0.2, d["ST"], 0.4, yerr=d["ST_conf"], capsize=2, label="$S_T$",
               color="tab:orange")
        ax.set_xticks(x, labels, rotation=0)
        ax.set_ylabel("Sobol index")
        ax.set_title(f"({letter}) {LABELS.get(o, o)}")
        ax.axhline(0, color="k", lw=0.5)
        ax.legend(fontsize=8)
    for ax in list(axes.flat)[len(outs):]:
        ax.set_visible(False)
    fig.suptitle(title or f"Sobol indices, N = {result.n} ({result.n_evaluations} "
                          f"evaluations, {int(100 * result.conf_level)} % CI)")
    fig.tight_layout()
    return save_figure(fig, path)


def plot_convergence(rows: Sequence[dict], path: str | Path, tol: float = CI_TOL) -> Path:
    """Largest CI half-width per output against N (log-log), with the tolerance line."""
    import matplotlib.pyplot as plt

    from analysis.plots import save_figure

    fig, ax = plt.subplots(figsize=(5.5, 4))
    n = [r["n"] for r in rows]
    for o in rows[0]["outputs"]:
        ax.loglog(n, [r["outputs"][o]["max_conf"] for r in rows], "o-", label=LABELS.get(o, o))
    ax.axhline(tol, color="k", ls="--", lw=0.8, label=f"tolerance {tol}")
    ax.set_xlabel("N (base sample size)")
    ax.set_ylabel("largest CI half-width")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


# ---------------------------------------------------------------------- study
def model_path(m) -> str | None:
    p = getattr(m, "path", None) or (getattr(m, "info", None) or {}).get("path")
    return str(p) if p else None


def sobol_study(m, out_dir: str | Path, n: int = 2**14, n_min: int = 256, seed: int = 0,
                tol: float = CI_TOL, dataset=None, given_method: str = "rbd_fast",
                spread_n: int | None = None, progress: bool = True,
                batch_size: int = BATCH_SIZE, reference: Mapping | None = None) -> dict:
    """The full sensitivity study of a surrogate into ``out_dir`` (``analysis sobol``).

    Writes ``sobol.json`` (indices at the last level, the convergence table, the ensemble
    spread, the given-data cross-check when ``dataset`` is given, wall times) and PNGs:
    ``sobol_indices.png`` (Fig. 10), ``sobol_convergence.png``. Returns the JSON dict.
    The convergence loop runs up to ``n`` and keeps going past convergence (so the final
    indices are at the requested N); the table marks the first converged level. The JSON
    also checks the paper's Fig. 10 claims (:func:`paper_claims`), the surrogate's top two
    against the given-data estimate (:func:`given_data_check`) and, with ``reference`` (an
    earlier ``sobol.json``, e.g. of another cell), the rankings against it
    (:func:`compare_to_reference`).
    """
    from analysis.plots import atomic_write_json

    n = check_power_of_two(n)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    space = m.space
    names = space.names
    spread_n = check_power_of_two(spread_n or max(256, n // 4), "--spread-n")
    single = ensemble_single_pass(m) if spread_n <= n else None
    seen: dict[str, list[np.ndarray]] = {}
    inner = single if single is not None else surrogate_model(m)

    def model(u):
        # keep every output: the spread at spread_n reuses the first rows of the nested
        # design (one pass over the members gives the mean outputs and every member's)
        out = inner(u)
        for key, v in out.items():
            seen.setdefault(key, []).append(v)
        return {o: out[o] for o in OUTPUTS}

    rows_n = spread_n * (len(names) + 2)
    t0 = time.perf_counter()
    rows, res = sobol_convergence(model, names, n, n_min=min(n_min, n), seed=seed, tol=tol,
                                  stop=False, batch_size=batch_size, progress=progress)
    t_sobol = time.perf_counter() - t0
    first = next((r["n"] for r in rows if r["converged"]), None)
    t1 = time.perf_counter()
    if single is not None:
        per = []
        for k in range(len(m.members)):
            y = {o: np.concatenate(seen[f"member{k}/{o}"])[:rows_n] for o in OUTPUTS}
            per.append(analyze_outputs(names, y, spread_n, seed))
        spread = spread_summary(per)
        spread["note"] = "members evaluated once with the mean, on the first rows of the design"
    elif member_models(m) is None and spread_n <= n:
        y = {o: np.concatenate(seen[o])[:rows_n] for o in OUTPUTS}
        spread = bootstrap_spread(analyze_outputs(names, y, spread_n, seed,
                                                  keep_resamples=True))
    else:
        spread = ensemble_spread(m, names, spread_n, seed, batch_size=batch_size,
                                 progress=progress)
    t_spread = time.perf_counter() - t1
    out = {"model": model_path(m),
           "is_ensemble": bool(getattr(m, "is_ensemble", False)),
           "parameters": [{"name": p.name, "symbol": p.symbol, "unit": p.unit,
                           "lower": p.lower, "upper": p.upper, "scale": p.scale}
                          for p in space],
           "bounds": "unit cube of the parameter space (scaled by its bounds and scales)",
           "outputs": {o: {"unit": UNITS[o]} for o in OUTPUTS},
           "sobol": res.to_json(), "convergence": rows, "converged_at_n": first,
           "tolerance": tol, "ensemble_spread": spread,
           "wall_time_s": {"sobol_convergence": t_sobol, "ensemble_spread": t_spread}}
    if dataset is not None:
        out["given_data"] = dataset_given_data(dataset, given_method, seed=seed)
    out["paper_claims"] = paper_claims(out["sobol"])
    if "given_data" in out:
        out["given_data_check"] = given_data_check(out["sobol"], out["given_data"])
    if reference is not None:
        out["reference"] = {"path": reference.get("path"),
                            "comparison": compare_to_reference(out["sobol"],
                                                               reference["sobol"])}
    symbols = space.symbols
    paths = [plot_sobol(res, out_dir / "sobol_indices.png", symbols),
             plot_convergence(rows, out_dir / "sobol_convergence.png", tol)]
    out["figures"] = [p.name for p in paths]
    atomic_write_json(out_dir / "sobol.json", out)
    if progress:
        log(f"sobol: N = {n}, largest CI half-width {res.max_conf():.4f}, converged at "
            f"N = {first}; wrote {out_dir / 'sobol.json'}")
    return out


__all__ = [
    "CI_TOL",
    "GIVEN_DATA_METHODS",
    "NEGLIGIBLE_ST",
    "PAPER_FIG10",
    "Model",
    "SobolResult",
    "analyze_outputs",
    "bootstrap_spread",
    "check_power_of_two",
    "compare_to_reference",
    "dataset_given_data",
    "ensemble_single_pass",
    "ensemble_spread",
    "evaluate",
    "given_data_check",
    "given_data_indices",
    "ishigami",
    "ishigami_indices",
    "member_models",
    "model_path",
    "paper_claims",
    "plot_convergence",
    "plot_sobol",
    "ranking_stable",
    "sobol_convergence",
    "sobol_indices",
    "sobol_sample",
    "sobol_study",
    "spread_summary",
    "surrogate_model",
    "unit_problem",
]
