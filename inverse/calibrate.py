"""One calibration, end to end: target + surrogate -> result dict (see :mod:`inverse.report`).

    >>> import surrogate
    >>> from inverse.targets import load_target
    >>> from inverse.calibrate import calibrate_target
    >>> m = surrogate.load("model.pt")
    >>> out = calibrate_target(m, load_target("curve.csv", m), fix={"damage_constant": 5.549})
    >>> out.result["parameters"][2]["value"]      # d0 [m]
"""

from __future__ import annotations

import datetime
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from inverse.loss import CompositeLoss, LossConfig, weights_frozen
from inverse.optimise import (
    DEFAULT_MULTISTART,
    OptimisationResult,
    OptimiserConfig,
    calibrate,
    cluster_optima,
    fixed_unit_values,
)
from inverse.report import FORMAT, SCHEMA_VERSION, parameter_rows
from inverse.targets import Target


@dataclass
class Outcome:
    """The result dict plus the live objects (for plots)."""

    result: dict
    loss: CompositeLoss
    optimisation: OptimisationResult
    posterior: object | None = None
    extras: dict = field(default_factory=dict)


def fit_errors(model, target: Target, u: np.ndarray) -> tuple[dict, np.ndarray]:
    """Surrogate pressure at ``u`` against the target: RMSE, relative RMSE, max |error| [Pa]
    over the valid points; returns (errors, predicted pressure (m,) [Pa])."""
    with torch.no_grad():
        p_norm, _, _ = model.torch_forward(
            torch.as_tensor(np.atleast_2d(u), dtype=torch.float32), distribution=False)
    pred = np.asarray(model.pressure_from_normalised(p_norm.double().numpy()), float)[0]
    v = target.valid
    err = pred[v] - target.pressure[v]
    rmse = float(np.sqrt(np.mean(err**2)))
    return {"points": int(v.sum()), "rmse_Pa": rmse,
            "relative_rmse": rmse / max(float(np.mean(np.abs(target.pressure[v]))), 1e-30),
            "max_abs_Pa": float(np.max(np.abs(err)))}, pred


def calibrate_target(model, target: Target, **kw) -> Outcome:
    """Calibrate the surrogate's parameters to ``target`` (see :func:`_calibrate_target`
    for the arguments); the surrogate's weights are frozen meanwhile."""
    with weights_frozen(model):
        return _calibrate_target(model, target, **kw)


def _calibrate_target(model, target: Target, *, optimiser: OptimiserConfig | None = None,
                     loss_config: LossConfig | None = None,
                     fix: Mapping[str, float] | None = None, multistart: int | None = None,
                     posterior=None, identifiability: bool = True,
                     profile_mode: str = "slice", cluster_rtol: float = 0.05,
                     cluster_radius: float = 0.05, progress: bool = False,
                     model_path: str = "") -> Outcome:
    """Calibrate the surrogate's parameters to ``target``.

    Args:
        model: surrogate API object.
        target: a :class:`~inverse.targets.Target` on ``model.depth``.
        optimiser: two-phase settings (paper defaults: 500 iterations x 3 restarts).
        loss_config: term weights and shapes.
        fix: ``{name: physical value}`` parameters held exactly.
        multistart: if given, that many Sobol-started restarts, batched (the "many restarts"
            mode, default count :data:`~inverse.optimise.DEFAULT_MULTISTART`).
        posterior: a :class:`~inverse.posterior.PosteriorConfig` to sample the posterior.
        identifiability: compute the Hessian spectrum and loss profiles at the optimum.
        profile_mode: ``"slice"`` or ``"optimised"`` profiles.
    """
    space = model.space
    optimiser = optimiser or OptimiserConfig()
    if multistart:
        optimiser = replace(optimiser, restarts=int(multistart),
                            batch=True if optimiser.batch is None else optimiser.batch)
    fixed = fixed_unit_values(space, fix)
    fixed_phys = space.check(dict(fix)) if fix else {}
    free = np.ones(len(space), bool)
    for j in fixed:
        free[j] = False
    loss = CompositeLoss(model, target, loss_config, free=free)
    timings = {}
    t0 = time.perf_counter()
    opt = calibrate(loss, len(space), optimiser, fixed=fixed, progress=progress)
    timings["optimise"] = time.perf_counter() - t0
    u = opt.u.copy()
    x = space.from_unit(u)
    for name, v in fixed_phys.items():  # held values are reported exactly as given
        x[space.index(name)] = v
    terms = {k: float(v[0]) for k, v in loss.evaluate(u).items()}
    fit, pred = fit_errors(model, target, u)
    clusters = cluster_optima(opt.all_optima, opt.all_losses, free, rtol=cluster_rtol,
                              radius=cluster_radius)
    for c in clusters["clusters"]:
        c["centre_physical"] = space.from_unit(np.array(c["centre"])).tolist()
        c["lower_physical"] = space.from_unit(np.array(c["lower"])).tolist()
        c["upper_physical"] = space.from_unit(np.array(c["upper"])).tolist()
    with torch.no_grad():
        _, dist, _ = model.torch_forward(torch.as_tensor(u[None], dtype=torch.float32))
        c_pred = loss.unscale_centroid(loss.predicted_centroid(dist).double().numpy()[0])
    result = {
        "format": FORMAT, "schema_version": SCHEMA_VERSION,
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "model": {"path": str(model_path), "is_ensemble": bool(getattr(model, "is_ensemble",
                                                                        False)),
                  "pressure_head": str(getattr(model, "pressure_head", "mlp")),
                  "parameter_space": space.to_json()},
        "fixed": fixed_phys, "seed": optimiser.seed,
        "loss": {**terms, "weights": loss.weights, "config": loss.config.to_json()},
        "fit": fit, "target": target.to_json(),
        "prediction": {"pressure_Pa": pred.tolist(),
                       "centroid": {"load_N": float(c_pred[0]), "diameter_m": float(c_pred[1])}},
        "optimiser": optimiser.to_json(), "evaluations": opt.evaluations,
        "restarts": [{**r, "best_physical": space.from_unit(np.array(r["best"])).tolist()}
                     for r in opt.restarts],
        "history": opt.history, "clusters": clusters,
        "parameters_unit": u.tolist(),
    }
    outcome = Outcome(result=result, loss=loss, optimisation=opt)
    if identifiability:
        from inverse.identifiability import identifiability_report

        t1 = time.perf_counter()
        result["identifiability"] = identifiability_report(loss, u, free, space.names,
                                                           profile_mode=profile_mode)
        pc = (getattr(model, "info", None) or {}).get("dataset", {}).get("pressure_components")
        if pc:  # the training curves' resolvable components bound what one curve pins
            result["identifiability"]["curve_components"] = {
                **pc, "free_parameters": int(np.sum(free))}
        timings["identifiability"] = time.perf_counter() - t1
    post_summary = None
    if posterior is not None:
        from inverse.posterior import observation_sigma, sample_posterior

        t1 = time.perf_counter()
        post = sample_posterior(model, target, u, free, posterior, loss=loss, progress=progress)
        timings["posterior"] = time.perf_counter() - t1
        result["posterior"] = post.to_json()
        result["posterior"]["sigma_Pa"] = observation_sigma(target, posterior).tolist()
        post_summary = post.summary
        rng = np.random.default_rng(posterior.seed + 2)
        pick = rng.choice(len(post.samples_unit), size=min(16, len(post.samples_unit)),
                          replace=False)
        draws = np.repeat(u[None, :], len(pick), axis=0)
        draws[:, free] = post.samples_unit[pick]
        result["posterior"]["draws_physical"] = space.from_unit(draws).tolist()
        outcome.posterior = post
    result["parameters"] = parameter_rows(space, x, u, set(fixed_phys), post_summary)
    result["timings_s"] = timings
    return outcome


__all__ = ["DEFAULT_MULTISTART", "Outcome", "calibrate_target", "fit_errors"]
