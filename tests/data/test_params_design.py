"""The parameter space (Table 2) and the experimental designs (LHS, Sobol, CSV)."""

import numpy as np
import pytest

from calendaring.core.errors import ConfigError
from calendaring.data.design import design_report, make_design, plot_correlation, write_design_csv
from calendaring.data.params import PAPER_SPACE, Parameter, ParameterSpace


def test_paper_space_matches_table2():
    s = PAPER_SPACE
    assert s.names == ["damage_constant", "e_inf", "d0", "phi", "sigma_e", "alpha_percentage",
                       "b_prime", "truncation_ratio"]
    np.testing.assert_array_equal(s.lower, [1, 1500, 4e-6, 0.1, 0.1, 20, 0.01, 80])
    np.testing.assert_array_equal(s.upper, [10, 3500, 12e-6, 3.5, 1.0, 85, 0.1, 100])
    # the Table 4 optimum lies inside the Table 2 box
    assert np.all((s.reference > s.lower) & (s.reference < s.upper))


def test_unit_transform_round_trip_and_end_points():
    s = PAPER_SPACE
    np.testing.assert_allclose(s.to_unit(s.lower), 0.0, atol=1e-15)
    np.testing.assert_allclose(s.to_unit(s.upper), 1.0, atol=1e-15)
    u = np.random.default_rng(1).random((50, 8))
    np.testing.assert_allclose(s.to_unit(s.from_unit(u)), u, atol=1e-12)
    # d0 = 8 um is the middle of 4..12 um on the linear scale
    assert s.to_unit(s.reference)[2] == pytest.approx((9.396e-6 - 4e-6) / 8e-6)


def test_log_scale_maps_geometric_midpoint_to_half():
    s = ParameterSpace((Parameter("b_prime", "b'", "1", 0.01, 0.1, 0.03, scale="log"),
                        Parameter("phi", "phi", "1", 0.1, 3.5, 2.0)))
    u = s.to_unit([np.sqrt(0.01 * 0.1), 1.8])
    assert u[0] == pytest.approx(0.5)
    assert u[1] == pytest.approx(0.5)
    np.testing.assert_allclose(s.from_unit(u), [np.sqrt(0.001), 1.8])


def test_check_names_key_value_and_range():
    with pytest.raises(ConfigError, match=r"d0 = 2e-05 .*\[4e-06, 1.2e-05\] m"):
        PAPER_SPACE.check({"d0": 20e-6})
    with pytest.raises(ConfigError, match="parameter = 'gamma'"):
        PAPER_SPACE.check({"gamma": 5.0})
    with pytest.raises(ConfigError, match="missing"):
        PAPER_SPACE.check({"d0": 8e-6}, complete=True)
    with pytest.raises(ConfigError, match="phi"):
        PAPER_SPACE.check_array(np.tile(PAPER_SPACE.reference, (3, 1)) * [1, 1, 1, 2, 1, 1, 1, 1])
    with pytest.raises(ConfigError, match="last axis has 8"):
        PAPER_SPACE.to_unit(np.zeros((2, 7)))


def test_json_round_trip():
    s2 = ParameterSpace.from_json(PAPER_SPACE.to_json())
    assert s2 == PAPER_SPACE


def test_lhs_is_stratified_and_nearly_uncorrelated():
    n = 280
    x = make_design("lhs", n, seed=0)
    u = PAPER_SPACE.to_unit(x)
    for j in range(8):  # one point in each of the n strata of every parameter
        np.testing.assert_array_equal(np.sort(np.floor(u[:, j] * n)), np.arange(n))
    rep = design_report(x)
    assert rep["max_abs_r"] < 0.3  # the paper's design criterion
    assert rep["n"] == n
    # reproducible under the seed, different under another
    np.testing.assert_array_equal(make_design("lhs", n, seed=0), x)
    assert not np.allclose(make_design("lhs", n, seed=1), x)


def test_sobol_reference_centre_and_csv(tmp_path):
    x = make_design("sobol", 64, seed=3)
    assert x.shape == (64, 8)
    PAPER_SPACE.check_array(x)
    np.testing.assert_array_equal(make_design("reference", 2)[1], PAPER_SPACE.reference)
    np.testing.assert_allclose(PAPER_SPACE.to_unit(make_design("centre", 1)), 0.5)
    p = write_design_csv(tmp_path / "d.csv", x[:5])
    np.testing.assert_array_equal(make_design(str(p)), x[:5])
    (tmp_path / "partial.csv").write_text("d0,phi\n5e-6,1.0\n")
    row = make_design(str(tmp_path / "partial.csv"))[0]
    assert row[2] == 5e-6 and row[3] == 1.0 and row[0] == PAPER_SPACE.reference[0]
    (tmp_path / "bad.csv").write_text("d0,gamma\n5e-6,1.0\n")
    with pytest.raises(ConfigError, match="gamma"):
        make_design(str(tmp_path / "bad.csv"))
    (tmp_path / "out.csv").write_text("d0\n50e-6\n")
    with pytest.raises(ConfigError, match="d0"):
        make_design(str(tmp_path / "out.csv"))
    with pytest.raises(ConfigError, match="--design"):
        make_design("latin")


def test_correlation_heatmap_written(tmp_path):
    rep = design_report(make_design("lhs", 40, seed=2))
    p = plot_correlation(rep, tmp_path / "corr.png")
    assert p.stat().st_size > 10_000
    assert list(tmp_path.iterdir()) == [p]  # no temporary left behind


def test_sweep_preset_keeps_the_quick_physics():
    import json

    from calendaring.core.config import config_json, load_preset

    q = json.loads(config_json(load_preset("quick")))
    s = json.loads(config_json(load_preset("sweep").check_run()))
    for section in q:  # only the plate speed and the output differ
        if section not in ("protocol", "output"):
            assert s[section] == q[section], section
    assert s["protocol"]["stroke"] == q["protocol"]["stroke"]
    assert s["protocol"]["inertial_number"] == 1.5 * q["protocol"]["inertial_number"]
