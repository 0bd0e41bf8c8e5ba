"""Key outputs, Sobol indices (Ishigami), convergence, ensemble spread, given-data check.

The surrogate is replaced by :class:`AnalyticSurrogate`, an object with the surrogate API
(``space``, ``depth``, edges, ``is_ensemble``, ``predict_unit``) whose outputs have known
Sobol indices. One integration test trains a tiny real surrogate on synthetic data.
"""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from analysis.outputs import OUTPUTS, key_outputs, outputs_of_dataset
from analysis.sensitivity import (
    check_power_of_two,
    compare_to_reference,
    dataset_given_data,
    ensemble_spread,
    given_data_check,
    ishigami,
    ishigami_indices,
    member_models,
    paper_claims,
    sobol_convergence,
    sobol_indices,
    sobol_study,
    surrogate_model,
)
from calendaring.core.errors import ConfigError
from calendaring.data.dataset import synthetic_dataset
from calendaring.data.params import PAPER_SPACE

IE, ID0, IPHI, ISIG = 1, 2, 3, 4  # e_inf, d0, phi, sigma_e columns of PAPER_SPACE


class AnalyticSurrogate:
    """Stand-in with the surrogate API and analytic key outputs.

    peak pressure = P0 (1 + c u[e_inf] + u[d0]): first-order indices c^2/(c^2+1), 1/(c^2+1);
    all probability in the load bin floor(30 u[phi]) and the diameter bin
    floor(30 u[sigma_e]): the stress centroid and low-stress ratio depend on phi only, the
    diameter centroid on sigma_e only.
    """

    def __init__(self, c: float = 2.0, members=None):
        self.c = c
        self.space = PAPER_SPACE
        edges = np.linspace(0.0, 19.5e-6, 197)
        self.depth = 0.5 * (edges[1:] + edges[:-1])
        self.load_edges = np.geomspace(1e-3, 1.0, 31)
        self.diameter_edges = np.linspace(4e-6, 16e-6, 31)
        self.load_scale = "log"
        self.members = members
        self.is_ensemble = bool(members)
        self.info = {"path": "analytic"}

    def predict_unit(self, u):
        u = np.atleast_2d(np.asarray(u, float))
        if self.members:
            preds = [m.predict_unit(u) for m in self.members]
            return SimpleNamespace(pressure=np.mean([p.pressure for p in preds], 0),
                                   distribution=np.mean([p.distribution for p in preds], 0))
        shape = (self.depth / self.depth[-1]) ** 2
        peak = 1e6 * (1 + self.c * u[:, IE] + u[:, ID0])
        d = np.zeros((len(u), 30, 30))
        il = np.minimum((30 * u[:, IPHI]).astype(int), 29)
        jd = np.minimum((30 * u[:, ISIG]).astype(int), 29)
        d[np.arange(len(u)), il, jd] = 1.0
        return SimpleNamespace(pressure=peak[:, None] * shape[None, :], distribution=d)


# ---------------------------------------------------------------------- outputs
def test_outputs_of_hand_made_histogram_and_curve():
    # log load axis, 3 bins: geometric centres 10^0.5, 10^1.5, 10^2.5 N
    le = np.array([1.0, 10.0, 100.0, 1000.0])
    de = np.array([2e-6, 4e-6, 6e-6])  # centres 3 and 5 um
    h = np.array([[0.2, 0.1], [0.3, 0.1], [0.1, 0.2]])  # load marginal .3 .4 .3; diam .6 .4
    p = np.array([0.0, 1e6, 3e6, 2e6])
    out = key_outputs(p, h, le, de)
    assert out["peak_pressure"] == pytest.approx(3e6)
    # exp(sum p ln c) = 10^(0.3*0.5 + 0.4*1.5 + 0.3*2.5) = 10^1.5
    assert out["stress_centroid"] == pytest.approx(10**1.5, rel=1e-12)
    assert out["diameter_centroid"] == pytest.approx(0.6 * 3e-6 + 0.4 * 5e-6, rel=1e-12)
    assert out["low_stress_ratio"] == pytest.approx(0.3)  # lowest third = first bin
    # a linear load axis with 6 bins, counts instead of probabilities, batched with an
    # empty histogram (no events): centroids and ratio NaN
    le6 = np.arange(7.0)  # centres 0.5 .. 5.5 N
    h6 = np.zeros((2, 6, 1))
    h6[0, :, 0] = [1, 2, 3, 4, 0, 0]
    out6 = key_outputs(np.array([[1.0, 5.0], [2.0, 1.0]]), h6, le6, np.array([1e-6, 2e-6]))
    np.testing.assert_allclose(out6["peak_pressure"], [5.0, 2.0])
    assert out6["stress_centroid"][0] == pytest.approx((0.5 + 2 * 1.5 + 3 * 2.5 + 4 * 3.5)
                                                        / 10)
    assert out6["low_stress_ratio"][0] == pytest.approx(0.3)  # bins 0-1 of 6: 3/10
    assert out6["diameter_centroid"][0] == pytest.approx(1.5e-6)
    assert np.isnan(out6["stress_centroid"][1]) and np.isnan(out6["low_stress_ratio"][1])


def test_outputs_reject_mismatched_shapes():
    with pytest.raises(ConfigError, match="distribution"):
        key_outputs(np.ones(4), np.ones((3, 3)), np.arange(3.0), np.arange(4.0))
    with pytest.raises(ConfigError, match="load_edges"):
        key_outputs(np.ones(4), np.ones((3, 3)), np.array([3.0, 2.0, 1.0, 0.5]), np.arange(4.0))


def test_outputs_of_synthetic_dataset_follow_its_formulas():
    ds = synthetic_dataset(n=8, seed=3)
    out = outputs_of_dataset(ds)
    u = ds.unit_params
    # synthetic pressure P0 (exp(k z / stroke) - 1) is increasing: peak at the last point
    np.testing.assert_allclose(out["peak_pressure"], ds.pressure[:, -1])
    # the diameter blob is centred at 6 + 6 u[phi] um (truncated Gaussian: close, not equal)
    np.testing.assert_allclose(out["diameter_centroid"], 6e-6 + 6e-6 * u[:, 3], atol=1.2e-6)
    assert np.all((out["low_stress_ratio"] >= 0) & (out["low_stress_ratio"] <= 1))


# ---------------------------------------------------------------------- Sobol
def test_ishigami_analytic_values():
    ref = ishigami_indices(7.0, 0.1)
    np.testing.assert_allclose(ref["S1"], [0.3139, 0.4424, 0.0], atol=1e-4)
    np.testing.assert_allclose(ref["ST"], [0.5576, 0.4424, 0.2437], atol=1e-4)


def test_ishigami_indices_within_0p05():
    res = sobol_indices(ishigami, ["x1", "x2", "x3"], 2**12, seed=1)
    ref = ishigami_indices()
    d = res.indices["y"]
    np.testing.assert_allclose(d["S1"], ref["S1"], atol=0.05)
    np.testing.assert_allclose(d["ST"], ref["ST"], atol=0.05)
    assert res.n_evaluations == 2**12 * 5
    assert np.all(d["S1_conf"] > 0) and np.all(d["ST_conf"] < 0.1)
    assert res.ranking("y") == ["x1", "x2", "x3"]


def test_convergence_evaluates_each_row_once_and_stops():
    calls = []

    def counted(u):
        calls.append(len(u))
        return ishigami(u)

    rows, res = sobol_convergence(counted, ["x1", "x2", "x3"], 2**14, n_min=2**8, seed=1)
    ns = [r["n"] for r in rows]
    assert ns == [2**8 * 2**i for i in range(len(ns))]
    assert rows[-1]["converged"] and rows[-1]["max_conf"] < 0.05
    assert not any(r["converged"] for r in rows[:-1])
    assert not rows[0]["ranking_stable"]  # nothing to compare with at the first level
    # nested designs: each level evaluates only its new rows
    assert sum(calls) == res.n * 5
    ref = ishigami_indices()
    np.testing.assert_allclose(res.indices["y"]["ST"], ref["ST"], atol=0.05)


def test_power_of_two_checked():
    assert check_power_of_two(1024) == 1024
    for bad in (1000, 0, -4, "x", 2.5):
        with pytest.raises(ConfigError, match="power of two"):
            check_power_of_two(bad)


def test_stand_in_surrogate_indices_and_member_spread(tmp_path):
    members = [AnalyticSurrogate(c) for c in (1.5, 2.0, 2.5)]
    ens = AnalyticSurrogate(members=members)
    assert member_models(ens) == members
    res = sobol_indices(surrogate_model(ens), PAPER_SPACE.names, 2**11, seed=2)
    # ensemble mean: peak = P0 (1 + 2 u_E + u_d0): S1 = 4/5, 1/5; the rest 0
    pk = res.indices["peak_pressure"]
    np.testing.assert_allclose(pk["S1"][[IE, ID0]], [0.8, 0.2], atol=0.03)
    np.testing.assert_allclose(np.delete(pk["ST"], [IE, ID0]), 0, atol=0.01)
    for out, col in (("stress_centroid", IPHI), ("low_stress_ratio", IPHI),
                     ("diameter_centroid", ISIG)):
        assert res.indices[out]["S1"][col] == pytest.approx(1.0, abs=0.03)
        assert np.all(np.abs(np.delete(res.indices[out]["ST"], col)) < 0.01)
    sp = ensemble_spread(ens, PAPER_SPACE.names, 2**10, seed=2)
    assert sp["method"] == "per-member" and sp["n_members"] == 3
    s1 = np.array(sp["indices"]["peak_pressure"]["S1"]["members"])[:, IE]
    np.testing.assert_allclose(s1, [c**2 / (c**2 + 1) for c in (1.5, 2.0, 2.5)], atol=0.03)
    assert sp["indices"]["peak_pressure"]["S1"]["std"][IE] > 0.02
    # a single model: bootstrap spread, labelled as such
    single = AnalyticSurrogate()
    assert member_models(single) is None
    sb = ensemble_spread(single, PAPER_SPACE.names, 2**9, seed=2)
    assert sb["method"] == "bootstrap" and "not the epistemic" in sb["note"]
    assert 0 < sb["indices"]["peak_pressure"]["ST"]["std"][IE] < 0.1


def test_sobol_study_writes_json_and_figures(tmp_path):
    ds = synthetic_dataset(n=96, seed=4)
    res = sobol_study(AnalyticSurrogate(), tmp_path, n=2**9, n_min=2**8, seed=0, dataset=ds,
                      spread_n=2**8, progress=False)
    js = json.loads((tmp_path / "sobol.json").read_text())
    assert js["sobol"]["n"] == 2**9 and [r["n"] for r in js["convergence"]] == [256, 512]
    assert js["sobol"]["names"] == PAPER_SPACE.names
    assert set(js["sobol"]["indices"]) == set(OUTPUTS)
    assert js["outputs"]["peak_pressure"]["unit"] == "Pa"
    assert js["ensemble_spread"]["method"] == "bootstrap"
    assert js["given_data"]["method"] == "rbd_fast"
    for f in ("sobol_indices.png", "sobol_convergence.png"):
        assert (tmp_path / f).stat().st_size > 1000
    assert res["sobol"]["ranking_by_ST"]["diameter_centroid"][0] == "sigma_e"
    assert set(js["paper_claims"]["outputs"]) == set(OUTPUTS)
    assert set(js["given_data_check"]) == set(OUTPUTS)
    assert not list(tmp_path.glob(".*tmp*"))  # no temporary files left


def test_given_data_cross_check_on_dataset_runs():
    # synthetic dataset: the diameter blob centre depends on phi only
    ds = synthetic_dataset(n=160, seed=5, replicate_groups=2, replicates=3)
    res = dataset_given_data(ds, "rbd_fast", seed=0)
    assert res["rows_total"] == 160  # replicates excluded (role 'train' only)
    s1 = np.array(res["indices"]["diameter_centroid"]["S1"])
    assert np.argmax(s1) == IPHI and s1[IPHI] > 0.7
    with pytest.raises(ConfigError, match="method"):
        dataset_given_data(ds, "morris")
    # 40 rows: RBD-FAST's halved bootstrap would divide by zero; reported, not raised
    small = dataset_given_data(synthetic_dataset(n=40, seed=5), "rbd_fast", seed=0)
    assert all("need at least 42" in v["error"] for v in small["indices"].values())


# ---------------------------------------------------------------------- real surrogate
def test_sobol_on_a_tiny_trained_surrogate(tmp_path):
    """Integration: a tiny real 2-member ensemble trained on synthetic data, saved, loaded
    and analysed (per-member spread through single-member wrappers)."""
    surrogate = pytest.importorskip("surrogate")
    if not hasattr(surrogate, "load"):
        pytest.skip("surrogate.load not available yet")
    import torch

    from surrogate.api import SurrogateModel
    from surrogate.ensemble import train_ensemble
    from surrogate.model import ModelConfig
    from surrogate.train import TrainConfig

    torch.set_num_threads(1)
    ds = synthetic_dataset(n=40, seed=0)
    mc = ModelConfig(embed_width=16, block_widths=(16,), pressure_hidden=16,
                     dist_hidden=(16,))
    tc = TrainConfig(epochs=2, batch_size=16, seed=0, snapshot_epochs=())
    results = train_ensemble(ds, 2, tc, mc, progress=False)
    path = SurrogateModel.from_training(results, ds).save(tmp_path / "model.pt")
    m = surrogate.load(path)
    assert m.is_ensemble
    res = sobol_indices(surrogate_model(m), m.space.names, 2**7, seed=0)
    for o in OUTPUTS:
        assert np.all(np.isfinite(res.indices[o]["ST"]))
    assert res.n_evaluations == 2**7 * 10
    members = member_models(m)
    assert members is not None and len(members) == 2
    u = np.full((1, 8), 0.3)
    p_mean = m.predict_unit(u).pressure_normalised
    p_members = [x.predict_unit(u).pressure_normalised for x in members]
    np.testing.assert_allclose(np.mean(p_members, axis=0), p_mean, rtol=1e-5, atol=1e-6)
    sp = ensemble_spread(m, m.space.names, 2**6, seed=0)
    assert sp["method"] == "per-member" and sp["n_members"] == 2
    # the study evaluates the members once (mean and member outputs from one pass): the
    # same indices as the separate paths above
    js = sobol_study(m, tmp_path / "s", n=2**7, n_min=2**6, spread_n=2**6, seed=0,
                     progress=False)
    for o in OUTPUTS:
        np.testing.assert_allclose(js["sobol"]["indices"][o]["ST"], res.indices[o]["ST"],
                                   atol=1e-4)
        np.testing.assert_allclose(js["ensemble_spread"]["indices"][o]["S1"]["members"],
                                   sp["indices"][o]["S1"]["members"], atol=1e-4)


# ---------------------------------------------------------------------- against the paper
def _sobol_json(st, conf=0.01, s1=None):
    names = PAPER_SPACE.names
    st = np.asarray(st, float)
    s1 = st if s1 is None else np.asarray(s1, float)
    d = {"S1": s1.tolist(), "S1_conf": [conf] * 8, "ST": st.tolist(), "ST_conf": [conf] * 8}
    return {"names": names, "indices": {"peak_pressure": d, "diameter_centroid": d}}


def test_paper_claims_dominant_and_negligible_verdicts():
    # order of PAPER_SPACE: gamma, E_inf, d0, phi, sigma_E, A, b', R_t
    res = paper_claims(_sobol_json([0.01, 0.1, 0.5, 0.3, 0.05, 0.02, 0.02, 0.048]))
    c = res["outputs"]["peak_pressure"]
    assert c["dominant_holds"] and c["rank_of"] == {"d0": 1, "phi": 2}
    assert c["negligible"]["damage_constant"]["verdict"] == "negligible"  # 0.02 < 0.05
    assert c["negligible"]["truncation_ratio"]["verdict"] == "not resolved"  # 0.048 +- 0.01
    assert res["dominant_holds_in"] == "2 of 2 outputs"
    res = paper_claims(_sobol_json([0.2, 0.6, 0.5, 0.1, 0.0, 0.0, 0.0, 0.0]))
    c = res["outputs"]["peak_pressure"]
    assert not c["dominant_holds"] and c["rank_of"] == {"d0": 2, "phi": 4}
    assert c["negligible"]["damage_constant"]["verdict"] == "not negligible"


def test_compare_to_reference_and_given_data_check():
    a = _sobol_json([0.01, 0.1, 0.5, 0.3, 0.05, 0.02, 0.02, 0.0])
    same = compare_to_reference(a, a)["peak_pressure"]
    assert same["kendall_tau_ST"] == pytest.approx(1.0) and same["differ"] == {}
    b = _sobol_json([0.01, 0.1, 0.3, 0.5, 0.05, 0.02, 0.02, 0.0])  # d0 and phi swapped
    c = compare_to_reference(a, b)["peak_pressure"]
    assert c["same_top2"] and c["top2"] == ["d0", "phi"] and c["reference_top2"] == ["phi", "d0"]
    assert set(c["differ"]) == {"d0", "phi"} and c["kendall_tau_ST"] < 1
    with pytest.raises(ConfigError):
        compare_to_reference(a, {**b, "names": list(reversed(PAPER_SPACE.names))})
    given = {"indices": {"peak_pressure": {"S1": [0, 0.6, 0.3, 0, 0, 0, 0, 0],
                                           "S1_conf": [0.05] * 8},
                         "diameter_centroid": {"error": "3 usable rows"}}}
    g = given_data_check(a, given)
    assert g["peak_pressure"]["given_data_top2_S1"] == ["e_inf", "d0"]
    assert not g["peak_pressure"]["agree"] and "error" in g["diameter_centroid"]
