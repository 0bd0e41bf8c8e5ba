"""``analysis`` command line: bad input exits 2 with a clear message; sobol and trends write
their JSON and PNGs (surrogate replaced by the analytic stand-in)."""

from __future__ import annotations

import json

import pytest

import analysis.cli as cli
from analysis.cli import main, parse_power_of_two
from calendaring.core.errors import ConfigError
from tests.analysis.test_sensitivity import AnalyticSurrogate


@pytest.fixture
def fake_model(tmp_path, monkeypatch):
    f = tmp_path / "model.pt"
    f.write_bytes(b"stand-in")
    monkeypatch.setattr(cli, "_load_model", lambda path: AnalyticSurrogate())
    return f


def test_parse_power_of_two():
    assert parse_power_of_two("2**14") == 16384
    assert parse_power_of_two("2^10") == 1024
    assert parse_power_of_two("512") == 512
    for bad in ("1000", "2**0", "abc", "2**x", "-8"):
        with pytest.raises(ConfigError):
            parse_power_of_two(bad)


@pytest.mark.parametrize("argv, needle", [
    ([], "command"),
    (["sobol", "{tmp}/missing.pt"], "MODEL"),
    (["sobol", "{model}", "--n", "1000"], "--n"),
    (["sobol", "{model}", "--n", "2**8", "--n-min", "2**9"], "--n-min"),
    (["sobol", "{model}", "--dataset", "{tmp}/none.h5"], "no such file"),
    (["trends", "{tmp}/missing.pt"], "MODEL"),
    (["trends", "{model}", "--at", "{tmp}/missing.json"], "--at"),
    (["trends", "{model}", "--at", "{bad_at}"], "d0"),
    (["trends", "{model}", "--points", "1"], "--points"),
    (["microstructure", "{tmp}/missing.h5"], "no such file"),
    (["microstructure", "{model}"], "not a readable HDF5"),
    (["compare", "--preset", "tiny", "--out-dir", "{tmp}/c", "--studies", "r0r1,bogus"],
     "--studies"),
    (["compare", "--preset", "huge", "--out-dir", "{tmp}/c"], "preset"),
    (["compare", "--preset", "tiny", "--out-dir", "{tmp}/c", "--jobs", "0"], "--jobs"),
    (["compare", "--preset", "tiny"], "--out-dir"),
    (["compare", "--preset", "tiny", "--out-dir", "{tmp}/c", "--set", "numerics.nope=1"],
     "numerics.nope"),
])
def test_bad_input_exits_2(tmp_path, fake_model, capsys, argv, needle):
    bad_at = tmp_path / "bad.json"
    bad_at.write_text(json.dumps({"parameters": {"d0": 1.0}}))
    argv = [a.format(tmp=tmp_path, model=fake_model, bad_at=bad_at) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "error" in err and needle in err
    assert not (tmp_path / "c").exists()  # nothing written on bad input
    assert not (tmp_path / "model_sobol").exists()


def test_sobol_and_trends_commands_write_outputs(tmp_path, fake_model, capsys):
    out = tmp_path / "s"
    assert main(["sobol", str(fake_model), "--n", "2**8", "--n-min", "2**7",
                 "--spread-n", "128", "--out-dir", str(out), "--quiet"]) == 0
    js = json.loads((out / "sobol.json").read_text())
    assert js["sobol"]["n"] == 256 and (out / "sobol_indices.png").exists()
    printed = capsys.readouterr().out
    assert "Sobol indices at N = 256" in printed and "peak_pressure" in printed
    assert "paper (Fig. 10)" in printed
    # against a reference study (itself: identical rankings)
    assert main(["sobol", str(fake_model), "--n", "2**7", "--n-min", "2**7", "--spread-n",
                 "128", "--out-dir", str(tmp_path / "s2"), "--reference",
                 str(out / "sobol.json"), "--quiet"]) == 0
    js2 = json.loads((tmp_path / "s2" / "sobol.json").read_text())
    assert set(js2["reference"]["comparison"]) == set(js["sobol"]["indices"])
    assert "against the reference" in capsys.readouterr().out
    assert main(["sobol", str(fake_model), "--n", "2**7", "--n-min", "2**7", "--reference",
                 str(res_missing := tmp_path / "none.json"), "--quiet"]) == 2
    assert "--reference" in capsys.readouterr().err and not res_missing.exists()
    res = tmp_path / "RESULT.json"
    res.write_text(json.dumps({"parameters": {"d0": 6e-6}}))
    assert main(["trends", str(fake_model), "--at", str(res), "--points", "5",
                 "--quiet"]) == 0  # default folder next to the model
    js = json.loads((tmp_path / "model_trends" / "trends.json").read_text())
    assert js["at_physical"]["d0"] == pytest.approx(6e-6)
    assert (tmp_path / "model_trends" / "trends.png").exists()


def test_microstructure_command_on_a_small_run(tmp_path, capsys):
    pytest.importorskip("analysis.microstructure")
    from tests.analysis import write_small_run

    run = write_small_run(tmp_path / "small.h5")
    assert main(["microstructure", str(run), "--snapshots", "0,5"]) == 2
    assert "--snapshots" in capsys.readouterr().err
    assert main(["microstructure", str(run), "--supersample", "0"]) == 2
    out = tmp_path / "m"
    assert main(["microstructure", str(run), "--snapshots", "1", "--voxels-per-diameter", "2",
                 "--no-second-resolution", "--no-render", "--out-dir", str(out),
                 "--quiet"]) == 0
    js = json.loads((out / "microstructure.json").read_text())
    snaps = js["result"]["snapshots"]
    assert [s["index"] for s in snaps] == [1] and 0 < snaps[0]["voxel_porosity"] < 1
    assert js["figures"] and all((out / f).exists() for f in js["figures"])
