"""Dataset transforms against analytic results, the file round trip and its rejections."""

import h5py
import numpy as np
import pytest

from calendaring.core.errors import ConfigError
from calendaring.data.dataset import (
    DatasetError,
    bin_events,
    build_dataset,
    centroids,
    histogram_edges,
    kl_divergence,
    noise_floor,
    perfect_model_kl,
    pressure_components,
    read_dataset,
    resample_pressure,
    sampled_kl_floor,
    seed_means,
    smooth,
    synthetic_dataset,
    write_dataset,
)


def test_resample_is_the_exact_interval_mean():
    # P = a z^2 sampled finely and unevenly: the mean over [z0, z1] is a (z1^3 - z0^3)/(3 dz)
    stroke, a = 19.5e-6, 3e17
    z = np.sort(np.concatenate([np.linspace(0, stroke, 20001),
                                np.random.default_rng(0).random(5000) * stroke]))
    mid, p = resample_pressure(z, a * z**2, stroke, 196)
    e = np.linspace(0, stroke, 197)
    exact = a * (e[1:] ** 3 - e[:-1] ** 3) / (3 * np.diff(e))
    np.testing.assert_allclose(mid, 0.5 * (e[1:] + e[:-1]))
    np.testing.assert_allclose(p, exact, rtol=1e-4)  # trapezoid error of the fine trace
    # a linear trace is exact whatever the sampling
    zc = np.linspace(0, stroke, 7)
    _, pl = resample_pressure(zc, 5e12 * zc, stroke, 196)
    np.testing.assert_allclose(pl, 5e12 * mid, rtol=1e-12)


def test_resample_rejects_short_or_bad_traces():
    with pytest.raises(ValueError, match="short of"):
        resample_pressure([0, 1e-6], [0, 1], 19.5e-6)
    with pytest.raises(ValueError, match="non-decreasing"):
        resample_pressure([0, 2e-5, 1e-5], [0, 1, 2], 1e-5)
    with pytest.raises(ValueError, match="non-finite"):
        resample_pressure([0, 1e-5], [0, np.nan], 1e-5)


def test_savgol_order3_reproduces_a_cubic_and_smooths_noise():
    x = np.linspace(-1, 1, 196)
    cubic = 2 + x - 3 * x**2 + 0.5 * x**3
    np.testing.assert_allclose(smooth(cubic, 17, 3), cubic, atol=1e-12)
    noisy = cubic + 0.1 * np.random.default_rng(0).standard_normal(196)
    assert np.std(smooth(noisy) - cubic) < 0.6 * np.std(noisy - cubic)
    with pytest.raises(ConfigError, match="savgol_window"):
        smooth(cubic, 16, 3)


def test_pressure_transform_round_trip():
    ds = synthetic_dataset(20, seed=1)
    x = ds.pressure_normalised
    assert x.min() == pytest.approx(0.0, abs=1e-12) and x.max() == pytest.approx(1.0)
    np.testing.assert_allclose(ds.pressure_from_normalised(x), ds.pressure, rtol=1e-10,
                               atol=1e-6)


def test_histogram_counts_and_normalisation():
    le, de = histogram_edges([np.array([1e-3, 1.0])], [np.array([4e-6, 16e-6])], bins=3)
    np.testing.assert_allclose(le, [1e-3, 1e-2, 1e-1, 1.0])
    np.testing.assert_allclose(de, [4e-6, 8e-6, 12e-6, 16e-6])
    h = bin_events([2e-3, 2e-3, 0.5, 1.0], [5e-6, 5e-6, 13e-6, 16e-6], le, de)
    assert h.sum() == pytest.approx(1.0)
    assert h[0, 0] == pytest.approx(0.5) and h[2, 2] == pytest.approx(0.5)
    assert bin_events([], [], le, de).sum() == 0.0  # no event: all zeros
    c = centroids(h, np.sqrt(le[:-1] * le[1:]), 0.5 * (de[1:] + de[:-1]))
    assert c[1] == pytest.approx(0.5 * 6e-6 + 0.5 * 14e-6)
    assert c[0] == pytest.approx(np.sqrt(np.sqrt(1e-3 * 1e-2) * np.sqrt(1e-1 * 1.0)))


def test_kl_divergence_of_identical_and_known_pair():
    p = np.full((2, 2), 0.25)
    q = np.array([[0.5, 0.5], [0.0, 0.0]])
    assert kl_divergence(p, p) == pytest.approx(0.0, abs=1e-12)
    # KL(q || p) = sum q log(q / p) = log 2 (the 1e-8 floor changes it by ~1e-8)
    assert kl_divergence(q, p) == pytest.approx(np.log(2), rel=1e-6)


def test_file_round_trip_and_noise_floor(tmp_path):
    ds = synthetic_dataset(30, seed=2, replicate_groups=3, replicates=6, noise=0.05)
    path = write_dataset(tmp_path / "d.h5", ds)
    back = read_dataset(path)
    assert back.fingerprint == ds.fingerprint
    np.testing.assert_array_equal(back.role, ds.role)
    np.testing.assert_array_equal(back.group, ds.group)
    with h5py.File(path) as f:
        for name, obj in f.items():
            for sub in obj.values():
                assert "unit" in sub.attrs, f"{name}/{sub.name} has no unit"
    nf = noise_floor(back)
    assert len(nf["groups"]) == 3
    # 5 % multiplicative noise on a whole curve: relative spread ~0.05 at every depth
    rel = [g["pressure_rel_std"]["100%"] for g in nf["groups"]]
    assert 0.01 < np.mean(rel) < 0.12
    assert nf["kl_pairwise"] == pytest.approx(0.0, abs=1e-9)  # identical histograms


def test_sampled_kl_floor_matches_the_chi_square_limit():
    """Many events per run: 2 n KL(p_hat || q) -> chi^2 with K - 1 degrees of freedom, so a
    perfect model scores (K - 1) / (2 n); against the pooled histogram of R equal runs
    (which contains the run itself) the deviation shrinks by (1 - 1/R), so the floor reads
    (K - 1) / (2 n) (R - 1) / R and the ratio is R / (R - 1)."""
    q = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 1.0], [3.0, 1.0, 2.0]])
    q /= q.sum()
    k, n, runs = q.size, 5000, 5
    rng = np.random.default_rng(4)
    counts = np.stack([rng.multinomial(n, q.ravel()).reshape(3, 3) for _ in range(runs)])
    out = sampled_kl_floor(counts, n_sim=400, seed=1)
    assert out["perfect"] == pytest.approx((k - 1) / (2 * n), rel=0.08)
    assert out["floor_like"] == pytest.approx((k - 1) / (2 * n) * (runs - 1) / runs, rel=0.08)
    assert out["ratio"] == pytest.approx(runs / (runs - 1), rel=0.05)
    with pytest.raises(ConfigError):
        sampled_kl_floor(counts[:1])


def test_perfect_model_kl_matches_the_chi_square_limit():
    """n events drawn from q: 2 n KL(p_hat || q) -> chi^2 with K - 1 degrees of freedom."""
    q = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 1.0], [3.0, 1.0, 2.0]])
    n = 4000
    assert perfect_model_kl(q, n, n_sim=2000, seed=3) == pytest.approx((q.size - 1) / (2 * n),
                                                                       rel=0.05)
    # more events, proportionally less
    assert perfect_model_kl(q, 4 * n, n_sim=2000, seed=3) == pytest.approx(
        (q.size - 1) / (8 * n), rel=0.05)
    with pytest.raises(ConfigError, match="n_events"):
        perfect_model_kl(q, 0)
    with pytest.raises(ConfigError):
        perfect_model_kl(np.zeros((3, 3)), 10)


def test_seed_means_average_pressure_and_pool_events():
    ds = synthetic_dataset(6, seed=5, replicate_groups=3, replicates=3, noise=0.05)
    role = ds.role.copy()
    role[ds.group == 0] = "holdout"
    role[ds.group == 1] = "holdout"
    group = ds.group.copy()
    group[np.nonzero(ds.group == 1)[0][1:]] = 7  # group 1 keeps one run: not a mean
    ds.role, ds.group = role, group
    hist = ds.histogram.copy()
    i0 = np.nonzero(ds.group == 0)[0]
    hist[i0] = 0.0
    for k, r in enumerate(i0):  # run k of group 0: all events in bin (k, k)
        hist[r, k, k] = 1.0
    ds.histogram = hist
    ds.n_events = ds.n_events.copy()
    ds.n_events[i0] = [100, 200, 700]
    m = seed_means(ds, "holdout")
    assert len(m) == 2 and list(m.group) == [0, 7]  # group 1 (one run) left out
    np.testing.assert_allclose(m.pressure[0], ds.pressure[i0].mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(m.pressure_raw[0], ds.pressure_raw[i0].mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose([m.histogram[0, k, k] for k in range(3)], [0.1, 0.2, 0.7])
    assert m.histogram[0].sum() == pytest.approx(1.0)
    assert m.n_events[0] == 1000 and m.seed[0] == 3 and m.seed[1] == 2
    assert list(m.role) == ["holdout", "holdout"]
    np.testing.assert_array_equal(m.params[0], ds.params[i0[0]])
    assert len(seed_means(ds, "replicate")) == 1  # group 2
    assert len(seed_means(ds, "train")) == 0
    with pytest.raises(ConfigError, match="role"):
        seed_means(ds, "test")


def test_noise_floor_reports_the_perfect_model_ratio_for_counted_histograms():
    ds = synthetic_dataset(30, seed=2, replicate_groups=2, replicates=4, noise=0.05)
    assert noise_floor(ds)["kl_perfect_model_ratio"] is None  # smooth, not counted
    rng = np.random.default_rng(0)
    hist = np.zeros_like(ds.histogram)
    n_events = np.full(len(ds.n_events), 300)
    for r in range(len(hist)):
        c = rng.multinomial(300, np.full(900, 1 / 900)).reshape(hist.shape[1:])
        hist[r] = c / 300
    from dataclasses import replace
    counted = replace(ds, histogram=hist, n_events=n_events)
    nf = noise_floor(counted)
    assert nf["kl_perfect_model_ratio"] is not None and nf["kl_perfect_model_ratio"] > 1.0
    assert all(g["kl_sampled"]["perfect"] > g["kl_sampled"]["floor_like"] for g in nf["groups"])


def test_reader_rejects_foreign_and_incomplete_files(tmp_path):
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["x"] = np.arange(3)
    with pytest.raises(DatasetError, match="not a calendaring dataset"):
        read_dataset(foreign)
    path = write_dataset(tmp_path / "d.h5", synthetic_dataset(5))
    with h5py.File(path, "a") as f:
        del f["distribution/histogram"]
    with pytest.raises(DatasetError, match="missing dataset 'distribution/histogram'"):
        read_dataset(path)
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    with pytest.raises(DatasetError, match="not a readable HDF5"):
        read_dataset(tmp_path / "junk.h5")


def test_builder_skips_foreign_and_corrupt_run_files(tmp_path):
    with h5py.File(tmp_path / "foreign.h5", "w") as f:
        f.attrs["format"] = "something-else"
    (tmp_path / "truncated.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 100)
    with pytest.raises(DatasetError, match=r"no usable run files \(2 skipped"):
        build_dataset(tmp_path, progress=False)
    with pytest.raises(ConfigError, match="RUNS"):
        build_dataset(tmp_path / "nope", progress=False)


def _curves_of_rank(rank_signal, noise, seed=0, groups=12, replicates=4, n=150):
    """Cube-root curves = base + sum_j a_j(u) f_j(z) (``rank_signal`` terms, amplitudes of
    order 1) + per-run noise spread over 30 other smooth shapes (sd ``noise`` each): the
    signal lives in exactly ``rank_signal`` components."""
    from dataclasses import replace

    ds = synthetic_dataset(n, seed=seed, replicate_groups=groups, replicates=replicates)
    rng = np.random.default_rng(seed)
    z = np.linspace(0.0, 1.0, len(ds.depth))
    shapes = np.array([np.sin((j + 1) * np.pi * z) for j in range(rank_signal + 30)])
    u = ds.unit_params
    amp = np.column_stack([np.cos(2.0 * u[:, j]) + u[:, j + 1] ** 2
                           for j in range(rank_signal)])
    c = 100.0 + 60.0 * z + 3.0 * amp @ shapes[:rank_signal] \
        + noise * rng.standard_normal((len(u), 30)) @ shapes[rank_signal:]
    p = c**3
    return replace(ds, pressure=p, pressure_raw=p, cbrt_min=float(c.min()),
                   cbrt_max=float(c.max()))


def test_pressure_components_count_the_signal_above_the_bed_to_bed_scatter():
    """Curves built from 2 (then 3) parameter-driven shapes plus per-run scatter in 30 other
    shapes: exactly those components are resolved, the rest are scatter (noise share ~1)."""
    for rank in (2, 3):
        r = pressure_components(_curves_of_rank(rank, noise=0.05, seed=rank))
        assert r["groups"] == 12 and r["dof_bed_to_bed"] == 36 and r["tested"] == 10
        assert r["resolved"] == rank and r["resolved_components"] == list(range(1, rank + 1))
        assert r["signal_share_resolved"] > 0.99
        for c in r["components"][:rank]:
            assert c["noise_share"] < 0.05 and c["p_value"] < 1e-6
        shares = [c["noise_share"] for c in r["components"][rank:]]
        assert 0.6 < np.median(shares) < 1.6  # scatter only: variance ~ bed-to-bed
    # no replicate group: nothing to compare against
    assert pressure_components(synthetic_dataset(20, seed=1)) is None
    with pytest.raises(ConfigError, match="alpha"):
        pressure_components(_curves_of_rank(2, 0.05), alpha=1.5)
