"""Evaluation metrics against analytic values; the baseline on a low-rank function."""

import numpy as np
import pytest
import torch

from calendaring.data.dataset import kl_divergence, noise_floor, seed_means, synthetic_dataset
from surrogate.api import SurrogateModel
from surrogate.baseline import PCAGPBaseline
from surrogate.data import Normalisation
from surrogate.evaluate import (
    distribution_errors,
    loss_table_markdown,
    pressure_errors,
    replicate_comparison,
    seed_mean_comparison,
)
from surrogate.model import DualBranchMLP


def _model(ds, norm=None):
    torch.manual_seed(0)
    norm = norm or Normalisation(ds.cbrt_min, ds.cbrt_max)
    return SurrogateModel([DualBranchMLP()], norm, ds.space, ds.depth, ds.load_edges,
                          ds.diameter_edges, ds.load_scale)


def test_pressure_errors_analytic():
    ds = synthetic_dataset(5, seed=4)
    m = _model(ds)
    p = ds.pressure + 1.0  # strictly positive everywhere
    e = pressure_errors(p, 1.1 * p, m)
    for v in e["at_stroke"].values():
        assert v["rel_error_mean"] == pytest.approx(0.1, rel=1e-12)
    assert e["pressure_rmse_Pa"] == pytest.approx(0.1 * np.sqrt(np.mean(p**2)), rel=1e-12)
    x = m.normalise_pressure(p)
    y = (np.cbrt(1.1) * np.cbrt(p) - m.normalisation.cbrt_min) / m.normalisation.span
    assert e["pressure_mse_normalised"] == pytest.approx(np.mean((y - x) ** 2), rel=1e-9)
    assert e["at_stroke"]["100%"]["depth_m"] == ds.depth[-1]
    assert e["at_stroke"]["50%"]["depth_m"] == ds.depth[97]


def test_distribution_errors_shift_by_one_diameter_bin():
    ds = synthetic_dataset(3, seed=0)
    m = _model(ds)
    h = np.zeros((1, 30, 30))
    h[0, 10, 12] = 1.0
    g = np.zeros((1, 30, 30))
    g[0, 10, 13] = 1.0
    e = distribution_errors(h, g, m)
    width = ds.diameter_edges[1] - ds.diameter_edges[0]
    assert e["centroid_diameter_abs_error_m_mean"] == pytest.approx(width, rel=1e-9)
    assert e["centroid_load_rel_error_mean"] == pytest.approx(0.0, abs=1e-12)
    # KL of two point masses with the 1e-8 floor: ~ ln(1 / 1e-8) = 18.4
    assert e["kl_mean"] == pytest.approx(np.log(1 / 1e-8), rel=1e-3)
    same = distribution_errors(h, h, m)
    assert same["kl_mean"] == pytest.approx(0.0, abs=1e-12)


def test_replicate_floor_matches_dataset_noise_floor():
    ds = synthetic_dataset(10, seed=2, replicate_groups=3, replicates=4, noise=0.05)
    m = _model(ds)  # the dataset's own normalisation: both floors must agree
    r = replicate_comparison(m, ds)
    nf = noise_floor(ds)
    assert r["groups"] == 3 and r["runs"] == 12
    assert r["pressure_mse_normalised_floor"] == pytest.approx(nf["pressure_mse_normalised"],
                                                               rel=1e-9)
    assert r["kl_floor"] == nf["kl_to_group_mean"]
    assert r["pressure_mse_normalised_model"] > 0


def test_pca_gp_baseline_recovers_a_low_rank_function():
    rng = np.random.default_rng(0)
    u = rng.random((60, 8))
    z = np.linspace(0, 1, 50)
    f = lambda u: (0.5 + 0.3 * u[:, :1]) * z**2 + 0.2 * np.sin(2 * u[:, 1:2]) * z  # noqa: E731
    b = PCAGPBaseline(n_components=3).fit(u, f(u))
    ut = rng.random((20, 8))
    mean, sd = b.predict(ut)
    assert np.sqrt(np.mean((mean - f(ut)) ** 2)) < 1e-3
    assert mean.shape == sd.shape == (20, 50) and np.all(sd >= 0)


def test_loss_table_markdown_has_the_three_splits():
    t = {k: {"mse": 0.001, "kl": 0.2, "total": 0.0607, "n_rows": 3} for k in
         ("train", "val", "test")}
    md = loss_table_markdown(t)
    assert md.count("| 0.00100 | 0.2000 | 0.0607 |") == 3


def _holdout_groups(ds, groups):
    role = ds.role.copy()
    role[np.isin(ds.group, groups)] = "holdout"
    ds.role = role
    return ds


def test_seed_mean_floor_is_the_replicate_floor_over_the_seed_count():
    """Equal groups of n seeds: the exact mean curve scores the per-point variance / n."""
    ds = _holdout_groups(synthetic_dataset(10, seed=2, replicate_groups=3, replicates=4,
                                           noise=0.05), [0, 1, 2])
    m = _model(ds)
    h = seed_mean_comparison(m, ds, kl_simulations=50)
    nf = noise_floor(ds)
    assert h["groups"] == 3 and h["runs_per_group"] == [4, 4, 4] and h["runs"] == 12
    assert h["pressure_mse_normalised_floor"] == pytest.approx(
        nf["pressure_mse_normalised"] / 4, rel=1e-9)
    # the metrics are those of the model against the seed means
    means = seed_means(ds)
    pred = m.predict_unit(means.unit_params)
    direct = pressure_errors(means.pressure, pred.pressure, m)
    assert h["pressure_mse_normalised"] == pytest.approx(direct["pressure_mse_normalised"],
                                                         rel=1e-12)
    assert h["kl_model"] == pytest.approx(
        float(np.mean(kl_divergence(means.histogram, pred.distribution))), rel=1e-12)
    # 1500 pooled events on a smooth 900-bin map: a perfect model cannot score zero
    assert 0 < h["kl_perfect"] < h["kl_model"]
    assert h["meets"]["kl_over_perfect"] is False
    assert seed_mean_comparison(m, synthetic_dataset(10, seed=2)) is None
