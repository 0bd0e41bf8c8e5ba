"""Calibration results: the paper's Table 4 layout on the console, JSON on disk.

The result file (``format`` = "inverse-calibration", ``schema_version`` 1) is one JSON object,
written atomically. Physical values are SI (percent for A and R_t, as in
:data:`calendaring.data.params.PAPER_SPACE`), with the unit next to each value; unit-cube values
carry ``_unit`` in their key. Main keys: ``parameters`` (list in PAPER_SPACE order: name,
symbol, unit, value, value_unit, fixed, ci90 when a posterior was sampled), ``loss``, ``fit``
(errors of the surrogate at the optimum against the target, Pa), ``target`` (the resampled
target curve), ``prediction``, ``optimiser``, ``restarts``, ``clusters``,
``identifiability``, ``posterior``, ``timings_s``.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from calendaring import ConfigError
from calendaring import write_json as _write_json

FORMAT = "inverse-calibration"
SCHEMA_VERSION = 1

# Table 4 of the paper: row labels and printed precision
TABLE4 = {
    "damage_constant": ("Damage constant, γ", "{:.3f}"),
    "e_inf": ("E50 parameter, E∞", "{:.0f}"),
    "d0": ("E50 parameter, d0", "{:.3f}"),
    "phi": ("Fitting parameter, φ", "{:.3f}"),
    "sigma_e": ("Standard deviation, σE", "{:.3f}"),
    "alpha_percentage": ("Alpha percentage, A", "{:.3f}"),
    "b_prime": ("Fracture parameter, b'", "{:.3f}"),
    "truncation_ratio": ("Truncation ratio, R_t", "{:.3f}"),
}


def write_json(path: str | Path, obj: dict) -> Path:
    """Write ``obj`` as JSON atomically (temporary name in the same folder, then rename)."""
    path = Path(path)
    if path.suffix.lower() != ".json":
        raise ConfigError("--out", str(path), "a path ending in .json")
    return _write_json(path, obj)


def file_sha256(path: str | Path) -> str:
    """The first 16 hex digits of a file's SHA-256 (identifies a model or dataset file)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def read_result(path: str | Path) -> dict:
    """Read a result JSON; ConfigError if it is not one."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError("RESULT", str(path), "an existing calibration result JSON")
    try:
        with open(path) as f:
            obj = json.load(f)
    except (OSError, json.JSONDecodeError) as err:
        raise ConfigError("RESULT", str(path), f"a readable JSON file ({err})") from None
    if obj.get("format") != FORMAT:
        raise ConfigError("RESULT", str(path), f"a file with format = {FORMAT!r} (written by "
                          "`inverse calibrate`)")
    return obj


def parameter_rows(space, x_phys: np.ndarray, u: np.ndarray, fixed_names, posterior=None
                   ) -> list[dict]:
    """One dict per parameter (PAPER_SPACE order) for the result file."""
    rows = []
    for j, p in enumerate(space):
        row = {"name": p.name, "symbol": p.symbol, "unit": p.unit, "value": float(x_phys[j]),
               "value_unit": float(u[j]), "fixed": p.name in fixed_names,
               "display_unit": p.display_unit or p.unit,
               "display_value": float(x_phys[j] * p.display_factor),
               "display_factor": p.display_factor,
               "reference_table4": p.reference}
        if posterior is not None and p.name in posterior:
            s = posterior[p.name]
            row["ci90"] = s["ci90"]
            row["posterior_mean"] = s["mean"]
            row["std_ratio"] = s["std_ratio"]
        rows.append(row)
    return rows


def _unit_label(p: dict) -> str:
    u = p["display_unit"]
    return {"1": "-", "um": "μm"}.get(u, u)


def format_table4(result: dict) -> str:
    """The parameters in the layout of the paper's Table 4 (display units), with the
    posterior 90 % interval and posterior/prior width when present."""
    rows = result["parameters"]
    has_ci = any("ci90" in r for r in rows)
    head = f"{'Parameter':<26s}{'Unit':<7s}{'Value':>10s}"
    if has_ci:
        head += f"   {'90 % credible interval':<24s}{'width/prior':>11s}"
    lines = ["Table 4 layout: breakage parameters inferred by the surrogate inversion", head,
             "-" * len(head)]
    for r in rows:
        label, fmt = TABLE4.get(r["name"], (f"{r['name']}, {r['symbol']}", "{:.4g}"))
        f = r.get("display_factor", 1.0)
        val = fmt.format(r["display_value"]) + (" (fixed)" if r["fixed"] else "")
        line = f"{label:<26s}{_unit_label(r):<7s}{val:>10s}"
        if has_ci and "ci90" in r:
            lo, hi = (fmt.format(v * f) for v in r["ci90"])
            line += f"   [{lo}, {hi}]".ljust(27) + f"{r['std_ratio']:>8.2f}"
        lines.append(line)
    loss = result.get("loss", {})
    fit = result.get("fit", {})
    if loss:
        lines.append(f"loss {loss['total']:.4g} (pressure {loss['pressure']:.4g}, centroid "
                     f"{loss.get('centroid', float('nan')):.4g}, boundary "
                     f"{loss['boundary']:.4g}); best of {len(result.get('restarts', []))} "
                     "restarts")
    if fit:
        lines.append(f"fit on {fit['points']} target points: RMSE {fit['rmse_Pa'] / 1e6:.4g} MPa"
                     f" ({100 * fit['relative_rmse']:.2f} % of the mean target pressure), "
                     f"max |error| {fit['max_abs_Pa'] / 1e6:.4g} MPa")
    cl = result.get("clusters")
    if cl and cl.get("clusters"):
        lines.append(f"{len(cl['within'])} optima within the loss tolerance form "
                     f"{len(cl['clusters'])} cluster(s) (radius {cl['tolerance']['radius_unit']}"
                     " in unit parameters)")
    ident = result.get("identifiability")
    if ident:
        flat = ident["profiles"]["flat"]
        sloppy = ident["hessian"]["sloppy"]
        lines.append(f"identifiability: Hessian condition number "
                     f"{ident['hessian']['condition_number']:.3g}; {len(sloppy)} sloppy "
                     f"direction(s); flat {ident['profiles']['mode']} profiles: "
                     f"{', '.join(flat) if flat else 'none'}")
        cc = ident.get("curve_components")
        if cc:
            lines.append(f"the model's training curves resolve {cc['resolved']} of "
                         f"{cc['tested']} principal components above the bed-to-bed scatter: "
                         f"one curve can pin at most {cc['resolved']} combination(s) of the "
                         f"{cc['free_parameters']} free parameters (the breakage centroids "
                         "add at most 2)")
    post = result.get("posterior")
    if post:
        d = post["diagnostics"]
        tau = max(d["autocorr_time"].values())
        lines.append(f"posterior: {d['walkers']} walkers x {d['steps']} steps (burn "
                     f"{d['burn']}), acceptance {d['acceptance_mean']:.2f}, max "
                     f"autocorrelation time {tau:.0f} steps, predictive 90 % band covers "
                     f"{100 * post['predictive']['target_coverage_90']:.0f} % of the target")
    return "\n".join(lines)


__all__ = ["FORMAT", "SCHEMA_VERSION", "TABLE4", "file_sha256", "format_table4", "parameter_rows",
           "read_result", "write_json"]
