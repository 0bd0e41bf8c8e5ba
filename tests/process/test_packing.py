"""Packing validation and file exchange: CSV and LAMMPS round trips (bit-exact), malformed
files, VTK output read back with pyvista, and atomic writes (calendaring.process.packing)."""

import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest

import calendaring.process.packing as pk
from calendaring.process.packing import (
    Packing,
    PackingError,
    read_csv,
    read_lammps_data,
    write_csv,
    write_lammps_data,
    write_vtk,
)

N = 50


@pytest.fixture
def packing() -> Packing:
    rng = np.random.default_rng(1234)
    cell_x, cell_y, z_bottom, z_top = 1.1e-4, 0.9e-4, 2.5e-6, 8.3e-5
    material = rng.integers(0, 2, N).astype(np.int32)
    radius = np.where(material == 0, rng.uniform(2e-6, 8e-6, N), rng.uniform(2e-7, 9e-7, N))
    position = np.column_stack([rng.uniform(0, cell_x, N), rng.uniform(0, cell_y, N),
                                rng.uniform(z_bottom, z_top, N)])
    ids = rng.permutation(np.arange(1, 4 * N))[:N].astype(np.int64) + 2**40
    density = np.where(material == 0, 4750.0, 1800.0) * rng.uniform(0.9, 1.1, N)
    return Packing(position, radius, material, ids, cell_x, cell_y, z_bottom, z_top, density)


def assert_identical(a: Packing, b: Packing, density: bool = True) -> None:
    assert a.n == b.n
    for name in ("position", "radius", "material", "ids"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name, strict=True)
        assert x.tobytes() == y.tobytes(), name  # bit-exact
    for name in ("cell_x", "cell_y", "z_bottom", "z_top"):
        assert getattr(a, name) == getattr(b, name), name
    if density:
        assert a.density is not None and b.density is not None
        assert a.density.tobytes() == b.density.tobytes()


# ------------------------------------------------------------------------------ Packing


def test_packing_dtypes_and_n(packing):
    assert packing.n == N
    assert packing.position.dtype == np.float64 and packing.radius.dtype == np.float64
    assert packing.material.dtype == np.int32 and packing.ids.dtype == np.int64


def test_packing_rejects_negative_radius(packing):
    radius = packing.radius.copy()
    radius[7] = -1e-6
    with pytest.raises(PackingError, match=r"radius\[7\] = -1e-06.*> 0") as info:
        dataclasses.replace(packing, radius=radius)
    assert info.value.field == "radius[7]"


def test_packing_rejects_duplicate_ids(packing):
    ids = packing.ids.copy()
    ids[9] = ids[3]
    with pytest.raises(PackingError, match=r"ids\[9\].*unique.*ids\[3\]"):
        dataclasses.replace(packing, ids=ids)


@pytest.mark.parametrize("change, match", [
    ({"position": np.zeros((N, 2))}, r"position\.shape"),
    ({"radius": np.ones(N - 1)}, r"radius\.shape"),
    ({"material": np.full(N, -1)}, r"material\[0\]"),
    ({"z_top": 0.0}, r"z_top = 0\.0.*> z_bottom"),
    ({"cell_x": 0.0}, r"cell_x = 0\.0"),
    ({"density": np.full(N, np.nan)}, r"density\[0\] = nan.*finite"),
])
def test_packing_rejects_inconsistent_fields(packing, change, match):
    with pytest.raises(PackingError, match=match):
        dataclasses.replace(packing, **change)


# ---------------------------------------------------------------------------------- CSV


def test_csv_round_trip_bit_exact(packing, tmp_path):
    path = write_csv(tmp_path / "p.csv", packing)
    assert path == tmp_path / "p.csv"
    assert_identical(read_csv(path), packing)
    assert os.listdir(tmp_path) == ["p.csv"]


def test_csv_round_trip_without_density(packing, tmp_path):
    bare = dataclasses.replace(packing, density=None)
    write_csv(tmp_path / "p.csv", bare)
    back = read_csv(tmp_path / "p.csv")
    assert back.density is None
    assert_identical(back, bare, density=False)


def test_csv_text_layout(packing, tmp_path):
    write_csv(tmp_path / "p.csv", packing)
    lines = (tmp_path / "p.csv").read_text().splitlines()
    assert lines[0] == "# calendaring packing v1"
    assert f"# cell_x_m = {packing.cell_x!r}" in lines
    header = lines.index("id,material,diameter_m,density_kg_m3,x_m,y_m,z_m")
    first = lines[header + 1].split(",")
    assert int(first[0]) == packing.ids[0]
    assert first[1] == ("AM", "CB")[packing.material[0]]
    assert float(first[2]) == 2 * packing.radius[0]
    assert [float(v) for v in first[4:]] == packing.position[0].tolist()


def _rewrite(path, edit):
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(edit(lines)))


def _bad_csv_cases():
    def truncated_row(lines):
        return [*lines[:-1], lines[-1].rsplit(",", 3)[0]]

    def no_marker(lines):
        return [s for s in lines if s != "# calendaring packing v1\n"]

    def non_numeric(lines):
        parts = lines[-3].split(",")
        parts[5] = "abc"
        return [*lines[:-3], ",".join(parts), *lines[-2:]]

    def missing_key(lines):
        return [s for s in lines if not s.startswith("# z_top_m")]

    def missing_row(lines):
        return lines[:-1]

    return [
        (truncated_row, r"line 58: expected 7 comma-separated values.*got 4"),
        (no_marker, r"line 7: expected the format marker"),
        (non_numeric, r"line 56: column 'y_m': expected a real number, got 'abc'"),
        (missing_key, r"line 7: missing header key 'z_top_m'"),
        (missing_row, r"expected 50 data rows.*found 49"),
    ]


@pytest.mark.parametrize("edit, match", _bad_csv_cases(),
                         ids=["truncated", "no-marker", "non-numeric", "missing-key",
                              "missing-row"])
def test_read_csv_rejects_malformed(packing, tmp_path, edit, match):
    path = write_csv(tmp_path / "bad.csv", packing)
    _rewrite(path, edit)
    with pytest.raises(PackingError, match=match) as info:
        read_csv(path)
    assert str(path) in str(info.value) and info.value.path == path


def test_read_csv_wraps_validation_errors_with_file(packing, tmp_path):
    path = write_csv(tmp_path / "dup.csv", packing)
    _rewrite(path, lambda lines: [*lines[:-1], lines[-2]])  # duplicate the row above
    with pytest.raises(PackingError, match=r"dup\.csv.*ids\[49\].*unique"):
        read_csv(path)


# ------------------------------------------------------------------------------- LAMMPS


def test_lammps_round_trip_bit_exact(packing, tmp_path):
    path = write_lammps_data(tmp_path / "p.data", packing)
    assert_identical(read_lammps_data(path), packing)
    assert os.listdir(tmp_path) == ["p.data"]


def test_lammps_text_layout(packing, tmp_path):
    path = write_lammps_data(tmp_path / "p.data", packing)
    lines = path.read_text().splitlines()
    assert f"{N} atoms" in lines and "2 atom types" in lines
    assert f"0 {packing.cell_x:.17g} xlo xhi" in lines
    assert f"{packing.z_bottom:.17g} {packing.z_top:.17g} zlo zhi" in lines
    atoms = lines.index("Atoms # granular")
    assert lines[atoms + 1] == ""
    # atom-ID atom-type diameter density x y z
    row = lines[atoms + 2].split()
    assert len(row) == 7
    assert int(row[0]) == packing.ids[0]
    assert int(row[1]) == packing.material[0] + 1
    assert float(row[2]) == 2 * packing.radius[0]
    assert float(row[3]) == packing.density[0]
    assert [float(v) for v in row[4:]] == packing.position[0].tolist()


def test_lammps_density_by_material(packing, tmp_path):
    bare = dataclasses.replace(packing, density=None)
    with pytest.raises(PackingError, match="density"):
        write_lammps_data(tmp_path / "p.data", bare)
    with pytest.raises(PackingError, match="missing 1"):
        write_lammps_data(tmp_path / "p.data", bare, density_by_material={0: 4750.0})
    assert not list(tmp_path.iterdir())
    back = read_lammps_data(write_lammps_data(tmp_path / "p.data", bare,
                                              density_by_material={0: 4750.0, 1: 1800.0}))
    np.testing.assert_array_equal(back.density, np.where(packing.material == 0, 4750.0, 1800.0))
    assert_identical(back, bare, density=False)


def test_lammps_reader_tolerates_extras(packing, tmp_path):
    path = write_lammps_data(tmp_path / "p.data", packing)
    text = path.read_text()
    text = text.replace("2 atom types\n", "2 atom types  # comment\n0 bonds\n")
    text = text.replace("zlo zhi\n", "zlo zhi\n0.0 0.0 0.0 xy xz yz\n")
    velocities = "".join(f"{i} 0 0 0 0 0 0\n" for i in packing.ids.tolist())
    text += f"\nVelocities\n\n{velocities}"
    path.write_text(text)
    assert_identical(read_lammps_data(path), packing)
    moved = read_lammps_data(path, cell=(2e-4, 2e-4, 0.0, 1e-4))
    assert (moved.cell_x, moved.z_top) == (2e-4, 1e-4)


def test_read_lammps_rejects_missing_rows(packing, tmp_path):
    path = write_lammps_data(tmp_path / "p.data", packing)
    _rewrite(path, lambda lines: lines[:-2])
    with pytest.raises(PackingError, match=r"has 48 rows: expected 50 as declared on line 3"
                       ) as info:
        read_lammps_data(path)
    assert str(path) in str(info.value)


def test_read_lammps_rejects_tilted_box(packing, tmp_path):
    path = write_lammps_data(tmp_path / "p.data", packing)
    path.write_text(path.read_text().replace("zlo zhi\n", "zlo zhi\n1e-6 0 0 xy xz yz\n"))
    with pytest.raises(PackingError, match=r"line 9: tilted .*orthogonal") as info:
        read_lammps_data(path)
    assert str(path) in str(info.value)


def test_read_lammps_rejects_other_atom_style(packing, tmp_path):
    path = write_lammps_data(tmp_path / "p.data", packing)
    path.write_text(path.read_text().replace("Atoms # granular", "Atoms # atomic"))
    with pytest.raises(PackingError, match=r"p\.data, line 10: .*'atomic'"):
        read_lammps_data(path)


# ---------------------------------------------------------------------------------- VTK


def test_write_vtk_round_trip(packing, tmp_path):
    pv = pytest.importorskip("pyvista")
    velocity = np.arange(3.0 * N).reshape(N, 3)
    paths = write_vtk(tmp_path / "p.vtp", packing, point_data={"velocity": velocity})
    assert paths == [tmp_path / "p.vtp", tmp_path / "p_plates.vtp"]
    assert sorted(os.listdir(tmp_path)) == ["p.vtp", "p_plates.vtp"]

    cloud = pv.read(paths[0])
    assert cloud.n_points == N
    np.testing.assert_array_equal(cloud.points, packing.position)
    np.testing.assert_array_equal(cloud.point_data["radius"], packing.radius)
    np.testing.assert_array_equal(cloud.point_data["id"], packing.ids)
    np.testing.assert_array_equal(cloud.point_data["material"], packing.material)
    np.testing.assert_array_equal(cloud.point_data["velocity"], velocity)

    plates = pv.read(paths[1])
    assert plates.n_cells == 2
    np.testing.assert_array_equal(plates.cell_data["plate"], [0, 1])
    for k, z in enumerate((packing.z_bottom, packing.z_top)):
        corners = plates.get_cell(k).points
        np.testing.assert_array_equal(corners[:, 2], np.full(4, z))
        assert corners[:, 0].max() == packing.cell_x and corners[:, 1].max() == packing.cell_y


def test_write_vtk_without_plates_and_bad_suffix(packing, tmp_path):
    pytest.importorskip("pyvista")
    assert write_vtk(tmp_path / "p.vtp", packing, plates=False) == [tmp_path / "p.vtp"]
    with pytest.raises(PackingError, match=r"\.vtp"):
        write_vtk(tmp_path / "p.vtk", packing)
    assert os.listdir(tmp_path) == ["p.vtp"]


# ---------------------------------------------------------------------------- atomicity


def test_vtk_bad_point_data_writes_nothing(packing, tmp_path):
    pytest.importorskip("pyvista")
    with pytest.raises(PackingError, match=r"point_data\['v'\]\.shape"):
        write_vtk(tmp_path / "p.vtp", packing, point_data={"v": np.zeros(N - 1)})
    assert not list(tmp_path.iterdir())


def test_vtk_failure_mid_way_leaves_nothing(packing, tmp_path, monkeypatch):
    pv = pytest.importorskip("pyvista")
    save = pv.PolyData.save
    calls = []

    def failing_save(self, filename, *args, **kwargs):
        calls.append(filename)
        if len(calls) == 2:  # particles written, plates fail half-way
            with open(filename, "w") as f:
                f.write("<VTKFile")
            raise OSError("disk full")
        return save(self, filename, *args, **kwargs)

    monkeypatch.setattr(pv.PolyData, "save", failing_save)
    with pytest.raises(OSError, match="disk full"):
        write_vtk(tmp_path / "p.vtp", packing)
    assert len(calls) == 2 and all(str(c).endswith(".tmp.vtp") for c in calls)
    assert not list(tmp_path.iterdir())


def test_csv_failure_mid_way_leaves_nothing(packing, tmp_path, monkeypatch):
    lines = pk._csv_lines

    def failing_lines(*args):
        for k, line in enumerate(lines(*args)):
            if k == 20:
                raise RuntimeError("interrupted")
            yield line

    monkeypatch.setattr(pk, "_csv_lines", failing_lines)
    with pytest.raises(RuntimeError, match="interrupted"):
        write_csv(tmp_path / "p.csv", packing)
    assert not list(tmp_path.iterdir())


def test_lammps_failed_replace_keeps_old_file(packing, tmp_path, monkeypatch):
    path = tmp_path / "p.data"
    path.write_text("old")

    def failing_replace(src, dst):
        raise OSError("rename failed")

    monkeypatch.setattr(pk.os, "replace", failing_replace)
    with pytest.raises(OSError, match="rename failed"):
        write_lammps_data(path, packing)
    assert path.read_text() == "old"
    assert os.listdir(tmp_path) == ["p.data"]


def test_module_is_host_only():
    code = ("import sys, calendaring.process.packing; "
            "assert 'taichi' not in sys.modules and 'pyvista' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_write_vtk_without_pyvista_says_how_to_install(packing, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyvista", None)
    with pytest.raises(ImportError, match="pip install pyvista"):
        write_vtk(tmp_path / "p.vtp", packing)
    assert not list(tmp_path.iterdir())
