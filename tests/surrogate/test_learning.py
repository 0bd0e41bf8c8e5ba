"""Learning curve: nested training subsets scored on held-out seed means; the target size."""

import json

import numpy as np
import pytest

from calendaring import ConfigError
from calendaring.data.dataset import synthetic_dataset, write_dataset
from surrogate.cli import main
from surrogate.learning import (
    default_sizes,
    learning_curve,
    power_law_fit,
    runs_for_target,
)
from surrogate.train import TrainConfig


@pytest.fixture(scope="module")
def lc_ds():
    ds = synthetic_dataset(48, seed=3, replicate_groups=3, replicates=3, noise=0.02)
    ds.role = np.where(ds.role == "replicate", "holdout", ds.role)
    return ds


def test_power_law_fit_recovers_known_exponents():
    n = np.array([20, 40, 80, 160, 320])
    fit = power_law_fit(n, 2e-4 + 0.05 * n**-0.8)
    assert fit["a"] == pytest.approx(0.05, rel=1e-3)
    assert fit["b"] == pytest.approx(0.8, rel=1e-3)
    assert fit["c"] == pytest.approx(2e-4, rel=1e-3)
    assert power_law_fit(n[:2], [1e-3, 5e-4]) is None


def test_runs_for_target_measured_extrapolated_or_unreachable():
    fit = {"a": 0.05, "b": 0.8, "c": 2e-4}
    assert runs_for_target([10, 20], [1e-3, 2e-4], 3e-4, fit) == {"runs": 20,
                                                                  "how": "measured"}
    t = runs_for_target([10, 20], [1e-2, 5e-3], 3e-4, fit)
    assert t["how"].startswith("extrapolated")
    # c + a n^-b at the returned n is at or just below the target
    n = t["runs"]
    assert 2e-4 + 0.05 * n**-0.8 <= 3e-4 < 2e-4 + 0.05 * (n - 1) ** -0.8
    assert runs_for_target([10], [1e-2], 1e-4, fit)["runs"] is None  # floor above target
    assert runs_for_target([10], [1e-2], 1e-4, None)["runs"] is None


def test_default_sizes_are_halvings():
    assert default_sizes(280) == [35, 70, 140, 280]
    assert default_sizes(30) == [15, 30]
    assert default_sizes(5) == [5]


def test_learning_curve_trains_nested_subsets_and_resumes(lc_ds, tmp_path):
    cfg = TrainConfig(epochs=4, batch_size=8, seed=2)
    out = learning_curve(lc_ds, [12, 24, 48], repeats=2, cfg=cfg, out_dir=tmp_path,
                         kl_simulations=20, progress=False)
    assert [s["n"] for s in out["sizes"]] == [12, 24, 48]
    assert all(s["repeats"] == 2 for s in out["sizes"])
    assert out["holdout_groups"] == 3 and out["trainable_rows"] == 48
    for p in out["points"]:
        assert p["n_fit"] + p["n_val"] == p["n"] and p["n_val"] == max(1, round(p["n"] / 9))
        assert p["pressure_mse_normalised"] > 0 and p["kl_perfect"] > 0
    assert (tmp_path / "learning_curve.json").is_file()
    assert (tmp_path / "learning_curve.png").stat().st_size > 0
    # a rerun with one more repeat fits only the new points
    first = {(p["repeat"], p["n"]): p["fit_seconds"] for p in out["points"]}
    again = learning_curve(lc_ds, [12, 24, 48], repeats=3, cfg=cfg, out_dir=tmp_path,
                           kl_simulations=20, progress=False)
    assert len(again["points"]) == 9
    for p in again["points"]:
        if (p["repeat"], p["n"]) in first:
            assert p["fit_seconds"] == first[(p["repeat"], p["n"])]
    # other training settings in the same folder: refused, nothing lost
    with pytest.raises(ConfigError, match="--out-dir"):
        learning_curve(lc_ds, [12], cfg=TrainConfig(epochs=5, batch_size=8, seed=2),
                       out_dir=tmp_path, progress=False)
    assert len(json.loads((tmp_path / "learning_curve.json").read_text())["points"]) == 9


def test_learning_curve_needs_holdout_means_and_valid_sizes(lc_ds):
    cfg = TrainConfig(epochs=1)
    with pytest.raises(ConfigError, match="holdout"):
        learning_curve(synthetic_dataset(20, seed=1), [10], cfg=cfg, progress=False)
    with pytest.raises(ConfigError, match="--sizes"):
        learning_curve(lc_ds, [49], cfg=cfg, progress=False)


def test_learning_curve_cli(lc_ds, tmp_path, capsys):
    data = write_dataset(tmp_path / "lc.h5", lc_ds)
    rc = main(["learning-curve", str(data), "--out-dir", str(tmp_path / "lc"), "--sizes",
               "12", "24", "--repeats", "1", "--epochs", "2", "--batch-size", "8", "--quiet"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "| 12 |" in out and "| 24 |" in out and "target MSE 0.0003" in out
    rc = main(["learning-curve", str(data), "--out-dir", str(tmp_path / "lc2"), "--sizes", "2",
               "--quiet"])
    assert rc == 2 and "--sizes" in capsys.readouterr().err


def test_evaluate_scores_model_and_baseline_on_held_out_seed_means(lc_ds, tmp_path):
    from calendaring.data.dataset import seed_means
    from surrogate.evaluate import baseline_metrics, pressure_errors, split_rows

    data = write_dataset(tmp_path / "lc.h5", lc_ds)
    model = tmp_path / "m.pt"
    assert main(["train", str(data), "--out", str(model), "--epochs", "2", "--batch-size",
                 "8", "--quiet"]) == 0
    assert main(["evaluate", str(model), str(data), "--out-dir", str(tmp_path / "e"),
                 "--quiet"]) == 0
    m = json.loads((tmp_path / "e" / "metrics.json").read_text())
    h = m["holdout_means"]
    assert h["groups"] == 3 and h["runs_per_group"] == [3, 3, 3]
    import surrogate

    sm = surrogate.load(model)
    means = seed_means(lc_ds)
    direct = pressure_errors(means.pressure, sm.predict_unit(means.unit_params).pressure, sm)
    assert h["pressure_mse_normalised"] == pytest.approx(direct["pressure_mse_normalised"],
                                                         rel=1e-6)
    split = split_rows(sm, lc_ds)
    rows = np.concatenate([split["train"], split["val"]])
    b = baseline_metrics(sm, lc_ds, rows, np.arange(3), test_ds=means)
    assert m["baseline_holdout_means"]["pressure_mse_normalised"] == pytest.approx(
        b["pressure_mse_normalised"], rel=1e-6)
