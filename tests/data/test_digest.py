"""Run digests (calendaring.data.digest): a dataset built from a sweep's digests alone equals the
one built from its run files, and a sweep counts a run with a complete digest as finished."""

from __future__ import annotations

import shutil

import h5py
import numpy as np
import pytest

from calendaring.core.config import load_preset, with_overrides
from calendaring.data.dataset import DatasetError, build_dataset, resample_pressure
from calendaring.data.digest import digest_ok, digest_path, read_digest, write_digest
from calendaring.data.sweep import finished
from calendaring.process.runfile import (
    BREAKAGE,
    FRAGMENTS,
    SERIES_UNITS,
    RunFileError,
    read_run,
    write_run,
)

D0 = (4e-6, 5e-6, 6e-6, 7e-6)


def _fake_run(path, d0: float, seed: int, rng):
    """A schema-valid, complete run file (no DEM): a rough rising trace and events."""
    cfg = with_overrides(load_preset("tiny"), {"breakage.d0": d0, "numerics.seed": seed})
    stroke = cfg.protocol.stroke
    n = 3001
    depth = np.sort(rng.uniform(0, stroke, n))
    depth[0], depth[-1] = 0.0, stroke
    pressure = 1e8 * (depth / stroke) ** 2 + rng.normal(0, 1e6, n) ** 2
    k = 40 + seed
    brk = {name: np.zeros(k) for name in BREAKAGE}
    brk["peak_load"] = 10 ** rng.uniform(-3, -1, k)
    brk["diameter"] = rng.uniform(3e-6, 12e-6, k)
    brk["fragments"] = {name: np.zeros(0) for name in FRAGMENTS}
    series = {name: np.zeros(3) for name in SERIES_UNITS}
    series["particles"] = np.array([100.0, 120.0, 140.0])
    return write_run(path, {
        "config": cfg, "preset": "tiny", "seed": seed,
        "info": {"final_depth": stroke, "wall_seconds": 12.5 + seed, "n_particles": 100},
        "breakage_model": "tavares_ufrj", "breakage": brk,
        "pressure": {"step": np.arange(n), "time": np.arange(n) * 1e-9, "depth": depth,
                     "value": pressure, "bottom": pressure},
        "unloading": {"depth": np.zeros(0), "value": np.zeros(0), "bottom": np.zeros(0)},
        "series": series, "energy": {"kinetic": np.zeros(3)}, "snapshots": []})


@pytest.fixture()
def sweep_folder(tmp_path):
    folder = tmp_path / "sweep"
    (folder / "runs").mkdir(parents=True)
    rng = np.random.default_rng(5)
    for i, d0 in enumerate(D0):
        path = _fake_run(folder / "runs" / f"train-x-{i:04d}-s{i}-abc.h5", d0, i, rng)
        write_digest(digest_path(folder, path.stem), read_run(path))
    return folder


def test_digest_round_trip_and_exact_interval_means(sweep_folder):
    path = sorted((sweep_folder / "runs").glob("*.h5"))[1]
    rec, dg = read_run(path), read_digest(digest_path(sweep_folder, path.stem))
    assert dg.run == path.stem and dg.seed == rec.seed and dg.preset == "tiny"
    assert dg.config == rec.config and dg.stroke == rec.stroke
    assert dg.final_depth == rec.stroke and dg.wall_seconds == 13.5 and dg.particles_end == 140
    np.testing.assert_array_equal(dg.peak_load, rec.breakage["peak_load"])
    np.testing.assert_array_equal(dg.diameter, rec.breakage["diameter"])
    for n in (196, 98, 1960, 10):
        mid, means = dg.pressure_means(n)
        mid_r, means_r = resample_pressure(rec.pressure["depth"], rec.pressure["value"],
                                           rec.stroke, n)
        np.testing.assert_allclose(mid, mid_r, rtol=1e-15)
        np.testing.assert_allclose(means, means_r, rtol=1e-12)
    with pytest.raises(ValueError, match="must divide"):
        dg.pressure_means(195)
    assert path.stat().st_size > 5 * digest_path(sweep_folder, path.stem).stat().st_size


def test_a_dataset_from_digests_alone_equals_the_one_from_run_files(sweep_folder, tmp_path):
    full = build_dataset(sweep_folder, progress=False)
    alone = tmp_path / "digests-only"
    shutil.copytree(sweep_folder / "digests", alone / "digests")
    ds = build_dataset(alone, progress=False)
    assert ds.provenance["from_digests"] == len(D0) and full.provenance["from_digests"] == 0
    np.testing.assert_allclose(ds.pressure_raw, full.pressure_raw, rtol=1e-12)
    np.testing.assert_allclose(ds.pressure, full.pressure, rtol=1e-10)
    np.testing.assert_array_equal(ds.histogram, full.histogram)
    np.testing.assert_array_equal(ds.params, full.params)
    for key in ("run_id", "files", "seed", "role", "n_events", "wall_time"):
        np.testing.assert_array_equal(getattr(ds, key), getattr(full, key))
    with pytest.raises(DatasetError, match="must divide"):
        build_dataset(alone, n_points=195, savgol_window=17, progress=False)


def test_a_broken_run_file_falls_back_to_its_digest(sweep_folder):
    first = sorted((sweep_folder / "runs").glob("*.h5"))[0]
    first.write_bytes(first.read_bytes()[:1000])  # cut short
    ds = build_dataset(sweep_folder, progress=False)
    assert len(ds) == len(D0) and ds.provenance["from_digests"] == 1
    dg = digest_path(sweep_folder, first.stem)
    dg.write_bytes(dg.read_bytes()[:500])
    ds = build_dataset(sweep_folder, progress=False)
    assert len(ds) == len(D0) - 1
    (name, why), = ds.skipped
    assert name == first.name and "digest:" in why


def test_the_sweep_counts_a_complete_digest_as_a_finished_run(sweep_folder):
    path = sorted((sweep_folder / "runs").glob("*.h5"))[2]
    rel = f"runs/{path.name}"
    assert finished(sweep_folder, rel)
    path.unlink()
    assert finished(sweep_folder, rel)  # the digest alone
    dg = digest_path(sweep_folder, path.stem)
    raw = dg.read_bytes()
    dg.write_bytes(raw[: len(raw) // 2])
    assert not finished(sweep_folder, rel) and not digest_ok(dg)[0]
    with pytest.raises(RunFileError):
        read_digest(dg)


def test_sweep_keep_round_trip_resumes_a_sweep_on_a_fresh_machine(sweep_folder, tmp_path):
    """scripts/sweep-keep.sh keeps manifest and digests (no run files); a restore into an
    empty folder gives a sweep folder whose runs count as finished."""
    import subprocess
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "scripts" / "sweep-keep.sh"
    from calendaring.data.sweep import read_manifest, write_manifest

    write_manifest(sweep_folder, {})
    (sweep_folder / "digests" / "half.h5.tmp-x").write_bytes(b"partial")
    keep, fresh = tmp_path / "keep", tmp_path / "fresh"
    subprocess.run(["bash", str(script), str(sweep_folder), str(keep)], check=True)
    assert not (keep / "runs").exists() and not list(keep.rglob("*.tmp*"))
    assert sorted(p.name for p in (keep / "digests").iterdir()) == sorted(
        p.name for p in (sweep_folder / "digests").glob("*.h5"))
    subprocess.run(["bash", str(script), "--restore", str(keep), str(fresh)], check=True)
    for path in (sweep_folder / "runs").glob("*.h5"):
        assert finished(fresh, f"runs/{path.name}")
    assert read_manifest(fresh) == {} and len(build_dataset(fresh, progress=False)) == len(D0)
    # a restore never replaces what the sweep folder has
    (fresh / "manifest.json").write_text('{"newer": 1}')
    subprocess.run(["bash", str(script), "--restore", str(keep), str(fresh)], check=True)
    assert "newer" in (fresh / "manifest.json").read_text()
    bad = subprocess.run(["bash", str(script), str(tmp_path / "nothing"), str(keep)],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "not a sweep, compare, refine or keep folder" in bad.stderr


def test_sweep_keep_round_trip_of_a_compare_study(tmp_path):
    """A compare folder (no manifest.json) keeps its case records and analyses, seed by
    seed, never its run files or the temporaries of an atomic write; a restore never
    replaces them; the repository's keep folder (data/compare/) does not ignore records."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    script = root / "scripts" / "sweep-keep.sh"
    study, keep, fresh = tmp_path / "study", tmp_path / "keep", tmp_path / "fresh"
    kept = ["seed-0/runs/R1.record.h5", "seed-0/runs/R1.microstructure.json",
            "seed-1/runs/R0.record.h5"]
    for rel in [*kept, "seed-0/runs/R1.h5", "seed-0/runs/.R0.record.h5.tmp-7",
                "seed-0/compare.json"]:
        (study / rel).parent.mkdir(parents=True, exist_ok=True)
        (study / rel).write_text(rel)
    res = subprocess.run(["bash", str(script), str(study), str(keep)], capture_output=True,
                         text=True)
    assert res.returncode == 0 and "3 files copied" in res.stdout, res.stderr
    assert sorted(str(p.relative_to(keep)) for p in keep.rglob("*") if p.is_file()) == \
        sorted(kept)
    subprocess.run(["bash", str(script), "--restore", str(keep), str(fresh)], check=True,
                   capture_output=True)
    assert all((fresh / rel).read_text() == rel for rel in kept)
    (fresh / kept[1]).write_text("newer analysis")
    subprocess.run(["bash", str(script), "--restore", str(keep), str(fresh)], check=True,
                   capture_output=True)
    assert (fresh / kept[1]).read_text() == "newer analysis"
    if (root / ".git").exists():
        probe = "data/compare/rve/seed-0/runs/R1.record.h5"
        res = subprocess.run(["git", "-C", str(root), "check-ignore", "-q", "--no-index",
                              probe], capture_output=True)
        assert res.returncode == 1, f"{probe} is git-ignored"


def test_sweep_keep_round_trip_of_a_refine_study(tmp_path):
    """A folder of `inverse refine` twins keeps each twin's state and its round sweeps'
    manifests, designs and digests, never run files, checkpoints, packings, posterior
    samples, models or round datasets (all rebuilt on resume); a restore puts them back; the
    repository's keep folder (data/refine/) does not ignore the digests."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    script = root / "scripts" / "sweep-keep.sh"
    study, keep, fresh = tmp_path / "twins", tmp_path / "keep", tmp_path / "fresh"
    kept = ["twin-row0064/refine.json", "twin-row0064/base.json",
            "twin-row0064/target.json", "twin-row0064/rounds/r00/round.json",
            "twin-row0064/rounds/r01/refine-r01.csv", "twin-row0064/runs/manifest.json",
            "twin-row0064/runs/designs/refine-r01.json",
            "twin-row0064/runs/digests/refine-r01-0000-s18-ab.h5",
            "twin-row0065/refine.json"]
    left = ["twin-row0064/rounds/r00/posterior.npz", "twin-row0064/rounds/r01/model.pt",
            "twin-row0064/rounds/r01/dataset.h5", "twin-row0064/runs/runs/a.h5",
            "twin-row0064/runs/runs/a.h5.ckpt", "twin-row0064/runs/packings/b.csv",
            "twin-row0064/runs/logs/a.log", "twin-row0064/runs/designs/r01_correlation.png",
            "twin-row0064/.refine.json.tmp-3"]
    for rel in kept + left:
        (study / rel).parent.mkdir(parents=True, exist_ok=True)
        (study / rel).write_text(rel)
    res = subprocess.run(["bash", str(script), str(study), str(keep)], capture_output=True,
                         text=True)
    assert res.returncode == 0 and f"{len(kept)} files copied" in res.stdout, res.stderr
    assert sorted(str(p.relative_to(keep)) for p in keep.rglob("*") if p.is_file()) == \
        sorted(kept)
    subprocess.run(["bash", str(script), "--restore", str(keep), str(fresh)], check=True,
                   capture_output=True)
    assert all((fresh / rel).read_text() == rel for rel in kept)
    if (root / ".git").exists():
        probe = "data/refine/rve/twin-row0064/runs/digests/refine-r01-0000-s18-ab.h5"
        res = subprocess.run(["git", "-C", str(root), "check-ignore", "-q", "--no-index",
                              probe], capture_output=True)
        assert res.returncode == 1, f"{probe} is git-ignored"


def test_sweep_keep_refuses_a_keep_folder_that_git_ignores(sweep_folder, tmp_path):
    """Keeping digests into a folder of a git work tree that ignores them would lose the
    sweep with the machine: the script stops with exit code 3 and names the files; the
    repository's own keep folder (data/sweeps/) is not ignored."""
    import shutil
    import subprocess
    from pathlib import Path

    from calendaring.data.sweep import write_manifest

    if shutil.which("git") is None:
        pytest.skip("git not installed")
    root = Path(__file__).resolve().parents[2]
    script = root / "scripts" / "sweep-keep.sh"
    write_manifest(sweep_folder, {})
    repo = tmp_path / "repo"
    repo.mkdir()
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    (repo / ".gitignore").write_text("*.h5\n")
    res = subprocess.run(["bash", str(script), str(sweep_folder), str(repo / "keep")],
                         capture_output=True, text=True)
    assert res.returncode == 3 and "git ignores" in res.stderr and ".h5" in res.stderr
    (repo / ".gitignore").write_text("*.h5\n!keep/digests/*.h5\n")
    res = subprocess.run(["bash", str(script), str(sweep_folder), str(repo / "keep")],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    if (root / ".git").exists():
        probe = "data/sweeps/rve/digests/run.h5"
        res = subprocess.run(["git", "-C", str(root), "check-ignore", "-q", "--no-index",
                              probe], capture_output=True)
        assert res.returncode == 1, f"{probe} is git-ignored"


def test_runs_and_digests_record_the_source_commit_and_the_dataset_counts_them(sweep_folder):
    from calendaring._version import source_commit

    here = source_commit()
    paths = sorted((sweep_folder / "runs").glob("*.h5"))
    assert read_run(paths[0]).source_commit == here
    assert read_digest(digest_path(sweep_folder, paths[0].stem)).source_commit == here
    # a run written before the attribute existed: its run file is gone and its digest
    # lacks the attribute, so it counts as unrecorded
    paths[0].unlink()
    with h5py.File(digest_path(sweep_folder, paths[0].stem), "a") as f:
        del f.attrs["source_commit"]
    assert read_digest(digest_path(sweep_folder, paths[0].stem)).source_commit == ""
    ds = build_dataset(sweep_folder, progress=False, notes={"why": "a test"})
    expect = {"unrecorded": 1}
    expect[here or "unrecorded"] = expect.get(here or "unrecorded", 0) + 3
    assert ds.provenance["source_commits"] == expect
    assert ds.provenance["notes"] == {"why": "a test"}


def test_source_commit_names_the_checkout_and_its_local_changes(tmp_path):
    """The function run from a copy of the package: no repository, then a committed one,
    then one with a tracked file changed."""
    import importlib.util
    import subprocess
    from pathlib import Path

    import calendaring._version as version

    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    pkg = tmp_path / "calendaring"
    pkg.mkdir()
    shutil.copy(Path(version.__file__), pkg / "_version.py")

    def fresh():
        spec = importlib.util.spec_from_file_location("_v", pkg / "_version.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod.source_commit()

    assert fresh() == ""  # not a checkout
    git = ["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    subprocess.run([*git, "add", "calendaring/_version.py"], check=True)
    subprocess.run([*git, "commit", "-q", "-m", "x"], check=True)
    sha = subprocess.run([*git, "rev-parse", "HEAD"], check=True, capture_output=True,
                         text=True).stdout.strip()
    assert len(sha) == 40 and fresh() == sha
    (pkg / "_version.py").write_text((pkg / "_version.py").read_text() + "\n# changed\n")
    assert fresh() == sha + "+dirty"
