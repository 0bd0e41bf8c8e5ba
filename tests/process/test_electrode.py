"""Electrode recipe: particle counts from the coating's mass balance and the size
distributions (normal, lognormal, constant, measured table), host side only."""

import math

import numpy as np
import pytest
from scipy import stats

from calendaring.core.config import SimConfig, SizeConfig, load_config_dict
from calendaring.core.errors import ConfigError
from calendaring.process.electrode import random_insertion, recipe, sample_diameters


def test_paper_recipe_matches_the_mass_balance():
    cfg = SimConfig()
    rec = recipe(cfg, np.random.default_rng(0))
    area = cfg.domain.cell_x * cfg.domain.cell_y
    total = 2560.0 * area * 75e-6
    for name, w, rho, d_max in (("AM", 0.94, 4740.0, 10.69e-6), ("CB", 0.06, 2200.0, 3e-6)):
        half_particle = 0.5 * rho * math.pi / 6 * d_max**3
        assert rec.target_mass[name] == pytest.approx(w * total, rel=1e-12)
        assert abs(rec.mass[name] - w * total) <= half_particle
    # solid density 1 / (0.94/4740 + 0.06/2200) -> porosity 1 - 2560 / 4434 = 42.26 %
    phi = 1 - 2560.0 / (1 / (0.94 / 4740 + 0.06 / 2200))
    assert rec.porosity == pytest.approx(phi, abs=2e-3)
    assert 1300 < rec.counts["AM"] < 1600 and 3600 < rec.counts["CB"] < 3800
    vol = np.sum(math.pi / 6 * rec.diameter**3)
    assert rec.porosity == pytest.approx(1 - vol / (area * 75e-6), rel=1e-12)


def test_truncated_normal_sizes():
    size = SimConfig().electrode.sizes["AM"]
    d = sample_diameters(size, np.random.default_rng(1), 20000)
    assert d.min() >= 4.94e-6 and d.max() <= 10.69e-6
    a, b = (4.94 - 7.74) / 1.35, (10.69 - 7.74) / 1.35
    mean = stats.truncnorm.mean(a, b, loc=7.74e-6, scale=1.35e-6)
    sd = stats.truncnorm.std(a, b, loc=7.74e-6, scale=1.35e-6)
    assert abs(d.mean() - mean) < 4 * sd / math.sqrt(d.size)


def test_lognormal_sizes_have_the_requested_moments():
    size = SizeConfig(distribution="lognormal", mean=8e-6, std=1.5e-6, min=1e-7, max=1e-4)
    d = sample_diameters(size, np.random.default_rng(2), 40000)
    assert d.mean() == pytest.approx(8e-6, rel=0.01)
    assert d.std() == pytest.approx(1.5e-6, rel=0.03)


def test_measured_table_by_volume(tmp_path):
    table = tmp_path / "psd.csv"
    table.write_text("diameter_m,fraction\n1e-6,0.5\n2e-6,0.5\n")
    size = SizeConfig(distribution="table", table=str(table), table_basis="volume")
    d = sample_diameters(size, np.random.default_rng(3), 90000)
    # equal volumes: 8 small spheres per large one
    assert np.mean(d == 1e-6) == pytest.approx(8 / 9, abs=0.005)
    bad = tmp_path / "bad.csv"
    bad.write_text("diameter_m,fraction\n1e-6,abc\n")
    with pytest.raises(ConfigError, match=r"bad\.csv"):
        sample_diameters(SizeConfig(distribution="table", table=str(bad)),
                         np.random.default_rng(0), 3)


def test_insertion_is_non_overlapping_and_periodic():
    rng = np.random.default_rng(5)
    diam = np.concatenate([rng.uniform(4e-6, 9e-6, 60), np.full(200, 3e-6)])
    mat = np.concatenate([np.zeros(60, np.int32), np.ones(200, np.int32)])
    pos, rad, _ = random_insertion(diam, mat, 30e-6, 30e-6, 80e-6, rng)
    d = pos[None] - pos[:, None]
    d[..., :2] -= 30e-6 * np.round(d[..., :2] / 30e-6)
    dist = np.linalg.norm(d, axis=-1) + np.eye(len(rad))
    assert np.all(dist >= (rad[None] + rad[:, None]) * (1 - 1e-12) - np.eye(len(rad)) * 1)
    assert np.all(pos[:, 2] - rad >= 0) and np.all(pos[:, 2] + rad <= 80e-6)
    with pytest.raises(ConfigError, match=r"domain\.height"):
        random_insertion(np.full(500, 9e-6), np.zeros(500, np.int32), 30e-6, 30e-6, 20e-6,
                         rng, max_tries=20)


@pytest.mark.parametrize("data, key", [
    ({"electrode": {"composition": {"AM": 0.9, "CB": 0.06}}}, "electrode.composition"),
    ({"electrode": {"sizes": {"AM": {"distribution": "normal", "mean": 7e-6, "std": 0.0}}}},
     "electrode.sizes.AM.std"),
    ({"electrode": {"sizes": {"AM": {"distribution": "gamma"}}}},
     "electrode.sizes.AM.distribution"),
    ({"bonds": {"normal_criterion": "both"}}, "bonds.normal_criterion"),
    ({"protocol": {"inertial_number": 0.0}}, "protocol.inertial_number"),
])
def test_run_sections_reject_bad_values(data, key):
    with pytest.raises(ConfigError) as err:
        load_config_dict(data).check_run()
    assert err.value.key == key


def test_check_run_rejects_impossible_geometry():
    for data, key in (({"protocol": {"stroke": 80e-6}}, "protocol.stroke"),
                      ({"electrode": {"thickness": 250e-6}}, "electrode.thickness"),
                      ({"domain": {"cell_x": 15e-6}}, "domain.cell_x"),
                      ({"electrode": {"composition": {"AM": 0.94, "CB": 0.0, "XX": 0.06}}},
                       "electrode.composition.XX")):
        with pytest.raises(ConfigError) as err:
            load_config_dict(data).check_run()
        assert err.value.key == key
