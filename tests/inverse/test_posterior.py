"""Posterior: emcee on a linear-Gaussian stand-in against the closed-form posterior."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calendaring.core.errors import ConfigError
from inverse.posterior import (
    PosteriorConfig,
    normalised_sigma,
    observation_sigma,
    sample_posterior,
    savgol_correlation_length,
    with_normalised_sigma,
)
from inverse.targets import Target
from tests.inverse.standins import CBRT_MAX, LinearSurrogate

U_TRUE = np.array([0.3, 0.6, 0.45, 0.7, 0.25, 0.55, 0.4, 0.65])


def _noisy_target(model, s_norm, seed=1):
    """Target with Gaussian noise of ``s_norm`` normalised units and the matching sigma [Pa]
    (derivative of P = (y cbrt_max)^3 written out here, independently of the code)."""
    y = model.p_norm_numpy(U_TRUE)[0] + s_norm * np.random.default_rng(seed).standard_normal(
        len(model.depth))
    p = (y * CBRT_MAX) ** 3
    sigma_pa = s_norm * 3 * (y * CBRT_MAX) ** 2 * CBRT_MAX
    return Target(model.depth, p, np.ones(len(p), bool), sigma=sigma_pa), y


def test_sigma_conversion_is_the_derivative_of_the_normalisation():
    m = LinearSurrogate()
    p = np.array([1e5, 1e6, 1e8])
    s = 0.01 * p
    got = normalised_sigma(m, p, s, floor_frac=0.0)
    h = 1e-6 * p  # central difference of the model's own normalisation
    deriv = (m.normalise_pressure(p + h) - m.normalise_pressure(p - h)) / (2 * h)
    np.testing.assert_allclose(got, s * deriv, rtol=1e-6)


def test_a_normalised_sigma_converts_back_to_itself():
    m = LinearSurrogate()
    p = np.linspace(0.0, 2e8, len(m.depth))
    valid = p > 0
    t = with_normalised_sigma(m, Target(m.depth, np.where(valid, p, np.nan), valid), 0.0093)
    assert np.all(np.isnan(t.sigma[~valid])) and np.all(t.sigma[valid] > 0)
    np.testing.assert_allclose(normalised_sigma(m, p[valid], t.sigma[valid], 0.0), 0.0093,
                               rtol=1e-9)
    with pytest.raises(ConfigError, match="normalised"):
        with_normalised_sigma(m, t, 0.0)


def test_default_sigma_and_rejection():
    m = LinearSurrogate()
    t = Target(m.depth, np.linspace(0, 1e8, len(m.depth)), np.ones(len(m.depth), bool))
    s = observation_sigma(t, PosteriorConfig(sigma_rel=0.05, sigma_abs_frac=0.01))
    np.testing.assert_allclose(s, 0.05 * t.pressure + 1e6)
    t0 = Target(m.depth, np.zeros(len(m.depth)), np.ones(len(m.depth), bool))
    with pytest.raises(ConfigError):
        observation_sigma(t0, PosteriorConfig())


def test_posterior_matches_the_linear_gaussian_closed_form():
    var_model = 4e-5  # the stand-in's "ensemble" variance, normalised units
    m = LinearSurrogate(var=var_model, blob=False)
    s_norm = 0.01
    t, y = _noisy_target(m, s_norm)
    w = 1.0 / (s_norm**2 + var_model)
    cov = np.linalg.inv(w * m.A.T @ m.A)
    mean = cov @ (w * m.A.T @ (y - m.b))
    sd = np.sqrt(np.diag(cov))
    assert np.all(mean - 4 * sd > 0) and np.all(mean + 4 * sd < 1)  # prior bounds irrelevant
    cfg = PosteriorConfig(walkers=32, steps=2000, burn=600, seed=0, predictive_draws=100,
                          correlation_length=1.0)  # the target's noise is independent
    r = sample_posterior(m, t, mean, np.ones(8, bool), cfg)
    got_mean = np.array([r.summary[n]["mean_unit"] for n in r.names])
    got_sd = np.array([r.summary[n]["std_unit"] for n in r.names])
    n_eff = np.array([r.diagnostics["effective_samples"][n] for n in r.names])
    # sampling error of the mean is sd / sqrt(n_eff) (~0.04 sd here): allow 5 of those
    assert np.all(np.abs(got_mean - mean) < 5 * sd / np.sqrt(n_eff) + 0.05 * sd)
    np.testing.assert_allclose(got_sd, sd, rtol=0.12)
    # 90 % interval of a Gaussian: mean -+ 1.645 sd
    lo = np.array([r.summary[n]["ci90_unit"][0] for n in r.names])
    np.testing.assert_allclose((got_mean - lo) / sd, 1.645, rtol=0.15)
    # posterior/prior width
    np.testing.assert_allclose([r.summary[n]["std_ratio"] for n in r.names],
                               got_sd * np.sqrt(12), rtol=1e-9)
    assert 0.2 < r.diagnostics["acceptance_mean"] < 0.7
    assert r.chain_unit.shape == (2000, 32, 8)
    assert 0.7 < r.predictive["target_coverage_90"] <= 1.0
    assert m.calls > 0 and m.distribution_calls == 0  # a pressure-only target skips it


def test_model_variance_widens_the_posterior():
    s_norm = 0.005
    narrow = LinearSurrogate(var=None, blob=False)
    wide = LinearSurrogate(var=(3 * s_norm) ** 2, blob=False)
    t, _ = _noisy_target(narrow, s_norm, seed=2)
    cfg = PosteriorConfig(walkers=24, steps=600, burn=200, seed=1, predictive_draws=20)
    a = sample_posterior(narrow, t, U_TRUE, np.ones(8, bool), cfg)
    b = sample_posterior(wide, t, U_TRUE, np.ones(8, bool), cfg)
    ratio = np.mean([b.summary[n]["std_unit"] / a.summary[n]["std_unit"] for n in a.names])
    assert ratio == pytest.approx(np.sqrt(10), rel=0.25)  # sqrt((s^2 + 9 s^2) / s^2)
    # a declared constant surrogate error acts the same way on a single model
    c = sample_posterior(narrow, t, U_TRUE, np.ones(8, bool),
                         replace(cfg, model_error_sigma=3 * s_norm))
    ratio = np.mean([c.summary[n]["std_unit"] / a.summary[n]["std_unit"] for n in a.names])
    assert ratio == pytest.approx(np.sqrt(10), rel=0.25)


def test_fixed_parameters_are_not_sampled():
    m = LinearSurrogate()
    t, _ = _noisy_target(m, 0.02)
    free = np.ones(8, bool)
    free[[0, 7]] = False
    cfg = PosteriorConfig(walkers=20, steps=200, burn=50, predictive_draws=10)
    r = sample_posterior(m, t, U_TRUE, free, cfg)
    assert r.names == [n for i, n in enumerate(m.space.names) if free[i]]
    assert r.samples_unit.shape[1] == 6


def test_correlation_length_tempers_the_likelihood():
    # a boxcar (order 0) filter of width w has noise correlation length exactly w
    assert savgol_correlation_length(9, 0) == pytest.approx(9.0)
    assert savgol_correlation_length(17, 3) == pytest.approx(7.5116, rel=1e-4)
    # dividing a Gaussian log-likelihood by L multiplies the posterior variance by L
    s_norm = 0.005
    m = LinearSurrogate(var=None, blob=False)
    t, _ = _noisy_target(m, s_norm, seed=3)
    cfg = PosteriorConfig(walkers=24, steps=600, burn=200, seed=1, predictive_draws=20,
                          correlation_length=1.0)
    a = sample_posterior(m, t, U_TRUE, np.ones(8, bool), cfg)
    b = sample_posterior(m, t, U_TRUE, np.ones(8, bool), replace(cfg, correlation_length=4.0))
    ratio = np.mean([b.summary[n]["std_unit"] / a.summary[n]["std_unit"] for n in a.names])
    assert ratio == pytest.approx(2.0, rel=0.2)
    with pytest.raises(ConfigError, match="correlation_length"):
        PosteriorConfig(correlation_length=0.5)
