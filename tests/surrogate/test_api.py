"""Checkpoint round trip, the load/predict contract, input validation, ensembles."""

import copy

import numpy as np
import pytest
import torch

import surrogate
from calendaring.core.errors import ConfigError
from surrogate.api import SurrogateModel
from surrogate.checkpoint import CheckpointError
from surrogate.train import TrainConfig, train


@pytest.fixture(scope="module")
def trained(tiny_ds):
    return train(tiny_ds, TrainConfig(epochs=2, patience=0, seed=5), progress=False)


@pytest.fixture(scope="module")
def model(trained, tiny_ds):
    return SurrogateModel.from_training(trained, tiny_ds)


def test_checkpoint_round_trip_gives_identical_predictions(model, tiny_ds, tmp_path):
    path = model.save(tmp_path / "m.pt")
    assert not list(tmp_path.glob(".*tmp*"))  # atomic write left no temporary file
    back = surrogate.load(path)
    u = np.random.default_rng(1).random((9, 8))
    a, b = model.predict_unit(u), back.predict_unit(u)
    assert np.array_equal(a.pressure, b.pressure)
    assert np.array_equal(a.distribution, b.distribution)
    assert back.space.to_json() == tiny_ds.space.to_json()
    assert np.array_equal(back.depth, tiny_ds.depth)
    assert np.array_equal(back.load_edges, tiny_ds.load_edges)
    assert back.info["dataset"]["fingerprint"] == tiny_ds.fingerprint
    assert back.normalisation == model.normalisation
    assert not back.is_ensemble and back.config == model.config
    assert sorted(back.snapshots) == sorted(model.snapshots)


def test_predict_contract(model):
    ref = model.space.reference
    pred = model.predict({"d0": [6e-6, 8e-6], "phi": 1.5})
    assert pred.pressure.shape == (2, 196) and pred.distribution.shape == (2, 30, 30)
    assert pred.pressure_std is None and pred.distribution_std is None
    np.testing.assert_allclose(pred.distribution.sum(axis=(1, 2)), 1.0, rtol=1e-5)
    np.testing.assert_allclose(pred.pressure, model.pressure_from_normalised(
        pred.pressure_normalised), rtol=1e-12)
    assert "d0" not in pred.defaulted and "damage_constant" in pred.defaulted
    rows = np.tile(ref, (2, 1))
    rows[:, model.space.index("d0")] = [6e-6, 8e-6]
    rows[:, model.space.index("phi")] = 1.5
    np.testing.assert_allclose(model.predict(rows).pressure, pred.pressure, rtol=1e-12)
    same = model.predict_unit(model.space.to_unit(rows))
    np.testing.assert_allclose(same.pressure, pred.pressure, rtol=1e-6)


def test_torch_forward_is_differentiable(model):
    u = torch.full((3, 8), 0.5, requires_grad=True)
    p, d, var = model.torch_forward(u)
    assert p.shape == (3, 196) and d.shape == (3, 30, 30) and var is None
    (p.sum() + (d * torch.arange(900.0).reshape(30, 30)).sum()).backward()
    assert u.grad is not None and torch.all(torch.isfinite(u.grad)) and u.grad.abs().sum() > 0


def test_predict_rejects_bad_names_and_values(model):
    with pytest.raises(ConfigError) as err:
        model.predict({"d0": 20e-6})
    assert err.value.key == "d0" and err.value.value == pytest.approx(20e-6)
    with pytest.raises(ConfigError) as err:
        model.predict({"diameter": 8e-6})
    assert err.value.key == "parameter" and err.value.value == "diameter"
    with pytest.raises(ConfigError) as err:
        model.predict({"d0": 8e-6}, defaults=None)
    assert "missing" in str(err.value)
    with pytest.raises(ConfigError):
        model.predict({"d0": [6e-6, 7e-6], "phi": [1.0, 2.0, 3.0]})
    with pytest.raises(ConfigError) as err:
        model.predict_unit(np.full((1, 8), 1.5))
    assert "u[0, 0]" in err.value.key


def test_bfloat16_prediction_stays_close_to_float32(model):
    """The bfloat16 fast path changes the arithmetic, not the model: bfloat16 keeps 8
    significant bits (relative rounding 2^-9 per operation), so the normalised pressures
    agree to ~1e-2 and each distribution still sums to one."""
    u = np.random.default_rng(3).random((64, 8))
    a = model.predict_unit(u)
    b = model.predict_unit(u, precision="bfloat16", batch_size=16)
    assert b.pressure.dtype == np.float64 and b.pressure.shape == a.pressure.shape
    assert np.abs(b.pressure_normalised - a.pressure_normalised).max() < 2e-2
    assert np.abs(b.pressure_normalised - a.pressure_normalised).max() > 0.0  # really bf16
    np.testing.assert_allclose(b.distribution.sum(axis=(1, 2)), 1.0, rtol=1e-3)
    assert np.abs(b.distribution - a.distribution).max() < 1e-2
    with pytest.raises(ConfigError) as err:
        model.predict_unit(u, precision="float16")
    assert err.value.key == "precision" and err.value.value == "float16"


def test_load_rejects_other_files(tmp_path, tiny_h5):
    with pytest.raises(CheckpointError, match="no such file"):
        surrogate.load(tmp_path / "none.pt")
    with pytest.raises(CheckpointError, match="not a readable"):
        surrogate.load(tiny_h5)
    torch.save({"format": "other"}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="not a surrogate checkpoint"):
        surrogate.load(tmp_path / "other.pt")


def test_ensemble_of_identical_members_has_zero_spread(trained, tiny_ds, model, tmp_path):
    twin = copy.deepcopy(trained.model)
    ens = SurrogateModel.from_training([trained, trained], tiny_ds)
    ens.members[1] = twin
    assert ens.is_ensemble
    u = np.random.default_rng(2).random((5, 8))
    a, single = ens.predict_unit(u), model.predict_unit(u)
    assert np.all(a.pressure_std == 0) and np.all(a.pressure_normalised_var == 0)
    assert np.all(a.distribution_std == 0)
    np.testing.assert_allclose(a.pressure, single.pressure, rtol=1e-6)
    np.testing.assert_allclose(a.distribution, single.distribution, rtol=1e-6, atol=1e-12)
    back = surrogate.load(ens.save(tmp_path / "ens.pt"))
    assert back.is_ensemble and back.n_members == 2


def test_ensemble_spread_is_nonnegative_and_matches_members(tiny_ds):
    from surrogate.ensemble import train_ensemble

    res = train_ensemble(tiny_ds, 3, TrainConfig(epochs=1, patience=0), progress=False)
    assert len({id(r.normalisation) for r in res}) == 1  # one shared normalisation
    assert all(np.array_equal(r.rows["test"], res[0].rows["test"]) for r in res)
    ens = SurrogateModel.from_training(res, tiny_ds)
    u = np.random.default_rng(3).random((4, 8))
    pred = ens.predict_unit(u)
    assert np.all(pred.pressure_normalised_var >= 0) and np.all(pred.pressure_std >= 0)
    assert pred.pressure_normalised_var.max() > 0
    members = np.stack([ens.member(k).predict_unit(u).pressure_normalised for k in range(3)])
    assert not ens.member(0).is_ensemble
    np.testing.assert_allclose(pred.pressure_normalised, members.mean(0), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(pred.pressure_normalised_var, members.var(0), rtol=1e-3,
                               atol=1e-9)
    _p, d, var = ens.torch_forward(torch.as_tensor(u, dtype=torch.float32))
    assert var.shape == (4, 196) and torch.all(var >= 0)
    np.testing.assert_allclose(d.sum(dim=(1, 2)).detach().numpy(), 1.0, rtol=1e-5)
    # the pressure-only pass skips the distribution head and changes nothing else
    p_only, d_only, var_only = ens.torch_forward(torch.as_tensor(u, dtype=torch.float32),
                                                 distribution=False)
    assert d_only is None
    assert torch.equal(p_only, _p) and torch.equal(var_only, var)


def test_pressure_only_forward_matches_and_is_differentiable(model):
    u = torch.rand((5, 8), generator=torch.Generator().manual_seed(2))
    p, _d, _var = model.torch_forward(u)
    ug = u.clone().requires_grad_(True)
    p_only, d_only, var_only = model.torch_forward(ug, distribution=False)
    assert d_only is None and var_only is None
    assert torch.equal(p_only.detach(), p.detach())
    p_only.sum().backward()
    assert torch.isfinite(ug.grad).all() and ug.grad.abs().sum() > 0


def test_checkpoint_fingerprint_follows_the_weights_not_the_time_stamp(model, tmp_path):
    import hashlib

    from surrogate.checkpoint import checkpoint_fingerprint, read_checkpoint, write_checkpoint

    a = model.save(tmp_path / "a.pt")
    obj = read_checkpoint(a)
    obj["created"] = "2000-01-01T00:00:00+00:00"  # a retrained copy: same weights, new file
    b = write_checkpoint(tmp_path / "b.pt", obj)
    assert hashlib.sha256(a.read_bytes()).digest() != hashlib.sha256(b.read_bytes()).digest()
    assert checkpoint_fingerprint(a) == checkpoint_fingerprint(b)
    first = next(iter(obj["members"][0]))  # one weight moved by one ulp-sized step
    obj["members"][0][first] = obj["members"][0][first].clone()
    obj["members"][0][first].view(-1)[0] += 1e-6
    c = write_checkpoint(tmp_path / "c.pt", obj)
    assert checkpoint_fingerprint(c) != checkpoint_fingerprint(a)


def test_the_model_records_what_one_training_curve_can_tell(model, tiny_ds, tmp_path):
    """`from_training` keeps the dataset's resolvable pressure components (the replicate
    groups against the design spread) in the checkpoint, for the calibration's report."""
    from calendaring import pressure_components

    pc = pressure_components(tiny_ds)
    rec = surrogate.load(model.save(tmp_path / "m.pt")).info["dataset"]["pressure_components"]
    assert rec["resolved"] == pc["resolved"] >= 1 and rec["tested"] == pc["tested"]
    assert rec["noise_share"] == [c["noise_share"] for c in pc["components"]]
