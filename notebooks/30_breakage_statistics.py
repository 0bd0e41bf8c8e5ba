# ---
# jupyter:
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 30 Breakage statistics of a calendering run
#
# **Purpose.** The Tavares UFRJ breakage records of one `tiny` calendering run: the 30 x 30
# probability map of peak load against parent diameter (paper Fig. 9 and Eq. 43, binned
# exactly as the dataset builder bins it for the surrogate: log load axis, edges over the
# events, probabilities summing to 1, with its centroid), breakage events against depth,
# and the fragment size distribution. All from the run file's `breakage/` datasets
# (one row per event, one row per fragment) through `calendaring.process.runfile.read_run`.
#
# **Inputs.** None: the run is made here (`tiny` preset, seed 0). The reference dataset
# `data/rve.h5` is read only for its global histogram edges (the surrogate's bins).
# Outputs in `notebooks/_out/30_breakage_statistics/` (or `$CALENDARING_NOTEBOOK_OUT`).
#
# **Expected run time.** About 1 minute on 2 CPU cores (35-70 s measured on a 2-core machine
# shared with a sweep; the run is most of it). A `tiny`
# run has a few tens of events, so the map is sparse: the paper's maps pool a 100 x 100 um
# cell calendered by 19.5 um.

# %%
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import calendaring
from calendaring import (
    bin_centres,
    bin_events,
    centroids,
    histogram_edges,
    load_preset,
    notebook_output,
    read_dataset,
    read_run,
    run,
    show_figure,
    to_um,
)

ROOT = Path(calendaring.__file__).resolve().parents[1]
OUT = notebook_output("30_breakage_statistics")

# %%
run_file = OUT / "tiny.h5"
run_file.unlink(missing_ok=True)
t0 = time.perf_counter()
run(load_preset("tiny"), run_file, progress=False, preset="tiny")
rec = read_run(run_file)
b, frag = rec.breakage, rec.breakage["fragments"]
n_ev = len(b["parent_id"])
print(f"run in {time.perf_counter() - t0:.1f} s: {n_ev} breakage events, {len(frag['id'])} "
      f"fragments; first event at {to_um(b['depth'].min()):.2f} um" if n_ev else
      "no breakage event in this run")
assert n_ev > 0, "the statistics below need at least one breakage event"

# %% [markdown]
# ## Peak load against parent diameter (Fig. 9)
# `breakage/peak_load` is the largest total contact normal force the parent sustained
# before breaking. Left: this run's events on its own edges (`histogram_edges`, 30 x 30,
# log load axis) as probabilities (`bin_events`, Eq. 43) with the probability-weighted
# centroid (`centroids`, geometric on the log axis). Right: the same events on the global
# edges of the reference dataset, i.e. the map the surrogate is trained to predict (events
# outside those edges are clipped into the end bins).

# %%
load_edges, dia_edges = histogram_edges([b["peak_load"]], [b["diameter"]], bins=30,
                                        load_scale="log")
hist = bin_events(b["peak_load"], b["diameter"], load_edges, dia_edges)
c = centroids(hist, bin_centres(load_edges, "log"), bin_centres(dia_edges), log_load=True)

ds = read_dataset(ROOT / "data" / "rve.h5")
hist_ref = bin_events(b["peak_load"], b["diameter"], ds.load_edges, ds.diameter_edges)
c_ref = centroids(hist_ref, ds.load_centres, ds.diameter_centres, log_load=ds.load_scale == "log")
outside = int(np.sum((b["peak_load"] < ds.load_edges[0]) | (b["peak_load"] > ds.load_edges[-1])
                     | (b["diameter"] < ds.diameter_edges[0])
                     | (b["diameter"] > ds.diameter_edges[-1])))

fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
for ax, h, le, de, cc, title in (
        (axes[0], hist, load_edges, dia_edges, c, "this run's edges"),
        (axes[1], hist_ref, ds.load_edges, ds.diameter_edges, c_ref,
         f"reference-dataset edges ({outside} events clipped)")):
    im = ax.pcolormesh(to_um(de), 1e3 * le, np.ma.masked_equal(h, 0.0), cmap="viridis")
    ax.set_yscale("log")
    ax.plot(to_um(cc[1]), 1e3 * cc[0], "r+", ms=14, mew=2, label="centroid")
    ax.set_xlabel("parent diameter [um]")
    ax.set_ylabel("peak load before breakage [mN]")
    ax.set_title(f"{n_ev} events, 30 x 30 bins, {title}", fontsize=9)
    ax.legend(fontsize=8, loc="lower right")
    fig.colorbar(im, ax=ax, label="probability")
fig.tight_layout()
show_figure(fig, OUT / "fig9_load_diameter.png")
print(f"probabilities sum to {hist.sum():.6f}; {int(np.count_nonzero(hist))} of 900 bins occupied")
print(f"centroid (own edges): peak load {1e3 * c[0]:.3f} mN, parent diameter {to_um(c[1]):.2f} um")
print(f"centroid (reference edges): peak load {1e3 * c_ref[0]:.3f} mN, parent diameter "
      f"{to_um(c_ref[1]):.2f} um")

# %% [markdown]
# ## Events against depth, and the breakage model's records
# Left: cumulative events (from `breakage/depth`, and the `series/breakage_events` column,
# which must agree). Right: specific stressing energy at breakage against the (damaged)
# fracture energy: a particle breaks on the step `E_k` reaches `E'_f`, so the points sit on
# or just above the diagonal.

# %%
fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
d_sorted = np.sort(b["depth"])
axes[0].step(to_um(d_sorted), np.arange(1, n_ev + 1), where="post", label="breakage/depth")
axes[0].plot(to_um(rec.series["depth"]), rec.series["breakage_events"], "--",
             label="series/breakage_events")
axes[0].set_xlabel("calendering depth [um]")
axes[0].set_ylabel("breakage events so far")
axes[0].legend(fontsize=8)
axes[1].hist(to_um(b["depth"]), bins=13, color="tab:red", alpha=0.7)
axes[1].set_xlabel("calendering depth [um]")
axes[1].set_ylabel("events per depth bin")
axes[2].loglog(b["fracture_energy"], b["stressing_energy"], ".", ms=5)
lim = [min(b["fracture_energy"].min(), b["stressing_energy"].min()),
       max(b["fracture_energy"].max(), b["stressing_energy"].max())]
axes[2].plot(lim, lim, "k--", lw=0.8)
axes[2].set_xlabel("fracture energy at breakage E'_f [J/kg]")
axes[2].set_ylabel("stressing energy E_k [J/kg]")
fig.tight_layout()
show_figure(fig, OUT / "events_vs_depth.png")
print(f"E_k / E'_f at breakage: min {np.min(b['stressing_energy'] / b['fracture_energy']):.4f}, "
      f"median {np.median(b['stressing_energy'] / b['fracture_energy']):.4f}")
print(f"t10: median {100 * np.median(b['t10']):.1f} %, range {100 * b['t10'].min():.1f}-"
      f"{100 * b['t10'].max():.1f} %")

# %% [markdown]
# ## Fragment size distribution
# `breakage/fragments/diameter` (one row per fragment, with the row of its event). Fragments
# can break again, so a fragment can also appear as a parent. Right: the number of fragments
# per event against the parent diameter.

# %%
fd, pd_ = frag["diameter"], b["diameter"]
fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
bins = np.linspace(0, to_um(max(fd.max(), pd_.max())) * 1.02, 30)
axes[0].hist(to_um(fd), bins=bins, color="tab:orange", label=f"fragments ({len(fd)})")
axes[0].hist(to_um(pd_), bins=bins, histtype="step", color="k", lw=1.3,
             label=f"parents ({len(pd_)})")
axes[0].set_xlabel("diameter [um]")
axes[0].set_ylabel("count")
axes[0].legend(fontsize=8)
axes[1].scatter(to_um(pd_), b["n_fragments"], s=12)
axes[1].set_xlabel("parent diameter [um]")
axes[1].set_ylabel("fragments per event")
fig.tight_layout()
show_figure(fig, OUT / "fragment_sizes.png")

vol_parent = np.sum(pd_**3)
vol_frag = np.sum(fd**3)
print(f"fragments: {len(fd)} from {n_ev} events ({len(fd) / n_ev:.1f} per event), diameters "
      f"{to_um(fd.min()):.2f}-{to_um(fd.max()):.2f} um (median {to_um(np.median(fd)):.2f} um)")
print(f"volume of all fragments / volume of all parents: {vol_frag / vol_parent:.12f} "
      "(exact volume conservation per event gives 1)")
