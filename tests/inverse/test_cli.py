"""CLI (calibrate with a stand-in model), result files, Table 4 output, verify plumbing."""

from __future__ import annotations

import json

import numpy as np
import pytest

import inverse.cli as cli
from calendaring.data.params import PAPER_SPACE
from inverse.report import TABLE4, read_result
from inverse.verify import run_command, verify
from tests.inverse.conftest import write_fake_run
from tests.inverse.standins import LinearSurrogate

U_TRUE = np.array([0.3, 0.6, 0.45, 0.7, 0.25, 0.55, 0.4, 0.65])


@pytest.fixture(scope="module")
def model():
    return LinearSurrogate()


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory, model):
    """One CLI calibration with posterior on a CSV written from the stand-in at U_TRUE."""
    mp = pytest.MonkeyPatch()
    mp.setattr(cli, "_load_model", lambda path: model)
    d = tmp_path_factory.mktemp("cli")
    p = model.predict_unit(U_TRUE).pressure[0]
    np.savetxt(d / "curve.csv", np.column_stack([model.depth * 1e6, p / 1e6, 0.03 * p / 1e6
                                                 + 0.05]),
               delimiter=",", header="depth_um,pressure_MPa,sigma_MPa", comments="")
    (d / "model.pt").write_bytes(b"stand-in")
    out = d / "result.json"
    rc = cli.main(["calibrate", "--model", str(d / "model.pt"), "--target",
                   str(d / "curve.csv"), "--out", str(out), "--iterations", "60",
                   "--restarts", "2", "--posterior", "--steps", "200", "--burn", "50",
                   "--fix", "damage_constant=3.7", "--quiet"])
    yield rc, out, d
    mp.undo()


def test_calibrate_writes_a_result_in_physical_units(calibrated, capsys):
    rc, out, d = calibrated
    assert rc == 0
    res = read_result(out)
    names = [p["name"] for p in res["parameters"]]
    assert names == PAPER_SPACE.names
    p = {r["name"]: r for r in res["parameters"]}
    assert p["damage_constant"]["value"] == 3.7 and p["damage_constant"]["fixed"]
    # held at its true value: the fit is exact up to the boundary penalty
    x_true = PAPER_SPACE.from_unit(U_TRUE)
    for j, name in enumerate(names[1:], start=1):
        span = PAPER_SPACE.upper[j] - PAPER_SPACE.lower[j]
        assert abs(p[name]["value"] - x_true[j]) < 0.1 * span, name
        assert p[name]["ci90"][0] < p[name]["ci90"][1]
    assert p["d0"]["display_unit"] == "um"
    assert p["d0"]["display_value"] == pytest.approx(p["d0"]["value"] * 1e6)
    assert res["fit"]["relative_rmse"] < 0.05
    assert "identifiability" in res and "posterior" in res
    assert len(res["posterior"]["draws_physical"]) == 16
    for key in ("predictive", "trace", "identifiability"):
        assert (d / f"result_{key}.png").is_file()
    assert not list(d.glob(".*tmp*"))  # atomic write left nothing behind


def test_table4_layout(calibrated):
    from inverse.report import format_table4

    res = read_result(calibrated[1])
    text = format_table4(res)
    for _name, (label, _) in TABLE4.items():
        assert label in text
    line = next(x for x in text.splitlines() if x.startswith("E50 parameter, d0"))
    assert "μm" in line and f"{res['parameters'][2]['display_value']:.3f}" in line


@pytest.mark.parametrize("args,needle", [
    (["--fix", "d0=1"], "d0"),
    (["--fix", "nope=1"], "nope"),
    (["--fix", "d0"], "NAME=VALUE"),
    (["--iterations", "1"], "--iterations"),
])
def test_bad_arguments_exit_2(calibrated, capsys, args, needle):
    _, _out, d = calibrated
    rc = cli.main(["calibrate", "--model", str(d / "model.pt"), "--target", str(d / "curve.csv"),
                   "--out", str(d / "bad.json"), "--quiet", *args])
    assert rc == 2
    assert needle in capsys.readouterr().err
    assert not (d / "bad.json").exists()


def test_bad_csv_exits_2(calibrated, capsys):
    _, _, d = calibrated
    (d / "nounits.csv").write_text("depth,pressure\n0,0\n1,1\n")
    rc = cli.main(["calibrate", "--model", str(d / "model.pt"), "--target",
                   str(d / "nounits.csv"), "--out", str(d / "bad.json"), "--quiet"])
    assert rc == 2
    err = capsys.readouterr().err
    assert err.startswith("inverse: error:") and "depth_<m|mm|um>" in err


def test_run_command_sets_every_parameter():
    params = PAPER_SPACE.as_dict(PAPER_SPACE.reference)
    cmd = run_command(params, "tiny", 3, "out.h5")
    assert cmd[1:5] == ["-m", "calendaring.cli", "run", "--preset"] and cmd[5] == "tiny"
    sets = [cmd[i + 1] for i, a in enumerate(cmd) if a == "--set"]
    assert len(sets) == 8
    assert "breakage.d0=9.396e-06" in sets and "breakage.e_inf=2161.0" in sets
    assert cmd[cmd.index("--seed") + 1] == "3" and cmd[cmd.index("--out") + 1] == "out.h5"
    # the values parse back exactly through the config's override parser
    from calendaring.core.config import parse_override

    back = dict(parse_override(s) for s in sets)
    assert back == {f"breakage.{k}": v for k, v in params.items()}


def test_verify_runs_reads_and_scores(calibrated, model, tmp_path):
    _, out, _ = calibrated
    res = read_result(out)
    t_depth = np.array(res["target"]["depth_m"])
    t_p = np.array([np.nan if v is None else v for v in res["target"]["pressure_Pa"]])
    calls = []

    def fake_runner(cmd):  # writes a run whose trace is 1.1 x the target curve
        calls.append(cmd)
        d = np.linspace(0, 6.5e-6, 2001)
        write_fake_run(cmd[cmd.index("--out") + 1], d, 1.1 * np.interp(d, t_depth, t_p))
        return 0

    rep = verify(out, preset="tiny", seeds=2, draws=1, out_dir=tmp_path, runner=fake_runner,
                 progress=False)
    assert len(calls) == 3 and all("tiny" in c for c in calls)
    seeds = [c[c.index("--seed") + 1] for c in calls]
    assert seeds == ["0", "1", "0"]
    d0 = next(s for s in calls[0] if s.startswith("breakage.d0="))
    assert float(d0.split("=")[1]) == pytest.approx(res["parameters"][2]["value"], rel=1e-12)
    e = rep["optimum_mean_error"]
    assert e["points"] == int(np.sum(t_depth + 0.5 * (t_depth[1] - t_depth[0]) <= 6.5e-6))
    # 10 % high everywhere: relative RMSE = 0.1 x rms(P) / mean(P) on the covered points
    both = t_depth + 0.5 * (t_depth[1] - t_depth[0]) <= 6.5e-6
    expect = 0.1 * np.sqrt(np.mean(t_p[both] ** 2)) / np.mean(t_p[both])
    assert e["relative_rmse"] == pytest.approx(expect, rel=0.02)
    assert (tmp_path / "verify.png").is_file()
    assert json.loads((tmp_path / "verify.json").read_text())["preset"] == "tiny"
    # reuse: existing run files are not run again
    verify(out, preset="tiny", seeds=2, draws=1, out_dir=tmp_path, runner=fake_runner,
           progress=False)
    assert len(calls) == 3
