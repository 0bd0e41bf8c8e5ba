# ---
# jupyter:
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 60 Sobol sensitivity and one-at-a-time trends
#
# **Purpose.** The paper's global sensitivity analysis (section 3.3, Fig. 10) and parameter
# trends (Fig. 11) on a surrogate trained on the reference dataset, with `analysis.sensitivity`
# (SALib Sobol design and analysis, first-order S1 and total ST indices with bootstrap CIs) and
# `analysis.trends`. The four outputs (`analysis.outputs`): peak pressure, stress (peak-load)
# centroid, diameter centroid and low-stress ratio. A given-data cross-check (SALib
# `rbd_fast` on the raw DEM runs, no surrogate) shows which first-order effects the data
# themselves support.
#
# **Inputs.** `data/rve.h5`; a single MLP is trained here (30 epochs, about 10 s).
# Outputs in `notebooks/_out/60_sobol_and_trends/` (or `$CALENDARING_NOTEBOOK_OUT`).
#
# **Expected run time.** Under 1 minute on 2 CPU cores (41 s measured on a 2-core machine
# shared with a sweep). Sample sizes are small (Sobol base
# N = 256 to 4096, 21 points per trend) against the CLI's default N = 2^14, so confidence
# intervals are wide; the convergence table says whether they meet the 0.05 criterion.

# %%
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from IPython.display import Image, display

import calendaring
from calendaring import notebook_output, read_dataset

warnings.filterwarnings("ignore", message="IProgress not found")  # tqdm in a bare kernel
from analysis.outputs import OUTPUTS  # noqa: E402
from analysis.sensitivity import (  # noqa: E402
    dataset_given_data,
    plot_convergence,
    plot_sobol,
    sobol_convergence,
    surrogate_model,
)
from analysis.trends import plot_trends, sweep  # noqa: E402
from surrogate import SurrogateModel, TrainConfig, train  # noqa: E402

ROOT = Path(calendaring.__file__).resolve().parents[1]
OUT = notebook_output("60_sobol_and_trends")
torch.set_num_threads(1)  # small network, shared machine: one thread is fastest

# %%
ds = read_dataset(ROOT / "data" / "rve.h5")
t0 = time.perf_counter()
res = train(ds, TrainConfig(epochs=30, seed=0), progress=False)
model = SurrogateModel.from_training(res, ds)
space = model.space
print(f"trained {model} in {time.perf_counter() - t0:.1f} s on {len(res.rows['train'])} runs "
      f"of {ds.path.name}; test MSE {res.loss_table['test']['mse']:.4f} (normalised)")

# %% [markdown]
# ## Sobol indices (Fig. 10) and their convergence
# `surrogate_model` wraps the network as a unit-cube model of the four outputs;
# `sobol_convergence` evaluates the nested Sobol design at N = 256, 512, ..., 4096
# (N (k + 2) model evaluations each) and reports the largest CI half-width and whether the
# ranking by ST is stable between levels.

# %%
f = surrogate_model(model)
t0 = time.perf_counter()
rows, sob = sobol_convergence(f, space.names, n_max=4096, n_min=256, seed=0, stop=False)
print(f"Sobol in {time.perf_counter() - t0:.1f} s")
print(f"{'N':>6s}{'evaluations':>13s}{'largest CI half-width':>24s}{'ranking stable':>16s}"
      f"{'converged':>11s}")
for r in rows:
    print(f"{r['n']:>6d}{r['n_evaluations']:>13d}{r['max_conf']:>24.4f}"
          f"{r['ranking_stable']!s:>16s}{r['converged']!s:>11s}")
display(Image(filename=str(plot_convergence(rows, OUT / "sobol_convergence.png"))))

# %%
print(f"indices at N = {sob.n} ({sob.n_evaluations} evaluations), "
      f"{int(100 * sob.conf_level)} % CI half-widths")
for o in sob.indices:
    d = sob.indices[o]
    print(f"\n{o}: ranking by ST {sob.ranking(o)}")
    print(f"  {'parameter':<18s}{'S1':>8s}{'+-':>7s}{'ST':>8s}{'+-':>7s}")
    for j, name in enumerate(sob.names):
        print(f"  {name:<18s}{d['S1'][j]:8.3f}{d['S1_conf'][j]:7.3f}{d['ST'][j]:8.3f}"
              f"{d['ST_conf'][j]:7.3f}")
if sob.constant:
    print("outputs without variance (indices 0):", sob.constant)
display(Image(filename=str(plot_sobol(sob, OUT / "fig10_sobol.png", space.symbols))))

# %% [markdown]
# ## Given-data cross-check on the raw runs
# First-order indices straight from the dataset's `train` runs (their LHS design and the
# outputs of their DEM curves and maps), with no surrogate in between. A parameter the
# surrogate ranks high that the data do not support deserves suspicion, and the other way
# round.

# %%
gd = dataset_given_data(ds, method="rbd_fast")
print(f"SALib {gd['method']} on {gd['rows_total']} runs ({gd['roles']})")
print(f"  {'parameter':<18s}" + "".join(f"{o:>19s}" for o in OUTPUTS))
for j, name in enumerate(space.names):
    vals = []
    for o in OUTPUTS:
        io = gd["indices"].get(o, {})
        vals.append(f"{io['S1'][j]:8.3f} +-{io['S1_conf'][j]:6.3f}" if "S1" in io
                    else f"{'n/a':>16s}")
    print(f"  {name:<18s}" + "".join(f"{v:>19s}" for v in vals))
for o in OUTPUTS:
    io = gd["indices"].get(o, {})
    top = space.names[int(np.argmax(io["S1"]))] if "S1" in io else None
    print(f"{o}: largest S1 in the data: {top}; largest ST on the surrogate: "
          f"{sob.ranking(o)[0]}")
print("(with this many runs the given-data CI half-widths are wide: a weak ranking)")

# %% [markdown]
# ## One-at-a-time trends (Fig. 11)
# Each parameter swept over its normalised range with the others held at mid-range.
# Outputs are min-max scaled over all sweeps in the plot (so a steeper curve is a stronger
# effect); the table gives the physical change of each output over each sweep.

# %%
tr = sweep(f, space.names, at=None, n_points=21, space=space)
display(Image(filename=str(plot_trends(tr, OUT / "fig11_trends.png", space.symbols))))
scale = {"peak_pressure": (1e-6, "MPa"), "stress_centroid": (1e3, "mN"),
         "diameter_centroid": (1e6, "um"), "low_stress_ratio": (1.0, "-")}
print("change over each sweep (value at 1 minus value at 0):")
print(f"  {'parameter':<18s}" + "".join(f"{o + ' [' + scale[o][1] + ']':>26s}" for o in OUTPUTS))
for name in space.names:
    row = tr["outputs"][name]
    print(f"  {name:<18s}" + "".join(
        f"{(row[o][-1] - row[o][0]) * scale[o][0]:>26.4g}" for o in OUTPUTS))
print("held point outputs:", {o: f"{v * scale[o][0]:.4g} {scale[o][1]}"
                              for o, v in tr["at_outputs"].items()})
