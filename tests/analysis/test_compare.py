"""The comparison studies: the run plan (Table 5), and R0 vs R1 on the tiny preset.

``test_r0_r1_tiny_*`` run two real ``calendaring run`` subprocesses (tiny preset, stroke
shortened to 1.3 um, where seed 0 breaks a first particle at 1.05 um; 15-30 s each, two at
a time): the slowest tests of the analysis suite, marked ``slow`` (deselect them with
``-m "not slow"``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from analysis.compare import PSD_CASES, TABLE5, compare, plan, run_command
from calendaring.core.errors import ConfigError

TINY_SETS = ["protocol.stroke=1.3e-6", "protocol.snapshot_depths=[0.0, 1.3e-6]",
             "numerics.threads=1"]


def test_plan_sets_table5_distributions():
    cases = {c.name: c for c in plan(["r0r1", "psd"], "quick")}
    assert list(cases) == ["R1", "R0", *PSD_CASES]
    assert cases["R0"].no_breakage and not cases["R1"].no_breakage
    assert cases["R1"].sets == {} and cases["R1"].studies == ["r0r1", "psd"]
    for name in PSD_CASES:
        s = cases[name].sets
        mean, std = TABLE5[name][:2]
        assert s["electrode.sizes.AM.mean"] == mean and s["electrode.sizes.AM.std"] == std
        # the baseline's truncation, N(7.74, 1.35) in [4.94, 10.69] um, in units of sigma
        assert (mean - s["electrode.sizes.AM.min"]) / std == pytest.approx(2.80 / 1.35)
        assert (s["electrode.sizes.AM.max"] - mean) / std == pytest.approx(2.95 / 1.35)
    # R5's largest diameter (16.4 um) needs a cell wider than the quick preset's 30 um
    assert cases["R5"].sets["domain.cell_x"] > 30e-6
    assert "domain.cell_x" not in cases["C1"].sets
    cmd = run_command(cases["R0"], Path("x.h5"), "quick", 7)
    assert cmd[cmd.index("--seed") + 1] == "7" and "--no-breakage" in cmd
    cmd = run_command(cases["C1"], Path("x.h5"), "quick", 7, ["protocol.stroke=1e-6"])
    assert "electrode.sizes.AM.std=1.081e-06" in cmd and "protocol.stroke=1e-6" in cmd


def test_plan_bad_input():
    with pytest.raises(ConfigError, match="--studies"):
        plan(["r0r1", "nonsense"], "quick")
    with pytest.raises(ConfigError, match="--preset"):
        plan(["r0r1"], "huge")


@pytest.fixture(scope="module")
def tiny_r0r1(tmp_path_factory):
    out = tmp_path_factory.mktemp("compare")
    rep = compare(out, preset="tiny", studies=["r0r1"], seed=0, extra_sets=TINY_SETS, jobs=2,
                  micro=False, progress=False)
    return out, rep


@pytest.mark.slow
def test_r0_r1_tiny_share_packing_until_first_breakage(tiny_r0r1):
    """Slow (two tiny DEM runs): R0 and R1 from one seed are identical up to R1's first
    breakage event and differ after it."""
    from calendaring.process.runfile import read_run

    out, rep = tiny_r0r1
    assert rep["failures"] == []
    assert {r["name"]: r["status"] for r in rep["runs"]} == {"R1": "done", "R0": "done"}
    r1, r0 = read_run(out / "runs" / "R1.h5"), read_run(out / "runs" / "R0.h5")
    assert r0.breakage_model == "none" and r1.breakage_model != "none"
    assert r0.seed == r1.seed == 0
    ev = r1.breakage["depth"]
    assert len(ev) >= 1 and len(r0.breakage["depth"]) == 0
    first = float(ev.min())
    d = rep["r0r1"]
    assert d["same_initial_packing"]
    assert d["first_breakage_depth_m"] == pytest.approx(first)
    # independent check on the raw traces: bitwise equal before the first event
    before = r1.pressure["depth"] < first - 1e-12
    n = int(before.sum())
    assert n > 100
    np.testing.assert_array_equal(r1.pressure["value"][:n], r0.pressure["value"][:n])
    assert d["identical_samples"] >= n
    assert d["first_difference_depth_m"] is not None  # they do part after breakage
    assert d["first_difference_depth_m"] >= first - 1e-12
    spacing = float(np.max(np.diff(r1.pressure["depth"])))
    assert d["first_difference_depth_m"] <= first + 2 * spacing
    js = json.loads((out / "compare.json").read_text())
    assert js["summaries"]["R1"]["breakage_events"] == len(ev)
    assert (out / "r0r1_pressure.png").stat().st_size > 1000


@pytest.mark.slow
def test_r0_r1_tiny_resume_skips_existing_runs(tiny_r0r1, monkeypatch):
    out, _ = tiny_r0r1
    import analysis.compare as cmp

    def no_subprocess(*a, **k):
        raise AssertionError("a finished run was started again")

    monkeypatch.setattr(cmp.subprocess, "Popen", no_subprocess)
    rep = compare(out, preset="tiny", studies=["r0r1"], seed=0, extra_sets=TINY_SETS,
                  micro=False, progress=False)
    assert [r["status"] for r in rep["runs"]] == ["exists", "exists"]


def test_bad_override_is_bad_input(tmp_path):
    with pytest.raises(ConfigError, match=r"numerics\.nope"):
        compare(tmp_path, preset="tiny", studies=["r0r1"], extra_sets=["numerics.nope=1"],
                micro=False, progress=False)
    assert not (tmp_path / "compare.json").exists()


def test_failed_run_is_recorded_not_raised(tmp_path):
    # a run killed by the per-run time limit: the failure lands in the report
    rep = compare(tmp_path, preset="tiny", studies=["r0r1"], timeout=0.5, micro=False,
                  progress=False)
    assert len(rep["failures"]) == 2 and all(f["timed_out"] for f in rep["failures"])
    assert [r["status"] for r in rep["runs"]] == ["failed", "failed"]
    assert json.loads((tmp_path / "compare.json").read_text())["failures"]
    assert not (tmp_path / "runs" / "R1.h5").exists()
    assert "r0r1" not in rep


@pytest.mark.slow
def test_r0_r1_tiny_microstructure_table_and_cache(tiny_r0r1, monkeypatch):
    """The report takes porosity / tortuosity / D_eff from ``analyse_run`` at the snapshots
    nearest 0 and the end of the stroke, and caches them per run (a stand-in analyse_run
    here; the microstructure numbers themselves are tested with that module)."""
    micro = pytest.importorskip("analysis.microstructure")
    out, _ = tiny_r0r1
    calls = []

    class Fake:
        def __init__(self, run_file, snapshots):
            self.run_file, self.snapshots = run_file, snapshots

        def to_json(self):
            return {"snapshots": [{"index": k, "depth_m": 1e-6 * k, "voxel_porosity": 0.4 - k
                                   * 0.1, "tortuosity": 1.5 + k, "D_eff": (0.4 - k * 0.1)
                                   / (1.5 + k), "extrapolated": None}
                                  for k in self.snapshots]}

    def fake_analyse_run(run_file, snapshots=None, **kw):
        calls.append((Path(run_file).name, list(snapshots), kw))
        return Fake(run_file, snapshots)

    monkeypatch.setattr(micro, "analyse_run", fake_analyse_run)
    rep = compare(out, preset="tiny", studies=["r0r1"], seed=0, extra_sets=TINY_SETS,
                  micro=True, micro_kw={"voxels_per_diameter": 3.0}, progress=False)
    assert sorted(c[0] for c in calls) == ["R0.h5", "R1.h5"]
    assert all(c[1] == [0, 1] and c[2]["device"] == "cpu" and c[2]["voxels_per_diameter"] == 3
               for c in calls)  # snapshots at 0 and 1.3 um (the end of this stroke)
    rows = rep["microstructure"]["R1"]["table"]
    assert [r["snapshot"] for r in rows] == [0, 1]
    assert rows[1]["porosity"] == pytest.approx(0.3) and rows[1]["tortuosity"] == 2.5
    assert (out / "fig13bcd_microstructure.png").exists()
    calls.clear()
    rep2 = compare(out, preset="tiny", studies=["r0r1"], seed=0, extra_sets=TINY_SETS,
                   micro=True, micro_kw={"voxels_per_diameter": 3.0}, progress=False)
    assert calls == [] and rep2["microstructure"]["R0"]["cached"]
    # only R1's initial state (R0 starts from its packing): R0 analysed at the end only
    rep3 = compare(out, preset="tiny", studies=["r0r1"], seed=0, extra_sets=TINY_SETS,
                   micro=True, micro_kw={"voxels_per_diameter": 3.0}, progress=False,
                   initial="R1")
    assert calls[0][:2] == ("R0.h5", [1]) and len(calls) == 1 and rep3["initial"] == "R1"
    from analysis.compare import seed_metrics

    m = seed_metrics(rep3)
    assert m["R0"]["initial_tortuosity"] is None and m["R0"]["final_tortuosity"] == 2.5
    assert m["R1"]["initial_tortuosity"] == 1.5
    with pytest.raises(ConfigError, match="--initial-transport"):
        compare(out, preset="tiny", studies=["r0r1"], initial="some", progress=False)


def _fake_report(seed: int, values: dict[str, tuple[float, float, float]]) -> dict:
    """A compare() report with summaries and final-depth microstructure rows:
    ``values[case] = (porosity, tortuosity, D_eff)`` at 19.5 um."""
    rep = {"seed": seed, "failures": [], "summaries": {}, "microstructure": {}}
    for c, (por, tau, deff) in values.items():
        rep["summaries"][c] = {"final_pressure_Pa": 1e8 + seed, "peak_pressure_Pa": 1.1e8,
                               "breakage_events": 100 + seed}
        rep["microstructure"][c] = {"table": [
            {"depth_m": 0.0, "porosity": 0.42, "tortuosity": 1.5, "D_eff": 0.28},
            {"depth_m": 19.5e-6, "porosity": por, "tortuosity": tau, "D_eff": deff}]}
    return rep


def test_pool_seeds_statistics_paired_differences_and_claims():
    from scipy import stats

    from analysis.compare import pool_seeds

    rng = np.random.default_rng(0)
    reports = {}
    r1_tau = 1.9 + 0.02 * rng.standard_normal(4)
    for k, s in enumerate((0, 1, 2, 3)):
        reports[s] = _fake_report(s, {
            "R0": (0.22, r1_tau[k] + 0.35, 0.10),           # breakage lowers tau: holds
            "R1": (0.22, r1_tau[k], 0.16),
            "R4": (0.22, r1_tau[k] + 0.1 * (-1) ** k, 0.16 + 0.05 * (-1) ** k),  # unresolved
            "R5": (0.22, r1_tau[k] + 0.2, 0.13)})          # the opposite of the paper
    p = pool_seeds(reports)
    assert p["seeds"] == [0, 1, 2, 3]
    st = p["cases"]["R1"]["final_tortuosity"]
    assert st["mean"] == pytest.approx(r1_tau.mean())
    assert st["sd"] == pytest.approx(r1_tau.std(ddof=1))
    h = stats.t.ppf(0.975, 3) * r1_tau.std(ddof=1) / 2
    assert st["ci95"] == pytest.approx([r1_tau.mean() - h, r1_tau.mean() + h])
    d = p["differences"]["R1-R0"]["final_tortuosity"]
    assert d["mean"] == pytest.approx(-0.35) and d["sd"] == pytest.approx(0, abs=1e-12)
    assert d["relative"] == pytest.approx(-0.35 / (r1_tau.mean() + 0.35))
    verdicts = {c["claim"]: c["verdict"] for c in p["claims"]}
    assert verdicts["breakage lowers tortuosity at 19.5 um"] == "holds"
    assert verdicts["breakage raises D_eff at 19.5 um"] == "holds"
    assert verdicts["larger particles (R4) lower tortuosity at 19.5 um"].startswith(
        "not resolved")
    assert verdicts["larger particles (R5) lower tortuosity at 19.5 um"] == "opposite"
    assert verdicts["larger particles (R5) raise D_eff at 19.5 um"] == "opposite"
    paper = {c["claim"]: c["paper_relative_change"] for c in p["claims"]}
    assert paper["breakage lowers tortuosity at 19.5 um"] == pytest.approx(1.8976 / 2.2846 - 1)
    one = pool_seeds({0: reports[0]})
    assert all(c["verdict"] == "one seed: not resolved" for c in one["claims"])


def _with_levels(rep: dict, case: str, levels: dict[float, tuple[float, float]],
                 refine_tol: float = 0.02) -> dict:
    """Give ``case`` of a fake report the refinement levels of its final snapshot:
    ``levels[voxels per diameter] = (tortuosity, D_eff)``, and an initial snapshot without
    levels (it must not be the one read)."""
    rep["microstructure"][case]["result"] = {"settings": {"refine_tol": refine_tol}, "snapshots": [
        {"depth_m": 19.5e-6, "refinement": {"refine_tol": refine_tol, "levels": [
            {"voxels_per_diameter": v, "tortuosity": t, "D_eff": d}
            for v, (t, d) in levels.items()]}},
        {"depth_m": 0.0, "refinement": {"levels": [
            {"voxels_per_diameter": 3.0, "tortuosity": 9.0, "D_eff": 9.0}]}}]}
    return rep


def test_resolution_check_of_paired_differences():
    """The relative difference per level, its geometric tail, and convergence judged on
    what resolution may still change, not on the last step alone."""
    from analysis.compare import final_levels, pool_seeds, resolution_check

    vpd = (3.0, 4.5, 6.75)
    r1 = (2.10, 2.05, 2.02)
    reports = {}
    for s, jitter in enumerate((-0.01, 0.0, 0.01)):
        rep = _fake_report(s, {"R0": (0.22, 2.3, 0.10), "R1": (0.22, 2.0, 0.16),
                               "R5": (0.22, 2.1, 0.15)})
        # R1 / R0 - 1 = -0.10, -0.09, -0.085 (changes shrink by half): limit -0.080
        _with_levels(rep, "R1", {v: (t, 0.15) for v, t in zip(vpd, r1, strict=True)})
        _with_levels(rep, "R0", {v: (t / (1 + r), 0.15) for v, t, r
                                 in zip(vpd, r1, (-0.10 + jitter, -0.09 + jitter,
                                                  -0.085 + jitter), strict=True)})
        # R5 / R1 - 1 = 0.04, 0.05, 0.06: the changes do not shrink
        _with_levels(rep, "R5", {v: (t * (1 + r), 0.15) for v, t, r
                                 in zip(vpd, r1, (0.04, 0.05, 0.06), strict=True)})
        reports[s] = rep
    levels, tol = final_levels(reports[0], "R1")
    assert sorted(levels) == [3.0, 4.5, 6.75] and tol == 0.02
    assert levels[6.75]["tortuosity"] == pytest.approx(2.02)

    # a seed not analysed yet (a study still running) is left out of the check
    unfinished = {**reports, 3: _fake_report(3, {"R1": (0.22, 2.0, 0.16)})}
    assert resolution_check(unfinished, "R1", "R0", "tortuosity") == resolution_check(
        reports, "R1", "R0", "tortuosity")
    res = resolution_check(reports, "R1", "R0", "tortuosity")
    assert res["voxels_per_diameter"] == [3.0, 4.5, 6.75]
    assert res["relative_difference"] == pytest.approx([-0.10, -0.09, -0.085])
    assert res["last_change"] == pytest.approx(0.005)
    assert res["extrapolated"] == pytest.approx(-0.080)
    assert res["remaining"] == pytest.approx(0.005)
    assert res["ratio_change"] == pytest.approx(0.915 / 0.91 - 1)
    assert res["converged"] is True and res["tolerance"] == 0.02
    # seeds -0.095, -0.085, -0.075 at the finest level: a 95 % half-width of t * 0.01 / sqrt(3)
    from scipy import stats
    half = stats.t.ppf(0.975, 2) * 0.01 / np.sqrt(3)
    assert res["seed_ci95_half_width"] == pytest.approx(half)
    assert res["below_seed_scatter"] is True

    grow = resolution_check(reports, "R5", "R1", "tortuosity")
    assert grow["relative_difference"] == pytest.approx([0.04, 0.05, 0.06])
    assert grow["extrapolated"] is None and grow["remaining"] is None
    assert grow["converged"] is False   # every step 1 point: no sign of a limit
    assert grow["ratio_change"] < 0.02  # ... although the last step alone is small

    # only the levels every seed has count; two levels: the last change is what remains
    del reports[2]["microstructure"]["R1"]["result"]["snapshots"][0]["refinement"]["levels"][0]
    two = resolution_check(reports, "R1", "R0", "tortuosity")
    assert two["voxels_per_diameter"] == [4.5, 6.75] and two["extrapolated"] is None
    assert two["remaining"] == pytest.approx(0.005) and two["converged"] is True
    # a last change of 0.2 points: converged for a 2 % tolerance, not for 0.1 %
    for tol, expect in ((0.02, True), (0.001, False)):
        for rep in reports.values():
            levels = {v: (t * (1 + r), 0.15)
                      for v, t, r in zip(vpd, r1, (0.0, 0.0, 0.002), strict=True)}
            _with_levels(rep, "R5", levels, refine_tol=tol)
        tight = resolution_check(reports, "R5", "R1", "tortuosity")
        assert tight["tolerance"] == tol and tight["relative_difference"] == pytest.approx(
            [0.0, 0.002]) and tight["converged"] is expect
    for rep in reports.values():
        del rep["microstructure"]["R5"]["result"]
    assert resolution_check(reports, "R5", "R1", "tortuosity") is None
    pooled = pool_seeds(reports)
    claims = {c["claim"]: c for c in pooled["claims"]}
    assert claims["breakage lowers tortuosity at 19.5 um"]["resolution"]["converged"] is True
    assert claims["larger particles (R5) lower tortuosity at 19.5 um"]["resolution"] is None
    from analysis.cli import format_seeds

    text = format_seeds(pooled)
    assert ("breakage lowers tortuosity at 19.5 um: holds (here -13.0 %, paper -16.9 %; "
            "-9.0/-8.5 % at 4.5/6.75 voxels per diameter, converged") in text


def test_compare_seeds_runs_each_seed_in_its_folder(tmp_path, monkeypatch, capsys):
    import analysis.cli as cli
    import analysis.compare as cmp

    calls = []

    def fake_compare(out_dir, seed=0, **kw):
        calls.append((Path(out_dir).name, seed, kw["preset"]))
        return _fake_report(seed, {"R0": (0.22, 2.3 + 0.01 * seed, 0.10),
                                   "R1": (0.22, 1.9 + 0.02 * seed, 0.16)})

    monkeypatch.setattr(cmp, "compare", fake_compare)
    rc = cli.main(["compare", "--preset", "tiny", "--out-dir", str(tmp_path / "s"),
                   "--studies", "r0r1", "--seeds", "0", "1", "2", "--quiet"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert calls == [("seed-0", 0, "tiny"), ("seed-1", 1, "tiny"), ("seed-2", 2, "tiny")]
    pooled = json.loads((tmp_path / "s" / "seeds.json").read_text())
    assert pooled["seeds"] == [0, 1, 2] and (tmp_path / "s" / "seeds_final_transport.png").is_file()
    assert "breakage lowers tortuosity at 19.5 um: holds" in out
    rc = cli.main(["compare", "--preset", "tiny", "--out-dir", str(tmp_path / "t"),
                   "--studies", "r0r1", "--seeds", "1", "1", "--quiet"])
    assert rc == 2 and "--seeds" in capsys.readouterr().err


@pytest.mark.slow
def test_r0_r1_tiny_kept_records_replace_lost_run_files(tiny_r0r1, tmp_path, monkeypatch):
    """A fresh machine: the run files are gone, only the kept case records and analyses
    are there. The cases are not run again and the report is the same as from the run
    files; a record of another seed or setting is not taken."""
    import shutil

    import analysis.compare as cmp
    micro = pytest.importorskip("analysis.microstructure")
    out, _ = tiny_r0r1

    def fake_analyse_run(run_file, snapshots=None, **kw):
        class Fake:
            def to_json(self):
                return {"snapshots": [{"index": k, "depth_m": 1e-6 * k,
                                       "voxel_porosity": 0.4, "tortuosity": 1.5 + k,
                                       "D_eff": 0.2, "extrapolated": None}
                                      for k in snapshots]}
        return Fake()

    monkeypatch.setattr(micro, "analyse_run", fake_analyse_run)
    kw = dict(preset="tiny", studies=["r0r1"], seed=0, extra_sets=TINY_SETS,
              micro_kw={"voxels_per_diameter": 3.0}, progress=False)
    full = compare(out, **kw)
    assert (out / "runs" / "R1.record.h5").exists()  # written for a run that existed
    stamp = (out / "runs" / "R1.record.h5").stat().st_mtime_ns
    compare(out, **kw)  # a rerun beside the run files leaves the kept records as they are
    assert (out / "runs" / "R1.record.h5").stat().st_mtime_ns == stamp
    fresh = tmp_path / "fresh"
    (fresh / "runs").mkdir(parents=True)
    for f in (out / "runs").glob("R[01].*"):
        if f.name.endswith((".record.h5", ".microstructure.json")):
            shutil.copy(f, fresh / "runs" / f.name)
    rec = cmp.read_case_record(fresh / "runs" / "R1.record.h5",
                               cmp.case_key(plan(["r0r1"], "tiny")[0], "tiny", 0, TINY_SETS))
    from calendaring import read_run

    r1 = read_run(out / "runs" / "R1.h5")
    np.testing.assert_array_equal(rec["pressure"]["value"], r1.pressure["value"])
    assert rec["pressure"]["value"].dtype == np.float64
    assert cmp.read_case_record(fresh / "runs" / "R1.record.h5",
                                cmp.case_key(plan(["r0r1"], "tiny")[0], "tiny", 1,
                                             TINY_SETS)) is None

    def no_subprocess(*a, **k):
        raise AssertionError("a kept case was run again")

    monkeypatch.setattr(cmp.subprocess, "Popen", no_subprocess)
    rep = compare(fresh, **kw)
    assert [r["status"] for r in rep["runs"]] == ["kept", "kept"]
    assert rep["r0r1"] == full["r0r1"] and rep["r0r1"]["same_initial_packing"]
    for n in ("R0", "R1"):
        assert rep["summaries"][n]["breakage_events"] == full["summaries"][n]["breakage_events"]
        assert rep["summaries"][n]["curve"] == full["summaries"][n]["curve"]
        assert rep["microstructure"][n]["table"] == full["microstructure"][n]["table"]
    assert (fresh / "r0r1_pressure.png").stat().st_size > 1000
    # without its analysis a kept record is not enough: the case must run again
    (fresh / "runs" / "R0.microstructure.json").unlink()
    with pytest.raises(AssertionError, match="run again"):
        compare(fresh, **kw)
    # --no-run: what is on disk only; R0 (record without analysis) is missing, not run, not
    # analysed; beside the run files with their cached analyses nothing is recomputed
    monkeypatch.setattr(micro, "analyse_run", no_subprocess)
    part = compare(fresh, **kw, run=False)
    assert [r["status"] for r in part["runs"]] == ["kept", "missing"]
    assert part["missing"] == ["R0"] and list(part["summaries"]) == ["R1"]
    assert part["microstructure"]["R1"]["table"] == full["microstructure"]["R1"]["table"]
    again = compare(out, **kw, run=False)
    assert [r["status"] for r in again["runs"]] == ["exists", "exists"]
    assert again["r0r1"] == full["r0r1"] and again["missing"] == []
