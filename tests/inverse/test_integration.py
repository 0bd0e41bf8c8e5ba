"""Integration with the real surrogate: a tiny model trained on the synthetic dataset."""

from __future__ import annotations

import numpy as np
import pytest

surrogate = pytest.importorskip("surrogate")

from calendaring.data.dataset import synthetic_dataset, write_dataset  # noqa: E402
from inverse import cli  # noqa: E402
from inverse.calibrate import calibrate_target  # noqa: E402
from inverse.optimise import OptimiserConfig  # noqa: E402
from inverse.posterior import PosteriorConfig  # noqa: E402
from inverse.report import read_result  # noqa: E402
from inverse.targets import write_curve_csv  # noqa: E402
from inverse.validate import row_target, validate_to_dir  # noqa: E402


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    from surrogate import ModelConfig, SurrogateModel, TrainConfig, train

    ds = synthetic_dataset(n=128, seed=0)
    res = train(ds, TrainConfig(epochs=40, batch_size=32, patience=0, lr=3e-3),
                ModelConfig(embed_width=64, block_widths=(64, 32), pressure_hidden=64,
                            dist_hidden=(64, 64), dropout=0.0), progress=False)
    path = tmp_path_factory.mktemp("model") / "model.pt"
    SurrogateModel.from_training(res, ds).save(path)
    return path


@pytest.fixture(scope="module")
def truth():
    ds = synthetic_dataset(n=4, seed=7)
    ds.role = np.array(["holdout"] * len(ds))
    return ds


def test_cli_calibrates_a_synthetic_curve_with_the_real_model(model_file, truth, tmp_path):
    m = surrogate.load(model_file)
    csv = write_curve_csv(tmp_path / "curve.csv", truth.depth, truth.pressure[0])
    out = tmp_path / "result.json"
    rc = cli.main(["calibrate", "--model", str(model_file), "--target", str(csv), "--out",
                   str(out), "--restarts", "2", "--iterations", "120", "--no-plots",
                   "--profiles", "none", "--quiet"])
    assert rc == 0
    res = read_result(out)
    # the curve is reproduced (the synthetic pressure does not pin down all 8 parameters)
    assert res["fit"]["relative_rmse"] < 0.1
    x = np.array([p["value"] for p in res["parameters"]])
    m.space.check_array(x)


def test_posterior_and_identifiability_run_on_the_real_model(model_file, truth):
    m = surrogate.load(model_file)
    t = row_target(m, truth, 1)
    assert t.centroids is not None  # the synthetic histogram gives a centroid
    oc = calibrate_target(m, t, optimiser=OptimiserConfig(iterations=100, restarts=1),
                          posterior=PosteriorConfig(walkers=20, steps=150, burn=50),
                          fix={"damage_constant": 5.0})
    r = oc.result
    assert len(r["identifiability"]["hessian"]["eigenvalues"]) == 7
    assert set(r["posterior"]["parameters"]) == set(m.space.names) - {"damage_constant"}
    # phi sets the synthetic diameter centroid: it is pinned down better than the prior
    assert r["posterior"]["parameters"]["phi"]["std_ratio"] < 0.8


def test_the_calibration_reports_how_many_combinations_one_curve_can_pin(model_file, truth):
    """A model whose training curves resolve 2 components above the bed-to-bed scatter: the
    identifiability report carries the bound and the summary says it."""
    from inverse.report import format_table4

    m = surrogate.load(model_file)
    m.info["dataset"]["pressure_components"] = {
        "resolved": 2, "tested": 10, "alpha": 0.05, "groups": 19, "dof_bed_to_bed": 60,
        "signal_share_resolved": 0.999, "noise_share": [0.0, 0.09] + [1.0] * 8}
    oc = calibrate_target(m, row_target(m, truth, 0),
                          optimiser=OptimiserConfig(iterations=40, restarts=1),
                          fix={"damage_constant": 5.0}, profile_mode="slice")
    cc = oc.result["identifiability"]["curve_components"]
    assert cc["resolved"] == 2 and cc["free_parameters"] == 7
    assert "pin at most 2 combination(s) of the 7 free parameters" in format_table4(oc.result)


def test_validate_on_held_out_rows(model_file, truth, tmp_path):
    m = surrogate.load(model_file)
    ds_path = write_dataset(tmp_path / "holdout.h5", truth)
    from calendaring.data.dataset import read_dataset
    from inverse.validate import select_rows

    np.testing.assert_array_equal(select_rows(read_dataset(ds_path)), [0, 1, 2, 3])
    rep = validate_to_dir(m, read_dataset(ds_path), tmp_path / "val", rows=[0, 2],
                          optimiser=OptimiserConfig(iterations=60, restarts=1),
                          posterior=PosteriorConfig(walkers=18, steps=120, burn=40),
                          progress=False)
    assert rep["n_rows"] == 2 and set(rep["key_coverage"]) == {"d0", "phi"}
    for name, p in rep["per_parameter"].items():
        assert 0.0 <= p["coverage_ci90"] <= 1.0
        truth_u = [r["parameters"][name]["truth_unit"] for r in rep["rows"]]
        np.testing.assert_allclose(truth_u, truth.unit_params[[0, 2], m.space.index(name)])
    assert (tmp_path / "val" / "validation.json").is_file()
    assert (tmp_path / "val" / "validation.png").is_file()
    # identifiability per row and per parameter; the goal covers the identifiable ones
    assert all("flat" in r for r in rep["rows"])
    from inverse.validate import CONSTRAINED_WIDTH

    for name, p in rep["per_parameter"].items():
        steep = np.array([name not in r["flat"] for r in rep["rows"]])
        ci = np.array([r["parameters"][name]["ci90_unit"] for r in rep["rows"]])
        narrow = ci[:, 1] - ci[:, 0] <= CONSTRAINED_WIDTH * 0.9
        assert p["profile_fraction"] == pytest.approx(steep.mean())
        assert p["narrow_fraction"] == pytest.approx(narrow.mean())
        assert p["identifiable_fraction"] == pytest.approx((steep & narrow).mean())
        assert (name in rep["identifiable"]) == ((steep & narrow).mean() >= 0.5)
    assert set(rep["identifiable_coverage"]) == set(rep["identifiable"])
    assert not (tmp_path / "val" / "validation.partial.json").exists()


def test_validate_resumes_from_its_partial_file(model_file, truth, tmp_path, monkeypatch):
    import inverse.validate as v
    from calendaring.data.dataset import read_dataset

    m = surrogate.load(model_file)
    ds = read_dataset(write_dataset(tmp_path / "holdout.h5", truth))
    kw = {"optimiser": OptimiserConfig(iterations=40, restarts=1),
          "posterior": PosteriorConfig(walkers=18, steps=80, burn=20), "progress": False}
    real = v.calibrate_target
    calls = []

    def crash_on_third(*a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(v, "calibrate_target", crash_on_third)
    with pytest.raises(KeyboardInterrupt):
        validate_to_dir(m, ds, tmp_path / "val", rows=[0, 1, 2], **kw)
    partial = tmp_path / "val" / "validation.partial.json"
    assert partial.is_file()
    (tmp_path / "val2").mkdir()
    (tmp_path / "val2" / partial.name).write_text(partial.read_text())
    calls.clear()
    monkeypatch.setattr(v, "calibrate_target", real)
    counted = []
    monkeypatch.setattr(v, "calibrate_target", lambda *a, **k: counted.append(1) or real(*a, **k))
    rep = validate_to_dir(m, ds, tmp_path / "val", rows=[0, 1, 2], **kw)
    assert len(counted) == 1 and rep["resumed_rows"] == 2
    assert [r["row"] for r in rep["rows"]] == [0, 1, 2]
    # other settings: the partial rows are not reused
    counted.clear()
    rep2 = validate_to_dir(m, ds, tmp_path / "val2", rows=[0], identifiability=False, **kw)
    assert len(counted) == 1 and rep2["resumed_rows"] == 0 and "identifiable" not in rep2


def test_validate_in_worker_processes_gives_the_same_report(model_file, truth, tmp_path):
    """--jobs spreads the rows over spawned processes: every record, and so the report, is
    the one the serial run gives (each row depends on its settings only), the checkpoint
    holds every row, and a resumed parallel run calibrates only what is missing."""
    import json

    import inverse.validate as v
    from calendaring.data.dataset import read_dataset

    m = surrogate.load(model_file)
    ds = read_dataset(write_dataset(tmp_path / "holdout.h5", truth))
    kw = {"optimiser": OptimiserConfig(iterations=30, restarts=2),
          "posterior": PosteriorConfig(walkers=18, steps=40, burn=10),
          "identifiability": False, "progress": False}
    serial = validate_to_dir(m, ds, tmp_path / "serial", rows=[0, 3], **kw)
    seen = []
    par = v.validate(m, ds, rows=[0, 3], jobs=2, on_row=lambda r: seen.append(r["row"]),
                     **kw)
    assert sorted(seen) == [0, 3]
    assert [r["row"] for r in par["rows"]] == [0, 3]
    assert json.dumps(par["rows"], sort_keys=True) == json.dumps(serial["rows"], sort_keys=True)
    assert par["per_parameter"] == serial["per_parameter"]
    # a checkpoint with row 0: the parallel rerun calibrates row 3 only, in the parent
    # (one row left), and the jobs setting does not change the request key
    out = tmp_path / "resumed"
    out.mkdir()
    request = v._request(m, ds, kw | {"jobs": 2})
    assert request == v._request(m, ds, kw)
    keep = [r for r in serial["rows"] if r["row"] == 0]
    (out / v.PARTIAL).write_text(json.dumps({"request": request, "rows": keep}))
    rep = validate_to_dir(m, ds, out, rows=[0, 3], jobs=2, **kw)
    assert rep["resumed_rows"] == 1
    assert json.dumps(rep["rows"], sort_keys=True) == json.dumps(serial["rows"],
                                                                 sort_keys=True)
    with pytest.raises(Exception, match="--jobs"):
        v.validate(m, ds, rows=[0], jobs=0, **kw)
    # the same weights in a new file (a retrained model on a fresh machine: new time stamp,
    # new file hash) still match the checkpoint's request
    from surrogate.checkpoint import read_checkpoint, write_checkpoint

    obj = read_checkpoint(model_file)
    obj["created"] = "2000-01-01T00:00:00+00:00"
    again = surrogate.load(write_checkpoint(tmp_path / "retrained.pt", obj))
    assert v._request(again, ds, kw) == request


def test_validate_cli_prints_coverage_and_identifiability(model_file, truth, tmp_path, capsys):
    ds_path = write_dataset(tmp_path / "holdout.h5", truth)
    rc = cli.main(["validate", "--model", str(model_file), "--dataset", str(ds_path), "--out",
                   str(tmp_path / "v"), "--rows", "1", "--restarts", "1", "--iterations", "40",
                   "--walkers", "18", "--steps", "60", "--burn", "20", "--quiet"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "identifiable" in out and "CI width" in out and "1 rows (0 resumed)" in out
    assert (tmp_path / "v" / "validation.json").is_file()


def test_calibrate_on_a_dataset_row(model_file, truth, tmp_path, capsys):
    ds_path = write_dataset(tmp_path / "holdout.h5", truth)
    out = tmp_path / "row.json"
    rc = cli.main(["calibrate", "--model", str(model_file), "--target-row", "2", "--dataset",
                   str(ds_path), "--out", str(out), "--restarts", "1", "--iterations", "60",
                   "--no-plots", "--profiles", "none", "--quiet"])
    assert rc == 0
    res = read_result(out)
    assert res["truth"]["row"] == 2 and res["truth"]["role"] == "holdout"
    np.testing.assert_allclose(res["truth"]["parameters_unit"], truth.unit_params[2])
    np.testing.assert_allclose(res["target"]["pressure_Pa"], truth.pressure[2], rtol=1e-12)
    assert "truth (holdout row 2" in capsys.readouterr().out
    # --target-row needs --dataset; --dataset alone is refused; a row past the end too
    for argv, key in ((["--target-row", "1"], "--dataset"),
                      (["--target", "x.csv", "--dataset", str(ds_path)], "--dataset"),
                      (["--target-row", "9", "--dataset", str(ds_path)], "--target-row")):
        rc = cli.main(["calibrate", "--model", str(model_file), "--out",
                       str(tmp_path / "bad.json"), "--quiet", *argv])
        assert rc == 2 and key in capsys.readouterr().err
        assert not (tmp_path / "bad.json").exists()


class _DiesWhenUnpickled:
    """Stands in for the model: unpickling it in a worker ends that process at once, as a
    worker that re-runs an unguarded script (or is killed for memory) ends."""

    def __reduce__(self):
        import os

        return os._exit, (3,)


def test_a_dead_worker_process_gives_a_clear_error_not_a_hang():
    import inverse.validate as v

    records = v._rows_in_parallel(_DiesWhenUnpickled(), None, [0, 1], {}, 2)
    with pytest.raises(RuntimeError, match=r"worker process of --jobs 2 died.*__main__"):
        next(records)
