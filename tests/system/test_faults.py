"""Fault injection: a run, a sweep and their files survive a full disk, kills in the middle
of a checkpoint write, corrupt checkpoints, a killed sweep worker and a second sweep on the
same folder; the survivors resume to the uninterrupted result (bit-identical on one thread).
"""

from __future__ import annotations

import errno
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from calendaring.process import runfile
from calendaring.process.runfile import previous_checkpoint, read_checkpoint, read_run

# the slow tier (bash scripts/test.sh --slow; CI runs it): about 4 minutes of killed,
# full-disk and resumed runs
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
SETS = ["--set", "protocol.stroke=2.5e-6", "--set", "protocol.snapshot_depths=[0.0, 2.5e-6]",
        "--set", "output.record_spacing=0.25e-6",
        "--set", "output.checkpoint_interval=1e-9"]  # a checkpoint at every record


def _args(bed: Path) -> list[str]:
    """A short run of the tiny preset from the settled ``bed``, one thread."""
    return ["run", "--preset", "tiny", "--threads", "1", "--quiet", *SETS,
            "--set", f'electrode.packing="{bed}"']


def _cli(*argv, fault: tuple[str, int] | None = None, timeout: float = 300):
    """``calendaring ARGV`` in a subprocess (one CPU thread: bit-identical runs), with the
    full disk of tests/system/faultinject.py at ``fault`` = (function, call)."""
    head = (["-m", "tests.system.faultinject", fault[0], str(fault[1])] if fault
            else ["-m", "calendaring.cli"])
    return subprocess.run([sys.executable, *head, *argv], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


def _error_lines(res) -> list[str]:
    return [line for line in res.stderr.splitlines() if "error:" in line]


def _same_run(a: Path, b: Path) -> None:
    ra, rb = read_run(a), read_run(b)
    for key in ("depth", "value", "bottom"):
        np.testing.assert_array_equal(ra.pressure[key], rb.pressure[key])
    np.testing.assert_array_equal(ra.breakage["peak_load"], rb.breakage["peak_load"])
    np.testing.assert_array_equal(ra.snapshots[-1].position, rb.snapshots[-1].position)


def _no_temporaries(folder: Path) -> None:
    assert not [p.name for p in folder.iterdir() if ".tmp-" in p.name]


@pytest.fixture(scope="module")
def bed(tmp_path_factory):
    """The settled bed every run starts from (as in a sweep: no settling per run)."""
    out = tmp_path_factory.mktemp("bed") / "bed.csv"
    res = _cli("pack", "--preset", "tiny", "--threads", "1", "--quiet", "--out", str(out))
    assert res.returncode == 0, res.stderr[-2000:]
    return out


@pytest.fixture(scope="module")
def reference(tmp_path_factory, bed):
    """The uninterrupted run every faulty one must reproduce."""
    out = tmp_path_factory.mktemp("reference") / "ref.h5"
    res = _cli(*_args(bed), "--out", str(out))
    assert res.returncode == 0, res.stderr[-2000:]
    return out


def test_disk_full_during_a_checkpoint_write(tmp_path, bed, reference):
    out = tmp_path / "run.h5"
    res = _cli(*_args(bed), "--out", str(out), fault=("write_checkpoint", 4))
    assert res.returncode == 2, res.stderr[-2000:]
    (err,) = _error_lines(res)
    assert "No space left on device while writing the checkpoint" in err
    assert "rerun with --resume" in err and str(out) in err and "Traceback" not in res.stderr
    ck = out.with_name(out.name + ".ckpt")
    assert read_checkpoint(ck)["run"].stage >= 0  # the checkpoints before are intact
    assert read_checkpoint(previous_checkpoint(ck))
    assert not out.exists()
    _no_temporaries(tmp_path)
    res = _cli(*_args(bed), "--resume", "--out", str(out))  # space freed
    assert res.returncode == 0, res.stderr[-2000:]
    _same_run(out, reference)
    assert not ck.exists() and not previous_checkpoint(ck).exists()


def test_disk_full_during_the_run_file_write_keeps_the_checkpoint(tmp_path, bed,
                                                                  reference):
    out = tmp_path / "run.h5"
    res = _cli(*_args(bed), "--out", str(out), fault=("write_run", 1))
    assert res.returncode == 2, res.stderr[-2000:]
    (err,) = _error_lines(res)
    assert "while writing the run file; the last checkpoint is kept" in err
    ck = out.with_name(out.name + ".ckpt")
    assert not out.exists() and read_checkpoint(ck)
    _no_temporaries(tmp_path)
    res = _cli(*_args(bed), "--resume", "--out", str(out))
    assert res.returncode == 0, res.stderr[-2000:]
    _same_run(out, reference)


@pytest.fixture()
def stopped_run(tmp_path, bed):
    """A run stopped before its run file with two checkpoint generations on disk."""
    out = tmp_path / "run.h5"
    res = _cli(*_args(bed), "--out", str(out), fault=("write_run", 1))
    assert res.returncode == 2, res.stderr[-2000:]
    ck = out.with_name(out.name + ".ckpt")
    assert ck.exists() and previous_checkpoint(ck).exists()
    return out, ck


def test_a_corrupt_checkpoint_is_refused_and_the_previous_one_used(stopped_run, bed,
                                                                   reference):
    out, ck = stopped_run
    raw = ck.read_bytes()
    ck.write_bytes(raw[: len(raw) // 2])  # cut short
    res = _cli(*_args(bed), "--out", str(out), "--resume")
    assert res.returncode == 0, res.stderr[-2000:]
    assert "checkpoint refused" in res.stderr
    assert "resuming from the previous checkpoint" in res.stderr
    _same_run(out, reference)


def test_no_usable_checkpoint_is_an_error_or_a_fresh_start(stopped_run, bed, reference):
    out, ck = stopped_run
    ck.write_bytes(b"\x89HDF\r\n\x1a\n" + os.urandom(4000))  # a corrupt file
    previous_checkpoint(ck).write_bytes(b"")  # an empty one
    res = _cli(*_args(bed), "--out", str(out), "--resume")
    assert res.returncode == 2
    (err,) = _error_lines(res)
    assert "a usable checkpoint of this configuration" in err
    assert str(ck) in err and str(previous_checkpoint(ck)) in err
    res = _cli(*_args(bed), "--out", str(out), "--resume", "--restart-if-unusable")
    assert res.returncode == 0, res.stderr[-2000:]
    assert "starting afresh" in res.stderr
    _same_run(out, reference)


def test_a_checkpoint_of_another_configuration_is_refused(stopped_run, bed):
    out, _ = stopped_run
    res = _cli(*_args(bed), "--set", "breakage.d0=5e-6", "--out", str(out), "--resume")
    assert res.returncode == 2 and "written by another configuration" in res.stderr


def test_kills_at_random_moments_of_checkpointing_lose_nothing(tmp_path, bed, reference):
    """SIGKILL twice while checkpoints are written all the time: a usable checkpoint
    is always there after the first, and the resumed run is the uninterrupted one."""
    out = tmp_path / "run.h5"
    ck = out.with_name(out.name + ".ckpt")
    rng = random.Random(7)
    cmd = [sys.executable, "-m", "calendaring.cli", *_args(bed), "--out", str(out)]
    kills = 0
    for _ in range(2):
        resume = ["--resume"] if (ck.exists() or previous_checkpoint(ck).exists()) else []
        t_launch = time.time()
        proc = subprocess.Popen(cmd + resume, cwd=ROOT, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        # wait for a checkpoint written by this process, then kill at a random moment
        while time.time() < t_launch + 240 and proc.poll() is None and not (
                ck.exists() and ck.stat().st_mtime > t_launch):
            time.sleep(0.02)
        time.sleep(rng.uniform(0.0, 1.5))
        if proc.poll() is not None:
            break  # finished before the kill
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        if out.exists():  # killed on its way out, after the run file was complete
            read_run(out)
            break
        kills += 1
        usable = []
        for path in (ck, previous_checkpoint(ck)):
            try:
                usable.append(read_checkpoint(path) is not None)
            except (runfile.RunFileError, FileNotFoundError):
                pass
        assert any(usable), "no usable checkpoint after a kill"
    assert kills >= 1, "the run ended before any kill"
    res = subprocess.run([*cmd, "--resume"], cwd=ROOT, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    _same_run(out, reference)
    _no_temporaries(tmp_path)


# ------------------------------------------------------------------ sweeps


def _children_writing(path: Path) -> list[int]:
    """PIDs of the processes whose command line names ``path``."""
    pids = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit() and int(proc.name) != os.getpid():
            try:
                cmdline = (proc / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if str(path).encode() in cmdline and b"run" in cmdline:
                pids.append(int(proc.name))
    return pids


@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="needs /proc")
def test_a_killed_sweep_run_is_retried_and_the_manifest_is_right(tmp_path):
    from calendaring.data.sweep import SweepOptions, read_manifest, run_task, sweep

    design = tmp_path / "design.csv"
    design.write_text("damage_constant,e_inf,d0,phi,sigma_e,alpha_percentage,b_prime,"
                      "truncation_ratio\n5.0,1500.0,4e-06,0.1,0.9,34.0,0.03,90.0\n")
    folder = tmp_path / "sweep"
    marker = tmp_path / "killed"  # a file: Dask may hand the task a copy of its closure

    def task(folder_, entry, packing, threads, timeout):
        out = Path(folder_) / entry["file"]
        ck = out.with_name(out.name + ".ckpt")

        def killer():
            t_end = time.time() + 240
            while time.time() < t_end and not (ck.exists() and _children_writing(out)):
                time.sleep(0.05)
            pids = _children_writing(out)
            marker.write_text(" ".join(map(str, pids)))  # before the kill: no second killer
            for pid in pids:
                os.kill(pid, signal.SIGKILL)
        if not marker.exists():
            threading.Thread(target=killer, daemon=True).start()
        return run_task(folder_, entry, packing, threads, timeout)

    overrides = {"protocol.stroke": 2.5e-6, "protocol.snapshot_depths": [0.0, 2.5e-6],
                 "output.record_spacing": 0.25e-6, "output.checkpoint_interval": 1e-9}
    opt = SweepOptions(source="preset:tiny", out=folder, design=str(design),
                       overrides=overrides, workers=1, max_attempts=2, progress=False)
    runs = sweep(opt, task=task)
    assert marker.exists() and marker.read_text(), "the run was never killed"
    (e,) = runs.values()
    assert e.status == "done" and e.attempts == 2, (e.status, e.attempts, e.error)
    assert e.history[0][0] == "failed" and "killed (SIGKILL" in e.history[0][2]
    assert e.history[1][0] == "done"
    man = read_manifest(folder)
    assert man[e.run_id].status == "done" and man[e.run_id].attempts == 2
    assert read_run(folder / e.file).breakage_model != "none"
    log = (folder / "logs" / f"{e.run_id}.log").read_text()
    assert "resumed from" in log  # the retry continued from the checkpoint


def test_a_second_sweep_on_the_same_folder_is_refused(tmp_path, capsys):
    from calendaring.cli import main
    from calendaring.data.sweep import _folder_lock

    folder = tmp_path / "sweep"
    with _folder_lock(folder):
        rc = main(["sweep", "--preset", "tiny", "--design", "centre", "--out", str(folder),
                   "--quiet"])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "another sweep holds its lock" in err[0]
    assert sorted(p.name for p in folder.iterdir()) == [".sweep.lock"]


def test_disk_full_while_a_dataset_is_written(tmp_path, monkeypatch):
    """A dataset build that hits a full disk leaves neither the file nor a temporary, and
    the CLI's contract turns the error into one line with exit 2."""
    import calendaring.data.dataset as dataset_mod
    from calendaring.core.cli_contract import run_cli

    ds = dataset_mod.read_dataset(ROOT / "data" / "reference.h5")
    calls = {"n": 0}
    real = dataset_mod._put

    def full(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 4:  # part-way through, with the file open and half written
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*args, **kwargs)

    monkeypatch.setattr(dataset_mod, "_put", full)
    out = tmp_path / "ds.h5"
    assert run_cli("calendaring", lambda: dataset_mod.write_dataset(out, ds)) == 2
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(dataset_mod, "_put", real)
    assert dataset_mod.read_dataset(dataset_mod.write_dataset(out, ds)).fingerprint == \
        ds.fingerprint
