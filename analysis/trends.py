"""One-at-a-time parameter trends of the key outputs (paper section 3.3, Fig. 11).

Each parameter is swept over its whole range (``[0, 1]`` in unit coordinates, i.e. from its
lower to its upper bound on its own scale) while the others are held at one point: the
middle of the cube by default, or a calibration result. All sweeps are evaluated in one
batch through the same model interface as :mod:`analysis.sensitivity`::

    model(u (n, k) in [0, 1]) -> {output: (n,)}

    >>> tr = sweep(model, space.names, at=held_point(space, "RESULT.json"), n_points=41)
    >>> tr["outputs"]["d0"]["peak_pressure"]      # (41,) Pa along the d0 sweep

A calibration result is any JSON file with a top-level ``"parameters"`` mapping
``{name: physical value}`` (SI units, percent for A and R_t, as :mod:`calendaring.data.params`),
or a list of ``{"name", "value"}`` rows as ``inverse calibrate`` writes; missing names are
held at mid-range.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from analysis.outputs import DISPLAY, LABELS, OUTPUTS, UNITS
from calendaring import ConfigError

DEFAULT_POINTS = 41
COLOURS = {"peak_pressure": "tab:blue", "stress_centroid": "tab:orange",
           "diameter_centroid": "tab:green", "low_stress_ratio": "tab:red"}
"""The paper's Fig. 11 colours."""


def held_point(space, at=None) -> np.ndarray:
    """The unit-cube point ``(k,)`` at which the other parameters are held.

    Args:
        space: the :class:`calendaring.data.params.ParameterSpace` of the model.
        at: ``None`` (mid-range, 0.5 in every unit coordinate), a path to a JSON file with a
            top-level ``"parameters"`` mapping ``{name: physical value}`` (or a list of
            ``{"name", "value"}`` rows, as ``inverse calibrate`` writes), such a mapping
            itself, or a unit-coordinate array ``(k,)``.

    Raises:
        ConfigError: unreadable file, missing ``parameters`` key, unknown name or a value out
            of bounds (names the key, the value and the allowed range).
    """
    mid = np.full(len(space), 0.5)
    if at is None:
        return mid
    if isinstance(at, str | Path):
        path = Path(at)
        if not path.is_file():
            raise ConfigError("--at", str(path), "an existing JSON file with a top-level "
                              "\"parameters\" mapping {name: physical value}")
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise ConfigError("--at", str(path), f"a readable JSON file ({err})") from None
        params = data.get("parameters") if isinstance(data, dict) else None
        if isinstance(params, list) and all(isinstance(r, dict) and "name" in r
                                            and "value" in r for r in params):
            params = {r["name"]: r["value"] for r in params}  # `inverse calibrate` rows
        if not isinstance(params, dict):
            raise ConfigError(f"{path}: parameters", type(params).__name__,
                              "a top-level \"parameters\" mapping {name: physical value} "
                              "(or a list of {\"name\", \"value\"} rows)")
        at = params
    if isinstance(at, Mapping):
        values = {}
        for k, v in at.items():
            if isinstance(v, Mapping) and "value" in v:  # {"d0": {"value": ..., "unit": ...}}
                v = v["value"]
            values[k] = v
        row = space.from_dict(values, default=space.from_unit(mid))
        return np.clip(space.to_unit(row), 0.0, 1.0)
    u = np.asarray(at, dtype=float)
    if u.shape != (len(space),) or not np.all((u >= 0) & (u <= 1)):
        raise ConfigError("at", f"array of shape {u.shape}",
                          f"({len(space)},) unit coordinates in [0, 1]")
    return u


def sweep_design(at_unit, n_points: int = DEFAULT_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """All one-at-a-time rows: returns ``(grid (n_points,), u (k, n_points, k))`` where
    ``u[i, j]`` is the held point with coordinate ``i`` set to ``grid[j]``."""
    at = np.asarray(at_unit, dtype=float)
    if int(n_points) < 2:
        raise ConfigError("--points", n_points, "an integer >= 2")
    grid = np.linspace(0.0, 1.0, int(n_points))
    k = len(at)
    u = np.broadcast_to(at, (k, len(grid), k)).copy()
    for i in range(k):
        u[i, :, i] = grid
    return grid, u


def sweep(model, names: Sequence[str], at=None, n_points: int = DEFAULT_POINTS,
          space=None) -> dict:
    """One-at-a-time trends of every output of ``model``.

    Args:
        model: ``model(u (n, k)) -> {output: (n,)}`` over the unit cube.
        names: the k parameter names (column order of ``u``).
        at: held point (unit coordinates ``(k,)``; or anything :func:`held_point` accepts
            when ``space`` is given). Default: mid-range.
        n_points: points per sweep, evenly spaced on ``[0, 1]``.

    Returns:
        ``{"grid": (n_points,), "at_unit": (k,), "names": [...], "outputs":
        {name: {output: (n_points,)}}, "at_outputs": {output: value at the held point}}``.
    """
    k = len(names)
    if space is not None:
        at_u = held_point(space, at)
    elif at is None:
        at_u = np.full(k, 0.5)
    else:
        at_u = np.asarray(at, dtype=float)
    if at_u.shape != (k,):
        raise ConfigError("at", f"array of shape {at_u.shape}", f"({k},) unit coordinates")
    grid, u = sweep_design(at_u, n_points)
    rows = np.vstack([u.reshape(-1, k), at_u[None]])
    y = model(rows)
    n = len(grid)
    out = {names[i]: {o: np.asarray(v[i * n:(i + 1) * n], dtype=float) for o, v in y.items()}
           for i in range(k)}
    return {"grid": grid, "at_unit": at_u, "names": list(names), "outputs": out,
            "at_outputs": {o: float(v[-1]) for o, v in y.items()}}


def trends_to_json(tr: dict, space=None) -> dict:
    """JSON-ready copy of a :func:`sweep` result, with the physical sweep values and units
    when ``space`` is given."""
    out = {"grid_unit": tr["grid"].tolist(), "names": tr["names"],
           "at_unit": dict(zip(tr["names"], tr["at_unit"].tolist(), strict=True)),
           "at_outputs": tr["at_outputs"],
           "output_units": {o: UNITS.get(o, "") for o in tr["at_outputs"]},
           "outputs": {p: {o: v.tolist() for o, v in d.items()}
                       for p, d in tr["outputs"].items()}}
    if space is not None:
        out["at_physical"] = space.as_dict(space.from_unit(tr["at_unit"]))
        out["parameter_units"] = dict(zip(space.names, space.units, strict=True))
        phys = {}
        for i, p in enumerate(tr["names"]):
            u = np.broadcast_to(tr["at_unit"], (len(tr["grid"]), len(space))).copy()
            u[:, i] = tr["grid"]
            phys[p] = space.from_unit(u)[:, i].tolist()
        out["grid_physical"] = phys
    return out


def plot_trends(tr: dict, path: str | Path, symbols: Sequence[str] | None = None) -> Path:
    """Fig. 11: one panel per parameter, each output min-max scaled over all sweeps (so the
    panels share one scale: a steeper curve is a stronger effect). PNG, atomic."""
    import matplotlib.pyplot as plt

    from analysis.plots import save_figure

    names = tr["names"]
    labels = list(symbols) if symbols else names
    outs = [o for o in OUTPUTS if o in tr["at_outputs"]] + \
        [o for o in tr["at_outputs"] if o not in OUTPUTS]
    lo = {o: np.nanmin([np.nanmin(tr["outputs"][p][o]) for p in names]) for o in outs}
    hi = {o: np.nanmax([np.nanmax(tr["outputs"][p][o]) for p in names]) for o in outs}
    # the stress centroid lives on a log load axis: scale its logarithm
    logs = {o for o in outs if o == "stress_centroid" and lo[o] > 0}

    def scaled(o, v):
        a, b, v = lo[o], hi[o], np.asarray(v, dtype=float)
        if o in logs:
            a, b, v = np.log(a), np.log(b), np.log(v)
        return (v - a) / (b - a) if b > a else np.zeros_like(v)

    ncol = 4 if len(names) > 4 else len(names)
    nrow = -(-len(names) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.2 * ncol, 2.8 * nrow), squeeze=False,
                             sharey=True)
    for i, (ax, p) in enumerate(zip(axes.flat, names, strict=False)):
        for o in outs:
            unit, f = DISPLAY.get(o, ("", 1.0))
            ax.plot(tr["grid"], scaled(o, tr["outputs"][p][o]), color=COLOURS.get(o), lw=1.6,
                    label=f"{LABELS.get(o, o)} [{lo[o] * f:.3g}, {hi[o] * f:.3g}] {unit}"
                          + (" (log scale)" if o in logs else ""))
        ax.axvline(tr["at_unit"][i], color="0.6", ls=":", lw=0.8)
        ax.set_title(f"({'abcdefghijklmnop'[i]}) {labels[i]}")
        ax.set_xlabel("normalised parameter value")
        ax.set_ylim(-0.05, 1.05)
    for ax in list(axes.flat)[len(names):]:
        ax.set_visible(False)
    axes[0, 0].set_ylabel("scaled output")
    handles, leg = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, leg, loc="lower center", ncol=2, fontsize=8, frameon=False)
    fig.suptitle("One-at-a-time trends (others held at the dotted line; outputs scaled to "
                 "their range over all sweeps)", fontsize=10)
    fig.tight_layout(rect=(0, 0.09, 1, 0.96))
    return save_figure(fig, path)


def trends_study(m, out_dir: str | Path, at=None, n_points: int = DEFAULT_POINTS,
                 progress: bool = True) -> dict:
    """Trends of a surrogate into ``out_dir`` (``analysis trends``): ``trends.json`` and
    ``trends.png``. ``at`` as in :func:`held_point`. Returns the JSON dict."""
    from analysis.plots import atomic_write_json
    from analysis.sensitivity import log, model_path, surrogate_model

    space = m.space
    at_u = held_point(space, at)
    if progress:
        log(f"trends: {len(space)} parameters x {n_points} points, held at "
            f"{'mid-range' if at is None else at}")
    tr = sweep(surrogate_model(m), space.names, at_u, n_points)
    out = trends_to_json(tr, space)
    out["model"] = model_path(m)
    out["held_point_source"] = str(at) if isinstance(at, str | Path) else (
        "mid-range" if at is None else "given")
    out_dir = Path(out_dir)
    fig = plot_trends(tr, out_dir / "trends.png", space.symbols)
    out["figures"] = [fig.name]
    atomic_write_json(out_dir / "trends.json", out)
    if progress:
        log(f"trends: wrote {out_dir / 'trends.json'} and {fig}")
    return out


__all__ = ["DEFAULT_POINTS", "held_point", "plot_trends", "sweep", "sweep_design",
           "trends_study", "trends_to_json"]
