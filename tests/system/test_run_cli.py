"""The main job end to end: ``calendaring run --preset tiny`` through the CLI, the run-file
schema, mass balance, bond rules, restart after SIGKILL, bad input, corrupt files, export.

One uninterrupted single-thread run of the tiny preset is shared by the module (about 25 s);
the restart test kills a second run mid-way and resumes it.
"""

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from calendaring.cli import main
from calendaring.engine.bonds import INTACT
from calendaring.process.run import STAGES
from calendaring.process.runfile import (
    BONDS,
    PRESSURE,
    SERIES_UNITS,
    SNAPSHOT,
    RunFileError,
    read_run,
)

# checkpoint after every chunk so a kill always finds one; one thread for bit-identity
RUN_ARGS = ["--preset", "tiny", "--threads", "1", "--set", "output.checkpoint_interval=1e-9"]


def _cli(*args, timeout=300, **kw):
    return subprocess.run([sys.executable, "-m", "calendaring.cli", *args], capture_output=True,
                          text=True, timeout=timeout, **kw)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny") / "tiny.h5"
    res = _cli("run", *RUN_ARGS, "--out", str(out))
    assert res.returncode == 0, res.stderr[-3000:]
    assert "ETA" in res.stderr  # progress lines
    return out


def test_run_file_follows_the_schema(tiny_run):
    rec = read_run(tiny_run)
    with h5py.File(tiny_run) as f:
        for key in ("schema_version", "config", "seed", "software_version", "cell_x",
                    "cell_y", "format"):
            assert key in f.attrs
        for name, (unit, _) in PRESSURE.items():
            assert f[f"pressure/{name}"].attrs["unit"] == unit
        for name, unit in SERIES_UNITS.items():
            assert f[f"series/{name}"].attrs["unit"] == unit
        for k in f["snapshots"]:
            for name, (unit, _) in SNAPSHOT.items():
                assert f[f"snapshots/{k}/{name}"].attrs["unit"] == unit
            for name, (unit, _) in BONDS.items():
                assert f[f"snapshots/{k}/bonds/{name}"].attrs["unit"] == unit
            assert "depth" in f[f"snapshots/{k}"].attrs
        for name in f["energy"]:
            assert f[f"energy/{name}"].attrs["unit"] == "J"
    assert rec.cell_x == pytest.approx(25e-6) and rec.preset == "tiny"
    d = rec.pressure["depth"]
    assert np.all(np.diff(d) > 0) and d[-1] == pytest.approx(6.5e-6, rel=1e-9)
    # full resolution: one sample per calendering step
    assert len(d) == rec.info["calender_steps"]
    step_travel = rec.info["plate_speed"] * rec.info["dt"]  # snapshots land on steps
    assert [s.depth for s in rec.snapshots] == pytest.approx([0, 2e-6, 4e-6, 6.5e-6],
                                                             abs=0.5 * step_travel)
    assert rec.pressure["value"][-1] > 0
    # each stage's wall seconds and steps; together no more than the run's wall time
    stages = rec.info["stages"]
    assert "calender" in stages and set(stages) <= set(STAGES)
    assert stages["calender"]["steps"] == rec.info["calender_steps"]
    assert all(st["steps"] > 0 and st["wall_seconds"] > 0 for st in stages.values())
    assert sum(st["wall_seconds"] for st in stages.values()) <= rec.info["wall_seconds"]


def test_snapshot_porosity_is_mass_balance_and_no_particle_is_lost(tiny_run):
    rec = read_run(tiny_run)
    first = rec.snapshots[0]
    h0 = rec.thickness
    phi0 = first.porosity(rec.cell_x, rec.cell_y)
    assert phi0 == pytest.approx(rec.info["build"]["porosity_at_thickness"], abs=1e-12)
    for snap in rec.snapshots:
        h = snap.z_top - snap.z_bottom
        assert h == pytest.approx(h0 - snap.depth, rel=1e-9)
        expected = 1 - (1 - phi0) * h0 / h
        assert abs(snap.porosity(rec.cell_x, rec.cell_y) - expected) < 0.01
        inside = (snap.position[:, 2] > snap.z_bottom) & (snap.position[:, 2] < snap.z_top)
        assert inside.all()
    counts = rec.info["build"]["counts"]
    assert len(first.id) == counts["AM"] + counts["CB"]


def test_breakage_keeps_every_particle_and_the_active_material_volume(tiny_run):
    rec = read_run(tiny_run)
    b = rec.breakage
    assert rec.breakage_model == "tavares_ufrj" and len(b["parent_id"]) > 0
    first = rec.snapshots[0]
    am0 = np.sum(first.radius[first.material == 0] ** 3)
    frag = b["fragments"]
    for snap in rec.snapshots:
        done = b["step"] <= snap.step  # events before this snapshot
        born = set(frag["id"][np.isin(frag["event"], np.nonzero(done)[0])].tolist())
        alive = (set(first.id.tolist()) | born) - set(b["parent_id"][done].tolist())
        assert set(snap.id.tolist()) == alive  # no particle lost, none duplicated
        am = np.sum(snap.radius[snap.material == 0] ** 3)
        assert abs(am / am0 - 1) < 1e-9  # T18: the active material volume is conserved
        kids = snap.parent_id >= 0
        assert set(snap.parent_id[kids].tolist()) <= set(b["parent_id"].tolist())
    assert rec.series["particles"][-1] == len(rec.snapshots[-1].id)
    assert rec.series["breakage_events"][-1] == len(b["parent_id"])


def test_breakage_records_follow_the_model(tiny_run):
    from calendaring.engine import breakage as bk
    from calendaring.process.runfile import BREAKAGE, FRAGMENTS

    rec = read_run(tiny_run)
    with h5py.File(tiny_run) as f:
        for name, (unit, _) in BREAKAGE.items():
            assert f[f"breakage/{name}"].attrs["unit"] == unit
        for name, (unit, _) in FRAGMENTS.items():
            assert f[f"breakage/fragments/{name}"].attrs["unit"] == unit
    b, cfg = rec.breakage, rec.config.breakage
    e50 = bk.e50(b["diameter"], rec.config.materials["AM"], cfg)
    assert b["e50"] == pytest.approx(e50, rel=1e-12)
    assert np.all(b["stressing_energy"] >= b["fracture_energy"])
    assert np.all(b["fracture_energy"] < bk.truncation_factor(cfg) * e50)
    assert b["t10"] == pytest.approx(bk.t10(b["stressing_energy"], e50, cfg), rel=1e-12)
    assert np.all(b["peak_load"] > 0) and np.all(b["diameter"] >= cfg.min_breakable_diameter)
    assert np.all(np.diff(b["depth"]) >= 0) and np.all(b["depth"] <= rec.stroke + 1e-12)
    frag = b["fragments"]
    assert len(frag["id"]) == b["n_fragments"].sum()
    assert len(np.unique(frag["id"])) == len(frag["id"])
    for k in range(len(b["parent_id"])):
        d = frag["diameter"][frag["event"] == k]
        assert len(d) == b["n_fragments"][k] >= 2
        assert abs(np.sum(d**3) / b["diameter"][k] ** 3 - 1) < 1e-12
        assert np.all(d >= cfg.min_fragment_diameter * (1 - 1e-9)) or len(d) == 2


def test_no_breakage_control_starts_from_the_same_packing_and_seed(tiny_run, tmp_path):
    out = tmp_path / "r0.h5"
    res = _cli("run", *RUN_ARGS, "--no-breakage", "--out", str(out), "--quiet")
    assert res.returncode == 0, res.stderr[-3000:]
    r0, r1 = read_run(out), read_run(tiny_run)
    assert r0.breakage_model == "none" and len(r0.breakage["parent_id"]) == 0
    assert not r0.config.breakage.enabled and r0.seed == r1.seed
    np.testing.assert_array_equal(r0.snapshots[0].position, r1.snapshots[0].position)
    np.testing.assert_array_equal(r0.snapshots[0].radius, r1.snapshots[0].radius)
    assert len(r0.snapshots[-1].id) == len(r0.snapshots[0].id)
    # breakage relieves the load: the broken bed carries less at full stroke
    assert r1.pressure["value"][-1] < r0.pressure["value"][-1]


def test_bond_rules_hold_through_the_run(tiny_run):
    rec = read_run(tiny_run)
    first = rec.snapshots[0]  # taken at bond creation
    b = first.bonds
    assert len(b["id_a"]) == rec.info["bonds_created"] > 0
    index = {int(i): k for k, i in enumerate(first.id)}
    a = np.array([index[int(i)] for i in b["id_a"]])
    c = np.array([index[int(i)] for i in b["id_b"]])
    assert np.all((first.material[a] == 1) | (first.material[c] == 1))  # none AM-AM
    d = first.position[c] - first.position[a]
    d[:, :2] -= rec.cell_x * np.round(d[:, :2] / rec.cell_x)
    dist = np.linalg.norm(d, axis=1)
    assert np.all(dist <= 1.5 * (first.radius[a] + first.radius[c]) * (1 + 1e-12))
    assert np.all(b["state"] == INTACT)
    pairs0 = set(zip(b["id_a"].tolist(), b["id_b"].tolist(), strict=True))
    for snap in rec.snapshots[1:]:  # never re-created, never new
        pairs = set(zip(snap.bonds["id_a"].tolist(), snap.bonds["id_b"].tolist(), strict=True))
        assert pairs == pairs0
    intact = rec.series["bonds_intact"]
    assert np.all(np.diff(intact) <= 0)
    failed = rec.series["bonds_failed_normal"] + rec.series["bonds_failed_shear"]
    assert np.all(intact + failed + rec.series["bonds_removed"] == rec.info["bonds_created"])
    assert failed[-1] > 0  # calendering breaks bonds


@pytest.mark.slow  # a killed run resumed: the slow tier
def test_resume_after_sigkill_gives_the_uninterrupted_result(tiny_run, tmp_path):
    out = tmp_path / "killed.h5"
    ckpt = tmp_path / "killed.h5.ckpt"
    proc = subprocess.Popen([sys.executable, "-m", "calendaring.cli", "run", *RUN_ARGS,
                             "--out", str(out), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.time()
        while time.time() - t0 < 120:  # wait until the calendering stage is checkpointed
            if ckpt.exists():
                try:
                    with h5py.File(ckpt) as f:
                        if json.loads(f["run"].attrs["stage"]) >= 3:
                            break
                except (OSError, KeyError):
                    pass
            if proc.poll() is not None:
                pytest.fail(f"run ended before it could be killed: {proc.stderr.read()}")
            time.sleep(0.05)
        time.sleep(1.0)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists()  # a killed run leaves no file that looks complete
    assert ckpt.exists()
    res = _cli("run", *RUN_ARGS, "--out", str(out), "--resume")
    assert res.returncode == 0, res.stderr[-3000:]
    assert "resumed from" in res.stderr
    assert not ckpt.exists()
    a, b = read_run(tiny_run), read_run(out)
    # the stage records carry over the kill: the same steps per stage
    assert {k: v["steps"] for k, v in b.info["stages"].items()} == {
        k: v["steps"] for k, v in a.info["stages"].items()}
    for key in PRESSURE:
        np.testing.assert_array_equal(a.pressure[key], b.pressure[key])
    for key in SERIES_UNITS:
        np.testing.assert_array_equal(a.series[key], b.series[key])
    assert len(a.snapshots) == len(b.snapshots)
    for key in ("parent_id", "stressing_energy", "step", "peak_load"):
        np.testing.assert_array_equal(a.breakage[key], b.breakage[key])
    np.testing.assert_array_equal(a.breakage["fragments"]["diameter"],
                                  b.breakage["fragments"]["diameter"])
    for sa, sb in zip(a.snapshots, b.snapshots, strict=True):
        np.testing.assert_array_equal(sa.position, sb.position)
        np.testing.assert_array_equal(sa.normal_force, sb.normal_force)


@pytest.mark.parametrize("args, key", [
    (["--set", "electrode.thikness=1e-5"], "electrode.thikness"),
    (["--set", "protocol.stroke=\"deep\""], "protocol.stroke"),
    (["--set", "electrode.thickness=-7.5e-5"], "electrode.thickness"),
    (["--set", "protocol.stroke=30e-6"], "protocol.stroke"),
    (["--set", "electrode.composition.AM=0.5"], "electrode.composition"),
    (["--set", "numerics.timestep_fraction=0.5"], "numerics.timestep_fraction"),
    (["--set", "protocol.snapshot_depths=[0.0, 9e-6]"], "protocol.snapshot_depths"),
])
def test_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, args, key):
    out = tmp_path / "run.h5"
    rc = main(["run", "--preset", "tiny", *args, "--out", str(out)])
    assert rc == 2
    err = capsys.readouterr().err
    assert key in err and "allowed" in err
    assert list(tmp_path.iterdir()) == []


def test_cli_usage_errors_exit_2(tmp_path):
    res = _cli("run", "--preset", "nope", "--out", str(tmp_path / "a.h5"))
    assert res.returncode == 2 and "nope" in res.stderr
    res = _cli("run", "--out", str(tmp_path / "a.h5"))
    assert res.returncode == 2 and "--preset" in res.stderr
    existing = tmp_path / "keep.h5"
    existing.write_bytes(b"precious")
    res = _cli("run", "--preset", "tiny", "--out", str(existing))
    assert res.returncode == 2 and "--overwrite" in res.stderr
    assert existing.read_bytes() == b"precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.h5"]


def test_reader_rejects_truncated_foreign_and_edited_files(tiny_run, tmp_path, capsys):
    data = tiny_run.read_bytes()
    cut = tmp_path / "cut.h5"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(RunFileError, match=r"cut\.h5"):
        read_run(cut)
    assert main(["inspect", str(cut)]) == 2
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["x"] = np.arange(3)
    with pytest.raises(RunFileError, match="not a calendaring run file"):
        read_run(foreign)
    text = tmp_path / "text.h5"
    text.write_text("hello")
    with pytest.raises(RunFileError, match="HDF5"):
        read_run(text)
    edited = tmp_path / "edited.h5"
    shutil.copy(tiny_run, edited)
    with h5py.File(edited, "a") as f:
        del f["series/porosity"]
    with pytest.raises(RunFileError, match="series/porosity"):
        read_run(edited)


def test_files_of_an_older_version_read_and_edited_configs_do_not(tiny_run, tmp_path):
    """A file whose stored configuration lacks a key added since (here
    ``numerics.resort_fraction``) reads, with the key's default; an edited configuration
    text is refused."""
    import hashlib

    older = tmp_path / "older.h5"
    shutil.copy(tiny_run, older)
    with h5py.File(older, "a") as f:
        cfg = json.loads(str(f.attrs["config"]))
        del cfg["numerics"]["resort_fraction"]
        text = json.dumps(cfg, sort_keys=True)
        f.attrs["config"] = text
        f.attrs["config_hash"] = hashlib.sha256(text.encode()).hexdigest()
    rec = read_run(older)
    assert rec.config.numerics.resort_fraction == 0.1
    assert rec.config_json == text
    edited = tmp_path / "edited-config.h5"
    shutil.copy(older, edited)
    cfg["numerics"]["skin"] *= 2
    with h5py.File(edited, "a") as f:
        f.attrs["config"] = json.dumps(cfg, sort_keys=True)
    with pytest.raises(RunFileError, match="edited or corrupt"):
        read_run(edited)


def test_inspect_plot_and_export(tiny_run, tmp_path, capsys):
    assert main(["inspect", str(tiny_run), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["counts"]["AM"] > 0 and "6.5 um" in summary["pressure_at"]
    assert main(["plot", str(tiny_run), "--out-dir", str(tmp_path)]) == 0
    for name in ("tiny_pressure.png", "tiny_microstructure.png"):
        assert (tmp_path / name).stat().st_size > 10_000
    rec = read_run(tiny_run)
    last = len(rec.snapshots) - 1
    for flag, ext in (("--csv", ".csv"), ("--lammps", ".data"), ("--vtk", ".vtp")):
        out = tmp_path / f"snap{ext}"
        assert main(["export", str(tiny_run), "--snapshot", str(last), flag,
                     "--out", str(out)]) == 0
        assert out.exists()
    from calendaring.process.packing import read_csv, read_lammps_data

    for pk in (read_csv(tmp_path / "snap.csv"), read_lammps_data(tmp_path / "snap.data")):
        np.testing.assert_array_equal(pk.position, rec.snapshots[last].position)
        np.testing.assert_array_equal(pk.radius, rec.snapshots[last].radius)
    assert main(["export", str(tiny_run), "--snapshot", "99", "--csv"]) == 2


def test_packing_start_pressure_target_and_unloading(tiny_run, tmp_path):
    """A run from an exported packing, calendered to a target pressure (servo stop), then
    unloaded until the plate loses contact (springback)."""
    packing = tmp_path / "start.csv"
    assert main(["export", str(tiny_run), "--snapshot", "0", "--csv", "--out",
                 str(packing)]) == 0
    out = tmp_path / "from_packing.h5"
    target = 50e6
    res = _cli("run", "--preset", "tiny", "--set", f"electrode.packing=\"{packing}\"",
               "--set", f"protocol.target_pressure={target}", "--set", "protocol.unload=true",
               "--out", str(out), "--quiet")
    assert res.returncode == 0, res.stderr[-3000:]
    rec = read_run(out)
    src = read_run(tiny_run).snapshots[0]
    assert rec.info["build"]["source"] == str(packing)
    assert sorted(rec.snapshots[0].radius) == pytest.approx(sorted(src.radius), rel=1e-15)
    # stopped at the first record row at or above the target, before the full stroke
    top = rec.series["top_pressure"]
    assert top[-1] >= target and np.all(top[:-1] < target)
    assert rec.info["final_depth"] < rec.stroke
    assert rec.snapshots[-1].depth == pytest.approx(rec.info["final_depth"], abs=1e-15)
    # unloading: the plate rises until the bed lets go of it
    un = rec.unloading
    assert len(un["depth"]) > 0 and np.all(np.diff(un["depth"]) < 0)
    assert un["value"][-1] <= 0.0
    spring = rec.info["unload"]
    assert spring["released"] and 0 < spring["springback"] < 0.5
    assert spring["h_release"] > spring["h_min"]
    assert not math.isnan(rec.pressure_at(rec.info["final_depth"]))
    assert os.path.getsize(out) > 0


def test_preflight_estimate_matches_the_run(tiny_run):
    """The pre-flight estimate (configuration only) against what the run did: the time step
    exactly, the plate speed, the particle count and the calendering steps closely."""
    from calendaring.process.preflight import estimate
    from calendaring.process.runfile import read_run

    rec = read_run(tiny_run)
    est = estimate(rec.config)
    info = rec.info
    assert est.dt == pytest.approx(info["dt"], rel=1e-9)
    assert est.plate_speed == pytest.approx(info["plate_speed"], rel=0.05)
    assert est.n_particles == pytest.approx(info["n_particles"], rel=0.10)
    assert est.steps["calender"] == pytest.approx(info["stages"]["calender"]["steps"], rel=0.05)
    assert est.pool_slots >= info["pool_capacity"] * 0.9
