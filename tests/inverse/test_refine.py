"""`inverse refine`: posterior-guided refinement, end to end on an analytic stand-in.

The "DEM" here is :func:`calendaring.data.dataset.synthetic_response` written as run files
by an injected sweep task (no packing, no Taichi), so the whole loop runs in seconds: the
selection from the posterior, the sweep's manifest and resume, the dataset with role
``refine``, the out-of-sample error measured before training, the retraining and the
recalibration with that error in the likelihood.
"""

from __future__ import annotations

import json
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest

from calendaring import ConfigError
from calendaring.core.config import config_json, load_preset
from calendaring.data.dataset import (
    DatasetError,
    append_runs,
    read_dataset,
    synthetic_dataset,
    synthetic_response,
    write_dataset,
)
from calendaring.data.design import read_design_csv
from calendaring.data.params import PAPER_SPACE
from calendaring.data.sweep import base_config, run_config
from inverse.optimise import OptimiserConfig
from inverse.posterior import PosteriorConfig
from inverse.refine import RefineConfig, Refinement, interval_change, select_points
from tests.inverse.conftest import write_fake_run

STROKE = 19.5e-6
N_EVENTS = 600
CALLS: list[str] = []
_LOCK = threading.Lock()


def _fake_pack(folder, source, overrides, seed, key, threads):
    return "no-packing-needed.csv"


def _fake_task(folder, entry, packing, threads, timeout):
    """The analytic stand-in as a run file of the entry's exact configuration."""
    from pathlib import Path

    with _LOCK:
        CALLS.append(entry["run_id"])
    cfg = run_config(base_config(entry["source"], entry["overrides"]), entry["params"],
                     entry["seed"])
    x = np.array([[entry["params"][n] for n in PAPER_SPACE.names]])
    depth = np.linspace(0.0, STROKE, 801)
    le, de = np.geomspace(1e-3, 1.0, 31), np.linspace(4e-6, 16e-6, 31)
    p, h = synthetic_response(PAPER_SPACE.to_unit(x), depth, STROKE, le, de)
    rng = np.random.default_rng(abs(hash(entry["run_id"])) % 2**32)
    cells = rng.choice(h[0].size, size=N_EVENTS, p=h[0].ravel())
    li, di = np.unravel_index(cells, h[0].shape)
    loads = np.sqrt(le[li] * le[li + 1])
    dias = 0.5 * (de[di] + de[di + 1])
    write_fake_run(Path(folder) / entry["file"], depth, p[0], loads, dias, cfg=cfg,
                   seed=entry["seed"], info={"final_depth": STROKE, "wall_seconds": 0.01})
    return {"status": "done", "wall_time": 0.01, "error": "", "reused": False}


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A synthetic dataset with the sweep preset's problem, 4 held-out rows, and a 2-member
    surrogate trained on its training rows."""
    import torch

    from surrogate import SurrogateModel, TrainConfig, train_ensemble
    from surrogate.evaluate import model_metrics

    torch.set_num_threads(1)
    tmp = tmp_path_factory.mktemp("refine")
    ds = synthetic_dataset(44, seed=3, stroke=STROKE)
    role = ds.role.astype(object)  # ds.role is "<U5": "holdout" would be cut to "holdo"
    role[-4:] = "holdout"
    cfg = load_preset("sweep")
    assert cfg.protocol.stroke == STROKE
    from dataclasses import replace

    ds = replace(ds, role=role, base_config=config_json(cfg))
    ds_path = write_dataset(tmp / "ds.h5", ds)
    ds = read_dataset(ds_path)
    res = train_ensemble(ds, 2, TrainConfig(epochs=12, seed=0), progress=False)
    model = SurrogateModel.from_training(res, ds)
    model.info["metrics"] = {"test": model_metrics(model, ds, res[0].rows["test"])}
    model_path = model.save(tmp / "model.pt")
    return tmp, ds_path, model_path


def _refinement(setup, out, **kw):
    _tmp, ds_path, model_path = setup
    cfg = kw.pop("cfg", RefineConfig(budget=4, batch=2, tol=1e-6, epochs=6, workers=1,
                                     candidates=500))
    return Refinement(model_path, ds_path, out, target_row=kw.pop("row", 41), cfg=cfg,
                      optimiser=OptimiserConfig(iterations=40, restarts=2),
                      posterior=PosteriorConfig(walkers=20, steps=160, burn=80),
                      progress=False, task=_fake_task, pack=_fake_pack, **kw)


@pytest.fixture(scope="module")
def refined(setup):
    tmp = setup[0]
    CALLS.clear()
    state = _refinement(setup, tmp / "out").run()
    return tmp / "out", state, list(CALLS)


def test_refinement_spends_the_budget_in_rounds_and_records_them(refined, setup):
    out, state, calls = refined
    assert state["status"] == "done" and "budget spent" in state["stop_reason"]
    assert [r["round"] for r in state["rounds"]] == [0, 1, 2]
    assert state["runs_done"] == state["runs_spent"] == 4 and len(calls) == 4
    assert (out / "refine.png").is_file() and (out / "base.json").is_file()
    ds2 = read_dataset(out / "rounds" / "r02" / "dataset.h5")
    ds0 = read_dataset(setup[1])
    ref = ds2.role == "refine"
    assert ref.sum() == 4 and len(ds2) == len(ds0) + 4
    np.testing.assert_array_equal(ds2.params[~ref], ds0.params)
    pts = np.vstack([read_design_csv(out / "rounds" / f"r0{r}" / f"refine-r0{r}.csv")
                     for r in (1, 2)])
    np.testing.assert_allclose(ds2.params[ref], pts, rtol=1e-12)
    # every new run on a bed of its own, on seeds the dataset never used
    assert sorted(ds2.seed[ref].tolist()) == [4, 5, 6, 7] and set(ds0.seed.tolist()) == {3}
    # the first point of round 1 is round 0's optimum (its free coordinates)
    r0 = state["rounds"][0]
    np.testing.assert_allclose(PAPER_SPACE.to_unit(pts[:1])[0], r0["optimum_unit"], atol=1e-9)
    # a twin: the truth is known and recorded in every round
    truth = ds0.params[41]
    for r in state["rounds"]:
        assert set(r["truth"]) == set(PAPER_SPACE.names)
        np.testing.assert_allclose([r["truth"][n]["truth"] for n in PAPER_SPACE.names], truth)


def test_the_error_is_measured_before_training_and_enters_the_likelihood(refined, setup):
    """Round r's error is that of round r-1's model on round r's new runs; the likelihood of
    round r uses the root mean square of every such per-run error so far."""
    import surrogate

    out, state, _ = refined
    ds2 = read_dataset(out / "rounds" / "r02" / "dataset.h5")
    models = [surrogate.load(setup[2]), surrogate.load(out / "rounds" / "r01" / "model.pt")]
    sq = []
    for r in (1, 2):
        err = json.loads((out / "rounds" / f"r0{r}" / "error.json").read_text())
        ids = [x["run_id"] for x in err["rows"]]
        rows = np.nonzero(np.isin(ds2.run_id, ids))[0]
        m = models[r - 1]
        pred = m.predict(ds2.params[rows])
        rmse = np.sqrt(np.mean((pred.pressure_normalised
                                - m.normalise_pressure(ds2.pressure[rows])) ** 2, axis=1))
        by_id = dict(zip(ds2.run_id[rows], rmse, strict=True))
        for x in err["rows"]:
            assert x["pressure_rmse_normalised"] == pytest.approx(by_id[x["run_id"]],
                                                                  rel=1e-5)
        sq += [v**2 for v in rmse]
        sigma = float(np.sqrt(np.mean(sq)))
        rec = state["rounds"][r]
        assert rec["model_error_sigma"] == pytest.approx(sigma, rel=1e-5)
        cal = json.loads((out / "rounds" / f"r0{r}" / "calibration.json").read_text())
        assert cal["posterior"]["config"]["model_error_sigma"] == pytest.approx(sigma,
                                                                                rel=1e-5)
    # round 0 used the model's recorded held-out RMSE
    m0 = models[0]
    s0 = np.sqrt(m0.info["metrics"]["test"]["pressure"]["pressure_mse_normalised"])
    assert state["rounds"][0]["model_error_sigma"] == pytest.approx(s0)
    # the retrained model has trained on the refine rows (they are in its training split)
    m1 = models[1]
    assert set(ds2.run_id[ds2.role == "refine"][:2]) <= set(m1.info["split"]["train"])


def test_a_rerun_resumes_without_redoing_finished_steps(refined, setup):
    out, state, _ = refined
    CALLS.clear()
    again = _refinement(setup, out).run()
    assert CALLS == [] and again["rounds"] == state["rounds"]
    # a kill after round 2's runs: its model, calibration and record are redone, no DEM run
    d = out / "rounds" / "r02"
    for name in ("model.pt", "calibration.json", "posterior.npz", "round.json"):
        (d / name).unlink()
    again = _refinement(setup, out).run()
    assert CALLS == [] and (d / "model.pt").is_file()
    assert again["rounds"][2]["points"] == state["rounds"][2]["points"]
    assert again["runs_done"] == 4


def test_a_larger_budget_goes_on_and_another_request_is_refused(refined, setup, tmp_path):
    out, _, _ = refined
    with pytest.raises(ConfigError, match="refine_weight"):
        _refinement(setup, out, cfg=RefineConfig(budget=4, batch=2, tol=1e-6, epochs=6,
                                                 workers=1, candidates=500,
                                                 refine_weight=3)).run()
    with pytest.raises(ConfigError, match="target"):
        _refinement(setup, out, row=40).run()
    copy = tmp_path / "more"
    shutil.copytree(out, copy)
    CALLS.clear()
    more = _refinement(setup, copy, cfg=RefineConfig(budget=6, batch=2, tol=1e-6, epochs=6,
                                                     workers=1, candidates=500)).run()
    assert len(CALLS) == 2 and [r["round"] for r in more["rounds"]] == [0, 1, 2, 3]


def test_a_retrained_identical_model_resumes_the_refinement(refined, setup, tmp_path):
    """The request holds the model's weights fingerprint, not its file hash: the same
    weights in a new file (a model retrained on a fresh machine) resume the folder without
    a DEM run."""
    from surrogate.checkpoint import read_checkpoint, write_checkpoint

    out, state, _ = refined
    tmp, ds_path, model_path = setup
    obj = read_checkpoint(model_path)
    obj["created"] = "2000-01-01T00:00:00+00:00"
    retrained = write_checkpoint(tmp_path / "retrained.pt", obj)
    assert retrained.read_bytes() != model_path.read_bytes()
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    before = json.loads((copy / "refine.json").read_text())  # as earlier tests left it
    assert len(before["rounds"]) == len(state["rounds"])
    CALLS.clear()
    again = _refinement((tmp, ds_path, retrained), copy).run()
    assert CALLS == [] and again["rounds"] == before["rounds"]


def test_the_twins_recalibrate_every_round_at_a_given_observation_sigma(refined, setup,
                                                                       tmp_path):
    """`benchmarks/refine_twins.py recalibrate`: each finished round's model again, with a
    smaller observation sigma, kept beside the round and reported; a rerun skips them."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "_refine_twins", Path(__file__).parents[2] / "benchmarks" / "refine_twins.py")
    twins = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(twins)
    out, state, _ = refined
    _tmp, ds_path, _model = setup
    folder = tmp_path / "twins" / "twin-row0041"
    shutil.copytree(out, folder)
    argv = ["recalibrate", "--out", str(folder.parent), "--dataset", str(ds_path),
            "--sigma", "0.002", "--name", "t", "--results-dir", str(tmp_path)]
    assert twins.main(argv) == 0
    rep = json.loads((tmp_path / "t.json").read_text())
    assert [r["round"] for r in rep["per_round"]] == [r["round"] for r in state["rounds"]]
    from calendaring import pressure_components, read_dataset

    pc = pressure_components(read_dataset(ds_path))
    assert (rep["pressure_components"] or {}).get("resolved") == (pc or {}).get("resolved")
    for r, row in zip(state["rounds"], rep["per_round"], strict=True):
        rec = json.loads((folder / "rounds" / f"r{r['round']:02d}"
                          / "recalibration-floor.json").read_text())
        assert rec["observation_sigma_normalised"] == 0.002
        assert rec["model_error_sigma"] == r["model_error_sigma"]
        assert row["floor_sigma"]["mean_width_unit"] == rec["mean_width_unit"]
        assert set(rec["truth"]) == set(r["truth"])
        assert 0 < row["mean_width_se_unit"] < row["mean_width_unit"]
    # per twin and round: the same figures, the width's sampling error kept beside the round
    (twin,) = rep["twins"]
    assert [x["round"] for x in twin["per_round"]] == [r["round"] for r in state["rounds"]]
    for r, x in zip(state["rounds"], twin["per_round"], strict=True):
        assert x["mean_width_unit"] == r["mean_width_unit"]
        assert x["truths_inside"] == sum(v["inside_ci90"] for v in r["truth"].values())
        assert x["floor"]["mean_width_unit"] == json.loads(
            (folder / "rounds" / f"r{r['round']:02d}" / "recalibration-floor.json")
            .read_text())["mean_width_unit"]
        assert (x["out_of_sample"] is None) == (r["round"] == 0)
    assert (tmp_path / "t.png").stat().st_size > 0
    assert "| 41 | 0 |" in (tmp_path / "t.md").read_text()
    se = [x["mean_width_se_unit"] for x in twin["per_round"]]
    stamp = {p: p.stat().st_mtime_ns for p in folder.glob("rounds/*/recalibration-floor.json")}
    assert twins.main(argv) == 0  # nothing recalibrated twice
    assert {p: p.stat().st_mtime_ns for p in stamp} == stamp
    assert twins.main([*argv[:-6], "--sigma", "0", *argv[-4:]]) == 2
    assert twins.main([*argv[:-6], "--sigma", "0.004", *argv[-4:]]) == 0  # another sigma
    assert all(p.stat().st_mtime_ns != t for p, t in stamp.items())
    assert json.loads(next(iter(stamp)).read_text())["observation_sigma_normalised"] == 0.004
    # --perfect: no surrogate error at all, kept in its own file beside the floor's
    floor = {p: p.stat().st_mtime_ns for p in stamp}
    assert twins.main([*argv, "--perfect"]) == 0
    assert {p: p.stat().st_mtime_ns for p in floor} == floor
    rep = json.loads((tmp_path / "t.json").read_text())
    for r, row in zip(state["rounds"], rep["per_round"], strict=True):
        rec = json.loads((folder / "rounds" / f"r{r['round']:02d}"
                          / "recalibration-perfect.json").read_text())
        assert rec["kind"] == "perfect" and rec["model_error_sigma"] == 0.0
        assert rec["use_model_variance"] is False
        assert row["perfect_surrogate"]["mean_width_unit"] == rec["mean_width_unit"]
        assert row["floor_sigma"]["model_error_sigma_mean"] == r["model_error_sigma"]
    assert "A perfect surrogate" in (tmp_path / "t.md").read_text()
    for x in rep["twins"][0]["per_round"]:
        rec = json.loads((folder / "rounds" / f"r{x['round']:02d}"
                          / "recalibration-perfect.json").read_text())
        assert x["perfect"]["truths_inside"] == sum(v["inside_ci90"]
                                                    for v in rec["truth"].values())
    for npz in folder.glob("rounds/*/posterior.npz"):
        npz.unlink()  # the samples are not kept; a later report takes the kept error
    assert twins.main(["report", "--out", str(folder.parent), "--name", "t",
                       "--results-dir", str(tmp_path)]) == 0
    again = json.loads((tmp_path / "t.json").read_text())
    assert [x["mean_width_se_unit"] for x in again["twins"][0]["per_round"]] == se
    assert None not in se


def test_one_given_dem_seed_puts_every_new_run_on_one_bed(setup, tmp_path):
    state = _refinement(setup, tmp_path / "one", cfg=RefineConfig(
        budget=2, batch=1, tol=1e-6, epochs=4, workers=1, candidates=500, dem_seed=9)).run()
    ds = read_dataset(tmp_path / "one" / "rounds" / "r02" / "dataset.h5")
    assert state["runs_done"] == 2 and ds.seed[ds.role == "refine"].tolist() == [9, 9]
    assert state["request"]["distinct_beds"] is False


def test_sweep_plan_gives_each_row_its_own_seed_on_request():
    from calendaring.data.sweep import plan

    _, _, same = plan("preset:tiny", {}, "lhs", 3, 0, 10, 2, "train")
    _, _, own = plan("preset:tiny", {}, "lhs", 3, 0, 10, 2, "train", seed_per_row=True)
    assert [e.seed for e in same] == [10, 11] * 3
    assert [e.seed for e in own] == [10, 11, 12, 13, 14, 15]
    assert len({e.packing for e in own}) == 6 and len({e.packing for e in same}) == 2
    _, _, turns = plan("preset:tiny", {}, "lhs", 5, 0, 10, 1, "train", beds=2)
    assert [e.seed for e in turns] == [10, 11, 10, 11, 10]
    _, _, turns = plan("preset:tiny", {}, "lhs", 3, 0, 10, 2, "train", beds=2)
    assert [e.seed for e in turns] == [10, 11, 12, 13, 10, 11]
    with pytest.raises(ConfigError, match="--beds"):
        plan("preset:tiny", {}, "lhs", 3, 0, 10, 1, "train", seed_per_row=True, beds=2)


def test_a_twin_must_be_a_row_the_model_never_trained_on(setup, tmp_path):
    with pytest.raises(ConfigError, match="never trained on"):
        _refinement(setup, tmp_path / "x", row=0)


def test_select_points_spreads_out_and_avoids_earlier_points():
    rng = np.random.default_rng(0)
    samples = np.column_stack([0.5 + 0.01 * rng.standard_normal(5000),
                               0.5 + 0.2 * rng.standard_normal(5000)])
    first = np.array([0.5, 0.5])
    pts, info = select_points(samples, 5, first=first, seed=1)
    np.testing.assert_array_equal(pts[0], first)
    z = pts / np.array(info["scale_unit"])
    d = np.linalg.norm(z[:, None] - z[None], axis=-1)[np.triu_indices(5, 1)]
    # spread in both directions, scaled by the posterior's own widths
    assert d.min() > 1.0 and np.ptp(pts[:, 0]) > 0.02 and np.ptp(pts[:, 1]) > 0.4
    # random posterior draws crowd together far more often
    rand = samples[rng.choice(5000, 5)] / np.array(info["scale_unit"])
    dr = np.linalg.norm(rand[:, None] - rand[None], axis=-1)[np.triu_indices(5, 1)]
    assert d.min() > dr.min()
    more, info2 = select_points(samples, 3, chosen=pts, seed=2)
    zz = more / np.array(info["scale_unit"])
    assert np.min(np.linalg.norm(zz[:, None] - z[None], axis=-1)) > 0.5
    assert info2["earlier_points"] == 5
    with pytest.raises(ConfigError):
        select_points(samples[:2], 3)


def test_interval_change_is_the_largest_move_of_an_interval_end():
    a = {"x": {"ci90_unit": [0.1, 0.5]}, "y": {"ci90_unit": [0.2, 0.3]}}
    b = {"x": {"ci90_unit": [0.15, 0.45]}, "y": {"ci90_unit": [0.2, 0.42]}}
    assert interval_change(a, b) == pytest.approx(0.12)


def test_refine_config_rejects_bad_values():
    for kw, key in (({"budget": 0, "batch": 1}, "--budget"),
                    ({"budget": 2, "batch": 3}, "--batch"),
                    ({"budget": 2, "batch": 1, "tol": 0.0}, "--tol"),
                    ({"budget": 2, "batch": 1, "refine_weight": 0}, "--refine-weight")):
        with pytest.raises(ConfigError, match=key):
            RefineConfig(**kw)


def test_append_runs_keeps_the_dataset_processing_and_refuses_foreign_runs(refined, setup,
                                                                         tmp_path):
    out, _, _ = refined
    ds0 = read_dataset(setup[1])
    ds = append_runs(ds0, out / "runs", role="refine")
    np.testing.assert_array_equal(ds.load_edges, ds0.load_edges)
    np.testing.assert_array_equal(ds.depth, ds0.depth)
    assert (ds.role[len(ds0):] == "refine").all() and ds.n_events[len(ds0):].min() == N_EVENTS
    c = np.cbrt(ds.pressure)
    assert ds.cbrt_min == pytest.approx(c.min()) and ds.cbrt_max == pytest.approx(c.max())
    with pytest.raises(DatasetError, match="already in the dataset"):
        append_runs(ds, out / "runs")
    # a run of another problem (another cell) is refused, naming it
    foreign = tmp_path / "foreign"
    shutil.copytree(out / "runs", foreign)
    src = json.loads((out / "base.json").read_text())
    src["domain"]["cell_x"] *= 2
    (foreign / "other.json").write_text(json.dumps(src))
    entry = {"run_id": "x", "file": "runs/x.h5", "source": str(foreign / "other.json"),
             "overrides": {}, "params": dict(zip(PAPER_SPACE.names, ds0.params[0],
                                                 strict=True)), "seed": 0}
    _fake_task(str(foreign), entry, "", 1, None)
    with pytest.raises(DatasetError, match="another problem"):
        append_runs(ds0, foreign, names=["x"])


def test_the_command_line_refines_and_prints_the_rounds(setup, tmp_path, monkeypatch, capsys):
    import calendaring.data.sweep as sweep_module
    import inverse.cli as cli

    monkeypatch.setattr(sweep_module, "run_task", _fake_task)
    monkeypatch.setattr(sweep_module, "pack_task", _fake_pack)
    _tmp, ds_path, model_path = setup
    common = ["refine", "--model", str(model_path), "--dataset", str(ds_path),
              "--target-row", "42", "--iterations", "40", "--restarts", "2", "--walkers", "20",
              "--steps", "160", "--burn", "80", "--epochs", "4", "--workers", "1", "--quiet"]
    rc = cli.main([*common, "--budget", "2", "--batch", "1", "--out", str(tmp_path / "a")])
    out = capsys.readouterr().out
    assert rc == 0, out
    state = json.loads((tmp_path / "a" / "refine.json").read_text())
    assert state["runs_done"] == 2 and len(state["rounds"]) == 3
    assert "budget spent" in out and out.count("\n") >= 5
    for args, needle in ((["--budget", "2", "--batch", "3"], "--batch"),
                         (["--budget", "0", "--batch", "1"], "--budget"),
                         (["--budget", "2", "--batch", "1", "--tol", "1.5"], "--tol")):
        rc = cli.main([*common, *args, "--out", str(tmp_path / "bad")])
        assert rc == 2 and needle in capsys.readouterr().err
        assert not (tmp_path / "bad" / "refine.json").exists()
    rc = cli.main([*[a if a != "42" else "0" for a in common], "--budget", "2", "--batch", "1",
                   "--out", str(tmp_path / "bad")])
    assert rc == 2 and "never trained on" in capsys.readouterr().err


def test_retrain_keeps_a_gp_pressure_head_refitted_on_the_refine_rows():
    """A surrogate whose pressure comes from the PCA + GP head retrains into one: the GP is
    refitted on the training and validation rows plus every refine row, counted
    ``refine_weight`` times (duplicated inputs are fine with its white-noise term), and it
    reproduces the new runs better than the initial model, which never saw them."""
    from dataclasses import replace

    import torch

    from inverse.refine import ROLE, retrain
    from surrogate import SurrogateModel, TrainConfig, train_ensemble

    torch.set_num_threads(1)
    ds = synthetic_dataset(40, seed=5, stroke=STROKE)
    role = ds.role.astype(object)
    role[-4:] = ROLE
    ds = replace(ds, role=role)
    model = SurrogateModel.from_training(
        train_ensemble(ds, 2, TrainConfig(epochs=6, seed=0, pressure_head="gp"),
                       progress=False), ds)
    assert model.pressure_head == "gp" and model.info["pressure_gp"]["n_rows"] == \
        len(model.info["split"]["train"]) + len(model.info["split"]["val"])
    new, seconds = retrain(model, ds, epochs=6, refine_weight=2)
    ref = np.nonzero(ds.role == ROLE)[0]
    assert new.pressure_head == "gp" and new.n_members == 2 and seconds > 0
    assert new.info["pressure_gp"]["n_rows"] == \
        model.info["pressure_gp"]["n_rows"] + 2 * len(ref)

    def err(m):
        pred = m.predict(ds.params[ref]).pressure_normalised
        return float(np.mean((pred - m.normalise_pressure(ds.pressure[ref])) ** 2))

    assert err(new) < 0.5 * err(model)


def test_the_width_standard_error_matches_the_spread_of_independent_draws():
    """`refine_twins.width_standard_error` from one chain against the spread of the mean 90 %
    width over many independent chains of the same size (independent samples: the walker
    split is then exact up to its own sampling error, 3 degrees of freedom)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "_refine_twins", Path(__file__).parents[2] / "benchmarks" / "refine_twins.py")
    twins = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(twins)
    rng = np.random.default_rng(3)
    steps, walkers, dims = 400, 32, 3

    def mean_width(x):
        q = np.quantile(x, [0.05, 0.95], axis=0)
        return np.mean(q[1] - q[0])

    draws = [mean_width(rng.normal(size=(steps * walkers, dims))) for _ in range(300)]
    truth = np.std(draws, ddof=1)
    est = [twins.width_standard_error(rng.normal(size=(steps * walkers, dims)), walkers)
           for _ in range(40)]
    assert 0.6 < np.sqrt(np.mean(np.square(est))) / truth < 1.5
    # walkers stuck at their own values: the chain holds 32 samples, not 12,800, and the
    # walker split (unlike a split by time) sees it
    truth_stuck = np.std([mean_width(rng.normal(size=(walkers, dims))) for _ in range(300)],
                         ddof=1)
    est = [twins.width_standard_error(np.repeat(rng.normal(size=(1, walkers, dims)), steps,
                                                axis=0).reshape(-1, dims), walkers)
           for _ in range(40)]
    assert truth_stuck > 4 * truth
    assert 0.5 < np.sqrt(np.mean(np.square(est))) / truth_stuck < 2.0
