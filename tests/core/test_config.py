"""Host-side configuration: strict loading, error messages, overrides, hashing, TOML round trip,
and the derived per-pair constants of calendaring.engine.contact_params (spec 1.2, 2.4, 9 T8)."""

import subprocess
import sys

import numpy as np
import pytest
import tomli_w

from calendaring.core.config import (
    SimConfig,
    config_hash,
    load_config,
    load_config_dict,
    to_dict,
    with_overrides,
)
from calendaring.core.errors import ConfigError
from calendaring.engine.contact_params import (
    COL,
    damping_ratio,
    pair_table,
    plate_table,
    reduced_modulus,
    reduced_shear_modulus,
)

HOST_MODULES = ("calendaring.core.config", "calendaring.core.units", "calendaring.engine.timestep",
                "calendaring.engine.contact_params", "calendaring.core.cli_contract",
                "calendaring.process.preflight")


def test_host_modules_do_not_import_taichi_or_torch():
    code = (
        "import sys\n"
        + "".join(f"import {m}\n" for m in HOST_MODULES)
        + "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('taichi', 'torch'))\n"
        + f"assert all(m in sys.modules for m in {HOST_MODULES!r})\n"
        + "print('HEAVY=' + ','.join(bad))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr
    assert "HEAVY=\n" in res.stdout, res.stdout


@pytest.mark.parametrize(
    "data, key, value, allowed",
    [
        ({"materials": {"AM": {"youngs_modulus": -1.0e9}}}, "materials.AM.youngs_modulus",
         "-1000000000.0", "> 0"),
        ({"materials": {"AM": {"youngs_modulus": 0.0}}}, "materials.AM.youngs_modulus",
         "0.0", "> 0"),
        ({"materials": {"AM": {"poisson_ratio": 0.5}}}, "materials.AM.poisson_ratio",
         "0.5", "(-1, 0.5)"),
        ({"materials": {"AM": {"poisson_ratio": -1.2}}}, "materials.AM.poisson_ratio",
         "-1.2", "(-1, 0.5)"),
        ({"contact": {"pairs": {"AM-AM": {"plasticity_ratio": 1.0}}}},
         "contact.pairs.AM-AM.plasticity_ratio", "1.0", "[0, 1)"),
        ({"contact": {"pairs": {"AM-AM": {"plasticity_ratio": -0.1}}}},
         "contact.pairs.AM-AM.plasticity_ratio", "-0.1", "[0, 1)"),
        ({"contact": {"pairs": {"AM-CB": {"surface_energy": -5.0}}}},
         "contact.pairs.AM-CB.surface_energy", "-5.0", ">= 0"),
    ],
)
def test_bad_material_values_name_key_value_and_range(data, key, value, allowed):
    with pytest.raises(ConfigError) as info:
        load_config_dict(data)
    err = info.value
    msg = str(err)
    assert err.key == key
    assert key in msg
    assert value in msg
    assert "allowed" in msg
    assert allowed in msg


@pytest.mark.parametrize(
    "data, key",
    [
        ({"numerics": {"timestep_fractoin": 0.02}}, "numerics.timestep_fractoin"),
        ({"materials": {"AM": {"youngs": 1.0e9}}}, "materials.AM.youngs"),
        ({"contact": {"pairs": {"AM-AM": {"frcition": 0.3}}}}, "contact.pairs.AM-AM.frcition"),
        ({"bogus": 1}, "bogus"),
    ],
)
def test_unknown_key_rejected_with_dotted_name(data, key):
    with pytest.raises(ConfigError) as info:
        load_config_dict(data)
    assert info.value.key == key
    assert key in str(info.value)


@pytest.mark.parametrize(
    "data, key, kind",
    [
        ({"numerics": {"timestep_fraction": "0.04"}}, "numerics.timestep_fraction", "a number"),
        ({"materials": {"AM": {"youngs_modulus": "168e9"}}}, "materials.AM.youngs_modulus",
         "a number"),
        ({"numerics": {"seed": 1.5}}, "numerics.seed", "an integer"),
        ({"numerics": {"track_energy": 1}}, "numerics.track_energy", "true or false"),
        ({"contact": {"pairs": {"AM-AM": {"friction": True}}}}, "contact.pairs.AM-AM.friction",
         "a number"),
        ({"contact": {"adhesion_mode": 1}}, "contact.adhesion_mode", "a string"),
    ],
)
def test_wrong_type_rejected(data, key, kind):
    with pytest.raises(ConfigError) as info:
        load_config_dict(data)
    assert info.value.key == key
    assert key in str(info.value)
    assert f"allowed {kind}" in str(info.value)


def test_partial_dict_keeps_paper_defaults():
    cfg = load_config_dict({"numerics": {"timestep_fraction": 0.02},
                            "contact": {"pairs": {"CB-CB": {"surface_energy": 30.0}}}})
    assert cfg.numerics.timestep_fraction == 0.02
    assert cfg.contact.pairs["CB-CB"].surface_energy == 30.0
    assert cfg.contact.pairs["CB-CB"].plasticity_ratio == 0.975  # untouched default
    assert cfg.materials["AM"].youngs_modulus == 168.30e9
    assert cfg.pair("CB", "AM").plasticity_ratio == 0.9  # order-insensitive lookup


def test_with_overrides():
    cfg = with_overrides(SimConfig(), {"numerics.seed": 3,
                                       "contact.pairs.AM-CB.friction": 0.3,
                                       "materials.CB.density": 1800.0})
    assert cfg.numerics.seed == 3
    assert cfg.contact.pairs["AM-CB"].friction == 0.3
    assert cfg.materials["CB"].density == 1800.0
    assert cfg.materials["AM"].density == 4740.0
    with pytest.raises(ConfigError) as info:
        with_overrides(SimConfig(), {"numerics.sede": 3})
    assert "numerics.sede" in str(info.value)
    with pytest.raises(ConfigError) as info:
        with_overrides(SimConfig(), {"numercs.seed": 3})
    assert "numercs" in str(info.value)
    with pytest.raises(ConfigError) as info:  # values are validated too
        with_overrides(SimConfig(), {"materials.AM.poisson_ratio": 0.7})
    assert info.value.key == "materials.AM.poisson_ratio"


def test_config_hash_stable_and_value_sensitive():
    h0 = config_hash(SimConfig())
    assert h0 == config_hash(SimConfig())
    assert h0 == config_hash(load_config_dict({}))
    assert len(h0) == 64 and int(h0, 16) >= 0  # sha256 hex digest
    h1 = config_hash(with_overrides(SimConfig(), {"numerics.seed": 1}))
    h2 = config_hash(with_overrides(SimConfig(), {"contact.pairs.CB-CB.surface_energy": 60.5}))
    assert len({h0, h1, h2}) == 3


def test_toml_round_trip(tmp_path):
    cfg = with_overrides(SimConfig(), {"numerics.seed": 7, "numerics.timestep_fraction": 0.02,
                                       "contact.adhesion_mode": "jkr_R",
                                       "contact.pairs.CB-CB.plasticity_ratio": 0.985})
    path = tmp_path / "run.toml"
    path.write_text(tomli_w.dumps(to_dict(cfg)))
    back = load_config(path)
    assert back == cfg
    assert config_hash(back) == config_hash(cfg)
    assert back.contact.pairs["CB-CB"].plasticity_ratio == 0.985
    assert back.contact.adhesion_mode == "jkr_R"


def test_invalid_toml_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[numerics\nseed = 1\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(path) in str(info.value)


# ------------------------------------------------------------- contact_params (spec 1.2, T8)

CFG = SimConfig()
AM = CFG.materials["AM"]
CB = CFG.materials["CB"]


def test_reduced_moduli_match_spec_table():
    """Spec 1.2 (4 significant figures -> rtol 3e-4)."""
    np.testing.assert_allclose(reduced_modulus(AM, AM), 8.957e10, rtol=3e-4)
    np.testing.assert_allclose(reduced_shear_modulus(AM, AM), 1.925e10, rtol=3e-4)
    np.testing.assert_allclose(reduced_modulus(AM, CB), 6.745e8, rtol=3e-4)
    np.testing.assert_allclose(reduced_shear_modulus(AM, CB), 1.499e8, rtol=3e-4)
    np.testing.assert_allclose(reduced_modulus(CB, CB), 3.385e8, rtol=3e-4)
    np.testing.assert_allclose(reduced_modulus(AM, CFG.plates.top), 1.004e11, rtol=3e-4)
    np.testing.assert_allclose(reduced_modulus(AM, CFG.plates.bottom), 5.328e10, rtol=3e-4)


def test_pair_table_columns():
    tab = pair_table(CFG)
    assert tab.shape == (2, 2, len(COL))
    np.testing.assert_allclose(tab[0, 0, COL["e_star"]], 8.957e10, rtol=3e-4)
    np.testing.assert_allclose(tab[0, 0, COL["g_star"]], 1.925e10, rtol=3e-4)
    np.testing.assert_allclose(tab[0, 1, COL["e_star"]], 6.745e8, rtol=3e-4)
    sym = [c for name, c in COL.items() if name != "stiffness_partition"]
    np.testing.assert_allclose(tab[1, 0, sym], tab[0, 1, sym], rtol=1e-15)  # symmetric pair data
    np.testing.assert_allclose(tab[:, :, COL["plasticity_ratio"]],
                               [[0.8, 0.9], [0.9, 0.975]], rtol=1e-15)
    np.testing.assert_allclose(tab[:, :, COL["surface_energy"]],
                               [[5.0, 20.0], [20.0, 60.0]], rtol=1e-15)
    np.testing.assert_allclose(tab[:, :, COL["beta_hat"]], 0.4037, rtol=3e-4)
    # T8: e_i + e_j = 1; e(AM|AM) = 0.5, e(AM|CB) = 0.0038
    part = tab[:, :, COL["stiffness_partition"]]
    np.testing.assert_allclose(part + part.T, 1.0, rtol=1e-14)
    np.testing.assert_allclose(part[0, 0], 0.5, rtol=1e-14)
    np.testing.assert_allclose(part[0, 1], 0.0038, rtol=1.5e-2)  # 2 significant figures


def test_plate_table_stiffness_partition():
    """T8: e(AM|steel) = 0.5606 (top plate, index 1), e(AM|Al) = 0.2974 (bottom, index 0)."""
    tab = plate_table(CFG)
    assert tab.shape == (2, 2, len(COL))
    np.testing.assert_allclose(tab[0, 1, COL["stiffness_partition"]], 0.5606, rtol=2e-4)
    np.testing.assert_allclose(tab[0, 0, COL["stiffness_partition"]], 0.2974, rtol=2e-4)
    np.testing.assert_allclose(tab[0, 1, COL["e_star"]], 1.004e11, rtol=3e-4)
    np.testing.assert_allclose(tab[0, 0, COL["e_star"]], 5.328e10, rtol=3e-4)
    # plate pairs: the particle's own-pair plasticity ratio and no adhesion (spec 6)
    np.testing.assert_allclose(tab[:, :, COL["plasticity_ratio"]], [[0.8, 0.8], [0.975, 0.975]],
                               rtol=1e-15)
    np.testing.assert_array_equal(tab[:, :, COL["surface_energy"]], 0.0)


@pytest.mark.parametrize("e, beta", [(0.25, 0.4037), (1.0, 0.0)])
def test_damping_ratio(e, beta):
    """beta_hat = -ln e / sqrt(ln^2 e + pi^2): 0.4037 for e = 0.25 (spec 2.4), 0 for e = 1."""
    np.testing.assert_allclose(damping_ratio(e), beta, rtol=2e-4, atol=0.0)


def test_json_config_round_trip(tmp_path):
    """A run file's or dataset's configuration JSON reruns exactly that problem."""
    from calendaring.core.config import config_json

    cfg = with_overrides(SimConfig(), {"numerics.seed": 3, "domain.cell_x": 40e-6})
    path = tmp_path / "run.json"
    path.write_text(config_json(cfg))
    back = load_config(path)
    assert back == cfg and config_hash(back) == config_hash(cfg)
    path.write_text("[1, 2]")
    with pytest.raises(ConfigError, match="JSON object"):
        load_config(path)
    path.write_text("{not json")
    with pytest.raises(ConfigError, match="valid JSON"):
        load_config(path)
