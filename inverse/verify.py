"""Forward verification: run the DEM at calibrated parameters and compare with the target.

``inverse verify RESULT.json --preset PRESET [--seeds K] [--draws M]`` runs
``calendaring run --preset P --set breakage.<name>=<value> ... --seed S --out RUN.h5`` as a
subprocess for K seeds at the calibrated parameters and one seed at each of M posterior draws
(from the result's ``posterior.draws_physical``), resamples each run's top-plate pressure onto
the target's depths exactly as the target was built (:func:`inverse.targets.target_from_run`
semantics), reports the error against the target (RMSE [Pa], relative RMSE, max |error|, over
the depths both cover) and draws the curves over the target in one PNG.

The DEM's stroke is the preset's: the comparison uses the depths covered by both the run and
the target. Run files are kept in the output folder (``<out>/runs/``) and reused if present.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from calendaring import PRESETS, ConfigError
from inverse.report import read_result, write_json
from inverse.targets import Target, interval_means, smooth_valid


def run_command(params: dict[str, float], preset: str, seed: int, out: str | Path,
                quiet: bool = True) -> list[str]:
    """The ``calendaring run`` command line for one DEM run at ``params`` (physical values,
    ``[breakage]`` keys, SI, percent for A and R_t)."""
    if preset not in PRESETS:
        raise ConfigError("--preset", preset, f"one of {PRESETS}")
    cmd = [sys.executable, "-m", "calendaring.cli", "run", "--preset", preset]
    for name, value in params.items():
        cmd += ["--set", f"breakage.{name}={float(value)!r}"]
    cmd += ["--seed", str(int(seed)), "--out", str(out), "--overwrite"]
    if quiet:
        cmd.append("--quiet")
    return cmd


def curve_from_run(path: str | Path, depth: np.ndarray, smooth: bool = True
                   ) -> tuple[np.ndarray, np.ndarray]:
    """A run file's top-plate pressure as interval means on ``depth`` (the model grid),
    smoothed as the targets are; returns (pressure [Pa] with NaN where not covered, mask)."""
    from calendaring import read_run

    rec = read_run(path)
    p, covered = interval_means(rec.pressure["depth"], rec.pressure["value"], depth)
    if smooth:
        p = smooth_valid(p, covered)
    return np.where(covered, p, np.nan), covered


def curve_error(target: Target, pressure: np.ndarray, covered: np.ndarray) -> dict:
    """Error of a curve against the target over the depths both cover [Pa]."""
    both = target.valid & covered & np.isfinite(pressure)
    if both.sum() == 0:
        return {"points": 0, "rmse_Pa": None, "relative_rmse": None, "max_abs_Pa": None}
    e = pressure[both] - target.pressure[both]
    rmse = float(np.sqrt(np.mean(e**2)))
    return {"points": int(both.sum()), "rmse_Pa": rmse,
            "relative_rmse": rmse / max(float(np.mean(np.abs(target.pressure[both]))), 1e-30),
            "max_abs_Pa": float(np.max(np.abs(e)))}


def plot_overlay(target: Target, curves: list[dict], path, prediction=None):
    """Target, surrogate prediction and DEM curves (depth in um, pressure in MPa)."""
    import matplotlib.pyplot as plt

    from calendaring import to_mpa, to_um

    fig, ax = plt.subplots(figsize=(6, 4))
    v = target.valid
    ax.plot(to_um(target.depth[v]), to_mpa(target.pressure[v]), "k-", lw=2, label="target")
    if prediction is not None:
        ax.plot(to_um(target.depth), to_mpa(np.asarray(prediction)), "C3--", lw=1,
                label="surrogate at optimum")
    for c in curves:
        p = np.asarray(c["pressure_Pa"], float)
        style = dict(color="C0", lw=1) if c["kind"] == "optimum" else dict(color="C2", lw=0.6,
                                                                          alpha=0.6)
        ax.plot(to_um(target.depth), to_mpa(p), **style)
    ax.plot([], [], color="C0", label="DEM at the optimum")
    if any(c["kind"] == "draw" for c in curves):
        ax.plot([], [], color="C2", label="DEM at posterior draws")
    ax.set_xlabel("calendering depth [um]")
    ax.set_ylabel("pressure [MPa]")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def verify(result_path: str | Path, preset: str = "quick", seeds: int = 1, draws: int = 0,
           out_dir: str | Path | None = None, first_seed: int = 0, runner=None,
           progress: bool = True) -> dict:
    """Run the DEM at the calibrated parameters (``seeds`` seeds) and at ``draws`` posterior
    draws, compare with the result's target, write ``verify.json`` and ``verify.png``.

    Args:
        runner: callable(cmd list) -> returncode, replacing ``subprocess.run`` (tests).
    """
    res = read_result(result_path)
    if seeds < 1:
        raise ConfigError("--seeds", seeds, ">= 1")
    if draws < 0:
        raise ConfigError("--draws", draws, ">= 0")
    post_draws = (res.get("posterior") or {}).get("draws_physical") or []
    if draws > len(post_draws):
        raise ConfigError("--draws", draws, f"<= {len(post_draws)} (posterior draws stored in "
                          "the result; calibrate with --posterior)")
    out_dir = Path(out_dir) if out_dir else Path(result_path).with_suffix("").with_name(
        Path(result_path).stem + "_verify")
    runs_dir = out_dir / "runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    target = Target.from_json(res["target"])
    names = [p["name"] for p in res["parameters"]]
    best = {p["name"]: p["value"] for p in res["parameters"]}
    jobs = [("optimum", first_seed + s, best) for s in range(seeds)]
    jobs += [("draw", first_seed + i, dict(zip(names, post_draws[i], strict=True)))
             for i in range(draws)]
    runner = runner or (lambda cmd: subprocess.run(cmd).returncode)
    curves = []
    for k, (kind, seed, params) in enumerate(jobs):
        out = runs_dir / f"{kind}{k:02d}_seed{seed}.h5"
        cmd = run_command(params, preset, seed, out)
        if not out.exists():
            if progress:
                print(f"[{k + 1}/{len(jobs)}] {' '.join(cmd[2:])}", file=sys.stderr, flush=True)
            t0 = time.perf_counter()
            rc = runner(cmd)
            if rc != 0:
                raise RuntimeError(f"calendaring run exited with {rc}: {' '.join(cmd)}")
            if progress:
                print(f"    done in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        p, covered = curve_from_run(out, target.depth)
        curves.append({"kind": kind, "seed": seed, "run_file": str(out), "params": params,
                       "command": cmd, "pressure_Pa": p.tolist(),
                       "error": curve_error(target, p, covered)})
    opt = [c for c in curves if c["kind"] == "optimum"]
    if opt:
        runs = np.array([c["pressure_Pa"] for c in opt], float)
        cov = np.isfinite(runs).any(axis=0)  # depths some run reached
        mean = np.full(runs.shape[1], np.nan)
        mean[cov] = np.nanmean(runs[:, cov], axis=0)
        summary = curve_error(target, mean, cov)
    else:
        summary = {}
    report = {"result": str(result_path), "preset": preset, "seeds": seeds, "draws": draws,
              "curves": curves, "optimum_mean_error": summary,
              "surrogate_error": res.get("fit")}
    png = plot_overlay(target, curves, out_dir / "verify.png",
                       prediction=res.get("prediction", {}).get("pressure_Pa"))
    report["plot"] = str(png)
    write_json(out_dir / "verify.json", report)
    return report


__all__ = ["PRESETS", "curve_error", "curve_from_run", "plot_overlay", "run_command", "verify"]
