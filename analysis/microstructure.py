"""Microstructure of calendered electrodes: voxel images, porosity, tortuosity, D_eff.

Paper section 3.5 and Fig. 13 (b-d): a snapshot of the sphere packing is turned into a voxel
image of the coating between the plates, and TauFactor (Cooper et al. 2016,
SoftwareX 5:203, doi:10.1016/j.softx.2016.09.002; TauFactor 2: Kench et al. 2023, JOSS;
pinned at 1.2.1) solves steady diffusion through the
thickness to give the tortuosity factor tau and the relative effective diffusivity

    D_eff / D_0 = porosity / tau            (TauFactor's definition, checked per result)

Pipeline (all lengths SI):

1. :func:`voxelise`: exact centre-in-sphere tests on a regular grid that spans the periodic
   cell (x, y) and the plate gap (z), with periodic wrapping of spheres that cross a lateral
   face; spheres are cropped by the plates. Optional partial-volume ("grey") voxels from
   ``supersample ** 3`` sub-voxel tests per voxel.
2. :func:`solve_tortuosity`: a percolation check of the conducting phase through the
   thickness (lateral faces periodic), then TauFactor's ``PeriodicSolver`` (binary image) or a
   laterally periodic ``MultiPhaseSolver`` (grey voxels, or carbon black as its own phase
   with a reduced diffusivity) on an explicitly passed device, at tolerance ``tol``.
3. :func:`analyse_snapshot` / :func:`analyse_run`: every snapshot at two resolutions (the
   requested one and a coarser one, same voxel sizes for every snapshot of a run), and a
   first-order extrapolation to zero voxel size (binary voxels converge about linearly in the
   voxel size: on sphere packings the tortuosity is still ~10 % too high at 20 voxels per
   smallest diameter and ~20-30 % at 10).

The image is indexed ``(z, y, x)``: axis 0 is the thickness (transport) direction, as
TauFactor expects. Binary images use 1 = pore (conducting), 0 = solid.

``MicrostructureResult.to_json()`` gives, per snapshot: ``depth_m``, ``particle_porosity``
(1 - sphere volume / cell volume, overlaps counted twice), ``voxel_porosity``,
``tortuosity`` (``None`` with ``tortuosity_reason`` when the pore phase does not percolate),
``D_eff`` (relative to the bulk diffusivity, dimensionless), ``D_eff_check``
(porosity / tortuosity), ``voxel_size_m``, ``voxels_per_diameter``, the same under
``second_resolution`` and the extrapolated values under ``extrapolated``.
"""

from __future__ import annotations

import os
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from calendaring import ConfigError

PHASES = ("solid", "am_cb")
#: Default voxels across the smallest particle diameter (2 um fragments in the quick and
#: paper presets): 0.5 um voxels, 60 x 60 x 111-150 voxels for a quick-run snapshot, so that
#: the five snapshots of a quick run take under 5 minutes on 2 CPU cores (benchmarks/
#: bench_voxelise.py). Binary voxels this coarse overestimate tau by tens of per cent: read
#: the extrapolated values and the change between the two resolutions, and compare runs
#: only at the same resolution. On a quick run (depth 0 / 19.5 um) tau was 1.89 / 2.94 at
#: 4 voxels per diameter, 1.68 / 2.28 at 8, and extrapolated 1.51 / 1.96 from 4 and 3,
#: 1.50 / 1.83 from 8 and 6. Partial-volume voxels (``supersample=3``) at 4 voxels per
#: diameter gave 1.61 / 2.09 for about twice the time of binary ones.
DEFAULT_VOXELS_PER_DIAMETER = 4.0
#: The second (convergence) resolution is this fraction of the first (coarser: cheaper).
SECOND_RESOLUTION_FACTOR = 0.75
#: Relative diffusivity of the carbon-binder phase when it conducts as its own phase: a
#: Bruggeman estimate eps^1.5 for a nano-porous CBD of internal porosity eps = 0.5 [A].
DEFAULT_CB_DIFFUSIVITY = 0.5**1.5
#: Converged microstructure (:func:`converge_snapshot`, the default of :func:`analyse_run`):
#: partial-volume voxels from REFINE_SUPERSAMPLE^3 sub-voxels at REFINE_START,
#: x REFINE_RATIO, ... voxels per smallest diameter, until tau changes by less than
#: REFINE_TOL between levels, within REFINE_MAX_VOXELS voxels a level.
REFINE_SUPERSAMPLE = 3
REFINE_START = 3.0
REFINE_RATIO = 1.5
REFINE_TOL = 0.02
REFINE_MAX_LEVELS = 5
REFINE_MAX_VOXELS = 40e6
#: TauFactor's solver stops when the flux through every layer agrees to this fraction.
DEFAULT_TOL = 1e-3
DEFAULT_ITER_LIMIT = 20_000

# ---------------------------------------------------------------------------- voxelisation
_SLAB_VOXELS = 1 << 22  # voxels per z slab while counting (bounds the memory use)
_THREADS = min(2, os.cpu_count() or 1)  # slabs filled in parallel


def _grid(length: float, voxel_size: float, key: str) -> tuple[int, float]:
    """Number of voxels along one edge and the exact voxel size that tiles it [m]."""
    n = round(length / voxel_size)
    if n < 1:
        raise ConfigError(key, length, f"at least one voxel of {voxel_size} m")
    return n, length / n


def _ragged_arange(start: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Concatenation of arange(start[i], start[i] + count[i]) over i."""
    total = int(count.sum())
    first = np.cumsum(count) - count
    return np.arange(total, dtype=np.int64) + np.repeat(start - first, count)


def _sphere_rows(c: np.ndarray, r: np.ndarray, h: tuple[float, float, float], nz: int):
    """Runs of voxels inside spheres, one per (sphere, z layer, y row) that it covers.

    Voxel (k, j, i) has its centre at ((k + 1/2) hz, (j + 1/2) hy, (i + 1/2) hx) relative to
    (z_bottom, 0, 0). On the voxel-centre line of layer k and row j a sphere covers exactly
    the voxels with |(i + 1/2) hx - cx| <= w, w = sqrt(r^2 - dz^2 - dy^2): an exact
    centre-in-sphere test, done per run of voxels instead of per voxel.

    Returns:
        k (layer, clipped to the plates), j (row, not wrapped), i0, i1 (first and last voxel
        of the run, inclusive, not wrapped), all int64.
    """
    hz, hy, hx = h
    k0 = np.maximum(np.ceil((c[:, 0] - r) / hz - 0.5), 0).astype(np.int64)
    k1 = np.minimum(np.floor((c[:, 0] + r) / hz - 0.5), nz - 1).astype(np.int64)
    n_k = np.maximum(k1 - k0 + 1, 0)
    sk = np.repeat(np.arange(len(r)), n_k)
    k = _ragged_arange(k0, n_k)
    dz = (k + 0.5) * hz - c[sk, 0]
    rho2 = r[sk] ** 2 - dz * dz  # squared radius of the sphere's section in layer k
    ok = rho2 >= 0
    sk, k, rho2 = sk[ok], k[ok], rho2[ok]
    rho = np.sqrt(rho2)
    j0 = np.ceil((c[sk, 1] - rho) / hy - 0.5).astype(np.int64)
    j1 = np.floor((c[sk, 1] + rho) / hy - 0.5).astype(np.int64)
    n_j = np.maximum(j1 - j0 + 1, 0)
    row = np.repeat(np.arange(len(sk)), n_j)
    j = _ragged_arange(j0, n_j)
    sj = sk[row]
    dy = (j + 0.5) * hy - c[sj, 1]
    w2 = rho2[row] - dy * dy
    ok = w2 >= 0
    row, j, sj, w = row[ok], j[ok], sj[ok], np.sqrt(w2[ok])
    i0 = np.ceil((c[sj, 2] - w) / hx - 0.5).astype(np.int64)
    i1 = np.floor((c[sj, 2] + w) / hx - 0.5).astype(np.int64)
    ok = i1 >= i0
    return k[row][ok], j[ok], i0[ok], i1[ok]


def _wrap_runs(k, j, i0, i1, ny: int, nx: int):
    """Wrap rows into [0, ny) and split runs that cross the periodic x face (a run longer
    than the cell covers the whole row)."""
    j = np.mod(j, ny)
    full = i1 - i0 + 1 >= nx
    a = np.where(full, 0, np.mod(i0, nx))
    b = np.where(full, nx - 1, np.mod(i1, nx))
    split = a > b  # crosses x = cell_x: [a, nx - 1] and [0, b]
    k = np.concatenate([k, k[split]])
    j = np.concatenate([j, j[split]])
    a2 = np.concatenate([a, np.zeros(int(split.sum()), np.int64)])
    b2 = np.concatenate([np.where(split, nx - 1, b), b[split]])
    return k, j, a2, b2


def _cover_slab(runs, z0: int, z1: int, ny: int, nx: int) -> np.ndarray:
    """Number of runs covering each voxel of layers [z0, z1): (z1 - z0, ny, nx) int64,
    from a difference array along x (+1 at each run start, -1 after its end)."""
    k, j, a, b = runs
    sel = (k >= z0) & (k < z1)
    base = ((k[sel] - z0) * ny + j[sel]) * (nx + 1)
    size = (z1 - z0) * ny * (nx + 1)
    diff = np.bincount(base + a[sel], minlength=size)
    diff -= np.bincount(base + b[sel] + 1, minlength=size)
    return np.cumsum(diff.reshape(z1 - z0, ny, nx + 1)[:, :, :nx], axis=2)


def _block_sum(a: np.ndarray, s: int) -> np.ndarray:
    """Sums of the s x s x s blocks of a boolean (z, y, x) array whose edges are multiples
    of s (strided adds: much faster than a 6-d reshape reduction)."""
    dt = np.uint8 if s**3 <= 255 else np.uint16
    a = a.view(np.uint8) if a.dtype == bool else a
    for axis in (2, 1, 0):
        sl = [slice(None)] * 3
        sl[axis] = slice(0, None, s)
        acc = a[tuple(sl)].astype(dt)
        for o in range(1, s):
            sl[axis] = slice(o, None, s)
            acc += a[tuple(sl)]
        a = acc
    return a


def voxelise(position, radius, material, cell_x: float, cell_y: float, z_bottom: float,
             z_top: float, voxel_size: float, supersample: int = 1,
             phases: str = "solid") -> np.ndarray:
    """Voxel image of a sphere packing between two plates in a laterally periodic cell.

    Args:
        position: (n, 3) sphere centres [m]; x and y are wrapped into the cell.
        radius: (n,) radii [m].
        material: (n,) material index (0 = AM, 1 = CB); used by ``phases="am_cb"``.
        cell_x, cell_y: periodic cell lengths [m].
        z_bottom, z_top: plate positions [m]; the image spans exactly this gap and spheres
            are cropped by it.
        voxel_size: target voxel edge [m]; the grid uses round(L / voxel_size) voxels per edge
            L, so the actual edges (``voxel_grid``) tile the cell and the gap exactly.
        supersample: s >= 1; with s > 1 every voxel is tested at s^3 sub-voxel centres and
            the result is its pore fraction in [0, 1] (multiples of 1 / s^3).
        phases: "solid" (1 = pore, 0 = solid) or "am_cb" (0 = pore, 1 = AM, 2 = CB; AM wins
            where an AM and a CB sphere overlap). "am_cb" requires supersample = 1.

    Returns:
        (nz, ny, nx) array along (thickness, y, x): uint8 for binary images, float32 pore
        fractions with supersample > 1.

    Raises:
        ConfigError: bad voxel size, supersample, phases, gap or array shapes.
    """
    if phases not in PHASES:
        raise ConfigError("phases", phases, f"one of {PHASES}")
    if not (isinstance(supersample, (int, np.integer)) and 1 <= supersample <= 16):
        raise ConfigError("supersample", supersample, "an integer in [1, 16]")
    if phases == "am_cb" and supersample != 1:
        raise ConfigError("supersample", supersample, "1 with phases='am_cb'")
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise ConfigError("voxel_size", voxel_size, "> 0 m")
    if not z_top > z_bottom:
        raise ConfigError("z_top", z_top, f"> z_bottom = {z_bottom} m")
    pos = np.asarray(position, dtype=float).reshape(-1, 3)
    rad = np.asarray(radius, dtype=float).reshape(-1)
    mat = np.asarray(material).reshape(-1)
    if not (len(pos) == len(rad) == len(mat)):
        raise ConfigError("position/radius/material", (len(pos), len(rad), len(mat)),
                          "arrays of the same length")
    if len(rad) and not np.all(rad > 0):
        raise ConfigError("radius", float(rad.min()), "> 0 m")
    nx, _ = _grid(cell_x, voxel_size, "cell_x")
    ny, _ = _grid(cell_y, voxel_size, "cell_y")
    nz, _ = _grid(z_top - z_bottom, voxel_size, "z_top - z_bottom")
    s = int(supersample)
    fx, fy, fz = nx * s, ny * s, nz * s
    h = ((z_top - z_bottom) / fz, cell_y / fy, cell_x / fx)
    # centres relative to (z_bottom, 0, 0), wrapped laterally, ordered (z, y, x)
    c = np.column_stack([pos[:, 2] - z_bottom, np.mod(pos[:, 1], cell_y),
                         np.mod(pos[:, 0], cell_x)])
    groups = [np.ones(len(rad), bool)] if phases == "solid" else [mat != 1, mat == 1]
    runs = [_wrap_runs(*_sphere_rows(c[g], rad[g], h, fz), fy, fx) for g in groups]
    if phases == "solid" and s == 1:
        out = np.empty((nz, ny, nx), np.uint8)
    elif phases == "solid":
        out = np.empty((nz, ny, nx), np.float32)
    else:
        out = np.empty((nz, ny, nx), np.uint8)
    # slabs of fine layers (a multiple of s), at least one per thread, filled in parallel:
    # numpy releases the GIL in bincount and cumsum
    n_slabs = max(min(_THREADS, fz // s), -(-fz * fy * fx // _SLAB_VOXELS))
    step = max(1, -(-(fz // s) // n_slabs)) * s

    def fill(z0: int) -> None:
        z1 = min(z0 + step, fz)
        if phases == "am_cb":
            am = _cover_slab(runs[0], z0, z1, fy, fx) > 0
            cb = _cover_slab(runs[1], z0, z1, fy, fx) > 0
            out[z0:z1] = np.where(am, np.uint8(1), np.where(cb, np.uint8(2), np.uint8(0)))
            return
        pore = _cover_slab(runs[0], z0, z1, fy, fx) == 0
        if s == 1:
            out[z0:z1] = pore
        else:
            out[z0 // s:z1 // s] = _block_sum(pore, s) / np.float32(s**3)

    starts = range(0, fz, step)
    if len(starts) == 1 or _THREADS == 1:
        for z0 in starts:
            fill(z0)
    else:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max_workers=_THREADS) as pool:
            list(pool.map(fill, starts))
    return out


def voxel_grid(cell_x: float, cell_y: float, z_bottom: float, z_top: float,
               voxel_size: float) -> dict[str, Any]:
    """Shape (nz, ny, nx) and the exact voxel edges [m] that :func:`voxelise` uses."""
    nx, hx = _grid(cell_x, voxel_size, "cell_x")
    ny, hy = _grid(cell_y, voxel_size, "cell_y")
    nz, hz = _grid(z_top - z_bottom, voxel_size, "z_top - z_bottom")
    return {"shape": (nz, ny, nx), "voxel_edges_m": (hz, hy, hx)}


# ---------------------------------------------------------------------------- transport
def _periodic_multiphase_class():
    """TauFactor's MultiPhaseSolver with periodic lateral (y, z of TauFactor) faces.

    TauFactor 1.2.1 offers lateral periodicity only for the binary ``PeriodicSolver``. This
    subclass builds the harmonic-mean pair conductances of ``MultiPhaseSolver`` from a
    conductivity map padded circularly in the two lateral axes, and copies the field's
    lateral halo before every sweep (as ``PeriodicSolver.apply_boundary_conditions`` does).
    """
    import torch
    from taufactor import MultiPhaseSolver

    class PeriodicMultiPhaseSolver(MultiPhaseSolver):
        def init_conductive_neighbours(self, img):
            img2 = torch.zeros_like(img)
            for ph, c in self.cond.items():
                img2[img == ph] = c
            # two layers in the transport direction: zero pads, then the boundary layer
            # takes the conductivity of its neighbouring image layer (as the parent does)
            img2 = torch.nn.functional.pad(img2, (0, 0, 0, 0, 2, 2))
            img2[:, 1] = img2[:, 2]
            img2[:, -2] = img2[:, -3]
            img2[:, 0] = 0
            img2[:, -1] = 0
            # two periodic layers in each lateral direction
            img2 = torch.cat([img2[:, :, -2:], img2, img2[:, :, :2]], dim=2)
            img2 = torch.cat([img2[:, :, :, -2:], img2, img2[:, :, :, :2]], dim=3)
            nn = torch.zeros_like(img2, dtype=self.precision)
            nn_list = []
            for dim in range(1, 4):
                for dr in (1, -1):
                    shift = torch.roll(img2, dr, dim)
                    pair = img2 + shift  # series resistance of two half voxels
                    pair[shift == 0] = 0
                    pair[img2 == 0] = 0
                    pair = 1 / pair
                    pair[pair == torch.inf] = 0
                    nn += pair
                    nn_list.append(self._crop(pair, 1).to(self.device))
            nn = self._crop(nn, 2)
            nn[img == 0] = torch.inf
            nn[nn == 0] = torch.inf
            nn_list.insert(0, nn.to(self.device))
            return nn_list

        def apply_boundary_conditions(self):
            self.field[:, :, 0, :] = self.field[:, :, -2, :]
            self.field[:, :, -1, :] = self.field[:, :, 1, :]
            self.field[:, :, :, 0] = self.field[:, :, :, -2]
            self.field[:, :, :, -1] = self.field[:, :, :, 1]

    return PeriodicMultiPhaseSolver


def percolating_fraction(conducting: np.ndarray, periodic: bool = True) -> float:
    """Fraction of the conducting voxels (bool, (z, y, x)) in face-connected clusters that
    touch both z faces, with periodic y and x unless ``periodic`` is False (TauFactor's
    ``extract_through_feature``)."""
    from taufactor.metrics import extract_through_feature

    img = np.ascontiguousarray(conducting, dtype=np.uint8)
    if not img.any():
        return 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, frac = extract_through_feature(img, 1, "x", periodic=[False, periodic, periodic],
                                          connectivity=1)
    return float(np.asarray(frac).reshape(-1)[0])


@dataclass
class TransportResult:
    """One TauFactor solve (SI; D_eff relative to the bulk diffusivity)."""

    porosity: float  # pore volume fraction of the image (grey: mean pore fraction) [-]
    tortuosity: float | None  # tau [-]; None when the conducting phase does not percolate
    D_eff: float  # effective / bulk diffusivity [-]
    D_eff_check: float | None  # porosity / tortuosity (or D_mean / tau with a CB phase) [-]
    reason: str | None  # why tortuosity is None
    percolating_fraction: float  # of the conducting volume [-]
    conducting_fraction: float  # pore (+ CB, if it conducts) volume fraction [-]
    solver: str
    iterations: int
    converged: bool
    seconds: float
    warm_start: bool = False  # started from a coarser level's potential
    potential: np.ndarray | None = field(default=None, repr=False)  # if keep_field

    def to_json(self) -> dict[str, Any]:
        return {"porosity": self.porosity, "tortuosity": self.tortuosity,
                "tortuosity_reason": self.reason, "D_eff": self.D_eff,
                "D_eff_check": self.D_eff_check,
                "percolating_fraction": self.percolating_fraction,
                "conducting_fraction": self.conducting_fraction, "solver": self.solver,
                "iterations": self.iterations, "converged": self.converged,
                "solve_seconds": self.seconds, "warm_start": self.warm_start}


def prolong_field(coarse: np.ndarray, conducting: np.ndarray,
                  shape: tuple[int, int, int]) -> np.ndarray:
    """A coarse level's potential (z, y, x) on a finer grid of ``shape``: the value of the
    coarse voxel that holds each fine voxel's centre (nearest), where the coarse voxel is
    solid its layer's mean potential over the conducting voxels. An initial guess for the
    fine solve: the smooth, slowly converging part of the solution is already there, and
    the SOR sweeps remove the local errors in a few hundred iterations."""
    f = np.asarray(coarse, dtype=np.float64)
    m = np.asarray(conducting, dtype=bool)
    layer = (f * m).sum(axis=(1, 2)) / np.maximum(m.sum(axis=(1, 2)), 1)
    f = np.where(m, f, layer[:, None, None])
    idx = [np.minimum(((np.arange(n) + 0.5) * c / n).astype(np.int64), c - 1)
           for n, c in zip(shape, f.shape, strict=True)]
    return f[np.ix_(*idx)].astype(np.float32)


def solve_tortuosity(img: np.ndarray, *, device: str = "cpu", tol: float = DEFAULT_TOL,
                     cb_diffusivity: float | None = None,
                     iter_limit: int = DEFAULT_ITER_LIMIT,
                     initial_field: np.ndarray | None = None,
                     keep_field: bool = False, periodic: bool = True) -> TransportResult:
    """Tortuosity factor and relative D_eff through axis 0 of a voxel image (TauFactor).

    Args:
        img: (nz, ny, nx) image: binary uint8 (1 = pore), float pore fractions in [0, 1]
            (partial-volume voxels: the fraction is the voxel's relative conductivity), or,
            with ``cb_diffusivity``, labels 0 = pore, 1 = AM, 2 = CB from
            ``voxelise(..., phases="am_cb")``.
        device: torch device for TauFactor, passed explicitly ("cpu", "cuda", ...).
        tol: TauFactor's convergence criterion (largest relative spread of the layer fluxes).
        cb_diffusivity: relative diffusivity of the CB phase (> 0); None for a two-phase
            image.
        iter_limit: SOR sweeps before giving up (the result is then marked not converged).
        initial_field: a potential of the image's shape to start from (a coarser level's,
            :func:`prolong_field`) instead of TauFactor's linear profile. Only the start
            changes: the solve stops on the same criterion.
        keep_field: return the solved potential ((nz, ny, nx), float32) in ``potential``.
        periodic: lateral faces periodic (a periodic cell, the default), or no-flux side
            walls (a window cut from a cell: TauFactor's ``Solver`` / ``MultiPhaseSolver``).

    Returns:
        :class:`TransportResult`. A conducting phase without a face-connected path between
        the two z faces (lateral faces periodic) gives ``tortuosity=None``, ``D_eff=0`` and a
        reason; TauFactor is not called.
    """
    import taufactor
    import torch

    if not (0 < tol < 1):
        raise ConfigError("tol", tol, "in (0, 1)")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise ConfigError("device", device, "a torch device such as 'cpu' or 'cuda'") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        # TauFactor would fall back to the CPU with a warning; say so instead
        raise ConfigError("device", device, "'cpu' (no CUDA device is available)")
    img = np.asarray(img)
    if img.ndim != 3:
        raise ConfigError("img.ndim", img.ndim, "3 (z, y, x)")
    if cb_diffusivity is not None:
        if not (0 < cb_diffusivity <= 1):
            raise ConfigError("cb_diffusivity", cb_diffusivity, "in (0, 1]")
        pore = img == 0
        cb = img == 2
        porosity = float(pore.mean())
        conducting = pore | cb
        labels = np.zeros(img.shape, dtype=np.int64)
        labels[pore] = 1
        labels[cb] = 2
        cond = {1: 1.0, 2: float(cb_diffusivity)}
        solver_name = f"PeriodicMultiPhaseSolver (pore 1, CB {cb_diffusivity:.3g})"
        d_mean = porosity + cb_diffusivity * float(cb.mean())
    elif np.issubdtype(img.dtype, np.floating):
        if img.min() < 0 or img.max() > 1:
            raise ConfigError("img", (float(img.min()), float(img.max())),
                              "pore fractions in [0, 1]")
        porosity = float(img.mean(dtype=np.float64))
        conducting = img > 0
        levels, labels = np.unique(img, return_inverse=True)
        labels = labels.reshape(img.shape)
        if levels[0] == 0:
            cond = {int(k): float(v) for k, v in enumerate(levels) if k > 0}
        else:  # no solid voxel: shift labels so that 0 stays free for the solid phase
            labels = labels + 1
            cond = {int(k) + 1: float(v) for k, v in enumerate(levels)}
        solver_name = f"PeriodicMultiPhaseSolver ({len(cond)} grey levels)"
        d_mean = porosity
    else:
        if not np.isin(np.unique(img), (0, 1)).all():
            raise ConfigError("img", np.unique(img)[:5].tolist(), "binary labels 0 / 1")
        labels = img.astype(np.uint8)
        porosity = float(labels.mean(dtype=np.float64))
        conducting = labels.astype(bool)
        cond = None
        solver_name = "PeriodicSolver"
        d_mean = porosity
    if not periodic:
        solver_name = solver_name.replace("Periodic", "") or "Solver"
    frac = percolating_fraction(conducting, periodic)
    cfrac = float(conducting.mean())
    # TauFactor's red-black SOR sweep with periodic lateral faces diverges when a periodic
    # axis has an odd length (two neighbours across the face share a colour); two periodic
    # copies side by side are the same structure with an even length.
    reps = (1, 1 + labels.shape[1] % 2, 1 + labels.shape[2] % 2) if periodic else (1, 1, 1)
    if reps != (1, 1, 1):
        labels = np.tile(labels, reps)
    if frac == 0.0:
        what = "pore phase" if cb_diffusivity is None else "pore + CB phase"
        return TransportResult(
            porosity=porosity, tortuosity=None, D_eff=0.0, D_eff_check=None,
            reason=f"the {what} does not percolate through the thickness (no face-connected "
                   f"path between the plates, lateral faces "
                   f"{'periodic' if periodic else 'closed'})",
            percolating_fraction=0.0, conducting_fraction=cfrac, solver=solver_name,
            iterations=0, converged=True, seconds=0.0)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if cond is None:
            solver = (taufactor.PeriodicSolver if periodic else taufactor.Solver)(
                labels, device=device)
        else:
            solver = (_periodic_multiphase_class() if periodic else taufactor.MultiPhaseSolver)(
                labels, cond=cond, device=device)
        if initial_field is not None:
            start = np.asarray(initial_field, dtype=np.float32)
            if start.shape != img.shape:
                raise ConfigError("initial_field.shape", start.shape, f"{img.shape}")
            start = np.tile(start, reps) * (labels > 0)
            solver.field[0, 1:-1, 1:-1, 1:-1] = torch.from_numpy(start).to(
                solver.field.device, solver.field.dtype)
        solver.solve(iter_limit=iter_limit, verbose=False, conv_crit=tol)
    seconds = time.perf_counter() - t0
    tau = float(np.asarray(solver.tau).reshape(-1)[0])
    d_eff = float(np.asarray(solver.D_eff if cond is not None else solver.D_rel).reshape(-1)[0])
    iterations, converged = int(solver.iter), bool(solver.converged)
    potential = None
    if keep_field:
        nz, ny, nx = img.shape
        potential = solver.field[0, 1:-1, 1:-1, 1:-1].cpu().numpy()[:nz, :ny, :nx].copy()
    del solver
    if device != "cpu" and torch.cuda.is_available():
        torch.cuda.empty_cache()
    if not np.isfinite(tau) or tau <= 0 or d_eff <= 0:
        return TransportResult(
            porosity=porosity, tortuosity=None, D_eff=0.0, D_eff_check=None,
            reason=f"TauFactor found no through-flux (tau = {tau})",
            percolating_fraction=frac, conducting_fraction=cfrac, solver=solver_name,
            iterations=iterations, converged=converged, seconds=seconds)
    return TransportResult(
        porosity=porosity, tortuosity=tau, D_eff=d_eff, D_eff_check=d_mean / tau, reason=None,
        percolating_fraction=frac, conducting_fraction=cfrac, solver=solver_name,
        iterations=iterations, converged=converged, seconds=seconds,
        warm_start=initial_field is not None, potential=potential)


# ---------------------------------------------------------------------------- snapshots
def reference_diameter(config) -> float:
    """Smallest particle diameter a run can contain [m]: the smallest fragment
    (``breakage.min_fragment_diameter``, kept whether or not breakage is on, so that runs
    with and without breakage get the same voxels) or the smallest drawable size."""
    sizes = []
    for sc in config.electrode.sizes.values():
        if sc.distribution != "table":
            sizes.append(sc.bounds[0])
    sizes.append(config.breakage.min_fragment_diameter)
    return float(min(sizes))


def voxel_size_for(cell_x: float, d_ref: float, voxels_per_diameter: float) -> float:
    """Voxel edge [m] near d_ref / voxels_per_diameter that puts an even number of voxels
    across cell_x (TauFactor's periodic sweep needs even periodic lengths)."""
    if not (np.isfinite(voxels_per_diameter) and voxels_per_diameter > 0):
        raise ConfigError("voxels_per_diameter", voxels_per_diameter, "> 0")
    n = max(2, 2 * round(cell_x * voxels_per_diameter / d_ref / 2.0))
    return cell_x / n


@dataclass
class ResolutionResult:
    """Voxel image and transport of one snapshot at one resolution."""

    voxel_size: float  # lateral voxel edge [m]
    voxel_edges: tuple[float, float, float]  # (z, y, x) edges [m]
    voxels_per_diameter: float  # reference diameter / voxel_size [-]
    shape: tuple[int, int, int]  # (nz, ny, nx)
    supersample: int
    voxel_porosity: float  # [-]
    cb_fraction: float | None  # CB volume fraction of the image with cb_phase [-]
    transport: TransportResult
    voxelise_seconds: float

    def to_json(self) -> dict[str, Any]:
        t = self.transport
        rel = None
        if t.tortuosity is not None and t.D_eff > 0 and t.D_eff_check is not None:
            rel = abs(t.D_eff - t.D_eff_check) / t.D_eff
        return {"voxel_size_m": self.voxel_size, "voxel_edges_zyx_m": list(self.voxel_edges),
                "voxels_per_diameter": self.voxels_per_diameter, "shape_zyx": list(self.shape),
                "supersample": self.supersample, "voxel_porosity": self.voxel_porosity,
                "cb_volume_fraction": self.cb_fraction, "tortuosity": t.tortuosity,
                "tortuosity_reason": t.reason, "D_eff": t.D_eff,
                "D_eff_check": t.D_eff_check, "D_eff_check_rel_err": rel,
                "percolating_fraction": t.percolating_fraction,
                "conducting_fraction": t.conducting_fraction, "solver": t.solver,
                "iterations": t.iterations, "converged": t.converged,
                "solve_seconds": t.seconds, "voxelise_seconds": self.voxelise_seconds}


def _extrapolate(x1, h1, x2, h2):
    """First-order (linear in h) extrapolation of x(h) to h = 0 from two resolutions."""
    if x1 is None or x2 is None or h1 == h2:
        return None
    return float(x1 + (x1 - x2) * h1 / (h2 - h1))


@dataclass
class SnapshotMicrostructure:
    """Porosity, tortuosity and D_eff of one snapshot at one or two resolutions."""

    index: int
    label: str
    depth: float  # calendering depth [m]
    z_bottom: float  # [m]
    z_top: float  # [m]
    n_particles: int
    smallest_diameter: float  # in this snapshot [m]
    particle_porosity: float  # 1 - sphere volume / (cell area x gap) [-]
    primary: ResolutionResult  # the finest level of a refinement
    second: ResolutionResult | None = None  # the level before it
    refinement: dict[str, Any] | None = None  # the refinement sequence (converge_snapshot)
    porosities: dict[str, Any] | None = None  # analysis.porosity.porosity_budget

    def extrapolated(self) -> dict[str, Any] | None:
        """Values extrapolated to zero voxel size from the two resolutions.

        D_eff and the porosity are extrapolated linearly in the voxel size h, and the
        tortuosity follows from TauFactor's definition, tau = porosity / D_eff (with a CB
        phase: the phase-weighted mean diffusivity / D_eff). Coarse voxels close pore throats,
        which lowers the through-flux about in proportion to h; tau ~ 1 / D_eff is then convex
        in h, and a linear extrapolation of tau itself would overshoot (below 1 at 3-5 voxels
        per diameter). Errors of 20-30 % in tau at 10 voxels per diameter and 9-12 % at 20
        are what a D_eff linear in h predicts.
        """
        if self.second is None:
            return None
        p, s = self.primary, self.second
        h1, h2 = p.voxel_size, s.voxel_size
        t1, t2 = p.transport, s.transport
        phi = _extrapolate(p.voxel_porosity, h1, s.voxel_porosity, h2)
        out = {"method": "porosity and D_eff linear in the voxel size; tortuosity = "
                         "porosity / D_eff", "voxel_porosity": phi, "tortuosity": None,
               "D_eff": None, "reason": None}
        if t1.tortuosity is None or t2.tortuosity is None:
            out["reason"] = "not percolating at one of the resolutions"
        else:
            d = _extrapolate(t1.D_eff, h1, t2.D_eff, h2)
            mean = _extrapolate(t1.tortuosity * t1.D_eff, h1, t2.tortuosity * t2.D_eff, h2)
            if d is None or d <= 0:
                out["reason"] = f"D_eff extrapolates to {d}: resolutions too coarse"
            else:
                out["D_eff"], out["tortuosity"] = d, mean / d
        for key, a, b in (("tortuosity", t1.tortuosity, t2.tortuosity),
                          ("D_eff", t1.D_eff, t2.D_eff),
                          ("voxel_porosity", p.voxel_porosity, s.voxel_porosity)):
            out[f"{key}_rel_change"] = (abs(a - b) / abs(a)
                                        if a is not None and b is not None and a else None)
        return out

    def to_json(self) -> dict[str, Any]:
        out = {"index": self.index, "label": self.label, "depth_m": self.depth,
               "z_bottom_m": self.z_bottom, "z_top_m": self.z_top,
               "thickness_m": self.z_top - self.z_bottom, "n_particles": self.n_particles,
               "smallest_diameter_m": self.smallest_diameter,
               "particle_porosity": self.particle_porosity}
        out.update(self.primary.to_json())
        out["second_resolution"] = None if self.second is None else self.second.to_json()
        out["extrapolated"] = self.extrapolated()
        out["refinement"] = self.refinement
        out["porosities"] = self.porosities
        return out


def _resolution(snapshot, cell_x, cell_y, voxel_size, d_ref, supersample, cb_phase,
                cb_diffusivity, device, tol, previous=None, keep_field=False
                ) -> tuple[ResolutionResult, tuple[np.ndarray, np.ndarray] | None]:
    """Voxelise and solve one snapshot at one voxel size. ``previous``: the (potential,
    conducting mask) of a coarser level to start from (:func:`prolong_field`); with
    ``keep_field`` the same pair of this level is returned for the next one, else None."""
    t0 = time.perf_counter()
    img = voxelise(snapshot.position, snapshot.radius, snapshot.material, cell_x, cell_y,
                   snapshot.z_bottom, snapshot.z_top, voxel_size, supersample=supersample,
                   phases="am_cb" if cb_phase else "solid")
    tv = time.perf_counter() - t0
    grid = voxel_grid(cell_x, cell_y, snapshot.z_bottom, snapshot.z_top, voxel_size)
    init = None if previous is None else prolong_field(*previous, img.shape)
    if cb_phase:
        porosity = float(np.mean(img == 0))
        cb = float(np.mean(img == 2))
        tr = solve_tortuosity(img, device=device, tol=tol, cb_diffusivity=cb_diffusivity,
                              initial_field=init, keep_field=keep_field)
    else:
        porosity = float(img.mean(dtype=np.float64))
        cb = None
        tr = solve_tortuosity(img, device=device, tol=tol, initial_field=init,
                              keep_field=keep_field)
    state = None
    if keep_field and tr.potential is not None:  # none when it does not percolate
        state = (tr.potential, (img != 1) if cb_phase else (img > 0))
        tr.potential = None
    res = ResolutionResult(voxel_size=voxel_size, voxel_edges=grid["voxel_edges_m"],
                           voxels_per_diameter=d_ref / voxel_size, shape=grid["shape"],
                           supersample=supersample, voxel_porosity=porosity, cb_fraction=cb,
                           transport=tr, voxelise_seconds=tv)
    return res, state


def _snapshot_result(snapshot, cell_x, cell_y, primary, second=None,
                     **extra) -> SnapshotMicrostructure:
    return SnapshotMicrostructure(
        index=int(snapshot.index), label=str(snapshot.label), depth=float(snapshot.depth),
        z_bottom=float(snapshot.z_bottom), z_top=float(snapshot.z_top),
        n_particles=len(snapshot.radius),
        smallest_diameter=float(2 * snapshot.radius.min()) if len(snapshot.radius) else 0.0,
        particle_porosity=float(snapshot.porosity(cell_x, cell_y)), primary=primary,
        second=second, **extra)


def _porosities(snapshot, cell_x, cell_y, solid_thickness, voxel_porosity):
    from analysis.porosity import porosity_budget

    return porosity_budget(snapshot.position, snapshot.radius, snapshot.material, cell_x,
                           cell_y, snapshot.z_bottom, snapshot.z_top,
                           solid_thickness=solid_thickness, voxel_porosity=voxel_porosity)


def refinement_levels(cell_x: float, d_ref: float, start: float = REFINE_START,
                      ratio: float = REFINE_RATIO, max_levels: int = REFINE_MAX_LEVELS
                      ) -> list[float]:
    """Voxel edges [m] of a refinement sequence: ``start``, ``start * ratio``, ... voxels
    per ``d_ref``, each with an even lateral voxel count (:func:`voxel_size_for`) and
    strictly finer than the one before."""
    if not (np.isfinite(ratio) and ratio > 1):
        raise ConfigError("refine_ratio", ratio, "> 1")
    if not (isinstance(max_levels, (int, np.integer)) and max_levels >= 2):
        raise ConfigError("max_levels", max_levels, "an integer >= 2")
    out = []
    for k in range(int(max_levels)):
        h = voxel_size_for(cell_x, d_ref, start * ratio**k)
        if out and h >= out[-1]:
            h = cell_x / (round(cell_x / out[-1]) + 2)
        out.append(h)
    return out


def _richardson(taus: list[float], hs: list[float]) -> dict[str, Any]:
    """Observed order and the extrapolated tau from the last three levels (a cross-check):
    tau(h) = tau_0 + C h^p."""
    out = {"observed_order": None, "tortuosity_richardson": None}
    if len(taus) < 3 or any(t is None for t in taus[-3:]):
        return out
    t1, t2, t3 = taus[-3:]
    h1, h2, h3 = hs[-3:]
    a, b = t1 - t2, t2 - t3
    if a == 0 or b == 0 or a * b < 0:  # not monotone: no asymptotic order to read
        return out
    r = (h1 / h2 + h2 / h3) / 2.0  # the level ratio (nearly constant)
    order = float(np.log(a / b) / np.log(r))
    if not np.isfinite(order) or order <= 0:
        return out
    out["observed_order"] = order
    out["tortuosity_richardson"] = float(t3 - b / (r**order - 1.0))
    return out


def converge_snapshot(snapshot, cell_x: float, cell_y: float, *,
                      reference_diameter: float = 2.0e-6, start: float = REFINE_START,
                      ratio: float = REFINE_RATIO, refine_tol: float = REFINE_TOL,
                      max_levels: int = REFINE_MAX_LEVELS,
                      max_voxels: float = REFINE_MAX_VOXELS,
                      supersample: int = REFINE_SUPERSAMPLE, cb_phase: bool = False,
                      cb_diffusivity: float = DEFAULT_CB_DIFFUSIVITY, device: str = "cpu",
                      tol: float = DEFAULT_TOL, warm_start: bool = True,
                      solid_thickness: float | None = None,
                      progress=None) -> SnapshotMicrostructure:
    """Resolution-converged porosity, tortuosity and D_eff of one snapshot.

    Partial-volume voxels (``supersample ** 3`` sub-voxel tests each; binary labels with
    ``cb_phase``) at ``start``, ``start * ratio``, ... voxels per ``reference_diameter``.
    Each level is solved by TauFactor, from the previous level's potential
    (``warm_start``), and the sequence stops at the first level whose tau differs from the
    previous one by less than ``refine_tol`` (relative): that level's values are the
    answer. It also stops, marked not converged with the reason, when the next level would
    exceed ``max_voxels`` or after ``max_levels``. Reported in ``refinement``: every level
    (voxel size, voxels per diameter, shape, porosity, tau, D_eff, iterations, seconds),
    the last relative change and two cross-checks: the first-order extrapolation of the
    last two levels (``extrapolated``, as :func:`analyse_snapshot`) and, from three
    levels, the observed order and the Richardson extrapolation of tau.

    ``progress``: optional callable(str) told about each level.
    """
    if not (0 < refine_tol < 1):
        raise ConfigError("refine_tol", refine_tol, "in (0, 1)")
    if not (np.isfinite(max_voxels) and max_voxels >= 1):
        raise ConfigError("max_voxels", max_voxels, ">= 1")
    if not (np.isfinite(start) and start > 0):
        raise ConfigError("start", start, "> 0 voxels per diameter")
    if cb_phase:
        supersample = 1
    hs = refinement_levels(cell_x, reference_diameter, start, ratio, max_levels)
    levels: list[ResolutionResult] = []
    rows, taus = [], []
    converged, reason, change = False, None, None
    state = None  # the previous level's potential and conducting mask
    for k, h in enumerate(hs):
        grid = voxel_grid(cell_x, cell_y, snapshot.z_bottom, snapshot.z_top, h)
        n_vox = int(np.prod(grid["shape"]))
        if n_vox > max_voxels:
            reason = (f"the next level ({reference_diameter / h:.2f} voxels per diameter, "
                      f"{h * 1e6:.3f} um, {n_vox:,} voxels) "
                      f"exceeds max_voxels = {max_voxels:,.0f}")
            break
        if progress is not None:
            progress(f"level {k}: {reference_diameter / h:.2f} vox/d, {n_vox:,} voxels")
        res, state = _resolution(snapshot, cell_x, cell_y, h, reference_diameter,
                                 supersample, cb_phase, cb_diffusivity, device, tol,
                                 previous=state, keep_field=warm_start)
        tr = res.transport
        levels.append(res)
        taus.append(tr.tortuosity)
        rows.append({"voxel_size_m": h, "voxels_per_diameter": reference_diameter / h,
                     "shape_zyx": list(grid["shape"]), "voxels": n_vox,
                     "voxel_porosity": res.voxel_porosity, "tortuosity": tr.tortuosity,
                     "D_eff": tr.D_eff, "iterations": tr.iterations,
                     "solver_converged": tr.converged, "warm_start": tr.warm_start,
                     "solve_seconds": tr.seconds, "voxelise_seconds": res.voxelise_seconds})
        if len(taus) >= 2 and taus[-1] is not None and taus[-2] is not None:
            change = abs(taus[-1] - taus[-2]) / taus[-1]
            rows[-1]["tortuosity_rel_change"] = change
            if change < refine_tol:
                converged = True
                break
    if not levels:
        raise ConfigError("max_voxels", max_voxels, f"at least the first level's voxels: {reason}")
    if not converged and reason is None:
        if taus[-1] is None:
            reason = "the pore phase does not percolate at the finest level"
        else:
            last = "-" if change is None else f"{change:.3g}"
            reason = f"max_levels = {max_levels} reached (last relative change {last})"
    refinement = {"method": f"partial-volume voxels ({supersample}^3 sub-voxels), levels x"
                            f"{ratio:g} from {start:g} voxels per diameter, stop when tau "
                            f"changes by < {refine_tol:g}",
                  "converged": converged, "reason": None if converged else reason,
                  "refine_tol": refine_tol, "tortuosity_rel_change": change,
                  "levels": rows, "warm_start": bool(warm_start),
                  "seconds": float(sum(r["solve_seconds"] + r["voxelise_seconds"]
                                       for r in rows)),
                  **_richardson(taus, [r["voxel_size_m"] for r in rows])}
    primary = levels[-1]
    por = _porosities(snapshot, cell_x, cell_y, solid_thickness, primary.voxel_porosity)
    return _snapshot_result(snapshot, cell_x, cell_y, primary,
                            levels[-2] if len(levels) > 1 else None, refinement=refinement,
                            porosities=por)


def analyse_snapshot(snapshot, cell_x: float, cell_y: float, *,
                     voxels_per_diameter: float = DEFAULT_VOXELS_PER_DIAMETER,
                     reference_diameter: float = 2.0e-6, supersample: int = 1,
                     cb_phase: bool = False, cb_diffusivity: float = DEFAULT_CB_DIFFUSIVITY,
                     device: str = "cpu", tol: float = DEFAULT_TOL,
                     second_resolution: bool = True,
                     second_factor: float = SECOND_RESOLUTION_FACTOR
                     ) -> SnapshotMicrostructure:
    """Porosity, tortuosity and D_eff of one snapshot (``calendaring.process.runfile.Snapshot``).

    Args:
        snapshot: a snapshot from :func:`calendaring.process.runfile.read_run`.
        cell_x, cell_y: periodic cell [m] (``RunRecord.cell_x``, ``cell_y``).
        voxels_per_diameter: voxels across ``reference_diameter`` (the lateral voxel count
            is rounded to an even number).
        reference_diameter: the smallest particle diameter of the run [m]
            (:func:`reference_diameter` of its config); fixes the voxel size.
        supersample: partial-volume voxels from supersample^3 sub-voxels (1 = binary).
        cb_phase: carbon black conducts as its own phase with ``cb_diffusivity`` (relative).
        device: torch device for TauFactor ("cpu" or "cuda").
        tol: TauFactor convergence tolerance.
        second_resolution: also solve at ``second_factor`` x the voxels per diameter (a
            coarser grid) and extrapolate both to zero voxel size.
        second_factor: ratio of the second to the first resolution, in (0, 1) or (1, 4].
    """
    if cb_phase and supersample != 1:
        raise ConfigError("supersample", supersample, "1 with cb_phase=True")
    if not (0 < second_factor <= 4 and second_factor != 1):
        raise ConfigError("second_factor", second_factor, "in (0, 1) or (1, 4]")
    h1 = voxel_size_for(cell_x, reference_diameter, voxels_per_diameter)
    args = (reference_diameter, supersample, cb_phase, cb_diffusivity, device, tol)
    primary, _ = _resolution(snapshot, cell_x, cell_y, h1, *args)
    second = None
    if second_resolution:
        h2 = voxel_size_for(cell_x, reference_diameter, voxels_per_diameter * second_factor)
        if h2 == h1:  # too coarse to differ: one lateral voxel pair coarser
            h2 = cell_x / max(2, round(cell_x / h1) - 2)
        second, _ = _resolution(snapshot, cell_x, cell_y, h2, *args)
    return _snapshot_result(snapshot, cell_x, cell_y, primary, second)


@dataclass
class MicrostructureResult:
    """Microstructure of the snapshots of one run, with the settings that produced it."""

    run_file: str
    label: str
    breakage_model: str
    cell_x: float  # [m]
    cell_y: float  # [m]
    settings: dict[str, Any]
    snapshots: list[SnapshotMicrostructure] = field(default_factory=list)
    wall_seconds: float = 0.0

    def series(self, key: str, extrapolated: bool = False) -> np.ndarray:
        """One value per snapshot as a float array (NaN where missing): ``depth_m``,
        ``particle_porosity``, ``voxel_porosity``, ``tortuosity``, ``D_eff``; with
        ``extrapolated`` the zero-voxel-size value."""
        vals = []
        for s in self.snapshots:
            j = s.to_json()
            if extrapolated and key in ("voxel_porosity", "tortuosity", "D_eff"):
                v = (j["extrapolated"] or {}).get(key)
            else:
                v = j[key]
            vals.append(np.nan if v is None else float(v))
        return np.asarray(vals)

    def to_json(self) -> dict[str, Any]:
        return {"run_file": self.run_file, "label": self.label,
                "breakage_model": self.breakage_model, "cell_x_m": self.cell_x,
                "cell_y_m": self.cell_y, "settings": dict(self.settings),
                "wall_seconds": self.wall_seconds,
                "units": {"depth_m": "m", "voxel_size_m": "m", "porosity": "1",
                          "tortuosity": "1", "D_eff": "1 (relative to bulk diffusivity)"},
                "snapshots": [s.to_json() for s in self.snapshots]}

    def write_json(self, path: str | Path) -> Path:
        """Write :meth:`to_json` atomically (temporary name, then rename)."""
        from calendaring import write_json

        return write_json(path, self.to_json(), indent=2)


def _select(record, snapshots) -> list:
    if snapshots is None:
        return list(record.snapshots)
    chosen = []
    for s in snapshots:
        if isinstance(s, (int, np.integer)) and not isinstance(s, bool):
            if not 0 <= s < len(record.snapshots):
                raise ConfigError("snapshots", s,
                                  f"snapshot indices in [0, {len(record.snapshots) - 1}]")
            chosen.append(record.snapshots[int(s)])
        elif isinstance(s, float):
            chosen.append(record.snapshot_near(s))
        else:
            raise ConfigError("snapshots", s, "snapshot indices (int) or depths [m] (float)")
    return chosen


RESOLUTIONS = ("converge", "two-point")


def analyse_run(run_file, snapshots=None, voxels_per_diameter: float | None = None,
                supersample: int | None = None, cb_phase: bool = False,
                device: str = "cpu", tol: float = DEFAULT_TOL, second_resolution: bool = True,
                progress: bool = True, cb_diffusivity: float = DEFAULT_CB_DIFFUSIVITY,
                label: str | None = None, resolution: str = "converge",
                refine_tol: float = REFINE_TOL, max_voxels: float = REFINE_MAX_VOXELS,
                max_levels: int = REFINE_MAX_LEVELS) -> MicrostructureResult:
    """Microstructure of a run's snapshots (Fig. 13 b-d), read through ``read_run``.

    Args:
        run_file: path of a run file.
        snapshots: None (all), or snapshot indices (int) and/or depths [m] (float, nearest).
        voxels_per_diameter: voxels across the run's smallest possible diameter
            (:func:`reference_diameter`): the first level of the refinement (default
            ``REFINE_START``), or the resolution of ``"two-point"`` (default
            ``DEFAULT_VOXELS_PER_DIAMETER``); the same for every snapshot.
        supersample: sub-voxels per axis (default ``REFINE_SUPERSAMPLE`` for
            ``"converge"``, 1 for ``"two-point"``).
        resolution: ``"converge"`` (:func:`converge_snapshot`: refine until tau changes by
            less than ``refine_tol``, within ``max_voxels`` and ``max_levels``) or
            ``"two-point"`` (:func:`analyse_snapshot`: one resolution and, with
            ``second_resolution``, a coarser one and the extrapolation).
        cb_phase, device, tol, second_resolution, cb_diffusivity: as in
            :func:`analyse_snapshot`.
        progress: a tqdm bar on stderr (one step per snapshot).
        label: name of the run in plots and tables (default: the file's stem).
    """
    from tqdm import tqdm

    from analysis.porosity import recipe_solid_thickness
    from calendaring import read_run

    if resolution not in RESOLUTIONS:
        raise ConfigError("resolution", resolution, f"one of {RESOLUTIONS}")
    converge = resolution == "converge"
    if voxels_per_diameter is None:
        voxels_per_diameter = REFINE_START if converge else DEFAULT_VOXELS_PER_DIAMETER
    if supersample is None:
        supersample = 1 if (cb_phase or not converge) else REFINE_SUPERSAMPLE
    t0 = time.perf_counter()
    record = read_run(run_file)
    chosen = _select(record, snapshots)
    d_ref = reference_diameter(record.config)
    solid = recipe_solid_thickness(record.config)
    import taufactor

    settings = {"resolution": resolution,
                "voxels_per_diameter": float(voxels_per_diameter),
                "reference_diameter_m": d_ref,
                "voxel_size_m": voxel_size_for(record.cell_x, d_ref, voxels_per_diameter),
                "second_resolution": bool(second_resolution),
                "second_resolution_factor": SECOND_RESOLUTION_FACTOR,
                "supersample": int(supersample), "cb_phase": bool(cb_phase),
                "cb_diffusivity": float(cb_diffusivity) if cb_phase else None,
                "device": str(device), "tol": float(tol),
                "taufactor_version": getattr(taufactor, "__version__", "1.2.1"),
                "transport_axis": "z (thickness), lateral faces periodic",
                "recipe_solid_thickness_m": solid}
    if converge:
        settings.update({"refine_ratio": REFINE_RATIO, "refine_tol": float(refine_tol),
                         "max_voxels": float(max_voxels), "max_levels": int(max_levels)})
    result = MicrostructureResult(run_file=str(run_file),
                                  label=label or Path(run_file).stem,
                                  breakage_model=record.breakage_model,
                                  cell_x=record.cell_x, cell_y=record.cell_y,
                                  settings=settings)
    bar = tqdm(chosen, desc=f"microstructure {result.label}", unit="snapshot",
               disable=not progress, file=sys.stderr)
    for snap in bar:
        bar.set_postfix_str(f"depth {snap.depth * 1e6:.1f} um")
        if converge:
            def say(msg, depth=snap.depth):
                bar.set_postfix_str(f"depth {depth * 1e6:.1f} um, {msg}")

            result.snapshots.append(converge_snapshot(
                snap, record.cell_x, record.cell_y, reference_diameter=d_ref,
                start=voxels_per_diameter, refine_tol=refine_tol, max_levels=max_levels,
                max_voxels=max_voxels, supersample=supersample, cb_phase=cb_phase,
                cb_diffusivity=cb_diffusivity, device=device, tol=tol,
                solid_thickness=solid, progress=say))
            continue
        one = analyse_snapshot(
            snap, record.cell_x, record.cell_y, voxels_per_diameter=voxels_per_diameter,
            reference_diameter=d_ref, supersample=supersample, cb_phase=cb_phase,
            cb_diffusivity=cb_diffusivity, device=device, tol=tol,
            second_resolution=second_resolution)
        one.porosities = _porosities(snap, record.cell_x, record.cell_y, solid,
                                     one.primary.voxel_porosity)
        result.snapshots.append(one)
    bar.close()
    result.wall_seconds = time.perf_counter() - t0
    return result


# ---------------------------------------------------------------------------- tables, plots
def microstructure_table(results: dict[str, MicrostructureResult],
                         depths=(0.0, 19.5e-6)) -> list[dict[str, Any]]:
    """Rows (run label x requested depth) with the snapshot nearest each depth [m]:
    porosity (particle, voxel), tortuosity and D_eff at the primary resolution, at the
    second one and extrapolated (the paper's R0/R1/R4/R5 comparison at 0 and 19.5 um)."""
    rows = []
    for name, res in results.items():
        if not res.snapshots:
            continue
        for d in depths:
            s = min(res.snapshots, key=lambda x: abs(x.depth - d))
            j = s.to_json()
            sec = j["second_resolution"] or {}
            ext = j["extrapolated"] or {}
            rows.append({"run": name, "requested_depth_m": float(d), "depth_m": j["depth_m"],
                         "particle_porosity": j["particle_porosity"],
                         "voxel_porosity": j["voxel_porosity"],
                         "tortuosity": j["tortuosity"], "D_eff": j["D_eff"],
                         "tortuosity_reason": j["tortuosity_reason"],
                         "voxel_size_m": j["voxel_size_m"],
                         "voxels_per_diameter": j["voxels_per_diameter"],
                         "tortuosity_second": sec.get("tortuosity"),
                         "D_eff_second": sec.get("D_eff"),
                         "voxel_size_second_m": sec.get("voxel_size_m"),
                         "tortuosity_extrapolated": ext.get("tortuosity"),
                         "D_eff_extrapolated": ext.get("D_eff"),
                         "refinement": _refinement_row(j["refinement"]),
                         "porosities": j["porosities"]})
    return rows


def _refinement_row(ref: dict[str, Any] | None) -> dict[str, Any] | None:
    if ref is None:
        return None
    return {"levels": len(ref["levels"]), "converged": ref["converged"],
            "reason": ref["reason"], "tortuosity_rel_change": ref["tortuosity_rel_change"],
            "voxels_per_diameter": [r["voxels_per_diameter"] for r in ref["levels"]],
            "tortuosity_levels": [r["tortuosity"] for r in ref["levels"]],
            "tortuosity_richardson": ref["tortuosity_richardson"],
            "observed_order": ref["observed_order"], "seconds": ref["seconds"]}


def format_table(rows: list[dict[str, Any]]) -> str:
    """Markdown table of :func:`microstructure_table` rows (um and % for display)."""

    def f(v, fmt):
        return "n/p" if v is None else format(v, fmt)

    def g(v):
        return "-" if v is None else format(v, ".4f")

    def pct(v):
        return "-" if v is None else f"{100 * v:.2f}"

    lines = ["| run | depth [um] | porosity sphere sum / voxel / mass balance [%] | tau | D_eff "
             "| tau / D_eff (previous level) | tau / D_eff (extrap.) | voxel [um] "
             "| refinement: tau per level (vox/d) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        por = r.get("porosities") or {}
        ref = r.get("refinement")
        if ref is None:
            seq = "two-point"
        else:
            seq = ", ".join(f"{f(t, '.3f')} ({v:.2g})" for t, v in
                            zip(ref["tortuosity_levels"], ref["voxels_per_diameter"],
                                strict=True))
            change = ref["tortuosity_rel_change"]
            seq += (f"; last change {100 * change:.1f} %" if change is not None else "")
            seq += "" if ref["converged"] else " (not converged)"
        lines.append(
            f"| {r['run']} | {r['depth_m'] * 1e6:.1f} | {100 * r['particle_porosity']:.2f} / "
            f"{100 * r['voxel_porosity']:.2f} / {pct(por.get('mass_balance'))} | "
            f"{f(r['tortuosity'], '.4f')} | "
            f"{f(r['D_eff'], '.4f')} | {g(r['tortuosity_second'])} / "
            f"{g(r['D_eff_second'])} | {g(r['tortuosity_extrapolated'])} / "
            f"{g(r['D_eff_extrapolated'])} | {r['voxel_size_m'] * 1e6:.3f} | {seq} |")
    lines.append("n/p: the pore phase does not percolate through the thickness; -: not "
                 "computed (no second resolution) or not percolating there. Sphere sum: "
                 "overlaps counted twice; voxel: the union of the spheres between the "
                 "plates; mass balance: the recipe's solids over the gap.")
    return "\n".join(lines)


def _save_figure(fig, path: Path) -> Path:
    from calendaring import save_figure

    return save_figure(fig, path, dpi=150, bbox_inches="tight")


def plot_microstructure(results: dict[str, MicrostructureResult], out_dir) -> list[Path]:
    """Porosity, tortuosity and D_eff against calendering depth for several runs (Fig. 13
    b-d): ``microstructure_porosity.png``, ``microstructure_tortuosity.png``,
    ``microstructure_deff.png``. Solid lines: primary resolution; dotted: extrapolated to zero
    voxel size; dashed (porosity): particle porosity."""
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    paths = []
    panels = (("porosity", "Porosity [%]", "voxel_porosity", 100.0),
              ("tortuosity", "Tortuosity factor [-]", "tortuosity", 1.0),
              ("deff", "Relative effective diffusivity [-]", "D_eff", 1.0))
    for name, ylabel, key, scale in panels:
        fig, ax = plt.subplots(figsize=(4.5, 3.5))
        for k, (lab, res) in enumerate(results.items()):
            color = f"C{k % 10}"
            depth = res.series("depth_m") * 1e6
            vox = res.settings.get("voxels_per_diameter", float("nan"))
            ax.plot(depth, res.series(key) * scale, "o-", color=color,
                    label=f"{lab} ({vox:g} vox/d)")
            ext = res.series(key, extrapolated=True) * scale
            if np.isfinite(ext).any():
                ax.plot(depth, ext, ":", color=color, label=f"{lab} extrapolated")
            if key == "voxel_porosity":
                ax.plot(depth, res.series("particle_porosity") * scale, "--", color=color,
                        alpha=0.6, label=f"{lab} particles")
        ax.set_xlabel("Calendering depth [um]")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        paths.append(_save_figure(fig, out_dir / f"microstructure_{name}.png"))
        plt.close(fig)
    return paths
