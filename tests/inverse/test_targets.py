"""Targets: CSV unit handling and rejections, run-file resampling, centroids."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calendaring.core.errors import ConfigError
from calendaring.data.dataset import centroids
from inverse.targets import (
    Target,
    interval_means,
    load_target,
    model_stroke,
    read_curve_csv,
    target_from_csv,
    target_from_run,
)
from tests.inverse.conftest import write_fake_run
from tests.inverse.standins import STROKE, LinearSurrogate


@pytest.fixture(scope="module")
def model():
    return LinearSurrogate()


def _write(path, header, rows):
    with open(path, "w") as f:
        f.write("# a comment line\n" + header + "\n")
        for r in rows:
            f.write(",".join(str(v) for v in r) + "\n")
    return path


def _curve(n=40, top_um=19.5):
    d_um = np.linspace(0.0, top_um, n)
    p_mpa = 2.0 * np.expm1(3.0 * d_um / 19.5)
    s_mpa = 0.05 * p_mpa + 0.1
    return d_um, p_mpa, s_mpa


def test_model_stroke_is_recovered_from_midpoints(model):
    assert model_stroke(model.depth) == pytest.approx(STROKE, rel=1e-12)


def test_csv_units_um_mpa_and_m_pa_give_identical_targets(tmp_path, model):
    d_um, p_mpa, s_mpa = _curve()
    a = _write(tmp_path / "a.csv", "depth_um,pressure_MPa,sigma_MPa",
               zip(d_um, p_mpa, s_mpa, strict=True))
    b = _write(tmp_path / "b.csv", "depth_m,pressure_Pa,sigma_Pa",
               zip(d_um * 1e-6, p_mpa * 1e6, s_mpa * 1e6, strict=True))
    c = _write(tmp_path / "c.csv", "depth [mm], pressure (kPa)",
               zip(d_um * 1e-3, p_mpa * 1e3, strict=True))
    ta, tb, tc = (target_from_csv(x, model) for x in (a, b, c))
    np.testing.assert_array_equal(ta.valid, tb.valid)
    assert ta.valid.all()  # the curve spans 0..19.5 um: every model depth covered
    np.testing.assert_allclose(ta.pressure, tb.pressure, rtol=1e-12)
    np.testing.assert_allclose(ta.sigma, tb.sigma, rtol=1e-12)
    np.testing.assert_allclose(tc.pressure, ta.pressure, rtol=1e-12)
    assert tc.sigma is None
    # SI values: linear interpolation of the SI curve at the model depths
    expect = np.interp(model.depth, d_um * 1e-6, p_mpa * 1e6)
    np.testing.assert_allclose(ta.pressure, expect, rtol=1e-12)


def test_partial_curve_masks_uncovered_depths(tmp_path, model):
    d_um, p_mpa, _ = _curve(top_um=10.0)
    t = target_from_csv(_write(tmp_path / "p.csv", "depth_um,pressure_MPa",
                               zip(d_um, p_mpa, strict=True)), model)
    np.testing.assert_array_equal(t.valid, model.depth <= 10e-6 + 1e-15)
    assert np.all(np.isnan(t.pressure[~t.valid]))
    assert t.n_valid == int(np.sum(model.depth <= 10e-6))


@pytest.mark.parametrize("header,rows,key_part", [
    ("depth,pressure", [(0, 0), (1, 1)], "header"),
    ("depth_um,pressure", [(0, 0), (1, 1)], "header"),
    ("depth_inch,pressure_MPa", [(0, 0), (1, 1)], "depth_inch"),
    ("depth_um,pressure_MPa", [(0, 0), (2, 1), (1, 2)], "row 4"),
    ("depth_um,pressure_MPa", [(0, 0), (1, 1), (1, 2)], "row 4"),
    ("depth_um,pressure_MPa", [(0, 0), (1, float("nan"))], "row 3"),
    ("depth_um,pressure_MPa", [(0, 0), (1, "abc")], "row 3"),
    ("depth_um,pressure_MPa", [(0, 0), (1, -2.0)], "row 3"),
    ("depth_um,pressure_MPa,sigma_MPa", [(0, 0, 1), (1, 1, 0)], "row 3"),
    ("depth_um,pressure_MPa", [(0, 0)], "rows"),
    ("depth_um,pressure_MPa", [(-1, 0), (1, 1)], "row 2"),
])
def test_bad_csv_is_rejected_with_a_clear_error(tmp_path, header, rows, key_part):
    with pytest.raises(ConfigError) as err:
        read_curve_csv(_write(tmp_path / "bad.csv", header, rows))
    assert key_part in err.value.key
    assert err.value.allowed  # the allowed range is named


def test_depth_beyond_the_trained_stroke_is_rejected(tmp_path, model):
    d_um, p_mpa, _ = _curve(top_um=25.0)
    with pytest.raises(ConfigError) as err:
        target_from_csv(_write(tmp_path / "long.csv", "depth_um,pressure_MPa",
                               zip(d_um, p_mpa, strict=True)), model)
    assert "stroke" in err.value.allowed and "depth" in err.value.key


def test_missing_file_and_bad_centroids(tmp_path, model):
    with pytest.raises(ConfigError):
        load_target(tmp_path / "none.csv", model)
    d_um, p_mpa, _ = _curve()
    f = _write(tmp_path / "ok.csv", "depth_um,pressure_MPa", zip(d_um, p_mpa, strict=True))
    with pytest.raises(ConfigError):
        load_target(f, model, centroids_si=(0.1, -1.0))
    t = load_target(f, model, centroids_si=(0.1, 9e-6))
    np.testing.assert_allclose(t.centroids, [0.1, 9e-6])


def test_interval_means_are_exact_for_a_piecewise_linear_trace(model):
    d = np.sort(np.random.default_rng(0).uniform(0, STROKE, 3000))
    d[-1] = STROKE
    a = 1e13  # Pa / m
    means, covered = interval_means(d, a * d, model.depth)  # starts above 0: held first value
    assert covered.all()
    inside = model.depth - 0.5 * (model.depth[1] - model.depth[0]) >= d[0]
    np.testing.assert_allclose(means[inside], a * model.depth[inside], rtol=1e-10)
    # a quadratic is approximated to second order in the trace spacing
    d = np.linspace(0, STROKE, 5001)
    means, _ = interval_means(d, 1e17 * d**2, model.depth)
    h = 0.5 * (model.depth[1] - model.depth[0])
    lo, hi = model.depth - h, model.depth + h
    np.testing.assert_allclose(means, 1e17 * (hi**3 - lo**3) / (3 * (hi - lo)), rtol=1e-3)


def test_run_file_target_pressure_events_and_centroid(tmp_path, model):
    d = np.linspace(0.0, 6.5e-6, 3001)  # the tiny preset's stroke, shorter than the model's
    a = 1e13
    le, de = model.load_edges, model.diameter_edges
    loads = np.full(7, np.sqrt(le[10] * le[11]))  # every event in load bin 10
    diam = np.full(7, 0.5 * (de[4] + de[5]))  # and diameter bin 4
    path = write_fake_run(tmp_path / "run.h5", d, a * d, loads, diam)
    t = target_from_run(path, model)
    np.testing.assert_array_equal(t.valid, model.depth + 0.5 * (model.depth[1] -
                                                                model.depth[0]) <= 6.5e-6)
    # interval means of a linear trace are its midpoint values, and Savitzky-Golay smoothing
    # of order 3 keeps a straight line
    np.testing.assert_allclose(t.pressure[t.valid], a * model.depth[t.valid], rtol=1e-9)
    assert t.distribution[10, 4] == pytest.approx(1.0)
    np.testing.assert_allclose(t.centroids, [loads[0], diam[0]], rtol=1e-12)
    lc, dc = np.sqrt(le[1:] * le[:-1]), 0.5 * (de[1:] + de[:-1])
    np.testing.assert_allclose(t.centroids, centroids(t.distribution, lc, dc), rtol=1e-12)


def test_target_json_round_trip(model):
    v = model.depth < 10e-6
    t = Target(model.depth, np.where(v, 1e6, np.nan), v, centroids=np.array([0.1, 8e-6]))
    t2 = Target.from_json(t.to_json())
    np.testing.assert_array_equal(t2.valid, v)
    np.testing.assert_allclose(t2.pressure[v], 1e6)
    np.testing.assert_allclose(t2.centroids, [0.1, 8e-6])


def test_a_byte_order_mark_is_not_part_of_the_header(tmp_path):
    plain = _write(tmp_path / "plain.csv", "depth_um,pressure_MPa", [(0, 0), (1, 2)])
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + plain.read_bytes())
    for a, b in zip(read_curve_csv(plain)[:2], read_curve_csv(bom)[:2], strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("content, key_part", [
    (b"depth_um;pressure_MPa\n0;0\n1;2\n", "header"),  # a semicolon-separated file
    (b"depth_um\tpressure_MPa\n0\t0\n1\t2\n", "header"),  # tab-separated
    (b"depth_um,pressure_MPa\n0,0\n1\n", "row 3"),  # a column missing
    (b"\xff\xfed\x00e\x00p\x00", "--target"),  # UTF-16
    (b"", "header"),
])
def test_foreign_csv_layouts_are_rejected(tmp_path, content, key_part):
    path = tmp_path / "x.csv"
    path.write_bytes(content)
    with pytest.raises(ConfigError) as err:
        read_curve_csv(path)
    assert key_part in err.value.key and err.value.allowed


@settings(max_examples=300, deadline=None)
@given(data=st.one_of(
    st.binary(max_size=200),
    st.lists(st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                                st.text(max_size=4)), min_size=1, max_size=4),
             max_size=6).map(lambda rows: ("depth_um,pressure_MPa\n" + "\n".join(
                 ",".join(str(v) for v in r) for r in rows)).encode())))
def test_any_file_is_a_valid_curve_or_a_config_error(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("csv") / "t.csv"
    path.write_bytes(data)
    try:
        depth, pressure, _ = read_curve_csv(path)
    except ConfigError as err:
        assert err.key and err.allowed
    else:
        assert len(depth) >= 2 and np.all(np.diff(depth) > 0) and depth[0] >= 0
        assert np.all(np.isfinite(pressure)) and np.all(pressure >= 0)
