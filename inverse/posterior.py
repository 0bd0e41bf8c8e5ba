"""Bayesian calibration over the surrogate: emcee on the unit cube.

Prior: uniform on ``[0, 1]`` for every free parameter (the paper's design ranges, linear).
Likelihood: Gaussian in the surrogate's normalised cube-root pressure units on the valid target
points,

    log L(u) = -1/2 sum_i [ r_i^2 / v_i + log(2 pi v_i) ],   r_i = y_pred_i(u) - y_obs_i,
    v_i = (sigma_i dy/dP|_{P_obs,i})^2 + var_model_i(u),

where ``sigma_i`` [Pa] is the observation uncertainty converted to normalised units with the
derivative of the cube-root normalisation at the observed pressure (delta method,
``dy/dP = 1 / (3 P^(2/3) (cbrt_max - cbrt_min))``; the observed pressure is floored at
``pressure_floor_frac x max P`` so the conversion stays finite near zero load), and
``var_model_i`` is the surrogate's own predictive variance (``p_norm_var`` of
``torch_forward``: the ensemble spread; zero for a single model) plus
``model_error_sigma^2``, an optional constant surrogate error (e.g. the model's held-out RMSE
in normalised units; a single model has no other way to admit its own error). With a target
centroid, a Gaussian term on the scaled centroid coordinates (``centroid_sigma``) is added.

Observation sigma: the target's own (CSV ``sigma_*`` column) or, without one,
``sigma_rel x P + sigma_abs_frac x max P`` (defaults 5 % and 1 %; documented, not measured).
Neighbouring points of a smoothed curve are correlated, so the 196 residuals are not 196
independent observations. The log-likelihood sum is divided by a correlation length ``L``
(points per independent observation; ``correlation_length``): by default the integrated
correlation length of white noise passed through the Savitzky-Golay filter of the dataset,
``L = (sum h)^2 / sum h^2`` (7.5 points for window 17, order 3; :func:`savgol_correlation_length`),
``L = 1`` gives the independent-point likelihood. Smooth model discrepancy is correlated over
longer ranges still; :func:`validation <inverse.validate>` measures the coverage that results.

Outputs (:class:`PosteriorResult`): samples (unit and physical), mean, std, median, 90 %
credible interval, posterior/prior width per parameter (std / (1/sqrt 12) and 90 % interval
width / 0.9), acceptance fraction, integrated autocorrelation time, effective samples,
posterior-predictive band, and plots (band over the target, trace).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch

from calendaring import ConfigError
from inverse.targets import Target

PRIOR_STD = 1.0 / np.sqrt(12.0)  # std of U(0, 1)
CI_LEVEL = 0.90


@dataclass(frozen=True)
class PosteriorConfig:
    """emcee settings and the likelihood's noise model."""

    walkers: int = 32
    steps: int = 3000
    burn: int = 1000
    seed: int = 0
    sigma_rel: float = 0.05  # default observation sigma: relative part
    sigma_abs_frac: float = 0.01  # default observation sigma: x max target pressure
    pressure_floor_frac: float = 1e-6  # floor on P_obs in the delta-method conversion
    centroid_sigma: float = 0.05  # scaled centroid coordinates
    use_model_variance: bool = True
    model_error_sigma: float = 0.0  # surrogate error, normalised units (e.g. its test RMSE)
    correlation_length: float | None = None  # points per independent residual (None: S-G)
    init_radius: float = 0.02  # walkers start in a ball of this radius around the optimum
    predictive_draws: int = 200

    def __post_init__(self) -> None:
        if self.walkers < 2:
            raise ConfigError("posterior.walkers", self.walkers, ">= 2 x free parameters")
        if not 0 <= self.burn < self.steps:
            raise ConfigError("posterior.burn", self.burn, f"0 <= burn < steps ({self.steps})")
        for k in ("sigma_rel", "sigma_abs_frac", "pressure_floor_frac", "centroid_sigma",
                  "init_radius", "model_error_sigma"):
            if not getattr(self, k) >= 0:
                raise ConfigError(f"posterior.{k}", getattr(self, k), ">= 0")

        if self.correlation_length is not None and not self.correlation_length >= 1:
            raise ConfigError("posterior.correlation_length", self.correlation_length,
                              ">= 1 point (1: independent points)")

    def to_json(self) -> dict:
        return asdict(self)


def savgol_correlation_length(window: int = 17, order: int = 3) -> float:
    """Integrated correlation length [points] of white noise after a Savitzky-Golay filter:
    ``(sum h)^2 / sum h^2`` for the filter's central coefficients ``h``."""
    from scipy.signal import savgol_coeffs

    h = savgol_coeffs(window, order)
    return float(h.sum() ** 2 / np.sum(h**2))


def observation_sigma(target: Target, cfg: PosteriorConfig) -> np.ndarray:
    """One standard deviation [Pa] per model depth: the target's own where it has one, else
    ``sigma_rel x P + sigma_abs_frac x max P``; NaN outside the valid points."""
    p = np.where(target.valid, target.pressure, np.nan)
    pmax = float(np.nanmax(p))
    default = cfg.sigma_rel * np.abs(p) + cfg.sigma_abs_frac * pmax
    if target.sigma is not None:
        s = np.where(np.isfinite(target.sigma), target.sigma, default)
    else:
        s = default
    if pmax <= 0 or not np.all(s[target.valid] > 0):
        raise ConfigError("target.sigma", "values", "> 0 at every valid point (a target with "
                          "zero pressure needs an explicit sigma column)")
    return np.where(target.valid, s, np.nan)


def _cbrt_span(model) -> float:
    """``cbrt_max - cbrt_min`` of the model's normalisation, read through
    ``pressure_from_normalised`` (its values at 0 and 1)."""
    c0 = float(np.cbrt(model.pressure_from_normalised(np.array(0.0))))
    c1 = float(np.cbrt(model.pressure_from_normalised(np.array(1.0))))
    return c1 - c0


def normalised_sigma(model, pressure_pa: np.ndarray, sigma_pa: np.ndarray,
                     floor_frac: float) -> np.ndarray:
    """Pa -> normalised units by the derivative of the cube-root normalisation at the
    observed pressure (delta method). The span ``cbrt_max - cbrt_min`` is read from the
    model through ``pressure_from_normalised`` (its values at 0 and 1)."""
    p = np.maximum(np.abs(pressure_pa), floor_frac * np.nanmax(np.abs(pressure_pa)))
    return sigma_pa / (3.0 * np.cbrt(p) ** 2 * _cbrt_span(model))


def with_normalised_sigma(model, target: Target, sigma_n: float) -> Target:
    """``target`` with its sigma [Pa] set to ``sigma_n`` normalised units at every valid point:
    the inverse of :func:`normalised_sigma` (no floor), e.g. a measured run-to-run floor."""
    if not sigma_n > 0:
        raise ConfigError("sigma (normalised)", sigma_n, "> 0")
    p = np.where(target.valid, np.abs(target.pressure), np.nan)
    return replace(target, sigma=np.where(
        target.valid, sigma_n * 3.0 * np.cbrt(p) ** 2 * _cbrt_span(model), np.nan))


class LogPosterior:
    """Vectorised log posterior over the free unit parameters (emcee ``vectorize=True``).

    Args:
        model: surrogate API object.
        target: the target on ``model.depth``.
        free: (8,) bool; ``fixed_u``: (8,) unit values used for the held columns.
        scale_centroid: callable mapping (load [N], diameter [m]) to scaled coordinates and
            ``predicted_centroid``: (n, L, D) tensor -> (n, 2) scaled, both from
            :class:`~inverse.loss.CompositeLoss` (used only with a target centroid).
    """

    def __init__(self, model, target: Target, free, fixed_u, cfg: PosteriorConfig,
                 loss=None) -> None:
        self.model = model
        self.free = np.asarray(free, bool)
        self.fixed_u = np.asarray(fixed_u, float)
        self.cfg = cfg
        self.valid = np.asarray(target.valid, bool)
        self.sigma_pa = observation_sigma(target, cfg)
        s = normalised_sigma(model, target.pressure[self.valid], self.sigma_pa[self.valid],
                             cfg.pressure_floor_frac)
        self.obs_var = torch.as_tensor(s**2 + cfg.model_error_sigma**2,
                                       dtype=torch.float64)  # (k,)
        self.y = torch.as_tensor(model.normalise_pressure(target.pressure[self.valid]),
                                 dtype=torch.float64)
        self.valid_t = torch.as_tensor(self.valid)
        self.correlation_length = (cfg.correlation_length if cfg.correlation_length is not None
                                   else savgol_correlation_length())
        self.loss = loss
        self.use_centroid = loss is not None and loss.has_centroid
        self.evaluations = 0

    def full(self, theta: np.ndarray) -> np.ndarray:
        """(n, k free) -> (n, 8) with the held columns filled."""
        theta = np.atleast_2d(theta)
        u = np.repeat(self.fixed_u[None, :], len(theta), axis=0)
        u[:, self.free] = theta
        return u

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        theta = np.atleast_2d(theta)
        out = np.full(len(theta), -np.inf)
        inside = np.all((theta >= 0) & (theta <= 1), axis=1)
        if not inside.any():
            return out
        u = torch.as_tensor(self.full(theta[inside]), dtype=torch.float32)
        self.evaluations += 1
        with torch.no_grad():
            p_norm, dist, var = self.model.torch_forward(u, distribution=self.use_centroid)
        r = p_norm.double()[:, self.valid_t] - self.y  # (n, k)
        v = self.obs_var.expand_as(r)
        if var is not None and self.cfg.use_model_variance:
            v = v + var.double()[:, self.valid_t]
        ll = -0.5 * (r**2 / v + torch.log(2 * np.pi * v)).sum(dim=1) / self.correlation_length
        if self.use_centroid:
            c = self.loss.predicted_centroid(dist).double() - self.loss.c_target.double()
            ll = ll - 0.5 * ((c / self.cfg.centroid_sigma) ** 2).sum(dim=1)
        out[inside] = ll.numpy()
        return out


@dataclass
class PosteriorResult:
    """Samples and their summary (see the module docstring)."""

    names: list[str]  # free parameter names
    samples_unit: np.ndarray  # (S, k) after burn-in, flattened over walkers
    chain_unit: np.ndarray  # (steps, walkers, k) the full chain, for the trace plot
    summary: dict  # per name: unit and physical statistics
    diagnostics: dict
    predictive: dict  # depth, quantiles of the predicted pressure [Pa], coverage
    seconds: float
    config: PosteriorConfig

    def to_json(self) -> dict:
        return {"parameters": self.summary, "diagnostics": self.diagnostics,
                "predictive": self.predictive, "seconds": self.seconds,
                "config": self.config.to_json(), "free": self.names,
                "n_samples": len(self.samples_unit)}


def _quantile_phys(space, j: int, q_unit: np.ndarray, fixed_u: np.ndarray) -> np.ndarray:
    row = np.repeat(fixed_u[None, :], len(q_unit), axis=0)
    row[:, j] = q_unit
    return space.from_unit(row)[:, j]


def sample_posterior(model, target: Target, u_start: np.ndarray, free: np.ndarray,
                     cfg: PosteriorConfig | None = None, loss=None, progress: bool = False
                     ) -> PosteriorResult:
    """Run emcee from a ball around ``u_start`` (the optimum) and summarise.

    Args:
        model: surrogate API object; target: the target; u_start: (8,) unit parameters,
        held columns at their fixed values; free: (8,) bool.
        loss: the :class:`~inverse.loss.CompositeLoss` (supplies the centroid scaling).
    """
    import emcee

    cfg = cfg or PosteriorConfig()
    free = np.asarray(free, bool)
    u_start = np.asarray(u_start, float)
    space = model.space
    names = [n for n, f in zip(space.names, free, strict=True) if f]
    k = int(free.sum())
    if k == 0:
        raise ConfigError("--fix", "all parameters", "at least one free parameter")
    walkers = max(cfg.walkers, 2 * k + 2)
    walkers += walkers % 2
    logp = LogPosterior(model, target, free, u_start, cfg, loss)
    rng = np.random.default_rng(cfg.seed)
    centre = np.clip(u_start[free], cfg.init_radius, 1 - cfg.init_radius)
    p0 = np.clip(centre + cfg.init_radius * rng.uniform(-1, 1, (walkers, k)), 1e-6, 1 - 1e-6)
    sampler = emcee.EnsembleSampler(walkers, k, logp, vectorize=True)
    sampler.random_state = np.random.RandomState(cfg.seed).get_state()
    t0 = time.perf_counter()
    sampler.run_mcmc(p0, cfg.steps, progress=progress)
    seconds = time.perf_counter() - t0
    chain = sampler.get_chain()  # (steps, walkers, k)
    flat = sampler.get_chain(discard=cfg.burn, flat=True)
    tau = sampler.get_autocorr_time(discard=cfg.burn, tol=0, quiet=True)
    kept = cfg.steps - cfg.burn
    acc = sampler.acceptance_fraction
    diagnostics = {
        "walkers": walkers, "steps": cfg.steps, "burn": cfg.burn,
        "acceptance_mean": float(acc.mean()), "acceptance_min": float(acc.min()),
        "autocorr_time": dict(zip(names, map(float, tau), strict=True)),
        "effective_samples": dict(zip(names, map(float, kept * walkers / tau),
                                      strict=True)),
        "long_enough": bool(np.all(kept > 50 * tau)),
        "acceptance_ok": bool(0.15 < acc.mean() < 0.7),
        "rule": "long_enough: kept steps > 50 x autocorrelation time (emcee's advice); "
                "acceptance_ok: mean acceptance in (0.15, 0.7)",
        "log_prob_evaluations": logp.evaluations}
    lo_q, hi_q = (1 - CI_LEVEL) / 2, 1 - (1 - CI_LEVEL) / 2
    summary = {}
    for i, name in enumerate(names):
        j = space.index(name)
        s = flat[:, i]
        q = np.quantile(s, [lo_q, 0.5, hi_q])
        qp = _quantile_phys(space, j, q, u_start)
        p = space[name]
        summary[name] = {
            "symbol": p.symbol, "unit": p.unit, "mean_unit": float(s.mean()),
            "std_unit": float(s.std(ddof=1)), "median_unit": float(q[1]),
            "ci90_unit": [float(q[0]), float(q[2])],
            "mean": float(_quantile_phys(space, j, np.array([s.mean()]), u_start)[0]),
            "median": float(qp[1]), "ci90": [float(qp[0]), float(qp[2])],
            "std_ratio": float(s.std(ddof=1) / PRIOR_STD),
            "ci_width_ratio": float((q[2] - q[0]) / CI_LEVEL)}
    predictive = posterior_predictive(model, target, logp, flat, cfg)
    return PosteriorResult(names=names, samples_unit=flat, chain_unit=chain, summary=summary,
                           diagnostics=diagnostics, predictive=predictive, seconds=seconds,
                           config=cfg)


def posterior_predictive(model, target: Target, logp: LogPosterior, flat: np.ndarray,
                         cfg: PosteriorConfig) -> dict:
    """5/50/95 % quantiles of the predicted pressure [Pa] over posterior draws (surrogate
    mean; with the observation noise and model spread added for the ``*_noisy`` band), and
    the fraction of valid target points inside the noisy 90 % band."""
    rng = np.random.default_rng(cfg.seed + 1)
    idx = rng.choice(len(flat), size=min(cfg.predictive_draws, len(flat)), replace=False)
    u = torch.as_tensor(logp.full(flat[idx]), dtype=torch.float32)
    with torch.no_grad():
        p_norm, _, var = model.torch_forward(u, distribution=False)
    y = p_norm.double().numpy()
    noise_var = np.zeros(y.shape[1])
    noise_var[logp.valid] = logp.obs_var.numpy()
    total_var = noise_var[None, :] + (var.double().numpy() if var is not None
                                      and cfg.use_model_variance else 0.0)
    y_noisy = y + np.sqrt(total_var) * rng.standard_normal(y.shape)
    p = np.asarray(model.pressure_from_normalised(y), float)
    pn = np.asarray(model.pressure_from_normalised(y_noisy), float)
    q = np.quantile(p, [0.05, 0.5, 0.95], axis=0)
    qn = np.quantile(pn, [0.05, 0.95], axis=0)
    v = target.valid
    inside = (target.pressure[v] >= qn[0][v]) & (target.pressure[v] <= qn[1][v])
    return {"depth_m": np.asarray(target.depth).tolist(), "q05_Pa": q[0].tolist(),
            "median_Pa": q[1].tolist(), "q95_Pa": q[2].tolist(),
            "q05_noisy_Pa": qn[0].tolist(), "q95_noisy_Pa": qn[1].tolist(),
            "target_coverage_90": float(inside.mean()), "draws": len(idx)}


def plot_predictive(target: Target, predictive: dict, path, best_pressure=None,
                    sigma_pa=None):
    """Posterior-predictive band over the target (depth in um, pressure in MPa)."""
    import matplotlib.pyplot as plt

    from calendaring import to_mpa, to_um

    d = to_um(np.asarray(predictive["depth_m"]))
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.fill_between(d, to_mpa(np.array(predictive["q05_noisy_Pa"])),
                    to_mpa(np.array(predictive["q95_noisy_Pa"])), color="C0", alpha=0.15,
                    label="90 % predictive (with noise)")
    ax.fill_between(d, to_mpa(np.array(predictive["q05_Pa"])),
                    to_mpa(np.array(predictive["q95_Pa"])), color="C0", alpha=0.35,
                    label="90 % band of the surrogate mean")
    ax.plot(d, to_mpa(np.array(predictive["median_Pa"])), color="C0", lw=1, label="median")
    v = target.valid
    if sigma_pa is not None:
        ax.errorbar(to_um(target.depth[v]), to_mpa(target.pressure[v]),
                    yerr=to_mpa(np.asarray(sigma_pa)[v]), fmt="none", ecolor="0.6", lw=0.5)
    ax.plot(to_um(target.depth[v]), to_mpa(target.pressure[v]), "k.", ms=2, label="target")
    if best_pressure is not None:
        ax.plot(d, to_mpa(np.asarray(best_pressure)), "C3--", lw=1, label="optimum")
    ax.set_xlabel("calendering depth [um]")
    ax.set_ylabel("pressure [MPa]")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_trace(result: PosteriorResult, path, symbols: dict[str, str] | None = None):
    """Walker traces per free parameter (unit scale), burn-in shaded."""
    import matplotlib.pyplot as plt

    symbols = symbols or {}
    k = len(result.names)
    fig, axes = plt.subplots(k, 1, figsize=(7, 1.3 * k + 0.6), sharex=True, squeeze=False)
    for i, name in enumerate(result.names):
        ax = axes[i, 0]
        ax.plot(result.chain_unit[:, :, i], color="k", alpha=0.15, lw=0.4)
        ax.axvspan(0, result.config.burn, color="C1", alpha=0.1)
        ax.set_ylim(0, 1)
        ax.set_ylabel(symbols.get(name, name), fontsize=8)
    axes[-1, 0].set_xlabel("step")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


__all__ = ["CI_LEVEL", "PRIOR_STD", "LogPosterior", "PosteriorConfig", "PosteriorResult",
           "normalised_sigma", "observation_sigma", "plot_predictive", "plot_trace",
           "posterior_predictive", "sample_posterior", "with_normalised_sigma"]
