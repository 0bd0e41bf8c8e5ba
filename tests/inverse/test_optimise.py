"""The two-phase optimiser: bounds, phase split, recovery, restarts, fixing, clustering."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from calendaring.core.errors import ConfigError
from calendaring.data.params import PAPER_SPACE
from inverse.calibrate import calibrate_target
from inverse.loss import CompositeLoss, LossConfig, boundary_penalty
from inverse.optimise import (
    OptimiserConfig,
    calibrate,
    cluster_optima,
    fixed_unit_values,
    multistart,
    sobol_starts,
)
from inverse.targets import Target, attach_distribution
from tests.inverse.standins import LinearSurrogate

U_TRUE = np.array([0.3, 0.6, 0.45, 0.7, 0.25, 0.55, 0.4, 0.65])


def _target(model, u, distribution=False):
    pr = model.predict_unit(u)
    t = Target(model.depth, pr.pressure[0], np.ones(len(model.depth), bool),
               distribution=pr.distribution[0] if distribution else None)
    return attach_distribution(t, model)


def test_parameters_never_leave_the_unit_cube():
    m = LinearSurrogate()
    # the pressure-optimal point lies outside the cube: the optimiser presses on the bounds
    t = _target(m, U_TRUE)
    t.pressure = m.pressure_from_normalised(
        m.p_norm_numpy(np.array([-0.4, 1.5, 0.5, 1.3, -0.2, 0.5, 0.5, 0.5]))[0])
    loss = CompositeLoss(m, t, LossConfig(boundary_weight=0.0))
    res = calibrate(loss, 8, OptimiserConfig(iterations=30, restarts=2))
    assert m.calls >= 30  # every closure evaluation went through the model
    assert m.u_min >= 0.0 and m.u_max <= 1.0  # line-search trial points included
    assert m.u_min == 0.0 and m.u_max == 1.0  # and the bounds were reached
    for r in res.restarts:
        assert 0.0 <= min(r["best"]) and max(r["best"]) <= 1.0
    assert res.u[0] == 0.0 and res.u[1] == 1.0


def test_adam_then_lbfgs_phase_split():
    c = torch.tensor([0.2, 0.8, 0.5])
    for iters, n_adam in ((10, 3), (7, 2), (500, 150)):
        cfg = OptimiserConfig(iterations=iters, restarts=1)
        res = calibrate(lambda u: ((u - c) ** 2).sum(dim=1), 3, cfg)
        ph = res.history["phase"]
        assert len(ph) == iters
        assert ph == ["adam"] * n_adam + ["lbfgs"] * (iters - n_adam)
        assert set(res.history["lr"][:n_adam]) == {0.05}
        assert set(res.history["lr"][n_adam:]) == {0.01}
    # the L-BFGS phase finishes what Adam started on a quadratic
    np.testing.assert_allclose(res.u, c.numpy(), atol=1e-4)


def test_recovers_the_minimiser_of_an_analytic_surrogate():
    m = LinearSurrogate()
    loss = CompositeLoss(m, _target(m, U_TRUE, distribution=True))
    res = calibrate(loss, 8, OptimiserConfig(iterations=300, restarts=1, seed=3))
    np.testing.assert_allclose(res.u, U_TRUE, atol=5e-3)
    assert res.loss < 1e-5


def _multimodal(c, k=12):
    c = torch.as_tensor(c, dtype=torch.float32)

    def f(u):  # many local minima, global one at c
        return (1 - torch.cos(k * torch.pi * (u - c))).sum(dim=1) + 2 * ((u - c) ** 2).sum(dim=1)
    return f


def test_restarts_keep_the_best_loss():
    f = _multimodal([0.33, 0.61])
    res = calibrate(f, 2, OptimiserConfig(iterations=40, restarts=6, seed=1))
    losses = np.array([r["loss"] for r in res.restarts])
    assert losses.max() - losses.min() > 0.1  # restarts ended in different minima
    k = int(np.argmin(losses))
    assert res.loss == losses[k]
    np.testing.assert_array_equal(res.u, res.restarts[k]["best"])
    with torch.no_grad():
        direct = f(torch.as_tensor(res.u[None], dtype=torch.float32)).item()
    assert direct == pytest.approx(res.loss, rel=1e-6)
    for r in res.restarts:  # the best point of a restart is never worse than its last one
        assert r["loss"] <= r["final_loss"] + 1e-12


def test_batched_restarts_match_the_sequential_winner():
    f = _multimodal([0.33, 0.61], k=6)
    seq = calibrate(f, 2, OptimiserConfig(iterations=60, restarts=16, seed=2, batch=False))
    bat = calibrate(f, 2, OptimiserConfig(iterations=60, restarts=16, seed=2, batch=True))
    np.testing.assert_array_equal([r["start"] for r in seq.restarts],
                                  [r["start"] for r in bat.restarts])
    np.testing.assert_allclose(bat.u, [0.33, 0.61], atol=2e-3)
    np.testing.assert_allclose(seq.u, [0.33, 0.61], atol=2e-3)


def test_boundary_penalty_grows_toward_both_bounds():
    x = torch.linspace(0.0, 0.5, 51)
    for scale in (0.02, 0.1):
        lo = boundary_penalty(x[:, None], scale)
        hi = boundary_penalty(1.0 - x[:, None], scale)
        assert torch.all(torch.diff(lo) < 0)  # decreasing away from 0 ...
        assert torch.all(torch.diff(hi) < 0)  # ... and away from 1
        torch.testing.assert_close(lo, hi)
        assert lo[0].item() == pytest.approx(1.0 + np.exp(-1 / scale), rel=1e-5)
        assert lo[-1].item() == pytest.approx(2 * np.exp(-0.5 / scale), rel=1e-5)
    # only free columns count
    u = torch.tensor([[0.0, 0.5]])
    assert boundary_penalty(u, 0.02, torch.tensor([False, True])).item() < 1e-9


def test_loss_weights_sum_to_one():
    m = LinearSurrogate()
    with_c = CompositeLoss(m, _target(m, U_TRUE, distribution=True))
    without = CompositeLoss(m, _target(m, U_TRUE))
    assert sum(with_c.weights.values()) == pytest.approx(1.0)
    assert sum(without.weights.values()) == pytest.approx(1.0)
    assert without.weights["centroid"] == 0.0 and with_c.weights["centroid"] > 0
    t = with_c.evaluate(np.vstack([U_TRUE, U_TRUE + 0.05]))
    assert t["pressure"][0] < 1e-9 and t["centroid"][0] < 1e-9
    assert t["pressure"][1] > 1e-4 and t["centroid"][1] > 1e-4
    # the distribution is computed only when a centroid term reads it
    asked = m.distribution_calls
    t0 = without.evaluate(np.vstack([U_TRUE, U_TRUE + 0.05]))
    assert m.distribution_calls == asked and "centroid" not in t0
    np.testing.assert_allclose(t0["pressure"], t["pressure"], rtol=1e-12)


def test_fix_holds_values_exactly():
    m = LinearSurrogate()
    fix = {"damage_constant": 7.25, "truncation_ratio": 95.0}
    out = calibrate_target(m, _target(m, U_TRUE, distribution=True), fix=fix,
                           optimiser=OptimiserConfig(iterations=100, restarts=2),
                           identifiability=False)
    p = {r["name"]: r for r in out.result["parameters"]}
    assert p["damage_constant"]["value"] == 7.25 and p["damage_constant"]["fixed"]
    assert p["truncation_ratio"]["value"] == 95.0 and p["truncation_ratio"]["fixed"]
    held = fixed_unit_values(PAPER_SPACE, fix)
    for r in out.optimisation.restarts:
        for j, v in held.items():
            assert r["best"][j] == pytest.approx(v, abs=1e-7)  # float32 of the held value
            assert r["start"][j] == v
    free = [j for j in range(8) if j not in held]
    assert not p["d0"]["fixed"]
    # the free parameters still move (the fixed ones are off their true values)
    assert np.ptp([r["best"][free[0]] for r in out.optimisation.restarts]) < 0.5
    with pytest.raises(ConfigError):
        fixed_unit_values(PAPER_SPACE, {"d0": 50e-6})
    with pytest.raises(ConfigError):
        fixed_unit_values(PAPER_SPACE, {"nope": 1.0})


def test_sobol_starts_are_seeded_and_respect_fixed_columns():
    a = sobol_starts(5, 8, seed=4, fixed={2: 0.125})
    b = sobol_starts(5, 8, seed=4, fixed={2: 0.125})
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, sobol_starts(5, 8, seed=5))
    assert np.all(a[:, 2] == 0.125) and a.min() >= 0 and a.max() <= 1


def test_multistart_clusters_two_equal_minima():
    def f(u):  # equal minima at u0 = 0.25 and u0 = 0.75
        return 50 * ((u[:, 0] - 0.25) * (u[:, 0] - 0.75)) ** 2 + ((u[:, 1:] - 0.5) ** 2).sum(1)
    res = multistart(f, 3, OptimiserConfig(iterations=80), restarts=16)
    assert len(res.restarts) == 16
    cl = cluster_optima(res.all_optima, res.all_losses, res.free, atol=1e-6)
    centres = sorted(round(c["centre"][0], 2) for c in cl["clusters"])
    assert centres == [0.25, 0.75]
    assert sum(c["size"] for c in cl["clusters"]) == len(cl["within"]) == 16
