"""Sphere packings: validation and file exchange (CSV, LAMMPS data, VTK).

Host-only module: it does not import taichi. A :class:`Packing` is a set of spheres in a
cell that is periodic in x and y (``0 <= x < cell_x``, ``0 <= y < cell_y``) and bounded
along z by two plates at ``z_bottom`` and ``z_top``. Every quantity is SI: metres and
kg/m^3. Material index 0 is the active material (AM), 1 carbon black (CB).

CSV format (:func:`write_csv`, :func:`read_csv`)
    A ``#`` comment header with the format marker and the cell, a column header, then one
    row per sphere. ``material`` is a name from the ``# materials`` line (its index is its
    position in that list) or a plain integer index. ``density_kg_m3`` is ``nan`` on every
    row when the packing carries no densities. Floats are written with ``repr``, so a
    round trip is bit-exact. ``n_particles`` and ``materials`` are optional on reading;
    when ``n_particles`` is present the row count must match it::

        # calendaring packing v1
        # n_particles = 2
        # cell_x_m = 0.0001
        # cell_y_m = 0.0001
        # z_bottom_m = 0.0
        # z_top_m = 8e-05
        # materials = AM,CB
        id,material,diameter_m,density_kg_m3,x_m,y_m,z_m
        1,AM,1e-05,4750.0,2.5e-05,3e-05,1e-05
        2,CB,1e-06,1800.0,6e-05,1e-05,4e-06

LAMMPS data format (:func:`write_lammps_data`, :func:`read_lammps_data`)
    A data file for ``units si``, ``atom_style granular`` and ``boundary p p f``. Atom
    rows are ``atom-ID atom-type diameter density x y z`` with ``atom-type = material + 1``;
    the box is ``[0, cell_x) x [0, cell_y) x [z_bottom, z_top]``. Floats are written with
    ``%.17g`` (bit-exact round trip)::

        LAMMPS data file: calendaring packing v1 (units si, atom_style granular)

        2 atoms
        2 atom types

        0 0.0001 xlo xhi
        0 0.0001 ylo yhi
        0 8.0000000000000007e-05 zlo zhi

        Atoms # granular

        1 1 1.0000000000000001e-05 4750 2.5000000000000001e-05 3.0000000000000001e-05 ...
        2 2 9.9999999999999995e-07 1800 6.0000000000000002e-05 1.0000000000000001e-05 ...

Example:
    >>> p = read_csv("packing.csv")                                   # doctest: +SKIP
    >>> write_lammps_data("packing.data", p, density_by_material={0: 4750.0, 1: 1800.0})
    ...                                                               # doctest: +SKIP
    >>> write_vtk("packing.vtp", p)                                   # doctest: +SKIP
    [PosixPath('packing.vtp'), PosixPath('packing_plates.vtp')]

Every writer is atomic: it writes a hidden temporary file in the target directory and
renames it onto the final name, so a failed write never leaves a partial file under the
final name.

See also: :mod:`calendaring.process.run` (writes the settled beds of ``calendaring pack`` and
starts runs from them), :mod:`calendaring.cli` (``calendaring export``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calendaring.core.fileio import atomic_path

__all__ = [
    "CSV_COLUMNS",
    "CSV_MARKER",
    "Packing",
    "PackingError",
    "read_csv",
    "read_lammps_data",
    "write_csv",
    "write_lammps_data",
    "write_vtk",
]

CSV_MARKER = "calendaring packing v1"
CSV_COLUMNS = ("id", "material", "diameter_m", "density_kg_m3", "x_m", "y_m", "z_m")
_CSV_CELL_KEYS = ("cell_x_m", "cell_y_m", "z_bottom_m", "z_top_m")
_LAMMPS_TITLE = f"LAMMPS data file: {CSV_MARKER} (units si, atom_style granular)"
_LAMMPS_ROW = "atom-ID atom-type diameter density x y z [ix iy iz]"

PathLike = str | os.PathLike


class PackingError(ValueError):
    """Invalid packing or malformed packing file.

    The message names the field (or the file and line), the offending value and what is
    allowed.

    Args:
        message: description of the problem.
        field: the offending :class:`Packing` field, if any.
        path: the file being read or written, if any.
        line: 1-based line number in ``path``, if any.
    """

    def __init__(self, message: str, *, field: str | None = None,
                 path: PathLike | None = None, line: int | None = None) -> None:
        self.field = field
        self.path = None if path is None else Path(path)
        self.line = line
        where = ""
        if path is not None:
            where = f"{path}" + (f", line {line}" if line is not None else "") + ": "
        super().__init__(where + message)


def _invalid(field: str, value: object, allowed: str) -> PackingError:
    return PackingError(f"{field} = {value!r} is invalid: allowed {allowed}", field=field)


def _float_array(name: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise _invalid(name, value, "an array of real numbers") from exc
    if arr.shape != shape:
        raise _invalid(f"{name}.shape", arr.shape, f"{shape} (n = {shape[0]} from position)")
    bad = np.flatnonzero(~np.isfinite(arr.reshape(shape[0], -1)).all(axis=1))
    if bad.size:
        raise _invalid(f"{name}[{bad[0]}]", arr[bad[0]].tolist(), "finite values")
    return arr


def _int_array(name: str, value: object, n: int, dtype: type) -> np.ndarray:
    arr = np.asarray(value)
    if arr.shape != (n,):
        raise _invalid(f"{name}.shape", arr.shape, f"({n},) (n from position)")
    if arr.dtype.kind == "f":
        bad = np.flatnonzero(~np.isfinite(arr) | (arr != np.round(arr)))
        if bad.size:
            raise _invalid(f"{name}[{bad[0]}]", arr[bad[0]].item(), "integers")
    elif arr.dtype.kind not in "iu" and n:
        raise _invalid(f"{name}.dtype", str(arr.dtype), "an integer array")
    info = np.iinfo(dtype)
    if n and (arr.min() < info.min or arr.max() > info.max):
        i = int(np.argmin(arr) if arr.min() < info.min else np.argmax(arr))
        raise _invalid(f"{name}[{i}]", arr[i].item(), f"values representable as {info.dtype}")
    return arr.astype(dtype)


def _positive_float(name: str, value: object) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise _invalid(name, value, "a finite real number > 0 [m]") from exc
    if not (math.isfinite(v) and v > 0):
        raise _invalid(name, value, "a finite real number > 0 [m]")
    return v


def _finite_float(name: str, value: object) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise _invalid(name, value, "a finite real number [m]") from exc
    if not math.isfinite(v):
        raise _invalid(name, value, "a finite real number [m]")
    return v


@dataclass(frozen=True, eq=False)
class Packing:
    """Spheres in an x/y-periodic cell between two plates along z (SI units).

    Arrays are converted to the documented dtypes on construction (copies are made only
    when a conversion is needed). Positions are expected, not required, to satisfy
    ``0 <= x < cell_x`` and ``0 <= y < cell_y``.

    Attributes:
        position: (n, 3) float64 sphere centres [m].
        radius: (n,) float64 radii [m], > 0.
        material: (n,) int32 material index (0 = AM, 1 = CB), >= 0.
        ids: (n,) int64 unique particle ids.
        cell_x: periodic length along x [m], > 0.
        cell_y: periodic length along y [m], > 0.
        z_bottom: bottom plate height [m].
        z_top: top plate height [m], > z_bottom.
        density: optional (n,) float64 particle densities [kg/m^3], > 0.

    Raises:
        PackingError: naming the field, the offending value and what is allowed.
    """

    position: np.ndarray
    radius: np.ndarray
    material: np.ndarray
    ids: np.ndarray
    cell_x: float
    cell_y: float
    z_bottom: float
    z_top: float
    density: np.ndarray | None = None

    def __post_init__(self) -> None:
        pos = np.asarray(self.position)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise _invalid("position.shape", pos.shape, "(n, 3)")
        n = pos.shape[0]
        fields: dict[str, object] = {
            "position": _float_array("position", pos, (n, 3)),
            "radius": _float_array("radius", self.radius, (n,)),
            "material": _int_array("material", self.material, n, np.int32),
            "ids": _int_array("ids", self.ids, n, np.int64),
            "cell_x": _positive_float("cell_x", self.cell_x),
            "cell_y": _positive_float("cell_y", self.cell_y),
            "z_bottom": _finite_float("z_bottom", self.z_bottom),
            "z_top": _finite_float("z_top", self.z_top),
        }
        if self.density is not None:
            fields["density"] = _float_array("density", self.density, (n,))
        for name, value in fields.items():
            object.__setattr__(self, name, value)

        bad = np.flatnonzero(self.radius <= 0)
        if bad.size:
            raise _invalid(f"radius[{bad[0]}]", self.radius[bad[0]].item(), "> 0 [m]")
        bad = np.flatnonzero(self.material < 0)
        if bad.size:
            raise _invalid(f"material[{bad[0]}]", self.material[bad[0]].item(),
                           ">= 0 (0 = AM, 1 = CB)")
        if n:
            order = np.argsort(self.ids, kind="stable")
            dup = np.flatnonzero(np.diff(self.ids[order]) == 0)
            if dup.size:
                i, j = sorted(order[dup[0]:dup[0] + 2].tolist())
                raise _invalid(f"ids[{j}]", self.ids[j].item(),
                               f"unique values (same id as ids[{i}])")
        if not self.z_top > self.z_bottom:
            raise _invalid("z_top", self.z_top, f"> z_bottom = {self.z_bottom!r}")
        if self.density is not None:
            bad = np.flatnonzero(self.density <= 0)
            if bad.size:
                raise _invalid(f"density[{bad[0]}]", self.density[bad[0]].item(),
                               "> 0 [kg/m^3]")

    @property
    def n(self) -> int:
        """Number of spheres."""
        return int(self.radius.shape[0])


# --------------------------------------------------------------------------- atomic I/O


def _tmp_name(path: Path, suffix: str = ".tmp") -> Path:
    return path.with_name(f".{path.name}{suffix}")


def _write_text_atomic(path: Path, lines: Iterable[str]) -> Path:
    """Write ``lines`` to a hidden temporary file next to ``path``, flush it to disk, then
    rename it (:func:`calendaring.core.fileio.atomic_path`)."""
    with (atomic_path(path, fsync=True) as tmp,
          open(tmp, "w", encoding="utf-8", newline="\n") as f):
        f.writelines(lines)
    return path


def _reraise_in_file(exc: PackingError, path: Path) -> PackingError:
    return PackingError(str(exc), field=exc.field, path=path)


# --------------------------------------------------------------------------------- CSV


def _check_material_names(names: Sequence[str]) -> list[str]:
    out = [str(s) for s in names]
    for s in out:
        if (not s or s != s.strip() or any(c in s for c in ",#= \t")
                or s.lstrip("+-").isdigit()):
            raise _invalid("material_names", tuple(names),
                           "non-empty, non-numeric names without spaces, ',', '#' or '='")
    if len(set(out)) != len(out):
        raise _invalid("material_names", tuple(names), "unique names")
    return out


def _csv_lines(packing: Packing, names: Sequence[str]) -> Iterator[str]:
    """Yield the lines of the CSV file of ``packing`` (see the module docstring)."""
    yield f"# {CSV_MARKER}\n"
    yield f"# n_particles = {packing.n}\n"
    for key, value in zip(_CSV_CELL_KEYS, (packing.cell_x, packing.cell_y,
                                           packing.z_bottom, packing.z_top), strict=True):
        yield f"# {key} = {float(value)!r}\n"
    yield f"# materials = {','.join(names)}\n"
    yield ",".join(CSV_COLUMNS) + "\n"
    dens = (np.full(packing.n, np.nan) if packing.density is None else packing.density)
    label = [str(m) if m >= len(names) else names[m] for m in packing.material.tolist()]
    for i, m, d, rho, (x, y, z) in zip(packing.ids.tolist(), label,
                                       (2.0 * packing.radius).tolist(), dens.tolist(),
                                       packing.position.tolist(), strict=True):
        yield f"{i},{m},{d!r},{rho!r},{x!r},{y!r},{z!r}\n"


def write_csv(path: PathLike, packing: Packing,
              material_names: Sequence[str] = ("AM", "CB")) -> Path:
    """Write ``packing`` as a CSV file (format in the module docstring), atomically.

    Args:
        path: destination file.
        packing: the packing to write.
        material_names: name of material index 0, 1, ...; indices without a name are
            written as integers.

    Returns:
        The written path.

    Raises:
        PackingError: if ``material_names`` are unusable as CSV labels.
    """
    names = _check_material_names(material_names)
    return _write_text_atomic(Path(path), _csv_lines(packing, names))


def _parse(text: str, conv: type, what: str, path: Path, line: int) -> int | float:
    try:
        return conv(text)
    except ValueError:
        kind = "an integer" if conv is int else "a real number"
        raise PackingError(f"{what}: expected {kind}, got {text!r}",
                           path=path, line=line) from None


def read_csv(path: PathLike) -> Packing:
    """Read a packing written by :func:`write_csv`.

    Args:
        path: CSV file.

    Returns:
        The packing; ``density`` is None when every density is ``nan``.

    Raises:
        PackingError: naming the file, the line and what was expected when the file is
            malformed (missing marker or header key, wrong column count, non-numeric value,
            unknown material, row count different from ``n_particles``) or describes an
            invalid packing.
    """
    path = Path(path)
    header: dict[str, tuple[str, int]] = {}
    marker = False
    columns_line = 0
    rows: list[tuple[int, int, float, float, float, float, float]] = []
    names: list[str] = []
    lineno = 0
    with open(path, encoding="utf-8") as f:
        for lineno, raw in enumerate(f, 1):
            line = raw.rstrip("\r\n")
            if not columns_line:
                if not line.strip():
                    continue
                if line.startswith("#"):
                    text = line[1:].strip()
                    if text == CSV_MARKER:
                        marker = True
                    elif text.startswith("calendaring packing"):
                        raise PackingError(f"unsupported format {text!r}: expected "
                                           f"'{CSV_MARKER}'", path=path, line=lineno)
                    elif "=" in text:
                        key, value = (s.strip() for s in text.split("=", 1))
                        if key in header:
                            raise PackingError(f"duplicate header key {key!r} (first on "
                                               f"line {header[key][1]})",
                                               path=path, line=lineno)
                        header[key] = (value, lineno)
                    continue
                columns_line = lineno
                if not marker:
                    raise PackingError(f"expected the format marker line '# {CSV_MARKER}' "
                                       "before the column header", path=path, line=lineno)
                for key in _CSV_CELL_KEYS:
                    if key not in header:
                        raise PackingError(f"missing header key {key!r}: expected a line "
                                           f"'# {key} = <float>' before the column header",
                                           path=path, line=lineno)
                if "materials" in header:
                    names = [s.strip() for s in header["materials"][0].split(",")]
                cols = tuple(s.strip() for s in line.split(","))
                if cols != CSV_COLUMNS:
                    raise PackingError(f"expected column header {','.join(CSV_COLUMNS)!r}, "
                                       f"got {line!r}", path=path, line=lineno)
                continue
            if not line.strip():
                continue
            parts = [s.strip() for s in line.split(",")]
            if len(parts) != len(CSV_COLUMNS):
                raise PackingError(f"expected {len(CSV_COLUMNS)} comma-separated values "
                                   f"({','.join(CSV_COLUMNS)}), got {len(parts)}",
                                   path=path, line=lineno)
            pid = _parse(parts[0], int, "column 'id'", path, lineno)
            label = parts[1]
            if label.lstrip("+-").isdigit():
                mat = int(label)
            elif label in names:
                mat = names.index(label)
            else:
                raise PackingError(f"column 'material': expected an integer index or one of "
                                   f"{names} (from '# materials'), got {label!r}",
                                   path=path, line=lineno)
            floats = [_parse(s, float, f"column {c!r}", path, lineno)
                      for c, s in zip(CSV_COLUMNS[2:], parts[2:], strict=True)]
            rows.append((pid, mat, *floats))  # type: ignore[arg-type]
    if not columns_line:
        what = (f"the format marker line '# {CSV_MARKER}'" if not marker
                else f"the column header {','.join(CSV_COLUMNS)!r}")
        raise PackingError(f"expected {what}, reached the end of the file",
                           path=path, line=lineno + 1)

    cell = {}
    for key in (*_CSV_CELL_KEYS, "n_particles"):
        if key in header:
            value, line_k = header[key]
            cell[key] = _parse(value, int if key == "n_particles" else float,
                               f"header key {key!r}", path, line_k)
    if "n_particles" in cell and cell["n_particles"] != len(rows):
        raise PackingError(f"expected {cell['n_particles']} data rows (n_particles on line "
                           f"{header['n_particles'][1]}), found {len(rows)}: file truncated?",
                           path=path, line=lineno + 1)
    table = np.array([r[2:] for r in rows], dtype=np.float64).reshape(len(rows), 5)
    density = table[:, 1]
    try:
        return Packing(
            position=table[:, 2:5].copy(),
            radius=table[:, 0] / 2.0,
            material=np.array([r[1] for r in rows], dtype=np.int64),
            ids=np.array([r[0] for r in rows], dtype=np.int64),
            cell_x=cell["cell_x_m"], cell_y=cell["cell_y_m"],
            z_bottom=cell["z_bottom_m"], z_top=cell["z_top_m"],
            density=None if np.isnan(density).all() else density.copy(),
        )
    except PackingError as exc:
        raise _reraise_in_file(exc, path) from exc


# ------------------------------------------------------------------------------ LAMMPS


def _lammps_density(packing: Packing,
                    density_by_material: Mapping[int, float] | None) -> np.ndarray:
    if packing.density is not None:
        return packing.density
    if density_by_material is None:
        raise _invalid("density", None, "per-particle densities in the packing or a "
                       "density_by_material mapping {material index: kg/m^3} (LAMMPS "
                       "atom_style granular needs a density per atom)")
    table = {}
    for m in np.unique(packing.material).tolist():
        if m not in density_by_material:
            raise _invalid("density_by_material", dict(density_by_material),
                           f"an entry for every material index present (missing {m})")
        rho = float(density_by_material[m])
        if not (math.isfinite(rho) and rho > 0):
            raise _invalid(f"density_by_material[{m}]", density_by_material[m],
                           "a finite density > 0 [kg/m^3]")
        table[m] = rho
    return np.array([table[m] for m in packing.material.tolist()], dtype=np.float64)


def write_lammps_data(path: PathLike, packing: Packing,
                      density_by_material: Mapping[int, float] | None = None,
                      atom_types: int | None = None) -> Path:
    """Write ``packing`` as a LAMMPS data file for ``atom_style granular``, atomically.

    Read it in LAMMPS with ``units si``, ``atom_style granular``, ``boundary p p f`` and
    ``read_data``. Atom type = material index + 1; the header declares
    ``max(2, max material + 1)`` atom types.

    Args:
        path: destination file.
        packing: the packing to write; its ids must be >= 1 (LAMMPS atom IDs).
        density_by_material: ``{material index: density [kg/m^3]}``, used when
            ``packing.density`` is None.
        atom_types: number of atom types to declare (default ``max(2, max material + 1)``);
            more leaves types free for walls (LIGGGHTS meshes need a type of their own).

    Returns:
        The written path.

    Raises:
        PackingError: if no density is available or an id is < 1.
    """
    density = _lammps_density(packing, density_by_material)
    bad = np.flatnonzero(packing.ids < 1)
    if bad.size:
        raise _invalid(f"ids[{bad[0]}]", packing.ids[bad[0]].item(),
                       "integers >= 1 (LAMMPS atom IDs)")
    ntypes = max(2, int(packing.material.max()) + 1) if packing.n else 2
    if atom_types is not None:
        if int(atom_types) < ntypes:
            raise _invalid("atom_types", atom_types, f"an integer >= {ntypes} (the materials)")
        ntypes = int(atom_types)

    def lines() -> Iterator[str]:
        yield f"{_LAMMPS_TITLE}\n\n{packing.n} atoms\n{ntypes} atom types\n\n"
        yield f"0 {packing.cell_x:.17g} xlo xhi\n0 {packing.cell_y:.17g} ylo yhi\n"
        yield f"{packing.z_bottom:.17g} {packing.z_top:.17g} zlo zhi\n\nAtoms # granular\n\n"
        for i, t, d, rho, (x, y, z) in zip(packing.ids.tolist(),
                                           (packing.material + 1).tolist(),
                                           (2.0 * packing.radius).tolist(), density.tolist(),
                                           packing.position.tolist(), strict=True):
            yield f"{i} {t} {d:.17g} {rho:.17g} {x:.17g} {y:.17g} {z:.17g}\n"

    return _write_text_atomic(Path(path), lines())


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def read_lammps_data(path: PathLike,
                     cell: tuple[float, float, float, float] | None = None) -> Packing:
    """Read a LAMMPS data file with ``atom_style granular`` atoms.

    The header must declare ``N atoms`` and an orthogonal box (``xy xz yz`` all zero);
    other header keywords and sections (``Velocities``, ``Masses``, ...) are ignored. Atom
    rows are ``atom-ID atom-type diameter density x y z`` with optional image flags
    (ignored); material = atom-type - 1. Positions are shifted by ``(xlo, ylo, 0)`` so
    that the periodic cell starts at the origin.

    Args:
        path: LAMMPS data file.
        cell: optional ``(cell_x, cell_y, z_bottom, z_top)`` [m] replacing the values
            taken from the box (``xhi - xlo``, ``yhi - ylo``, ``zlo``, ``zhi``), e.g. for a
            box that was shrink-wrapped or padded beyond the plates.

    Returns:
        The packing, with per-particle densities.

    Raises:
        PackingError: naming the file, the line and what was expected when the file is
            malformed (missing header line, tilted box, non-granular Atoms section,
            row count different from the header, bad row) or describes an invalid packing.
    """
    path = Path(path)
    with open(path, encoding="utf-8") as f:
        lines = f.read().split("\n")

    def err(msg: str, line: int) -> PackingError:
        return PackingError(msg, path=path, line=line)

    natoms: tuple[int, int] | None = None
    ntypes: int | None = None
    box: dict[str, tuple[float, float]] = {}
    idx = 1  # line 1 is the title
    while idx < len(lines):
        tokens = lines[idx].split("#", 1)[0].split()
        if tokens and not _is_number(tokens[0]):
            break  # first section keyword
        idx += 1
        if not tokens:
            continue
        if tokens[1:] == ["atoms"]:
            natoms = (int(_parse(tokens[0], int, "'N atoms'", path, idx)), idx)
        elif tokens[1:] == ["atom", "types"]:
            ntypes = int(_parse(tokens[0], int, "'N atom types'", path, idx))
        elif len(tokens) == 4 and tokens[2:] in (["xlo", "xhi"], ["ylo", "yhi"],
                                                 ["zlo", "zhi"]):
            lo, hi = (_parse(t, float, f"'{tokens[2]} {tokens[3]}'", path, idx)
                      for t in tokens[:2])
            box[tokens[2][0]] = (float(lo), float(hi))
        elif tokens[3:] == ["xy", "xz", "yz"]:
            tilt = [_parse(t, float, "'xy xz yz'", path, idx) for t in tokens[:3]]
            if any(tilt):
                raise err(f"tilted (triclinic) box xy xz yz = {tilt}: expected an "
                          "orthogonal box (all tilt factors 0)", idx)

    if natoms is None:
        raise err("missing header line 'N atoms' before the first section", idx + 1)
    for axis in "xyz":
        if axis not in box:
            raise err(f"missing header line '<lo> <hi> {axis}lo {axis}hi' before the first "
                      "section", idx + 1)

    atoms_line = 0
    section = ""
    rows: list[tuple[int, list[str]]] = []
    for i in range(idx, len(lines)):
        text, _, comment = lines[i].partition("#")
        tokens = text.split()
        if not tokens:
            continue
        if not _is_number(tokens[0]):
            section = " ".join(tokens)
            if section == "Atoms":
                if atoms_line:
                    raise err(f"second Atoms section (first on line {atoms_line})", i + 1)
                atoms_line = i + 1
                style = comment.strip()
                if style and style != "granular":
                    raise err(f"Atoms section style {style!r}: expected 'Atoms # granular'",
                              i + 1)
        elif section == "Atoms":
            rows.append((i + 1, tokens))

    n, n_line = natoms
    if n and not atoms_line:
        raise err(f"missing 'Atoms # granular' section ({n} atoms declared on line "
                  f"{n_line})", len(lines))
    if len(rows) != n:
        last = rows[-1][0] if rows else atoms_line
        raise err(f"Atoms section (line {atoms_line}) has {len(rows)} rows: expected {n} "
                  f"as declared on line {n_line}", last + (len(rows) < n))

    ids = np.empty(n, dtype=np.int64)
    types = np.empty(n, dtype=np.int64)
    table = np.empty((n, 5), dtype=np.float64)
    for k, (line, tokens) in enumerate(rows):
        if len(tokens) not in (7, 10):
            raise err(f"expected 7 or 10 values ({_LAMMPS_ROW}), got {len(tokens)}", line)
        ids[k] = _parse(tokens[0], int, "atom-ID", path, line)
        types[k] = _parse(tokens[1], int, "atom-type", path, line)
        if types[k] < 1 or (ntypes is not None and types[k] > ntypes):
            raise err(f"atom-type {types[k]}: expected 1..{ntypes or 'N atom types'}", line)
        for j, name in enumerate(("diameter", "density", "x", "y", "z")):
            table[k, j] = _parse(tokens[2 + j], float, name, path, line)

    (xlo, xhi), (ylo, yhi), (zlo, zhi) = box["x"], box["y"], box["z"]
    cx, cy, zb, zt = (xhi - xlo, yhi - ylo, zlo, zhi) if cell is None else cell
    position = table[:, 2:5].copy()
    position[:, 0] -= xlo
    position[:, 1] -= ylo
    try:
        return Packing(position=position, radius=table[:, 0] / 2.0, material=types - 1,
                       ids=ids, cell_x=cx, cell_y=cy, z_bottom=zb, z_top=zt,
                       density=table[:, 1].copy())
    except PackingError as exc:
        raise _reraise_in_file(exc, path) from exc


# --------------------------------------------------------------------------------- VTK


def _plates_mesh(pv: object, packing: Packing) -> object:
    cx, cy, zb, zt = packing.cell_x, packing.cell_y, packing.z_bottom, packing.z_top
    corners = [(0.0, 0.0), (cx, 0.0), (cx, cy), (0.0, cy)]
    points = np.array([(x, y, z) for z in (zb, zt) for x, y in corners], dtype=np.float64)
    # Both quads face into the packing: bottom normal +z, top normal -z.
    mesh = pv.PolyData(points, faces=np.array([4, 0, 1, 2, 3, 4, 4, 7, 6, 5]))
    mesh.cell_data["plate"] = np.array([0, 1], dtype=np.int32)
    return mesh


def write_vtk(path: PathLike, packing: Packing,
              point_data: Mapping[str, np.ndarray] | None = None,
              plates: bool = True) -> list[Path]:
    """Write ``packing`` as VTK XML PolyData for ParaView, atomically.

    Particles are a point cloud (one vertex per sphere centre) with point arrays ``id``,
    ``material``, ``radius`` [m], ``density`` [kg/m^3] when the packing has densities, and
    every entry of ``point_data``; the field array ``cell`` holds
    ``(cell_x, cell_y, z_bottom, z_top)``. In ParaView render the spheres with a Glyph
    filter: glyph type Sphere, scale array ``radius``, scale factor 2 (the default sphere
    glyph has radius 0.5), and colour by ``material`` or any other array.

    With ``plates``, ``<stem>_plates.vtp`` holds two quads spanning the cell at
    ``z_bottom`` and ``z_top``, with cell array ``plate`` = 0 (bottom), 1 (top).

    Args:
        path: particle file, ending in ``.vtp``.
        packing: the packing to write.
        point_data: extra per-particle arrays of shape (n,) or (n, k), e.g. velocities.
        plates: also write the plates file.

    Returns:
        The written paths (particles first, then plates).

    Raises:
        ImportError: if pyvista is not installed.
        PackingError: for a path not ending in ``.vtp`` or a bad ``point_data`` entry.
    """
    try:
        import pyvista as pv
    except ImportError as exc:
        raise ImportError("write_vtk needs pyvista: pip install pyvista "
                          "(or install the 'analysis' extra: pip install "
                          "'calendaring[analysis]')") from exc
    path = Path(path)
    if path.suffix != ".vtp":
        raise _invalid("path", str(path), "a file name ending in '.vtp' (VTK XML PolyData)")
    arrays: dict[str, np.ndarray] = {"id": packing.ids, "material": packing.material,
                                     "radius": packing.radius}
    if packing.density is not None:
        arrays["density"] = packing.density
    for name, values in (point_data or {}).items():
        key = f"point_data[{name!r}]"
        if not isinstance(name, str) or not name or name in arrays:
            raise _invalid("point_data", name, f"non-empty names other than {list(arrays)}")
        arr = np.asarray(values)
        if arr.ndim not in (1, 2) or arr.shape[0] != packing.n:
            raise _invalid(f"{key}.shape", arr.shape, f"({packing.n},) or ({packing.n}, k)")
        if arr.dtype.kind not in "biuf":
            raise _invalid(f"{key}.dtype", str(arr.dtype), "a numeric array")
        arrays[name] = arr

    cloud = pv.PolyData(np.array(packing.position, dtype=np.float64))
    for name, arr in arrays.items():
        cloud.point_data[name] = np.array(arr)
    cloud.field_data["cell"] = np.array([packing.cell_x, packing.cell_y,
                                         packing.z_bottom, packing.z_top])
    targets = [(path, cloud)]
    if plates:
        targets.append((path.with_name(f"{path.stem}_plates.vtp"), _plates_mesh(pv, packing)))

    tmps: list[Path] = []
    try:
        for final, mesh in targets:
            tmps.append(_tmp_name(final, ".tmp.vtp"))
            mesh.save(tmps[-1], binary=True)
        for (final, _), tmp in zip(targets, tmps, strict=True):
            os.replace(tmp, final)
    except BaseException:
        for tmp in tmps:
            tmp.unlink(missing_ok=True)
        raise
    return [final for final, _ in targets]
