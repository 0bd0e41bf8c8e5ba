"""Seeded determinism, early stopping, the collector."""

import numpy as np
import torch

from surrogate.train import Collector, TrainConfig, train


def _state(res):
    return {k: v.clone() for k, v in res.model.state_dict().items()}


def test_training_is_deterministic_under_a_seed(tiny_ds):
    cfg = TrainConfig(epochs=3, seed=11, patience=0, snapshot_epochs=(2,))
    a, b = _state(train(tiny_ds, cfg, progress=False)), _state(train(tiny_ds, cfg, progress=False))
    assert all(torch.equal(a[k], b[k]) for k in a)
    c = _state(train(tiny_ds, TrainConfig(epochs=3, seed=12, patience=0), progress=False))
    assert not all(torch.equal(a[k], c[k]) for k in a)


def test_histories_table_and_snapshots(tiny_ds):
    res = train(tiny_ds, TrainConfig(epochs=4, patience=0, snapshot_epochs=(1, 3)),
                progress=False)
    assert len(res.history.train_total) == len(res.history.val_kl) == 4
    assert 1 <= res.history.best_epoch <= 4
    assert sorted(res.snapshots) == [1, 3, 4]  # the last epoch is always collected
    assert set(res.loss_table) == {"train", "val", "test"}
    t = res.loss_table["test"]
    np.testing.assert_allclose(t["total"], 0.7 * t["mse"] + 0.3 * t["kl"], rtol=1e-5)
    s = res.snapshots[3]
    n_fit = len(res.rows["train"]) + len(res.rows["val"])
    assert s["pressure_true"].shape == s["pressure_pred"].shape == (n_fit, 196)


def test_early_stopping_when_validation_never_improves(tiny_ds):
    # a vanishing learning rate leaves the weights (and the validation loss) unchanged
    res = train(tiny_ds, TrainConfig(epochs=30, patience=3, lr=1e-30, weight_decay=0.0),
                progress=False)
    assert res.history.stopped_early
    assert len(res.history.val_total) == 4 and res.history.best_epoch == 1


def test_collector_caps_and_subsamples():
    c = Collector(max_samples=10, dist_per_batch=3, seed=0)
    for _ in range(6):
        c.add(np.ones((4, 5)), np.zeros((4, 5)), np.ones((4, 2, 2)), np.zeros((4, 2, 2)))
    a = c.arrays()
    assert a["pressure_true"].shape == (10, 5) and a["pressure_pred"].shape == (10, 5)
    assert a["dist_true"].shape == (10, 2, 2)  # 3 + 3 + 3 + 1
