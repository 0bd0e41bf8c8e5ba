"""The PCA + GP pressure branch (``--pressure-head gp``): the torch posterior against
scikit-learn's, its variance and gradients, and the model that carries it end to end."""

import numpy as np
import pytest
import torch

import surrogate
from calendaring import ConfigError
from surrogate.api import SurrogateModel
from surrogate.baseline import PCAGPBaseline
from surrogate.cli import main
from surrogate.ensemble import train_ensemble
from surrogate.gp import GPPressure, fit_pressure_gp
from surrogate.learning import learning_curve
from surrogate.train import TrainConfig


@pytest.fixture(scope="module")
def fitted():
    """A baseline on a smooth 8-parameter family of 40-point curves with a little noise."""
    rng = np.random.default_rng(4)
    u = rng.random((50, 8))
    z = np.linspace(0.0, 1.0, 40)
    y = (np.outer(0.4 + u[:, 0] + 0.3 * u[:, 1] ** 2, z ** 1.5)
         + 0.1 * np.sin(3.0 * u[:, 2])[:, None] + 0.005 * rng.standard_normal((50, 40)))
    b = PCAGPBaseline(4, seed=0).fit(u, y)
    return b, GPPressure.from_baseline(b), u


def test_torch_posterior_mean_is_scikit_learns(fitted):
    b, g, _ = fitted
    u = np.random.default_rng(5).random((11, 8))
    mean, _ = b.predict(u)
    m, _ = g(torch.as_tensor(u))
    np.testing.assert_allclose(m.numpy(), mean, rtol=0, atol=1e-9)
    m32, _ = g(torch.as_tensor(u, dtype=torch.float32))  # the network's dtype in and out
    assert m32.dtype == torch.float32
    np.testing.assert_allclose(m32.numpy(), mean, rtol=0, atol=1e-5)


def test_latent_variance_is_scikit_learns_less_the_white_noise(fitted):
    """scikit-learn's predictive variance adds each component's noise level (times its
    score scale squared) to the latent variance, mapped through the squared components."""
    b, g, _ = fitted
    u = np.random.default_rng(6).random((7, 8))
    _, sd = b.predict(u)
    _, var = g(torch.as_tensor(u))
    noise = np.array([gp.kernel_.k2.noise_level * float(np.ravel(gp._y_train_std)[0]) ** 2
                      for gp in b.gps])
    np.testing.assert_allclose(var.numpy() + noise @ b.pca.components_ ** 2, sd ** 2,
                               rtol=1e-7, atol=1e-14)
    assert np.all(var.numpy() >= 0)


def test_variance_small_at_training_rows_large_far_away(fitted):
    _, g, u = fitted
    _, at = g(torch.as_tensor(u[:5]))
    prior = (g.signal_var * g.y_std ** 2) @ g.components ** 2  # variance with no data
    assert torch.all(at < 0.05 * prior)
    _, far = g(torch.full((1, 8), 40.0, dtype=torch.float64))  # beyond every length scale
    np.testing.assert_allclose(far[0].numpy(), prior.numpy(), rtol=1e-6)


def test_gradient_matches_finite_differences_also_at_a_training_row(fitted):
    _, g, u = fitted
    for x0 in (np.random.default_rng(7).random(8), u[3]):
        x = torch.tensor(x0[None], dtype=torch.float64, requires_grad=True)
        m, v = g(x)
        (m[0, -1] + 10.0 * v[0, -1]).backward()
        grad = x.grad[0].numpy()
        assert np.all(np.isfinite(grad))
        h, fd = 1e-4, np.zeros(8)  # smaller steps meet the rounding of r^2
        for i in range(8):
            e = np.zeros(8)
            e[i] = h
            up = g(torch.as_tensor((x0 + e)[None]))
            dn = g(torch.as_tensor((x0 - e)[None]))
            fd[i] = ((up[0] - dn[0])[0, -1] + 10.0 * (up[1] - dn[1])[0, -1]).item() / (2 * h)
        np.testing.assert_allclose(grad, fd, rtol=1e-4, atol=1e-6)


def test_fit_describes_the_branch(fitted):
    _, _, u = fitted
    y = np.outer(u[:, 0], np.linspace(0, 1, 12)) + 0.01 * u[:, 1:2]
    g, info = fit_pressure_gp(u, y, n_components=3)
    assert info["n_rows"] == 50 and info["n_components"] == len(info["components"]) == 3
    assert len(info["components"][0]["length_scale"]) == 8
    assert 0.99 < sum(info["explained_variance_ratio"]) <= 1.0 + 1e-12
    assert g.shape == {"n_rows": 50, "n_inputs": 8, "n_components": 3, "n_pressure": 12}


@pytest.fixture(scope="module")
def hybrid(tiny_ds):
    cfg = TrainConfig(epochs=2, patience=0, seed=3, pressure_head="gp", gp_components=5)
    results = train_ensemble(tiny_ds, 2, cfg, progress=False)
    return SurrogateModel.from_training(results, tiny_ds), results


def test_hybrid_takes_pressure_from_the_gp_and_distribution_from_the_networks(hybrid, tiny_ds):
    m, results = hybrid
    assert m.pressure_head == "gp" and "PCA + GP" in repr(m)
    rows = np.sort(np.concatenate([results[0].rows["train"], results[0].rows["val"]]))
    assert m.info["pressure_gp"]["n_rows"] == len(rows)
    b = PCAGPBaseline(5, seed=3).fit(tiny_ds.unit_params[rows],
                                     m.normalise_pressure(tiny_ds.pressure[rows]))
    u = np.random.default_rng(8).random((6, 8))
    pred = m.predict_unit(u)
    np.testing.assert_allclose(pred.pressure_normalised, b.predict(u)[0], atol=1e-5)
    with torch.no_grad():  # the distribution is still the members' mean
        d = torch.stack([net(torch.as_tensor(u, dtype=torch.float32))[1]
                         for net in m.members]).mean(0)
    np.testing.assert_allclose(pred.distribution, d.numpy(), atol=1e-6)
    # the uncertainty is the GP's, for a single member too
    single = m.member(0)
    p1 = single.predict_unit(u)
    assert p1.pressure_normalised_var is not None and p1.pressure_std is not None
    np.testing.assert_allclose(p1.pressure_normalised_var, pred.pressure_normalised_var)
    # torch_forward (calibration) gives the same mean and variance, differentiably
    ut = torch.tensor(u, dtype=torch.float32, requires_grad=True)
    p, _, var = m.torch_forward(ut)
    np.testing.assert_allclose(p.detach().numpy(), pred.pressure_normalised, atol=1e-6)
    np.testing.assert_allclose(var.detach().numpy(), pred.pressure_normalised_var,
                               rtol=1e-4, atol=1e-10)
    p.sum().backward()
    assert torch.isfinite(ut.grad).all() and ut.grad.abs().sum() > 0
    p2, d2, var2 = m.torch_forward(torch.as_tensor(u, dtype=torch.float32), distribution=False)
    assert d2 is None
    np.testing.assert_allclose(p2.detach().numpy(), p.detach().numpy(), rtol=0, atol=0)
    np.testing.assert_allclose(var2.detach().numpy(), var.detach().numpy(), rtol=0, atol=0)


def test_hybrid_checkpoint_round_trip(hybrid, tmp_path):
    m, _ = hybrid
    back = surrogate.load(m.save(tmp_path / "h.pt"))
    assert back.pressure_head == "gp"
    assert back.info["train_config"]["pressure_head"] == "gp"
    u = np.random.default_rng(9).random((5, 8))
    a, b = m.predict_unit(u), back.predict_unit(u)
    assert np.array_equal(a.pressure, b.pressure)
    assert np.array_equal(a.pressure_normalised_var, b.pressure_normalised_var)
    assert np.array_equal(a.distribution, b.distribution)


def test_pressure_head_is_validated():
    with pytest.raises(ConfigError, match="--pressure-head"):
        TrainConfig(pressure_head="spline")
    with pytest.raises(ConfigError, match="--gp-components"):
        TrainConfig(gp_components=0)


def test_cli_trains_a_gp_pressure_head(tiny_h5, tmp_path, capsys):
    out = tmp_path / "g.pt"
    assert main(["train", str(tiny_h5), "--out", str(out), "--epochs", "2",
                 "--pressure-head", "gp", "--gp-components", "4", "--quiet"]) == 0
    assert "pressure from PCA + GP: 4 components" in capsys.readouterr().out
    assert surrogate.load(out).pressure_gp.shape["n_components"] == 4
    assert main(["train", str(tiny_h5), "--out", str(tmp_path / "x.pt"), "--pressure-head",
                 "spline", "--quiet"]) == 2


def test_learning_curve_of_the_gp_head_beats_the_short_trained_network(tiny_ds):
    """On the smooth synthetic family a GP fitted to 36 runs is far closer to the held-out
    curves than a network trained for 2 epochs: the head reaches the curve's models."""
    kw = {"sizes": [36], "kl_simulations": 0, "progress": False}
    ds = tiny_ds.subset(np.nonzero(tiny_ds.role != "replicate")[0])
    role = ds.role.copy()
    role[-4:] = "holdout"
    ds.role = role
    ds.group = np.where(role == "holdout", 7, -1)  # one held-out group of 4 runs
    net = learning_curve(ds, cfg=TrainConfig(epochs=2, seed=1), **kw)
    gp = learning_curve(ds, cfg=TrainConfig(epochs=2, seed=1, pressure_head="gp"), **kw)
    assert gp["request"]["train_config"]["pressure_head"] == "gp"
    assert gp["sizes"][0]["pressure_mse_normalised_mean"] < \
        0.2 * net["sizes"][0]["pressure_mse_normalised_mean"]


def test_sobol_single_pass_of_a_hybrid_ensemble_uses_the_gp_pressure(hybrid):
    from analysis.sensitivity import ensemble_single_pass

    m, _ = hybrid
    run = ensemble_single_pass(m)
    u = np.random.default_rng(10).random((5, 8))
    out = run(u)
    peak = m.predict_unit(u).pressure.max(axis=1)
    np.testing.assert_allclose(out["peak_pressure"], peak, rtol=1e-5)
    np.testing.assert_allclose(out["member0/peak_pressure"], peak, rtol=1e-5)
