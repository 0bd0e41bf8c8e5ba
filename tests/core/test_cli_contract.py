"""The error contract of the four command-line programs (calendaring.core.cli_contract).

Every user error exits 2 with one line naming the thing, the value and what is allowed, and
leaves the output folder as it was; a bug exits 1 with the traceback and a line saying so;
a guard exits 3. The bad invocations run in-process and stop before any simulation or
training starts, so the matrix is fast.
"""

from __future__ import annotations

import argparse
import errno
import math

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calendaring.core import cli_contract as cc
from calendaring.core.config import PRESETS, load_preset, to_dict, with_overrides
from calendaring.core.errors import ConfigError, SimulationError

# ------------------------------------------------------------------ the contract module


def test_integer_and_real_types_check_ranges_and_reject_nan():
    seed = cc.integer(0, 10)
    assert seed("7") == 7
    for bad in ("-1", "11", "3.5", "x", ""):
        with pytest.raises(argparse.ArgumentTypeError, match=r"allowed an integer in \[0, 10\]"):
            seed(bad)
    pos = cc.real(0, lo_open=True, unit="s")
    assert pos("2.5") == 2.5
    for bad in ("0", "-1", "nan", "inf", "-inf", "abc"):
        with pytest.raises(argparse.ArgumentTypeError, match="allowed a finite number > 0 s"):
            pos(bad)
    frac = cc.real(0, 1)
    assert frac("1") == 1.0 and frac("0") == 0.0
    with pytest.raises(argparse.ArgumentTypeError, match=r"in \[0, 1\]"):
        frac("1.0001")


def test_output_path_checks_without_creating_anything(tmp_path):
    deep = tmp_path / "a" / "b" / "run.h5"
    assert cc.output_path(deep, "--out", suffixes=(".h5",)) == deep
    assert sorted(tmp_path.iterdir()) == []  # nothing created, no probe file left
    with pytest.raises(cc.UserInputError, match=r"--out = .* a path ending in \.h5"):
        cc.output_path(tmp_path / "run.txt", "--out", suffixes=(".h5",))
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(cc.UserInputError, match="is a file, not a folder"):
        cc.output_path(blocker / "sub" / "run.h5", "--out")
    with pytest.raises(cc.UserInputError, match="pass --overwrite"):
        cc.output_path(blocker, "--out")
    assert cc.output_path(blocker, "--out", overwrite=True) == blocker
    with pytest.raises(cc.UserInputError, match="a folder"):
        cc.output_path(blocker, "--out-dir", folder=True)
    with pytest.raises(cc.UserInputError, match="not a folder"):
        cc.output_path(tmp_path, "--out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_input_file_and_folder(tmp_path):
    with pytest.raises(cc.UserInputError, match="there is none"):
        cc.input_file(tmp_path / "none.toml", "config")
    with pytest.raises(cc.UserInputError, match="it is a folder"):
        cc.input_file(tmp_path, "config")
    f = tmp_path / "c.txt"
    f.write_text("")
    with pytest.raises(cc.UserInputError, match=r"ending in \.toml"):
        cc.input_file(f, "config", (".toml",))
    with pytest.raises(cc.UserInputError, match="it is a file"):
        cc.input_folder(f, "RUNS")
    assert cc.input_folder(tmp_path, "RUNS") == tmp_path


def _raising(exc):
    def handler():
        raise exc
    return handler


@pytest.mark.parametrize("exc, code, text", [
    (ConfigError("protocol.stroke", -1.0, "> 0 m"), 2,
     "prog: error: protocol.stroke = -1.0 is invalid: allowed > 0 m"),
    (cc.UserInputError("--out", "x.h5", "a new file"), 2, "prog: error: --out = 'x.h5'"),
    (OSError(errno.ENOSPC, "No space left on device", "/data/run.h5"), 2,
     "prog: error: /data/run.h5: No space left on device"),
    (FileNotFoundError(errno.ENOENT, "No such file or directory", "/x/y"), 2,
     "prog: error: /x/y: No such file or directory"),
    (SimulationError("NaN in particle 3", step=10), 3, "prog: simulation stopped: NaN"),
    (KeyboardInterrupt(), 130, "prog: interrupted"),
])
def test_run_cli_maps_errors_to_exit_codes(capsys, exc, code, text):
    assert cc.run_cli("prog", _raising(exc)) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [err[0]] and err[0].startswith(text)


@pytest.mark.parametrize("exc", [RuntimeError("oops"), KeyError("k"), ZeroDivisionError(),
                                 OSError(errno.EIO, "Input/output error")])
def test_a_bug_exits_1_with_traceback_and_says_so(capsys, exc):
    assert cc.run_cli("prog", _raising(exc), version="9.9") == 1
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err
    assert err.strip().splitlines()[-1].startswith(
        "prog: internal error: this is a bug in prog 9.9")


def test_user_errors_of_a_package_exit_2(capsys):
    class Foreign(ValueError):
        pass
    assert cc.run_cli("prog", _raising(Foreign("bad file")), (Foreign,)) == 2
    assert capsys.readouterr().err.strip() == "prog: error: bad file"


# ------------------------------------------------------------------ the four programs


def _main(program):
    if program == "calendaring":
        from calendaring.cli import main
    elif program == "surrogate":
        from surrogate.cli import main
    elif program == "inverse":
        from inverse.cli import main
    else:
        from analysis.cli import main
    return main


@pytest.fixture()
def files(tmp_path):
    """A work folder with hostile inputs: a plain file, a cut HDF5 file, a text CSV."""
    work = tmp_path / "work"
    work.mkdir()
    (work / "plain.txt").write_text("not a run file\n")
    with h5py.File(work / "whole.h5", "w") as f:
        f["x"] = np.arange(1000.0)
    raw = (work / "whole.h5").read_bytes()
    (work / "cut.h5").write_bytes(raw[: len(raw) // 3])
    (work / "whole.h5").unlink()
    (work / "curve.csv").write_text("depth_um,pressure_MPa\n1,2\n")
    (work / "bad.toml").write_text("[domain\ncell_x = 1\n")
    (work / "unknown.toml").write_text("[domain]\ncell_z = 1e-5\n")
    return work


# (program, argv) with {w} the work folder; each must exit 2 before doing any work
BAD = [
    ("calendaring", "run {w}/missing.toml --out {w}/o.h5"),
    ("calendaring", "run {w}/bad.toml --out {w}/o.h5"),
    ("calendaring", "run {w}/unknown.toml --out {w}/o.h5"),
    ("calendaring", "run {w}/plain.txt --out {w}/o.h5"),
    ("calendaring", "run --preset tiny --out {w}/plain.txt/o.h5"),
    ("calendaring", "run --preset tiny --out {w}/o.csv"),
    ("calendaring", "run --preset tiny --out {w}"),
    ("calendaring", "run --preset tiny --seed -1 --out {w}/o.h5"),
    ("calendaring", "run --preset tiny --seed 4294967296 --out {w}/o.h5"),
    ("calendaring", "run --preset tiny --threads -2 --out {w}/o.h5"),
    ("calendaring", "run --preset tiny --set numerics.seed=-1 --out {w}/o.h5"),
    ("calendaring", "run --preset tiny --set domain.cell_x=nan --out {w}/o.h5"),
    ("calendaring", "run --preset tiny --set domain.cell_x=inf --out {w}/o.h5"),
    ("calendaring", "run --preset tiny --set domain.cell_z=1 --out {w}/o.h5"),
    ("calendaring", "run --preset tiny --set protocol.stroke='a' --out {w}/o.h5"),
    ("calendaring", "run --preset tiny --set nokey --out {w}/o.h5"),
    ("calendaring", "run --preset nosuch --out {w}/o.h5"),
    ("calendaring", "run --preset tiny --resume --out {w}/o.h5"),
    ("calendaring", "run --out {w}/o.h5"),
    ("calendaring", "pack --preset tiny --out {w}/o.h5"),
    ("calendaring", "run --preset tiny --set domain.cell_x=1.0 --set domain.cell_y=1.0 "
                    "--out {w}/o.h5"),
    ("calendaring", "run --preset tiny --set numerics.timestep_fraction=1e-9 --out {w}/o.h5"),
    ("calendaring", "run --preset tiny --max-hours 1e-9 --out {w}/o.h5"),
    ("calendaring", "pack --preset tiny --max-hours 0 --out {w}/o.csv"),
    ("calendaring", "inspect {w}/missing.h5"),
    ("calendaring", "inspect {w}/plain.txt"),
    ("calendaring", "inspect {w}/cut.h5"),
    ("calendaring", "inspect {w}"),
    ("calendaring", "plot {w}/cut.h5"),
    ("calendaring", "export {w}/cut.h5 --snapshot 0 --csv"),
    ("calendaring", "export {w}/cut.h5 --snapshot -1 --csv"),
    ("calendaring", "sweep --preset tiny --out {w}/plain.txt"),
    ("calendaring", "sweep --preset tiny --n 0 --out {w}/s"),
    ("calendaring", "sweep --preset tiny --timeout nan --out {w}/s"),
    ("calendaring", "sweep --preset tiny --replicates 0 --out {w}/s"),
    ("calendaring", "sweep {w}/missing.toml --out {w}/s"),
    ("calendaring", "sweep --preset tiny --beds 0 --out {w}/s"),
    ("calendaring", "sweep --preset tiny --beds 2 --seed-per-row --out {w}/s"),
    ("calendaring", "dataset {w}/missing --out {w}/d.h5"),
    ("calendaring", "dataset {w} --out {w}/d.txt"),
    ("calendaring", "dataset {w} --out {w}/d.h5 --bins 1"),
    ("calendaring", "dataset {w} --out {w}/d.h5 --load-range 1 inf"),
    ("surrogate", "train {w}/missing.h5 --out {w}/m.pt"),
    ("surrogate", "train {w}/cut.h5 --out {w}/m.pt"),
    ("surrogate", "train {w}/cut.h5 --out {w}/plain.txt/m.pt"),
    ("surrogate", "train {w}/cut.h5 --out {w}/m.pt --epochs x"),
    ("surrogate", "predict {w}/missing.pt"),
    ("surrogate", "predict {w}/plain.txt"),
    ("surrogate", "evaluate {w}/plain.txt {w}/cut.h5"),
    ("surrogate", "learning-curve {w}/missing.h5 --out-dir {w}/lc"),
    ("surrogate", "learning-curve {w}/cut.h5 --out-dir {w}/plain.txt"),
    ("inverse", "calibrate --model {w}/missing.pt --target {w}/curve.csv --out {w}/r.json"),
    ("inverse", "calibrate --model {w}/plain.txt --target {w}/curve.csv --out {w}/r.json"),
    ("inverse", "calibrate --model {w}/plain.txt --target {w}/curve.csv --out {w}/r.txt"),
    ("inverse", "calibrate --model {w}/plain.txt --target {w}/curve.csv "
                "--out {w}/plain.txt/r.json"),
    ("inverse", "calibrate --model {w}/plain.txt --target {w}/curve.csv --out {w}/r.json "
                "--threads 0"),
    ("inverse", "validate --model {w}/plain.txt --dataset {w}/cut.h5 --out {w}/plain.txt"),
    ("inverse", "verify {w}/missing.json"),
    ("inverse", "calibrate --model {w}/plain.txt --target-row 0 --out {w}/r.json"),
    ("analysis", "sobol {w}/missing.pt"),
    ("analysis", "sobol {w}/plain.txt --n 1000"),
    ("analysis", "sobol {w}/plain.txt --reference {w}/missing.json"),
    ("analysis", "trends {w}/plain.txt"),
    ("analysis", "microstructure {w}/missing.h5"),
    ("analysis", "microstructure {w}/cut.h5"),
    ("analysis", "microstructure {w}/cut.h5 --out-dir {w}/plain.txt"),
    ("analysis", "compare --preset tiny --out-dir {w}/plain.txt"),
    ("analysis", "nosuch"),
]


@pytest.mark.parametrize("program, argv", BAD, ids=[f"{p} {a.split()[0]}-{i}"
                                                     for i, (p, a) in enumerate(BAD)])
def test_bad_input_exits_2_with_one_line_and_writes_nothing(files, capsys, program, argv):
    import shlex

    before = sorted(p.relative_to(files) for p in files.rglob("*"))
    rc = _main(program)(shlex.split(argv.format(w=files)))
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert rc == 2, err
    assert "Traceback" not in "\n".join(err)
    errors = [line for line in err if "error:" in line]
    assert len(errors) == 1, err
    assert sorted(p.relative_to(files) for p in files.rglob("*")) == before


def test_a_bug_in_a_handler_exits_1_and_says_so(monkeypatch, capsys):
    import calendaring.cli as cli

    def broken(args):
        return {}["missing"]
    monkeypatch.setattr(cli, "cmd_inspect", broken)
    assert cli.main(["inspect", "anything.h5"]) == 1
    err = capsys.readouterr().err
    assert "KeyError" in err and "this is a bug in calendaring" in err


def test_help_exits_0(capsys):
    for program in ("calendaring", "surrogate", "inverse", "analysis"):
        assert _main(program)(["--help"]) == 0
    assert "usage" in capsys.readouterr().out


# ------------------------------------------------------------------ every config key


def _leaves(d, prefix=""):
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else k
        if isinstance(v, dict) and v:
            yield from _leaves(v, key)
        else:
            yield key, v


KEYS = sorted({(p, k) for p in PRESETS for k, _ in _leaves(to_dict(load_preset(p)))})
_CONFIGS = {p: load_preset(p) for p in PRESETS}

hostile = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([math.nan, math.inf, -math.inf, 1e300, -1e300, 0.0, -0.0, -1.0, 1e-300]),
    st.integers(min_value=-(2**80), max_value=2**80),
    st.sampled_from([0, -1, 2**31, 2**63, -(2**63)]),
    st.text(max_size=6), st.just(""), st.booleans(), st.none(),
    st.lists(st.floats(allow_nan=True), max_size=3),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)


@settings(max_examples=1500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(which=st.sampled_from(KEYS), value=hostile)
def test_every_config_key_rejects_bad_values_with_a_config_error(which, value):
    """Any value for any key of any preset is either valid or a ConfigError naming a key;
    NaN and infinities are always refused at the key itself."""
    preset, key = which
    try:
        with_overrides(_CONFIGS[preset], {key: value}).check_run()
    except ConfigError as err:
        assert err.key and err.allowed and "is invalid: allowed" in str(err)
        if isinstance(value, float) and not math.isfinite(value):
            assert err.key == key
    else:
        assert not (isinstance(value, float) and not math.isfinite(value)), \
            f"{preset}: {key} = {value!r} accepted"


# ------------------------------------------------------------------ files cut short


@pytest.fixture(scope="module")
def whole_files(tmp_path_factory):
    """A schema-valid run file (no DEM) and the shipped reference dataset, as bytes."""
    from pathlib import Path

    from tests.inverse.conftest import write_fake_run

    run = tmp_path_factory.mktemp("whole") / "run.h5"
    write_fake_run(run, np.linspace(0, 19.5e-6, 400), np.linspace(0, 1e8, 400),
                   loads=[0.01, 0.02], diameters=[1e-5, 2e-5])
    dataset = Path(__file__).resolve().parents[2] / "data" / "reference.h5"
    return {"run": run.read_bytes(), "dataset": dataset.read_bytes()}


@settings(max_examples=80, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kind=st.sampled_from(["run", "dataset"]), frac=st.floats(0.0, 1.0, exclude_max=True))
def test_a_file_cut_at_any_byte_is_refused_by_its_reader(whole_files, tmp_path, kind, frac):
    """Every prefix of a run file or a dataset is refused with the reader's own error (exit
    2 at the CLI), never a traceback."""
    from calendaring.data.dataset import DatasetError, read_dataset
    from calendaring.process.runfile import RunFileError, read_run

    raw = whole_files[kind]
    path = tmp_path / f"cut-{kind}.h5"
    path.write_bytes(raw[: int(frac * len(raw))])
    reader, error = (read_run, RunFileError) if kind == "run" else (read_dataset, DatasetError)
    with pytest.raises(error):
        reader(path)
