"""Voxelisation, porosity, tortuosity and D_eff against geometries with known answers."""

import itertools
import json

import numpy as np
import pytest
import torch

from analysis.microstructure import (
    MicrostructureResult,
    analyse_snapshot,
    format_table,
    microstructure_table,
    plot_microstructure,
    solve_tortuosity,
    voxelise,
)
from calendaring.core.errors import ConfigError
from calendaring.process.runfile import Snapshot

torch.set_num_threads(1)

L = 10e-6  # periodic cell edge [m]


def sphere_volume(r):
    return 4.0 / 3.0 * np.pi * r**3


def make_snapshot(position, radius, material, z_bottom, z_top, index=0, depth=0.0):
    """A ``calendaring.process.runfile.Snapshot`` built in memory (no run file needed)."""
    n = len(radius)
    zeros = np.zeros(n)
    return Snapshot(index=index, label=str(index), depth=depth, step=0, time=0.0,
                    z_top=z_top, z_bottom=z_bottom, top_pressure=0.0,
                    position=np.asarray(position, float), radius=np.asarray(radius, float),
                    material=np.asarray(material, np.int32), id=np.arange(n),
                    velocity=np.zeros((n, 3)), normal_force=zeros, n_contacts=zeros.astype(int),
                    parent_id=-np.ones(n, int), fracture_energy=zeros, peak_load=zeros,
                    bonds=None)


def lattice(r, offset=(0.0, 0.0)):
    """2 x 2 x 2 simple-cubic lattice of spacing L/2 in an L^3 box; with ``offset`` = 0 the
    lattice sites sit on the lateral faces, so half the spheres cross a periodic face."""
    a = L / 2
    g = np.arange(2) * a
    x, y, z = np.meshgrid(g + offset[0], g + offset[1], g + a / 2, indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()]), np.full(8, r)


# ---------------------------------------------------------------------------- voxelisation
def test_voxel_porosity_of_a_sphere_lattice_matches_the_analytic_value():
    r = 2.0123e-6  # no voxel centre exactly on a sphere surface
    pos, rad = lattice(r)
    exact = 1.0 - 8 * sphere_volume(r) / L**3  # spheres do not touch: 2r < L/2
    img = voxelise(pos, rad, np.zeros(8), L, L, 0.0, L, voxel_size=0.1e-6)
    assert img.shape == (100, 100, 100) and img.dtype == np.uint8
    assert set(np.unique(img)) <= {0, 1}
    # binary voxels at r / h = 20: the solid volume within 1 % (lattice-point counting error)
    np.testing.assert_allclose(1 - img.mean(), 1 - exact, rtol=0.01)
    # the image is exactly periodic: the same lattice shifted by 25 voxels along x and y
    moved = pos + np.array([2.5e-6, 2.5e-6, 0.0])
    shifted = voxelise(moved, rad, np.zeros(8), L, L, 0.0, L, 0.1e-6)
    np.testing.assert_array_equal(np.roll(img, (25, 25), axis=(1, 2)), shifted)


def test_voxelise_equals_a_brute_force_centre_in_sphere_test():
    rng = np.random.default_rng(1)
    pos = rng.uniform(-2e-6, L + 2e-6, (15, 3))
    rad = rng.uniform(0.5e-6, 2.5e-6, 15)
    z_bottom, z_top, n = 1e-6, 8.5e-6, 25
    img = voxelise(pos, rad, np.zeros(15), L, L, z_bottom, z_top, L / n)
    nz = round((z_top - z_bottom) / (L / n))  # 19 layers of 0.395 um
    z = z_bottom + (np.arange(nz) + 0.5) * (z_top - z_bottom) / nz
    y = (np.arange(n) + 0.5) * L / n
    zz, yy, xx = np.meshgrid(z, y, y, indexing="ij")
    solid = np.zeros(zz.shape, bool)
    for c, r in zip(pos, rad, strict=True):
        for sx in (-L, 0.0, L):  # periodic images in x and y
            for sy in (-L, 0.0, L):
                cx, cy = np.mod(c[0], L) + sx, np.mod(c[1], L) + sy
                solid |= (zz - c[2]) ** 2 + (yy - cy) ** 2 + (xx - cx) ** 2 <= r**2
    np.testing.assert_array_equal(img, (~solid).astype(np.uint8))


def test_a_sphere_crossing_the_cell_corner_is_counted_fully():
    r = 2.0123e-6
    h = 0.1e-6
    # the centre sits in a corner of the cell: the sphere crosses both lateral faces
    corner = voxelise([[0.02e-6, L - 0.02e-6, 5e-6]], [r], [0], L, L, 0.0, L, h)
    solid = (1 - corner).sum() * h**3
    np.testing.assert_allclose(solid, sphere_volume(r), rtol=0.01)
    # identical to the same sphere in the middle, moved by a whole number of voxels
    middle = voxelise([[5.02e-6, 4.98e-6, 5e-6]], [r], [0], L, L, 0.0, L, h)
    np.testing.assert_array_equal(np.roll(corner, (-50, 50), axis=(1, 2)), middle)
    # centres outside the cell are wrapped into it
    outside = voxelise([[L + 0.02e-6, -0.02e-6, 5e-6]], [r], [0], L, L, 0.0, L, h)
    np.testing.assert_array_equal(outside, corner)


def test_spheres_are_cropped_by_the_plates():
    r = 2.0123e-6
    h = 0.1e-6
    img = voxelise([[5e-6, 5e-6, 0.0]], [r], [0], L, L, 0.0, L, h)  # centre on the bottom
    np.testing.assert_allclose((1 - img).sum() * h**3, sphere_volume(r) / 2, rtol=0.01)
    assert img.shape == (100, 100, 100)


def test_partial_volume_mode_converges_faster_than_binary_voxels():
    r = 2.0123e-6
    exact = sphere_volume(r) / L**3
    rng = np.random.default_rng(0)
    centres = rng.uniform(0, L, (12, 3))
    centres[:, 2] = L / 2
    for h in (r / 2, r / 3, r / 4):
        err_bin, err_grey = [], []
        for c in centres:
            b = voxelise([c], [r], [0], L, L, 0.0, L, h)
            g = voxelise([c], [r], [0], L, L, 0.0, L, h, supersample=4)
            assert g.dtype == np.float32 and 0.0 <= g.min() and g.max() <= 1.0
            err_bin.append(abs(1 - b.mean() - exact) / exact)
            err_grey.append(abs(1 - g.mean() - exact) / exact)
        assert np.mean(err_grey) < 0.3 * np.mean(err_bin), h


def test_am_cb_phases_and_bad_input():
    pos = [[2.5e-6, 2.5e-6, 5e-6], [7.5e-6, 7.5e-6, 5e-6]]
    img = voxelise(pos, [1.5e-6, 1.5e-6], [0, 1], L, L, 0, L, 0.25e-6, phases="am_cb")
    assert set(np.unique(img)) == {0, 1, 2}
    np.testing.assert_allclose(np.mean(img == 1), np.mean(img == 2), rtol=1e-12)
    with pytest.raises(ConfigError, match="phases"):
        voxelise(pos, [1e-6, 1e-6], [0, 1], L, L, 0, L, 0.25e-6, phases="grey")
    with pytest.raises(ConfigError, match="voxel_size"):
        voxelise(pos, [1e-6, 1e-6], [0, 1], L, L, 0, L, -1.0)
    with pytest.raises(ConfigError, match="z_top"):
        voxelise(pos, [1e-6, 1e-6], [0, 1], L, L, L, 0, 0.25e-6)


# ---------------------------------------------------------------------------- transport
@pytest.mark.parametrize("shape", [(24, 12, 12), (23, 11, 13)])  # odd periodic lengths too
def test_straight_channels_have_tortuosity_one(shape):
    img = np.zeros(shape, np.uint8)
    img[:, ::3, ::4] = 1  # isolated straight columns along the thickness
    res = solve_tortuosity(img, device="cpu", tol=1e-3)
    np.testing.assert_allclose(res.tortuosity, 1.0, atol=2e-3)
    np.testing.assert_allclose(res.D_eff, img.mean(), rtol=2e-3)
    # the same channels as grey voxels (half-open pores) and with a CB phase
    grey = img.astype(np.float32) * 0.5
    grey[:, 1::3, 1::4] = 1.0
    g = solve_tortuosity(grey, device="cpu", tol=1e-3)
    np.testing.assert_allclose(g.tortuosity, 1.0, atol=2e-3)
    np.testing.assert_allclose(g.porosity, grey.mean(dtype=np.float64), rtol=1e-12)
    labels = np.ones(shape, np.uint8)  # AM everywhere
    labels[:, ::3, ::4] = 0  # pore columns
    labels[:, 1::3, 1::4] = 2  # CB columns
    c = solve_tortuosity(labels, device="cpu", tol=1e-3, cb_diffusivity=0.25)
    np.testing.assert_allclose(c.tortuosity, 1.0, atol=2e-3)
    np.testing.assert_allclose(c.D_eff, np.mean(labels == 0) + 0.25 * np.mean(labels == 2),
                               rtol=2e-3)


def test_a_blocked_pore_phase_is_reported_as_not_percolating():
    img = np.ones((20, 8, 8), np.uint8)
    img[10] = 0  # a dense solid layer across the whole cell
    res = solve_tortuosity(img, device="cpu")
    assert res.tortuosity is None and res.D_eff == 0.0
    assert "does not percolate" in res.reason
    assert res.percolating_fraction == 0.0
    with pytest.raises(ConfigError, match="tol"):
        solve_tortuosity(img, device="cpu", tol=0.0)
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="device"):
            solve_tortuosity(img, device="cuda")
    # the same from spheres: a square lattice of overlapping spheres closes a mid-plane
    a, r = 1.0e-6, 0.75e-6  # r > a / sqrt(2): the plane z = 5 um is fully covered
    g = (np.arange(10) + 0.5) * a
    x, y = np.meshgrid(g, g, indexing="ij")
    pos = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 5e-6)])
    snap = make_snapshot(pos, np.full(len(pos), r), np.zeros(len(pos)), 0.0, L)
    out = analyse_snapshot(snap, L, L, voxels_per_diameter=4, reference_diameter=1.5e-6,
                           second_resolution=True).to_json()
    assert out["tortuosity"] is None and "percolate" in out["tortuosity_reason"]
    assert out["second_resolution"]["tortuosity"] is None
    assert out["extrapolated"]["tortuosity"] is None
    json.dumps(out, allow_nan=False)  # None, never NaN


def test_lateral_periodicity_is_respected():
    # a pore path that switches from the last to the first x column halfway up: it
    # percolates only through the periodic face
    img = np.zeros((20, 8, 8), np.uint8)
    img[:11, 3, 7] = 1
    img[10:, 3, 0] = 1
    for image in (img, img.astype(np.float32)):  # binary and grey (multiphase) solvers
        res = solve_tortuosity(image, device="cpu", tol=1e-3)
        assert res.tortuosity is not None and res.percolating_fraction == 1.0
        # 21 pore voxels, one lateral step: the flux path is 21 voxels long for 20 layers
        assert 1.0 < res.tortuosity < 1.2
        # closed side walls (a window): the same path is cut at the face
        closed = solve_tortuosity(image, device="cpu", tol=1e-3, periodic=False)
        assert closed.tortuosity is None and "closed" in closed.reason
    straight = np.zeros((20, 8, 8), np.float32)
    straight[:, 3, 2] = 1.0  # a straight channel conducts with or without periodic faces
    for periodic in (True, False):
        res = solve_tortuosity(straight, device="cpu", tol=1e-3, periodic=periodic)
        np.testing.assert_allclose(res.tortuosity, 1.0, atol=2e-3)


def test_d_eff_is_porosity_over_tortuosity_on_a_sphere_packing():
    rng = np.random.default_rng(3)
    pos = rng.uniform(0, L, (30, 3))
    rad = rng.uniform(0.8e-6, 1.6e-6, 30)
    img = voxelise(pos, rad, np.zeros(30), L, L, 0.0, L, 0.4e-6)
    porosity = float(img.mean())
    res = solve_tortuosity(img, device="cpu", tol=1e-3)
    assert res.tortuosity > 1.0
    assert res.porosity == pytest.approx(porosity, rel=1e-12)
    np.testing.assert_allclose(res.D_eff, porosity / res.tortuosity, rtol=1e-5)
    grey = voxelise(pos, rad, np.zeros(30), L, L, 0.0, L, 0.4e-6, supersample=2)
    g = solve_tortuosity(grey, device="cpu", tol=1e-3)
    np.testing.assert_allclose(g.D_eff, grey.mean(dtype=np.float64) / g.tortuosity, rtol=1e-5)


# ---------------------------------------------------------------------------- snapshots
def test_analyse_snapshot_reports_two_resolutions_and_plots(tmp_path):
    r = 2.0123e-6
    pos, rad = lattice(r, offset=(1.0e-6, 0.0))
    snap = make_snapshot(pos, rad, np.zeros(8), 0.0, L, depth=1e-6)
    res = analyse_snapshot(snap, L, L, voxels_per_diameter=4, reference_diameter=2e-6)
    j = res.to_json()
    exact = 1.0 - 8 * sphere_volume(r) / L**3
    assert j["particle_porosity"] == pytest.approx(exact, rel=1e-12)
    assert j["voxel_size_m"] == pytest.approx(0.5e-6)
    assert j["voxels_per_diameter"] == pytest.approx(4.0)
    sec = j["second_resolution"]
    assert sec["voxel_size_m"] > j["voxel_size_m"]
    assert j["tortuosity"] > 1.0 and sec["tortuosity"] > 1.0
    ext = j["extrapolated"]
    h1, h2 = j["voxel_size_m"], sec["voxel_size_m"]
    d0 = j["D_eff"] + (j["D_eff"] - sec["D_eff"]) * h1 / (h2 - h1)  # linear in h
    phi0 = j["voxel_porosity"] + (j["voxel_porosity"] - sec["voxel_porosity"]) * h1 / (h2 - h1)
    assert ext["D_eff"] == pytest.approx(d0)
    assert ext["tortuosity"] == pytest.approx(phi0 / d0, rel=1e-4)
    assert j["D_eff_check_rel_err"] < 1e-5
    result = MicrostructureResult(run_file="mem", label="lattice", breakage_model="none",
                                  cell_x=L, cell_y=L, settings={"voxels_per_diameter": 4},
                                  snapshots=[res])
    path = result.write_json(tmp_path / "ms.json")
    assert json.loads(path.read_text())["snapshots"][0]["depth_m"] == 1e-6
    rows = microstructure_table({"lattice": result}, depths=(0.0,))
    assert rows[0]["tortuosity"] == j["tortuosity"]
    assert "lattice" in format_table(rows)
    pngs = plot_microstructure({"lattice": result}, tmp_path)
    assert len(pngs) == 3 and all(p.stat().st_size > 1000 for p in pngs)


def test_analyse_run_reads_the_run_file_and_keeps_one_voxel_size(tmp_path):
    from analysis.microstructure import analyse_run
    from tests.analysis import write_small_run

    path = write_small_run(tmp_path / "small.h5")
    res = analyse_run(path, voxels_per_diameter=2, progress=False, cb_phase=True,
                      resolution="two-point")
    j = res.to_json()
    assert [s["depth_m"] for s in j["snapshots"]] == pytest.approx([0.0, 5e-6])
    assert len({s["voxel_size_m"] for s in j["snapshots"]}) == 1  # same voxels throughout
    assert j["settings"]["reference_diameter_m"] == pytest.approx(2e-6)  # smallest fragment
    for s in j["snapshots"]:
        assert 0.0 < s["cb_volume_fraction"] < 1.0
        assert s["voxel_porosity"] > s["particle_porosity"] - 0.05  # overlaps count once
    only = analyse_run(path, snapshots=[1], voxels_per_diameter=2, progress=False,
                       second_resolution=False, resolution="two-point")
    assert len(only.snapshots) == 1 and only.snapshots[0].second is None
    with pytest.raises(ConfigError, match="snapshots"):
        analyse_run(path, snapshots=[5], progress=False)
    with pytest.raises(ConfigError, match="resolution"):
        analyse_run(path, progress=False, resolution="three-point")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_and_cpu_solves_agree():
    rng = np.random.default_rng(5)
    pos = rng.uniform(0, L, (30, 3))
    rad = rng.uniform(0.8e-6, 1.6e-6, 30)
    img = voxelise(pos, rad, np.zeros(30), L, L, 0.0, L, 0.4e-6)
    cpu = solve_tortuosity(img, device="cpu", tol=1e-3)
    gpu = solve_tortuosity(img, device="cuda", tol=1e-3)
    np.testing.assert_allclose(gpu.tortuosity, cpu.tortuosity, rtol=5e-3)


# ---------------------------------------------------------------------------- refinement
def _dilute_array(f=0.1, n=4):
    """n^3 simple-cubic array of equal spheres at solid fraction f in the L^3 box, the
    plates on the lattice's mid planes (mirror planes: equipotentials of the infinite
    array, so the slab has the array's effective diffusivity)."""
    a = L / n
    r = a * (3 * f / (4 * np.pi)) ** (1 / 3)
    g = (np.arange(n) + 0.5) * a
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    pos = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    return make_snapshot(pos, np.full(len(pos), r), np.zeros(len(pos)), 0.0, L), r


def test_converged_d_eff_of_a_dilute_sphere_array_matches_maxwell():
    """Insulating spheres at solid fraction f in a conducting matrix: D_eff = 2 (1 - f) /
    (2 + f) (Maxwell; Rayleigh's correction for a cubic array is ~1e-4 at f = 0.1), so tau =
    (2 + f) / 2. Binary voxels at the first level are 15 % off; the refined partial-volume
    answer is within the grey voxels' known residual (0.5-1 %)."""
    from analysis.microstructure import converge_snapshot

    f = 0.1
    snap, r = _dilute_array(f)
    res = converge_snapshot(snap, L, L, reference_diameter=2 * r, refine_tol=0.02)
    j = res.to_json()
    ref = j["refinement"]
    assert ref["converged"] and ref["tortuosity_rel_change"] < 0.02
    assert len(ref["levels"]) >= 2
    assert j["D_eff"] == pytest.approx(2 * (1 - f) / (2 + f), rel=0.015)
    assert j["tortuosity"] == pytest.approx((2 + f) / 2, rel=0.015)
    assert j["voxel_porosity"] == pytest.approx(1 - f, abs=2e-3)
    coarse = solve_tortuosity(voxelise(snap.position, snap.radius, snap.material, L, L, 0.0,
                                       L, ref["levels"][0]["voxel_size_m"]), tol=1e-3)
    assert abs(coarse.D_eff / (2 * (1 - f) / (2 + f)) - 1) > 0.1  # binary: far off
    # the porosity budget: no overlaps, nothing past the plates
    por = j["porosities"]
    assert por["pair_overlap"] == 0.0 and por["plate_caps"] == 0.0
    assert por["sphere_sum"] == pytest.approx(1 - f, rel=1e-12)
    json.dumps(j, allow_nan=False)


def test_refinement_levels_warm_starts_and_budget():
    from analysis.microstructure import converge_snapshot, prolong_field, refinement_levels

    hs = refinement_levels(L, 2e-6, start=3.0, ratio=1.5, max_levels=5)
    assert all(b < a for a, b in itertools.pairwise(hs))
    assert all(round(L / h) % 2 == 0 for h in hs)  # even lateral counts (TauFactor)
    rng = np.random.default_rng(3)
    pos = rng.uniform(0, L, (30, 3))
    rad = rng.uniform(0.8e-6, 1.6e-6, 30)
    snap = make_snapshot(pos, rad, np.zeros(30), 0.0, L)
    warm = converge_snapshot(snap, L, L, reference_diameter=1.6e-6, refine_tol=0.01,
                             max_levels=3).to_json()["refinement"]
    cold = converge_snapshot(snap, L, L, reference_diameter=1.6e-6, refine_tol=0.01,
                             max_levels=3, warm_start=False).to_json()["refinement"]
    assert [lv["warm_start"] for lv in warm["levels"]] == [False] + [True] * (
        len(warm["levels"]) - 1)
    for a, b in zip(warm["levels"], cold["levels"], strict=True):
        # the same answer from either start, to the solver's tolerance
        assert a["tortuosity"] == pytest.approx(b["tortuosity"], rel=5e-3)
    for k, lv in enumerate(warm["levels"][1:], start=1):
        prev = warm["levels"][k - 1]["tortuosity"]
        assert lv["tortuosity_rel_change"] == pytest.approx(
            abs(lv["tortuosity"] - prev) / lv["tortuosity"])
    if warm["converged"]:
        assert warm["tortuosity_rel_change"] < 0.01
    else:
        assert len(warm["levels"]) == 3 and "max_levels" in warm["reason"]
    # a budget below the second level: one level, not converged, the reason says why
    n0 = warm["levels"][0]["voxels"]
    small = converge_snapshot(snap, L, L, reference_diameter=1.6e-6, max_voxels=n0)
    ref = small.to_json()["refinement"]
    assert len(ref["levels"]) == 1 and not ref["converged"] and "max_voxels" in ref["reason"]
    with pytest.raises(ConfigError, match="max_voxels"):
        converge_snapshot(snap, L, L, reference_diameter=1.6e-6, max_voxels=n0 - 1)
    with pytest.raises(ConfigError, match="refine_tol"):
        converge_snapshot(snap, L, L, refine_tol=0.0)
    # prolongation: a linear potential stays linear (nearest-cell values) on a finer grid
    coarse = np.broadcast_to(np.linspace(-0.4, 0.4, 5)[:, None, None], (5, 4, 4)).copy()
    fine = prolong_field(coarse, np.ones(coarse.shape, bool), (10, 8, 8))
    np.testing.assert_allclose(fine[::2, 0, 0], coarse[:, 0, 0], rtol=1e-6)
    solid = np.ones(coarse.shape, bool)
    solid[2, 1, 1] = False  # a solid coarse voxel takes its layer's mean potential
    assert prolong_field(coarse, solid, (10, 8, 8))[4, 2, 2] == pytest.approx(0.0, abs=1e-7)


def test_lens_cap_volumes_and_the_porosity_budget():
    from analysis.porosity import cap_volume, lens_volume, porosity_budget, recipe_solid_thickness
    from calendaring.core.config import load_preset

    R = 1.0e-6
    for d in (0.3e-6, 1.0e-6, 1.9e-6):  # equal spheres: pi (4R + d)(2R - d)^2 / 12
        assert lens_volume(R, R, d) == pytest.approx(np.pi * (4 * R + d) * (2 * R - d) ** 2 / 12)
    assert lens_volume(R, 0.4e-6, 0.5e-6) == pytest.approx(sphere_volume(0.4e-6))  # inside
    assert lens_volume(R, R, 2.0e-6) == 0.0
    assert cap_volume(R, R) == pytest.approx(sphere_volume(R) / 2)
    assert cap_volume(R, 3 * R) == pytest.approx(sphere_volume(R))
    # two overlapping spheres across the periodic x face (AM + CB) and one sphere pressed
    # 0.4 um into the bottom plate: the union's porosity from the budget equals fine
    # partial-volume voxels
    pos = [[0.3e-6, 5e-6, 5e-6], [L - 0.9e-6, 5e-6, 5e-6], [5e-6, 5e-6, 0.6e-6]]
    rad = [1.2e-6, 0.8e-6, 1.0e-6]
    mat = [0, 1, 0]
    img = voxelise(pos, rad, mat, L, L, 0.0, L, L / 100, supersample=4)
    b = porosity_budget(pos, rad, mat, L, L, 0.0, L, voxel_porosity=float(img.mean()))
    assert b["overlapping_pairs"] == 1 and b["overlapping_pairs_am_cb"] == 1
    assert b["pair_overlap"] == pytest.approx(lens_volume(1.2e-6, 0.8e-6, 1.2e-6) / L**3)
    assert b["pair_overlap_am_cb"] == b["pair_overlap"] and b["pair_overlap_am_am"] == 0.0
    assert b["plate_caps"] == pytest.approx(cap_volume(1.0e-6, 0.4e-6) / L**3)
    assert b["union_estimate"] == pytest.approx(float(img.mean()), abs=2e-5)
    assert abs(b["multiple_overlap_and_voxel_error"]) < 2e-5
    # the paper's recipe (2.56 g/cm3, 94/6 wt%, 4740 / 2200 kg/m3) at the coating
    # thickness: 1 - 2560 (0.94 / 4740 + 0.06 / 2200) = 42.25 %
    cfg = load_preset("paper")
    solid = recipe_solid_thickness(cfg)
    h0 = cfg.electrode.thickness
    got = porosity_budget(pos, rad, mat, L, L, 0.0, h0, solid_thickness=solid)["mass_balance"]
    assert got == pytest.approx(0.42250, abs=5e-5)


def test_analyse_run_converges_by_default(tmp_path):
    from analysis.microstructure import analyse_run
    from tests.analysis import write_small_run

    path = write_small_run(tmp_path / "small.h5")
    res = analyse_run(path, progress=False, max_levels=3)
    j = res.to_json()
    assert j["settings"]["resolution"] == "converge"
    for s in j["snapshots"]:
        ref = s["refinement"]
        assert 1 <= len(ref["levels"]) <= 3 and ref["levels"][0]["voxels_per_diameter"] == \
            pytest.approx(3.0, rel=0.1)
        assert s["voxel_size_m"] == ref["levels"][-1]["voxel_size_m"]  # the finest level
        assert s["supersample"] == 3
        por = s["porosities"]
        assert por["sphere_sum"] == pytest.approx(s["particle_porosity"])
        assert por["mass_balance"] is not None and por["voxel"] == s["voxel_porosity"]
    rows = microstructure_table({"small": res}, depths=(0.0,))
    first = j["snapshots"][0]["refinement"]
    assert rows[0]["refinement"]["levels"] == len(first["levels"])
    table = format_table(rows)
    assert f"{first['levels'][0]['tortuosity']:.3f}" in table
    # carbon black as its own conducting phase: binary labels, warm starts as well
    cb = analyse_run(path, snapshots=[1], progress=False, max_levels=2, cb_phase=True)
    s = cb.to_json()["snapshots"][0]
    assert s["supersample"] == 1 and 0.0 < s["cb_volume_fraction"] < 1.0
    assert s["refinement"]["levels"][-1]["warm_start"] == (len(s["refinement"]["levels"]) > 1)
    json.dumps(j, allow_nan=False)
