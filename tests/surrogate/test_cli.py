"""`surrogate train | evaluate | predict` end to end on a tiny synthetic dataset."""

import json

import h5py
import numpy as np
import pytest

from calendaring.data.dataset import synthetic_dataset, write_dataset
from surrogate.cli import main


@pytest.fixture(scope="module")
def model_pt(tiny_h5, tmp_path_factory):
    out = tmp_path_factory.mktemp("model") / "m.pt"
    rc = main(["train", str(tiny_h5), "--out", str(out), "--epochs", "3", "--ensemble", "2",
               "--seed", "1", "--batch-size", "8", "--quiet"])
    assert rc == 0
    return out


def test_train_writes_a_model_without_holdout_rows(model_pt, tiny_ds, capsys):
    import surrogate

    m = surrogate.load(model_pt)
    assert m.is_ensemble and m.n_members == 2
    used = set(m.info["split"]["train"]) | set(m.info["split"]["val"]) | \
        set(m.info["split"]["test"])
    roles = dict(zip(tiny_ds.run_id, tiny_ds.role, strict=True))
    assert {roles[r] for r in used} == {"train"}
    assert len(used) == 36
    assert m.info["metrics"]["test"]["pressure"]["n_rows"] == len(m.info["split"]["test"])
    # an existing output is not replaced without --overwrite
    rc = main(["train", str(m.info["dataset"]["path"]), "--out", str(model_pt), "--quiet"])
    assert rc == 2 and "--overwrite" in capsys.readouterr().err


def test_evaluate_writes_metrics_and_figures(model_pt, tiny_h5, tmp_path, capsys):
    out = tmp_path / "eval"
    rc = main(["evaluate", str(model_pt), str(tiny_h5), "--out-dir", str(out), "--folds", "2",
               "--repeats", "1", "--epochs", "1", "--quiet"])
    assert rc == 0
    for name in ("metrics.json", "loss_table.json", "loss_table.md", "cv.json",
                 "pca_convergence.png", "loss_history.png", "pressure_examples.png"):
        assert (out / name).stat().st_size > 0, name
    m = json.loads((out / "metrics.json").read_text())
    assert m["same_dataset_as_training"]
    assert set(m["metrics"]) == {"test", "holdout", "replicate"}
    assert m["metrics"]["holdout"]["pressure"]["n_rows"] == 4
    at = m["metrics"]["test"]["pressure"]["at_stroke"]
    assert set(at) == {"25%", "50%", "75%", "100%"}
    r = m["replicates"]
    assert r["groups"] == 2 and r["pressure_mse_normalised_floor"] > 0
    assert m["noise_floor_comparison"]["rows"] == "test"
    t = m["loss_table"]["test"]
    np.testing.assert_allclose(t["total"], 0.7 * t["mse"] + 0.3 * t["kl"], rtol=1e-9)
    cv = json.loads((out / "cv.json").read_text())
    assert len(cv["per_fold"]) == 2 and "baseline_pressure_mse_normalised" in cv["summary"]
    assert "pressure MSE" in capsys.readouterr().out


def test_predict_text_and_json(model_pt, capsys):
    assert main(["predict", str(model_pt), "--params", "d0=8e-6", "phi=1,2"]) == 0
    text = capsys.readouterr().out
    assert "reference values" in text and "damage_constant=5.549" in text and "+-" in text
    assert main(["predict", str(model_pt), "--params", "d0=8e-6", "--json"]) == 0
    js = json.loads(capsys.readouterr().out)
    row = js["predictions"][0]
    assert len(row["pressure_Pa"]) == 196 and min(row["pressure_Pa"]) > 0
    np.testing.assert_allclose(np.sum(row["distribution"]), 1.0, rtol=1e-5)
    assert "d0" not in js["defaulted_to_reference"] and len(js["defaulted_to_reference"]) == 7


@pytest.mark.parametrize("params, key", [(["d0=2e-5"], "d0"), (["radius=1"], "radius"),
                                         (["d0"], "--params"), (["phi=abc"], "phi")])
def test_predict_bad_parameters_exit_2(model_pt, capsys, params, key):
    assert main(["predict", str(model_pt), "--params", *params]) == 2
    err = capsys.readouterr().err
    assert err.startswith("surrogate: error:") and key in err


def test_dataset_without_expected_datasets_exits_2(model_pt, tmp_path, capsys):
    bad = write_dataset(tmp_path / "bad.h5", synthetic_dataset(6))
    with h5py.File(bad, "a") as f:
        del f["pressure/smoothed"]
    assert main(["train", str(bad), "--out", str(tmp_path / "x.pt"), "--quiet"]) == 2
    assert "missing dataset 'pressure/smoothed'" in capsys.readouterr().err
    assert main(["evaluate", str(model_pt), str(bad), "--quiet"]) == 2
    assert "missing dataset" in capsys.readouterr().err
    assert not (tmp_path / "x.pt").exists()
    assert main(["predict", str(bad), "--params", "d0=8e-6"]) == 2
    assert "not a readable surrogate checkpoint" in capsys.readouterr().err


def test_train_loss_weights_and_dropout_reach_the_checkpoint(tiny_h5, tmp_path):
    import surrogate

    out = tmp_path / "w.pt"
    assert main(["train", str(tiny_h5), "--out", str(out), "--epochs", "2", "--mse-weight",
                 "30", "--kl-weight", "0.3", "--dropout", "0.1", "--quiet"]) == 0
    m = surrogate.load(out)
    assert m.config.dropout == pytest.approx(0.1)
    cfg = m.info["train_config"]
    assert cfg["mse_weight"] == pytest.approx(30.0) and cfg["kl_weight"] == pytest.approx(0.3)


@pytest.mark.parametrize("flag, value, key", [("--mse-weight", "-1", "--mse-weight"),
                                              ("--dropout", "1.5", "dropout")])
def test_train_bad_loss_weight_or_dropout_exit_2(tiny_h5, tmp_path, capsys, flag, value, key):
    out = tmp_path / "bad.pt"
    assert main(["train", str(tiny_h5), "--out", str(out), flag, value, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("surrogate: error:") and key in err and value in err
    assert not out.exists()
