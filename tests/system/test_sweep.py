"""Sweeps on a Dask LocalCluster with the tiny preset: end to end, failures, resume after
SIGKILL, and the dataset built from the run files.

The runs are the tiny preset shortened to a 2.5 um stroke at parameters that break early
(about 10-30 s per run on one thread); the packing is settled once per folder.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from calendaring.data.dataset import build_dataset, read_dataset, write_dataset
from calendaring.data.sweep import SweepOptions, read_manifest, run_task, sweep
from calendaring.process.runfile import read_run

ROOT = Path(__file__).resolve().parents[2]
OVERRIDES = {"protocol.stroke": 2.5e-6, "protocol.snapshot_depths": [0.0, 2.5e-6]}
SETS = ["--set", "protocol.stroke=2.5e-6", "--set", "protocol.snapshot_depths=[0.0, 2.5e-6]"]
# weak particles: low E_inf, d0 and phi put E50 near its floor, so the short stroke breaks some
DESIGN = ("damage_constant,e_inf,d0,phi,sigma_e,alpha_percentage,b_prime,truncation_ratio\n"
          "5.0,1500.0,4e-06,0.1,0.9,34.0,0.03,90.0\n"
          "9.0,1600.0,4.5e-06,0.2,0.5,60.0,0.05,85.0\n"
          "2.0,1550.0,4e-06,0.15,0.7,25.0,0.02,95.0\n")


def _fail_index_1(folder, entry, packing, threads, timeout):
    """A task that fails for design row 1 (an injected failing run) and runs the others."""
    if entry["index"] == 1:
        return {"status": "failed", "wall_time": 0.0, "reused": False,
                "error": "injected failure: the run stopped on a guard"}
    return run_task(folder, entry, packing, threads, timeout)


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep")
    design = out / "design.csv"
    design.write_text(DESIGN)
    opt = SweepOptions(source="preset:tiny", out=out / "runs", design=str(design),
                       overrides=OVERRIDES, workers=2, max_attempts=1, progress=False)
    runs = sweep(opt, task=_fail_index_1)
    return out, opt, runs


def test_sweep_end_to_end_with_an_injected_failure(swept):
    _out, opt, runs = swept
    folder = opt.out
    assert len(runs) == 3
    by_index = {e.index: e for e in runs.values()}
    assert by_index[1].status == "failed" and "injected failure" in by_index[1].error
    for i in (0, 2):
        e = by_index[i]
        assert e.status == "done", e.error
        assert e.attempts == 1 and e.wall_time > 0
        rec = read_run(folder / e.file)
        for k, v in e.params.items():  # each run ran at its own design row
            assert getattr(rec.config.breakage, k) == v
        assert rec.config.electrode.packing.endswith(f"{e.packing}.csv")
    # both runs share one settled bed: identical particles at the start of calendering
    a, b = (read_run(folder / by_index[i].file).snapshots[0] for i in (0, 2))
    np.testing.assert_array_equal(a.radius, b.radius)
    assert len(list((folder / "packings").glob("*.csv"))) == 1
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["counts"] == {"pending": 0, "running": 0, "done": 2, "failed": 1}
    assert (folder / "designs" / "design.json").exists()


def test_rerun_skips_done_and_gives_up_after_max_attempts(swept):
    _out, opt, runs = swept
    mtimes = {e.run_id: (opt.out / e.file).stat().st_mtime_ns
              for e in runs.values() if e.status == "done"}
    calls = []

    def task(*a):
        calls.append(a[1]["run_id"])
        return _fail_index_1(*a)

    again = sweep(opt, task=task)  # max_attempts = 1: the failed run is not retried
    assert calls == []
    for rid, m in mtimes.items():
        assert (opt.out / again[rid].file).stat().st_mtime_ns == m
        assert again[rid].attempts == 1


def test_dataset_from_the_sweep(swept, tmp_path):
    _out, opt, runs = swept
    (opt.out / "runs" / "not-a-run.h5").write_bytes(b"garbage")
    try:
        ds = build_dataset(opt.out, progress=False)
    finally:
        (opt.out / "runs" / "not-a-run.h5").unlink()
    assert len(ds) == 2
    assert [s[0] for s in ds.skipped] == ["not-a-run.h5"]
    assert ds.pressure.shape == (2, 196) and ds.histogram.shape == (2, 30, 30)
    assert np.all(ds.n_events > 0)
    np.testing.assert_allclose(ds.histogram.sum(axis=(1, 2)), 1.0, rtol=1e-12)
    # the stored transforms invert to the smoothed pressures in Pa
    path = write_dataset(tmp_path / "ds.h5", ds)
    back = read_dataset(path)
    np.testing.assert_allclose(back.pressure_from_normalised(back.pressure_normalised),
                               ds.pressure, rtol=1e-9, atol=1e-3)
    # raw points are the interval means of each run's recorded trace
    rec = read_run(opt.out / runs[back.run_id[0]].file)
    z = rec.pressure["depth"]
    sel = (z > 0) & (z <= back.depth[1] + 0.5 * (back.depth[1] - back.depth[0]))
    assert back.pressure_raw[0, 1] == pytest.approx(
        np.mean(rec.pressure["value"][sel & (z > back.depth[0] + (back.depth[1] -
                                                                   back.depth[0]) / 2)]),
        rel=0.05)
    # the event histogram counts every breakage event of the run
    assert back.n_events[0] == len(rec.breakage["peak_load"])


def test_dataset_cli_writes_the_provenance(swept, tmp_path):
    _out, opt, runs = swept
    from calendaring._version import source_commit

    cmd = [sys.executable, "-m", "calendaring.cli", "dataset", str(opt.out), "--quiet"]
    for bad in (["no-equals-sign"], ["=text"], ["key= "], ["a=1", "a=2"]):
        notes = [x for note in bad for x in ("--note", note)]
        r = subprocess.run([*cmd, "--out", str(tmp_path / "bad.h5"), *notes], cwd=ROOT,
                           capture_output=True, text=True)
        assert r.returncode != 0 and "--note" in r.stderr, (bad, r.stderr)
        assert not (tmp_path / "bad.h5").exists()
    r = subprocess.run([*cmd, "--out", str(tmp_path / "ds.h5"), "--note",
                        "engine=the commit of every run"], cwd=ROOT, capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr
    prov = json.loads((tmp_path / "ds.provenance.json").read_text())
    # every run records the commit that ran it (the same checkout as this test's)
    assert prov["source_commits"] == {source_commit() or "unrecorded": 2}
    assert prov["notes"] == {"engine": "the commit of every run"}
    assert prov["sweep"]["train"]["done"] == 2 and prov["sweep"]["train"]["failed"] == 1
    assert prov["software_version"] and "calendaring dataset" in prov["command"]
    assert prov["sweep"]["train"]["wall_seconds_total"] > 0
    assert [f[0] for f in prov["failed_runs"]] == [e.run_id for e in runs.values()
                                                    if e.status == "failed"]
    assert read_dataset(tmp_path / "ds.h5").fingerprint == prov["dataset_fingerprint"]
    assert prov["pressure_components"] is None  # no replicate group to set them against


@pytest.mark.slow  # a killed run resumed: the slow tier
def test_resume_after_the_sweep_is_killed(swept, tmp_path):
    out, _, _ = swept
    folder = tmp_path / "killed"
    (folder / "packings").mkdir(parents=True)
    for p in (out / "runs" / "packings").glob("*.csv"):  # reuse the settled bed
        shutil.copy(p, folder / "packings" / p.name)
    design = out / "design.csv"
    cmd = [sys.executable, "-m", "calendaring.cli", "sweep", "--preset", "tiny", *SETS,
           "--design", str(design), "--workers", "1", "--quiet", "--out", str(folder)]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.time() + 240
    first = None
    while time.time() < deadline and first is None:
        time.sleep(0.5)
        if (folder / "manifest.json").exists():
            done = [e for e in read_manifest(folder).values() if e.status == "done"]
            first = done[0] if done else None
        assert proc.poll() is None, "the sweep ended before it could be killed"
    assert first is not None, "no run finished within 240 s"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    t_first = (folder / first.file).stat().st_mtime_ns
    man = read_manifest(folder)
    assert sum(e.status == "done" for e in man.values()) < 3
    time.sleep(1.0)  # an orphaned child would still be writing; children die with the sweep
    assert not any(folder.joinpath("runs").glob(".*.tmp-*"))
    opt = SweepOptions(source="preset:tiny", out=folder, design=str(design),
                       overrides=OVERRIDES, workers=2, progress=False)
    runs = sweep(opt)
    assert all(e.status == "done" for e in runs.values()), [e.error for e in runs.values()]
    assert (folder / first.file).stat().st_mtime_ns == t_first  # not run again
    assert runs[first.run_id].attempts == 1


def test_sweep_cli_rejects_bad_input(tmp_path):
    def run(*args):
        return subprocess.run([sys.executable, "-m", "calendaring.cli", "sweep", *args],
                              cwd=ROOT, capture_output=True, text=True)

    r = run("--preset", "tiny", "--design", "latin", "--out", str(tmp_path / "a"))
    assert r.returncode == 2 and "--design = 'latin'" in r.stderr
    r = run("--preset", "tiny", "--role", "test", "--out", str(tmp_path / "a"))
    assert r.returncode == 2 and "--role = 'test'" in r.stderr
    r = run("--preset", "tiny", "--replicates", "0", "--out", str(tmp_path / "a"))
    assert r.returncode == 2 and "--replicates: 0 is invalid" in r.stderr
    (tmp_path / "file").write_text("x")
    r = run("--preset", "tiny", "--out", str(tmp_path / "file"))
    assert r.returncode == 2 and "a folder" in r.stderr
    r = subprocess.run([sys.executable, "-m", "calendaring.cli", "dataset", str(tmp_path),
                        "--out", str(tmp_path / "d.h5")], cwd=ROOT, capture_output=True,
                       text=True)
    assert r.returncode == 2 and "no usable run files" in r.stderr
    assert not (tmp_path / "d.h5").exists()


def test_the_sweep_resumes_from_digests_alone(swept, tmp_path):
    """A fresh machine with only the sweep's manifest and digests (kept in the repository):
    the finished runs are not run again and the dataset is the same."""
    _out, opt, runs = swept
    done = [e for e in runs.values() if e.status == "done"]
    for e in done:
        assert (opt.out / "digests" / f"{Path(e.file).stem}.h5").exists()
    fresh = tmp_path / "fresh"
    (fresh / "designs").mkdir(parents=True)
    shutil.copytree(opt.out / "digests", fresh / "digests")
    shutil.copy(opt.out / "manifest.json", fresh / "manifest.json")
    calls = []

    def task(*a):
        calls.append(a[1]["run_id"])
        return _fail_index_1(*a)

    again = sweep(replace(opt, out=fresh), task=task)
    assert calls == []  # the failed run has used its one attempt; the others are done
    assert {e.run_id for e in again.values() if e.status == "done"} == {e.run_id for e in done}
    a, b = build_dataset(opt.out, progress=False), build_dataset(fresh, progress=False)
    np.testing.assert_allclose(b.pressure_raw, a.pressure_raw, rtol=1e-12)
    np.testing.assert_array_equal(b.histogram, a.histogram)
    assert list(b.run_id) == list(a.run_id)
