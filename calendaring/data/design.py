"""Experimental designs over the breakage parameters: Latin hypercube, Sobol, fixed points.

Designs are drawn in the unit cube with :mod:`scipy.stats.qmc` (seeded) and mapped to
physical values by the :class:`~calendaring.data.params.ParameterSpace`. :func:`design_report`
gives the largest absolute pairwise Pearson correlation (the paper's design has |r| < 0.3)
and :func:`plot_correlation` the heatmap of paper Fig. 3.

See also: :mod:`calendaring.data.params` (the parameter space), :mod:`calendaring.data.sweep`
(which runs the designs).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from calendaring.core.errors import ConfigError
from calendaring.core.fileio import atomic_path, save_figure
from calendaring.data.params import PAPER_SPACE, ParameterSpace

DESIGNS = ("lhs", "sobol", "reference", "centre")


def unit_design(kind: str, n: int, d: int, seed: int = 0) -> np.ndarray:
    """``n`` points in ``[0, 1]^d``: ``lhs`` (scipy LatinHypercube, ``optimization =
    "random-cd"`` to lower the centred discrepancy), ``sobol`` (scrambled; ``n`` need not be
    a power of two, but balance is best when it is), ``centre`` (all 0.5)."""
    from scipy.stats import qmc

    if n < 1:
        raise ConfigError("--n", n, ">= 1")
    if kind == "lhs":
        return qmc.LatinHypercube(d=d, seed=seed, optimization="random-cd").random(n)
    if kind == "sobol":
        s = qmc.Sobol(d=d, scramble=True, seed=seed)
        m = int(np.ceil(np.log2(max(n, 1))))
        return s.random_base2(m)[:n]
    if kind == "centre":
        return np.full((n, d), 0.5)
    raise ConfigError("--design", kind, f"one of {DESIGNS} or a CSV file")


def make_design(kind: str, n: int = 1, seed: int = 0,
                space: ParameterSpace = PAPER_SPACE) -> np.ndarray:
    """Physical parameter rows ``(n, len(space))`` of a named design or a CSV file.

    ``reference`` is the paper's Table 4 point (``n`` copies). A CSV needs a header with the
    parameter names (SI units; percent for the two percentages); missing columns take the
    reference values; every value is checked against the bounds.
    """
    if kind == "reference":
        return np.repeat(space.reference[None, :], n, axis=0)
    if kind in DESIGNS:
        return space.from_unit(unit_design(kind, n, len(space), seed))
    path = Path(kind)
    if path.suffix.lower() != ".csv":
        raise ConfigError("--design", kind, f"one of {DESIGNS} or a path ending in .csv")
    return read_design_csv(path, space)


def read_design_csv(path: Path, space: ParameterSpace = PAPER_SPACE) -> np.ndarray:
    if not path.is_file():
        raise ConfigError("--design", str(path), "an existing CSV file")
    rows = list(csv.DictReader(io.StringIO(path.read_text())))
    if not rows:
        raise ConfigError("--design", str(path), "a CSV with a header and at least one row")
    unknown = [c for c in rows[0] if c not in space.names]
    if unknown:
        raise ConfigError(f"--design {path} column", unknown[0], f"one of {space.names}")
    return np.array([space.from_dict({k: float(v) for k, v in r.items()}, space.reference)
                     for r in rows])


def write_design_csv(path: Path, x: np.ndarray, space: ParameterSpace = PAPER_SPACE) -> Path:
    """Physical rows to CSV (header = parameter names), atomically."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(space.names)
        for row in x:
            w.writerow([repr(float(v)) for v in row])
    return path


def design_report(x: np.ndarray, space: ParameterSpace = PAPER_SPACE) -> dict:
    """Correlation and coverage of a design (physical rows): the Pearson matrix, the largest
    off-diagonal |r| and its pair, and per-parameter min/max in unit coordinates."""
    u = space.to_unit(np.asarray(x, float))
    out = {"n": len(u), "names": space.names}
    if len(u) >= 3:
        with np.errstate(invalid="ignore", divide="ignore"):  # a held (constant) column
            r = np.corrcoef(u, rowvar=False)
        off = np.abs(r - np.eye(len(r)))
    if len(u) >= 3 and np.isfinite(off).any():
        i, j = np.unravel_index(np.nanargmax(off), off.shape)
        out.update(pearson=r.tolist(), max_abs_r=float(off[i, j]),
                   max_pair=[space.names[i], space.names[j]])
    else:
        out.update(pearson=None, max_abs_r=None, max_pair=None)
    out["unit_min"] = u.min(axis=0).tolist()
    out["unit_max"] = u.max(axis=0).tolist()
    return out


def plot_correlation(report: dict, path: Path, space: ParameterSpace = PAPER_SPACE) -> Path:
    """Heatmap of the design's Pearson matrix (paper Fig. 3), atomically to ``path``."""
    import matplotlib.pyplot as plt

    r = np.asarray(report["pearson"])
    fig, ax = plt.subplots(figsize=(6.4, 5.4))
    im = ax.imshow(r, vmin=-1, vmax=1, cmap="RdBu_r")
    ax.set_xticks(range(len(r)), space.symbols, rotation=45, ha="right")
    ax.set_yticks(range(len(r)), space.symbols)
    for i in range(len(r)):
        for j in range(len(r)):
            ax.text(j, i, f"{r[i, j]:.2f}", ha="center", va="center", fontsize=7)
    ax.set_title(f"design correlation (n = {report['n']}, max |r| = {report['max_abs_r']:.3f})")
    fig.colorbar(im, ax=ax, label="Pearson r")
    fig.tight_layout()
    return save_figure(fig, path, dpi=120)


__all__ = ["DESIGNS", "design_report", "make_design", "plot_correlation", "read_design_csv",
           "unit_design", "write_design_csv"]
