# ---
# jupyter:
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 50 Inverse calibration against a held-out run
#
# **Purpose.** The paper's inverse problem (section 2.4, Table 4, Fig. 8) with the `inverse`
# API: infer the eight breakage parameters from a pressure-depth curve (and its breakage
# map) through a trained surrogate, here against a `holdout` row of the reference dataset,
# whose true parameters are known and which the surrogate never trained on. Then a short
# Bayesian posterior (emcee) and its posterior-predictive band over the target.
#
# **Inputs.** `data/rve.h5`. The surrogate is trained here (2 members x 25 epochs,
# about 15 s) so that this notebook does not depend on notebook 40. Outputs in
# `notebooks/_out/50_inverse_calibration/` (or `$CALENDARING_NOTEBOOK_OUT`).
#
# **Expected run time.** Under 1 minute on 2 CPU cores (27 s measured on a 2-core machine
# shared with a sweep). Everything is cut down from the
# paper's settings (500 iterations x 3 restarts, a posterior of 32 walkers x 3000 steps):
# 150 iterations x 3 restarts and 32 walkers x 600 steps, so the chain is short (its
# autocorrelation diagnostics are printed) and the surrogate is under-trained.

# %%
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from IPython.display import Image, display

import calendaring
from calendaring import notebook_output, read_dataset, to_mpa

warnings.filterwarnings("ignore", message="IProgress not found")  # tqdm in a bare kernel
from inverse.calibrate import calibrate_target  # noqa: E402
from inverse.optimise import OptimiserConfig  # noqa: E402
from inverse.posterior import PosteriorConfig, plot_predictive  # noqa: E402
from inverse.report import format_table4  # noqa: E402
from inverse.validate import row_target, select_rows  # noqa: E402
from surrogate import SurrogateModel, TrainConfig, train_ensemble  # noqa: E402

ROOT = Path(calendaring.__file__).resolve().parents[1]
OUT = notebook_output("50_inverse_calibration")
torch.set_num_threads(1)  # small network, shared machine: one thread is fastest

# %% [markdown]
# ## A small surrogate (an ensemble of 2, so the posterior sees the model's own spread)

# %%
ds = read_dataset(ROOT / "data" / "rve.h5")
t0 = time.perf_counter()
results = train_ensemble(ds, n_members=2, cfg=TrainConfig(epochs=25, seed=0), progress=False)
model = SurrogateModel.from_training(results, ds)
print(f"trained {model} in {time.perf_counter() - t0:.1f} s on "
      f"{len(results[0].rows['train'])} runs; test-split MSE (member 0) "
      f"{results[0].loss_table['test']['mse']:.4f} (normalised)")

# %% [markdown]
# ## The target: a held-out run
# `inverse.validate.row_target` turns a dataset row into a `Target` on the model's depths
# (the smoothed pressure curve, and the breakage map with its centroid).

# %%
holdout = select_rows(ds, roles=("holdout",))
row = int(holdout[0])
target = row_target(model, ds, row)
truth = ds.params[row]
print(f"{len(holdout)} holdout rows; calibrating against row {row} ({ds.run_id[row]}), "
      f"{target.n_valid} pressure points, distribution "
      f"{'yes' if target.distribution is not None else 'no'}, "
      f"{int(ds.n_events[row])} breakage events")
print(f"target pressure at the end of the stroke: {to_mpa(target.pressure[-1]):.1f} MPa")

# %% [markdown]
# ## Calibration and posterior
# Adam then L-BFGS on the unit cube (clamped after every update) from scrambled-Sobol
# starts; the best restart is kept. The posterior samples the unit cube with the
# observation sigma (default 5 % of the pressure + 1 % of its maximum) and the ensemble's
# predictive variance in the likelihood.

# %%
t0 = time.perf_counter()
out = calibrate_target(
    model, target,
    optimiser=OptimiserConfig(iterations=150, restarts=3, seed=0),
    posterior=PosteriorConfig(walkers=32, steps=600, burn=200, seed=0),
    identifiability=True)
print(f"calibration + posterior in {time.perf_counter() - t0:.1f} s "
      f"({ {k: round(v, 1) for k, v in out.result['timings_s'].items()} } s)")

# %% [markdown]
# ## Table 4 layout
# The inferred values in the paper's display units, with the 90 % credible interval and the
# posterior/prior width ratio (1 = the data say nothing about that parameter). Below, the
# held-out run's true values.

# %%
print(format_table4(out.result))
print()
space = model.space
print(f"{'parameter':<18s}{'unit':<7s}{'truth':>10s}{'optimum':>10s}{'90 % CI':>24s}  inside")
inside = 0
for j, p in enumerate(out.result["parameters"]):
    f = p["display_factor"]
    lo, hi = p["ci90"]
    ok = lo <= truth[j] <= hi
    inside += ok
    print(f"{p['name']:<18s}{p['display_unit']:<7s}{truth[j] * f:>10.4g}{p['value'] * f:>10.4g}"
          f"{f'[{lo * f:.4g}, {hi * f:.4g}]':>24s}  {'yes' if ok else 'no'}")
print(f"{inside} of {len(truth)} true values inside their 90 % credible interval "
      "(one short chain on an under-trained surrogate: indicative only)")

# %% [markdown]
# ## Posterior-predictive band over the target (Fig. 8 layout)

# %%
post = out.result["posterior"]
d = post["diagnostics"]
print(f"emcee: {d['walkers']} walkers x {d['steps']} steps (burn {d['burn']}), acceptance "
      f"{d['acceptance_mean']:.2f}, max autocorrelation time "
      f"{max(d['autocorr_time'].values()):.0f} steps, long enough: {d['long_enough']}")
print(f"the noisy 90 % predictive band covers {100 * post['predictive']['target_coverage_90']:.0f} "
      f"% of the target points; fit RMSE at the optimum "
      f"{to_mpa(out.result['fit']['rmse_Pa']):.2f} MPa")
png = plot_predictive(target, post["predictive"], OUT / "fig8_posterior_predictive.png",
                      best_pressure=out.result["prediction"]["pressure_Pa"],
                      sigma_pa=np.asarray(post["sigma_Pa"]))
display(Image(filename=str(png)))
