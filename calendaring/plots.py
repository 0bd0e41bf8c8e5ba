"""Figures of a run file (matplotlib, Agg backend; micrometres and MPa on the axes only)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from calendaring.runfile import RunRecord
from calendaring.units import to_mpa, to_um


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        fig.savefig(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
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
    out = _save(fig, Path(path))
    plt.close(fig)
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
    out = _save(fig, Path(path))
    plt.close(fig)
    return out
