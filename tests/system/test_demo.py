"""The main-job entry point runs end to end on a tiny bed and writes its outputs."""

import json

import numpy as np

from calendaring import demo


def test_demo_writes_pressure_curve_plot_and_summary(tmp_path):
    out = tmp_path / "demo"
    rc = demo.main(["--out", str(out), "--n-am", "12", "--n-cb", "30", "--cell", "30e-6",
                    "--speed", "1.0"])
    assert rc == 0
    header = (out / "pressure.csv").read_text().splitlines()[0]
    assert header == "plate_travel_m,top_pressure_Pa,bottom_pressure_Pa"
    data = np.loadtxt(out / "pressure.csv", delimiter=",", skiprows=1)
    assert data.shape[1] == 3 and data.shape[0] > 10
    assert np.all(np.diff(data[:, 0]) > 0)  # plate travel increases
    assert np.all(np.isfinite(data)) and np.all(data[:, 1] >= 0)
    assert data[-1, 1] > 0  # the bed is loaded at the end of the stroke
    assert (out / "pressure.png").stat().st_size > 1000
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_am"] == 12 and summary["n_cb"] == 30
    assert np.isfinite(summary["energy_J"]["total"])
    assert not list(out.glob("*.tmp*"))  # files were renamed into place
