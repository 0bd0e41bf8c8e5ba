"""Electrode builder, host side: particle sizes and counts from the coating's mass balance,
and random non-overlapping insertion (paper section 2.1; spec section 1.1).

The coating of thickness ``h0`` and bulk density ``rho_c`` over the periodic cell holds the
mass ``M = rho_c A h0``; material ``k`` gets ``w_k M`` (``electrode.composition``). Diameters
are drawn from each material's distribution and the count is the one whose cumulative mass is
closest to the target, so the porosity at ``h0`` is ``1 - sum(V_i) / (A h0)`` up to half a
particle. With the paper's inputs (2.56 g/cm3, 94/6 wt%, 4740/2200 kg/m3) the mass balance
gives 42.3 % (the paper quotes 41.42 % from the experiment).

The time-stepping stages (settling, pre-compaction, relaxation) are in
:mod:`calendaring.process.run`.

See also: :mod:`calendaring.process.preflight` (particle counts from the same recipe),
:mod:`calendaring.process.packing` (settled beds on disk).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calendaring.core.config import SimConfig, SizeConfig
from calendaring.core.errors import ConfigError


def _truncated(draw, lo: float, hi: float, n: int) -> np.ndarray:
    out = np.zeros(0)
    while out.size < n:
        d = draw(max(16, 2 * (n - out.size)))
        out = np.concatenate([out, d[(d >= lo) & (d <= hi)]])
    return out[:n]


def read_size_table(path: str | Path, basis: str = "number") -> tuple[np.ndarray, np.ndarray]:
    """Read a measured size table (CSV ``diameter_m,fraction``); returns diameters [m] and
    number probabilities (volume fractions are converted by ``f / d^3``)."""
    path = Path(path)
    try:
        with path.open(newline="") as fh:
            rows = [r for r in csv.reader(fh) if r and not r[0].lstrip().startswith("#")]
    except OSError as err:
        raise ConfigError("electrode.sizes.*.table", str(path), f"a readable CSV ({err})") from None
    if rows and rows[0][0].strip().lower().startswith("diameter"):
        rows = rows[1:]
    try:
        data = np.array([[float(a), float(b)] for a, b in rows])
    except ValueError:
        raise ConfigError("electrode.sizes.*.table", str(path),
                          "rows of two numbers: diameter_m,fraction") from None
    if data.size == 0 or np.any(data[:, 0] <= 0) or np.any(data[:, 1] < 0) or data[:, 1].sum() <= 0:
        raise ConfigError("electrode.sizes.*.table", str(path),
                          "diameters > 0 m and fractions >= 0 with a positive sum")
    d, f = data[:, 0], data[:, 1]
    if basis == "volume":
        f = f / d**3
    return d, f / f.sum()


def sample_diameters(size: SizeConfig, rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` diameters [m] from ``size`` (normal and lognormal truncated by resampling)."""
    lo, hi = size.bounds
    if size.distribution == "constant":
        return np.full(n, size.mean)
    if size.distribution == "normal":
        return _truncated(lambda k: rng.normal(size.mean, size.std, k), lo, hi, n)
    if size.distribution == "lognormal":
        s2 = math.log1p((size.std / size.mean) ** 2)
        mu = math.log(size.mean) - 0.5 * s2
        return _truncated(lambda k: rng.lognormal(mu, math.sqrt(s2), k), lo, hi, n)
    d, p = read_size_table(size.table, size.table_basis)
    return rng.choice(d, size=n, p=p)


def diameter_bounds(size: SizeConfig) -> tuple[float, float]:
    """Smallest and largest diameter the distribution can produce [m]."""
    if size.distribution == "table":
        d, _ = read_size_table(size.table, size.table_basis)
        return float(d.min()), float(d.max())
    return size.bounds


@dataclass(frozen=True)
class Recipe:
    """Particles of the electrode before insertion, and the mass balance behind them."""

    diameter: np.ndarray  # [m]
    material: np.ndarray  # material index
    target_mass: dict[str, float]  # [kg] per material
    mass: dict[str, float]  # [kg] per material, as sampled
    counts: dict[str, int]
    porosity: float  # 1 - sum(V) / (A h0) at the coating thickness [-]

    def summary(self) -> dict:
        """JSON-friendly summary (SI)."""
        return {"counts": self.counts, "target_mass_kg": self.target_mass,
                "mass_kg": self.mass, "porosity_at_thickness": self.porosity}


def recipe(cfg: SimConfig, rng: np.random.Generator) -> Recipe:
    """Particle sizes and counts of the coating from its mass balance."""
    el, dom = cfg.electrode, cfg.domain
    area = dom.cell_x * dom.cell_y
    total = el.coating_density * area * el.thickness
    names = cfg.material_names
    diam, mat = [], []
    target, got, counts = {}, {}, {}
    for name, w in el.composition.items():
        if w <= 0:
            continue
        rho = cfg.materials[name].density
        m_target = w * total
        d_mean = el.sizes[name].mean
        guess = max(8, int(1.5 * m_target / (rho * math.pi / 6 * d_mean**3)) + 8)
        d = sample_diameters(el.sizes[name], rng, guess)
        m = rho * math.pi / 6 * d**3
        while m.sum() < m_target:
            d = np.concatenate([d, sample_diameters(el.sizes[name], rng, guess)])
            m = rho * math.pi / 6 * d**3
        cum = np.cumsum(m)
        k = int(np.searchsorted(cum, m_target))
        if k > 0 and abs(cum[k - 1] - m_target) <= abs(cum[k] - m_target):
            k -= 1
        d = d[: k + 1]
        if d.size == 0:
            raise ConfigError(f"electrode.composition.{name}", w,
                              "a mass fraction large enough for one particle in this cell")
        diam.append(d)
        mat.append(np.full(d.size, names.index(name), np.int32))
        target[name] = m_target
        got[name] = float(cum[k])
        counts[name] = int(d.size)
    diameter = np.concatenate(diam)
    volume = float(np.sum(math.pi / 6 * diameter**3))
    return Recipe(diameter=diameter, material=np.concatenate(mat), target_mass=target,
                  mass=got, counts=counts, porosity=1.0 - volume / (area * el.thickness))


def _overlaps(cells, pos, diam, p, r, c, nx, ny, lx, ly) -> bool:
    """True if a sphere (centre p, radius r, cell c) overlaps one already in ``cells``."""
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                for j in cells.get(((c[0] + dx) % nx, (c[1] + dy) % ny, c[2] + dz), ()):
                    v = pos[j] - p
                    v[0] -= lx * round(v[0] / lx)
                    v[1] -= ly * round(v[1] / ly)
                    if v @ v < (r + 0.5 * diam[j]) ** 2:
                        return True
    return False


def random_insertion(diam: np.ndarray, mat: np.ndarray, cell_x: float, cell_y: float,
                     z_max: float, rng: np.random.Generator, max_tries: int = 500
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random sequential insertion of non-overlapping spheres in [0, L]^2 x [0, z_max].

    Largest spheres first, periodic in x and y, checked against a hashed cell grid.
    Returns (positions [m], radii [m], material indices), largest first.
    """
    order = np.argsort(-diam, kind="stable")
    diam, mat = diam[order], mat[order]
    h = float(diam.max())
    nx, ny = max(1, int(cell_x // h)), max(1, int(cell_y // h))
    cells: dict[tuple[int, int, int], list[int]] = {}
    pos = np.zeros((len(diam), 3))
    for k, d in enumerate(diam):
        r = 0.5 * d
        for _ in range(max_tries):
            p = np.array([rng.uniform(0, cell_x), rng.uniform(0, cell_y),
                          rng.uniform(r, z_max - r)])
            c = (int(p[0] / cell_x * nx) % nx, int(p[1] / cell_y * ny) % ny, int(p[2] // h))
            if not _overlaps(cells, pos, diam, p, r, c, nx, ny, cell_x, cell_y):
                pos[k] = p
                cells.setdefault(c, []).append(k)
                break
        else:
            raise ConfigError(
                "domain.height", z_max,
                f"a taller insertion domain: particle {k} of {len(diam)} found no free place "
                f"in {max_tries} tries (build.max_insert_tries)")
    return pos, 0.5 * diam, mat
