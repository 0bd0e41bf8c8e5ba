"""One-at-a-time trends: sweep shape, the held point (mid-range or a calibration result)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from analysis.trends import held_point, sweep, trends_study
from calendaring.core.errors import ConfigError
from calendaring.data.params import PAPER_SPACE
from tests.analysis.test_sensitivity import ID0, IE, AnalyticSurrogate

W = np.array([1.0, -2.0, 3.0, 0.5, 0.0, 4.0, -1.0, 2.0])


def linear(u):
    """y = W . u, and z = u0 * u1 (an interaction)."""
    return {"y": u @ W, "z": u[:, 0] * u[:, 1]}


def test_sweep_shape_and_held_point():
    at = np.linspace(0.1, 0.8, 8)
    tr = sweep(linear, PAPER_SPACE.names, at=at, n_points=11)
    grid = np.linspace(0, 1, 11)
    np.testing.assert_array_equal(tr["grid"], grid)
    assert list(tr["outputs"]) == PAPER_SPACE.names
    for i, name in enumerate(PAPER_SPACE.names):
        y = tr["outputs"][name]["y"]
        assert y.shape == (11,)
        # parameter i moves, every other one stays at its held value
        np.testing.assert_allclose(y, at @ W + W[i] * (grid - at[i]), rtol=1e-12)
    np.testing.assert_allclose(tr["outputs"]["damage_constant"]["z"], grid * at[1])
    np.testing.assert_allclose(tr["outputs"]["d0"]["z"], np.full(11, at[0] * at[1]))
    assert tr["at_outputs"]["y"] == pytest.approx(at @ W)
    # default: mid-range
    tr0 = sweep(linear, PAPER_SPACE.names, n_points=3)
    np.testing.assert_array_equal(tr0["at_unit"], np.full(8, 0.5))
    assert tr0["at_outputs"]["y"] == pytest.approx(0.5 * W.sum())


def test_held_point_from_calibration_result(tmp_path):
    ref = PAPER_SPACE.as_dict(PAPER_SPACE.reference)
    f = tmp_path / "RESULT.json"
    f.write_text(json.dumps({"parameters": ref, "loss": 0.1}))
    u = held_point(PAPER_SPACE, f)
    np.testing.assert_allclose(PAPER_SPACE.from_unit(u), PAPER_SPACE.reference, rtol=1e-12)
    # the rows `inverse calibrate` writes: [{"name", "value", ...}, ...]
    rows = [{"name": k, "symbol": "-", "value": v, "value_unit": 0.0} for k, v in ref.items()]
    f.write_text(json.dumps({"parameters": rows}))
    np.testing.assert_allclose(PAPER_SPACE.from_unit(held_point(PAPER_SPACE, f)),
                               PAPER_SPACE.reference, rtol=1e-12)
    # a partial mapping: the others at mid-range
    u2 = held_point(PAPER_SPACE, {"d0": 8e-6})
    assert u2[ID0] == pytest.approx(0.5) and u2[IE] == 0.5
    assert held_point(PAPER_SPACE, {"d0": 6e-6})[ID0] == pytest.approx(0.25)


@pytest.mark.parametrize("content, key", [
    ({"parameters": {"d0": 50e-6}}, "d0"),
    ({"parameters": {"nonsense": 1.0}}, "parameter"),
    ({"params": {}}, "parameters"),
    ("not json", "--at"),
])
def test_held_point_bad_input(tmp_path, content, key):
    f = tmp_path / "bad.json"
    f.write_text(content if isinstance(content, str) else json.dumps(content))
    with pytest.raises(ConfigError, match=key):
        held_point(PAPER_SPACE, f)
    with pytest.raises(ConfigError, match="--at"):
        held_point(PAPER_SPACE, tmp_path / "missing.json")


def test_trends_study_on_stand_in(tmp_path):
    f = tmp_path / "RESULT.json"
    f.write_text(json.dumps({"parameters": {"e_inf": 3000.0}}))
    js = trends_study(AnalyticSurrogate(c=2.0), tmp_path / "out", at=f, n_points=5,
                      progress=False)
    assert (tmp_path / "out" / "trends.png").stat().st_size > 1000
    disk = json.loads((tmp_path / "out" / "trends.json").read_text())
    assert disk["at_physical"]["e_inf"] == pytest.approx(3000.0)
    ue = 0.75  # (3000 - 1500) / 2000
    # peak pressure = 1e6 (1 + 2 u_E + u_d0): the d0 sweep at u_E = 0.75
    np.testing.assert_allclose(disk["outputs"]["d0"]["peak_pressure"],
                               1e6 * (1 + 2 * ue + np.linspace(0, 1, 5)), rtol=1e-9)
    np.testing.assert_allclose(disk["grid_physical"]["d0"], np.linspace(4e-6, 12e-6, 5))
    # gamma has no effect: a flat line at the held value
    np.testing.assert_allclose(disk["outputs"]["damage_constant"]["peak_pressure"],
                               1e6 * (1 + 2 * ue + 0.5))
    assert disk["output_units"]["stress_centroid"] == "N"
    assert js["held_point_source"] == str(f)
