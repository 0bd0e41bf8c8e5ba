"""Figures of a run file (matplotlib, Agg backend; micrometres and MPa on the axes only).

See also: :mod:`calendaring.process.runfile` (the run record plotted),
:mod:`calendaring.core.units`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from calendaring.core.fileio import save_figure
from calendaring.core.units import to_mpa, to_um
from calendaring.process.runfile import RunRecord


def _pyplot():
    import matplotlib.pyplot as plt

    return plt


NOTEBOOK_OUT_ENV = "CALENDARING_NOTEBOOK_OUT"


def notebook_output(name: str) -> Path:
    """The output folder of notebook ``name``, created: ``$CALENDARING_NOTEBOOK_OUT/name``,
    by default ``notebooks/_out/name`` in the checkout."""
    default = Path(__file__).resolve().parents[2] / "notebooks" / "_out"
    out = Path(os.environ.get(NOTEBOOK_OUT_ENV, default)) / name
    out.mkdir(parents=True, exist_ok=True)
    return out


def show_figure(fig, path: str | Path, dpi: float = 120) -> Path:
    """Save ``fig`` as ``path`` (under a temporary name, then renamed), close it and display
    the image in the running notebook (IPython)."""
    from IPython.display import Image, display

    path = save_figure(fig, path, dpi=dpi)
    display(Image(filename=str(path)))
    return path


def plot_pressure(rec: RunRecord, path: str | Path) -> Path:
    """Top- and bottom-plate pressure against calendering depth (and unloading, if any)."""
    plt = _pyplot()
    p = rec.pressure
    fig, ax = plt.subplots(figsize=(5.5, 4.0), dpi=130)
    ax.plot(to_um(p["depth"]), to_mpa(p["value"]), lw=0.8, label="top plate (per step)")
    s = rec.series
    ax.plot(to_um(s["depth"]), to_mpa(s["bottom_pressure"]), "--", lw=1.0,
            label="bottom plate (row mean)")
    u = rec.unloading
    if len(u["depth"]):
        ax.plot(to_um(u["depth"]), to_mpa(u["value"]), lw=0.8, label="unloading")
    for snap in rec.snapshots:
        ax.axvline(to_um(snap.depth), color="0.85", lw=0.6, zorder=0)
    ax.set_xlabel("calendering depth [um]")
    ax.set_ylabel("pressure [MPa]")
    ax.set_title(f"{rec.path.name}: {rec.preset or 'config'} ({rec.breakage_model} breakage)",
                 fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out = save_figure(fig, path, dpi="figure")  # the figure's own dpi
    return out


def plot_microstructure(rec: RunRecord, path: str | Path) -> Path:
    """Porosity, coordination number and bond counts against calendering depth."""
    plt = _pyplot()
    s = rec.series
    depth = to_um(s["depth"])
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.5), dpi=130)
    axes[0].plot(depth, 100 * s["porosity"])
    axes[0].set_ylabel("porosity [%]")
    axes[1].plot(depth, s["coordination"])
    axes[1].set_ylabel("coordination number [-]")
    axes[2].plot(depth, s["bonds_intact"], label="intact")
    axes[2].plot(depth, s["bonds_failed_normal"] + s["bonds_failed_shear"], label="failed")
    if np.any(s["bonds_removed"]):
        axes[2].plot(depth, s["bonds_removed"], label="removed with particle")
    axes[2].set_ylabel("bonds")
    axes[2].legend(fontsize=8)
    for ax in axes:
        ax.set_xlabel("calendering depth [um]")
    fig.tight_layout()
    out = save_figure(fig, path, dpi="figure")  # the figure's own dpi
    return out


def breakage_histogram(rec: RunRecord, bins: int = 30) -> tuple[np.ndarray, np.ndarray,
                                                                   np.ndarray]:
    """Counts of breakage events binned by parent diameter [m] and peak load [N] (paper
    Fig. 9 layout): (counts (diameter bin, load bin), diameter edges, load edges)."""
    b = rec.breakage
    d, f = b["diameter"], b["peak_load"]
    d_lo, d_hi = (d.min(), d.max()) if len(d) else (0.0, 1.0)
    f_lo, f_hi = (f.min(), f.max()) if len(f) else (0.0, 1.0)
    d_edges = np.linspace(d_lo, d_hi if d_hi > d_lo else d_lo + 1e-9, bins + 1)
    f_edges = np.linspace(f_lo, f_hi if f_hi > f_lo else f_lo + 1e-9, bins + 1)
    counts, _, _ = np.histogram2d(d, f, bins=(d_edges, f_edges))
    return counts, d_edges, f_edges


def plot_breakage(rec: RunRecord, path: str | Path) -> Path:
    """Breakage statistics: the 30 x 30 histogram of peak load against parent diameter,
    events against depth, and the fragment size distribution."""
    plt = _pyplot()
    b = rec.breakage
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8), dpi=130)
    counts, d_edges, f_edges = breakage_histogram(rec)
    im = axes[0].pcolormesh(to_um(d_edges), 1e3 * f_edges, counts.T, cmap="viridis")
    fig.colorbar(im, ax=axes[0], label="events")
    axes[0].set_xlabel("parent diameter [um]")
    axes[0].set_ylabel("peak load before breakage [mN]")
    axes[0].set_title(f"{len(b['parent_id'])} breakage events (30 x 30 bins)", fontsize=9)
    axes[1].plot(to_um(rec.series["depth"]), rec.series["breakage_events"])
    axes[1].set_xlabel("calendering depth [um]")
    axes[1].set_ylabel("breakage events so far")
    frag = to_um(b["fragments"]["diameter"])
    if len(frag):
        axes[2].hist(frag, bins=30, color="tab:orange", label="fragments")
    axes[2].hist(to_um(b["diameter"]), bins=30, histtype="step", color="k", label="parents")
    axes[2].set_xlabel("diameter [um]")
    axes[2].set_ylabel("count")
    axes[2].legend(fontsize=8)
    fig.tight_layout()
    out = save_figure(fig, path, dpi="figure")  # the figure's own dpi
    return out
