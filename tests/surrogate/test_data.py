"""Splits, row roles and normalisation fitted on the training split only."""

import numpy as np
import pytest

from calendaring.core.errors import ConfigError
from calendaring.data.dataset import synthetic_dataset
from surrogate.data import Normalisation, SurrogateDataset, split_indices, trainable_rows
from surrogate.train import TrainConfig, make_split, train


def test_split_is_8_1_1_disjoint_and_seeded():
    tr, va, te = split_indices(100, seed=4)
    assert (len(tr), len(va), len(te)) == (80, 10, 10)
    assert len(set(tr) | set(va) | set(te)) == 100
    again = split_indices(100, seed=4)
    assert all(np.array_equal(a, b) for a, b in zip((tr, va, te), again, strict=True))
    assert not np.array_equal(te, split_indices(100, seed=5)[2])


def test_holdout_never_trainable(tiny_ds):
    rows = trainable_rows(tiny_ds)
    assert set(tiny_ds.role[rows]) == {"train"}
    with_rep = trainable_rows(tiny_ds, ("train", "replicate"))
    assert "holdout" not in set(tiny_ds.role[with_rep]) and len(with_rep) == len(rows) + 6
    with pytest.raises(ConfigError) as err:
        trainable_rows(tiny_ds, ("train", "holdout"))
    assert err.value.key == "train_roles"


def test_normalisation_round_trip():
    n = Normalisation(10.0, 30.0)
    p = np.array([1e3, 8e3, 2.7e4])
    np.testing.assert_allclose(n.normalise(p), [0.0, (20 - 10) / 20, 1.0])
    np.testing.assert_allclose(n.denormalise(n.normalise(p)), p, rtol=1e-12)


def test_normalisation_uses_only_the_training_split():
    ds = synthetic_dataset(30, seed=2)
    cfg = TrainConfig(epochs=1, seed=3, patience=0)
    split = make_split(ds, cfg)
    # make every validation and test curve 8x larger: cbrt x2, outside the training range
    p = ds.pressure.copy()
    p[np.concatenate([split["val"], split["test"]])] *= 8.0
    ds.pressure = p
    res = train(ds, cfg, progress=False)
    c_train = np.cbrt(ds.pressure[split["train"]])
    assert res.normalisation.cbrt_max == pytest.approx(c_train.max(), rel=1e-12)
    assert res.normalisation.cbrt_min == pytest.approx(c_train.min(), rel=1e-12)
    assert np.cbrt(ds.pressure).max() > 1.5 * res.normalisation.cbrt_max


def test_replicate_groups_stay_in_one_part(tiny_ds):
    split = make_split(tiny_ds, TrainConfig(train_roles=("train", "replicate"), seed=2))
    where = {int(r): name for name, rows in split.items() for r in rows}
    assert len(where) == 36 + 6
    for g in (0, 1):
        rows = np.nonzero(tiny_ds.group == g)[0]
        assert len({where[int(r)] for r in rows}) == 1


def test_torch_dataset_from_file(tiny_h5, tiny_ds):
    norm = Normalisation.fit(tiny_ds.pressure)
    data = SurrogateDataset.from_file(tiny_h5, norm, np.array([0, 5]))
    u, p, d, w = data[1]
    assert u.shape == (8,) and p.shape == (196,) and d.shape == (30, 30) and float(w) == 1.0
    np.testing.assert_allclose(u.numpy(), tiny_ds.unit_params[5], rtol=1e-6)
    np.testing.assert_allclose(p.numpy(), norm.normalise(tiny_ds.pressure[5]), rtol=1e-5,
                               atol=1e-7)
