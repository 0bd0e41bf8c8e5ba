# ---
# jupyter:
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 70 Microstructure: porosity, tortuosity and effective diffusivity
#
# **Purpose.** The transport properties of a calendered electrode (paper section 3.5,
# Fig. 13 b-d) with `analysis.microstructure`: the first and last snapshot of a `tiny` run
# are voxelised (exact centre-in-sphere tests, periodic in x and y, cropped by the plates),
# and TauFactor 1.2.1 solves steady diffusion through the thickness for the tortuosity
# factor tau and the relative effective diffusivity D_eff = porosity / tau. Every result is
# resolution-converged: partial-volume (grey) voxels at 3, 4.5, 6.75, ... voxels per
# smallest diameter, each level started from the previous one's potential, until tau
# changes by less than 2 % between levels. The sequence is shown; the linear two-point
# extrapolation of the last two levels stays as a cross-check. Three porosities are
# compared: sphere sum, voxel image and the recipe's mass balance.
#
# **Inputs.** None: the run is made here (`tiny` preset, seed 0). Outputs in
# `notebooks/_out/70_microstructure/` (or `$CALENDARING_NOTEBOOK_OUT`).
#
# **Expected run time.** About 1 minute on 2 CPU cores (the run, then the refinement of two
# snapshots, with torch on one thread). The tiny preset stops at 6.5 um (the paper:
# 19.5 um of a 75 um coating).

# %%
import time
import warnings

import matplotlib.pyplot as plt
import torch
from IPython.display import Image, Markdown, display

from calendaring import load_preset, notebook_output, read_run, run, show_figure, to_um

warnings.filterwarnings("ignore", message="IProgress not found")  # tqdm in a bare kernel
from analysis.microstructure import (  # noqa: E402
    analyse_run,
    format_table,
    microstructure_table,
    plot_microstructure,
    voxelise,
)

OUT = notebook_output("70_microstructure")
# TauFactor solves with torch: one thread (on a shared 2-core machine more threads only
# wait on each other)
torch.set_num_threads(1)

# %%
run_file = OUT / "tiny.h5"
run_file.unlink(missing_ok=True)
t0 = time.perf_counter()
run(load_preset("tiny"), run_file, progress=False, preset="tiny")
rec = read_run(run_file)
first, last = rec.snapshots[0], rec.snapshots[-1]
print(f"run in {time.perf_counter() - t0:.1f} s; snapshots at "
      f"{[round(to_um(s.depth), 2) for s in rec.snapshots]} um; analysing "
      f"{to_um(first.depth):.1f} and {to_um(last.depth):.1f} um")

# %% [markdown]
# ## Porosity, tortuosity, D_eff

# %%
t0 = time.perf_counter()
res = analyse_run(run_file, snapshots=[first.index, last.index], progress=False,
                  label="tiny R1")
print(f"microstructure in {time.perf_counter() - t0:.1f} s; settings: "
      f"{res.settings['resolution']}, from {res.settings['voxels_per_diameter']:g} voxels per "
      f"{res.settings['reference_diameter_m'] * 1e6:g} um, stop at a tau change < "
      f"{100 * res.settings['refine_tol']:g} %, TauFactor "
      f"{res.settings['taufactor_version']}, tol {res.settings['tol']:g}")
rows = microstructure_table({"tiny R1": res}, depths=(first.depth, last.depth))
display(Markdown(format_table(rows)))
for s in res.snapshots:
    j = s.to_json()
    check = j["D_eff_check_rel_err"]
    print(f"{to_um(s.depth):4.1f} um: {s.n_particles} particles, particle porosity "
          f"{100 * s.particle_porosity:.2f} %, voxel porosity {100 * j['voxel_porosity']:.2f} %, "
          f"tau {j['tortuosity'] if j['tortuosity'] is None else round(j['tortuosity'], 4)}, "
          f"D_eff {j['D_eff']:.4f} (porosity / tau agrees to "
          f"{'n/a' if check is None else f'{check:.1e}'}), TauFactor converged "
          f"{j['converged']} in {j['iterations']} iterations")
    ref = j["refinement"]
    for lv in ref["levels"]:
        print(f"    {lv['voxels_per_diameter']:5.2f} vox/d {lv['voxels']:>9,} voxels: tau "
              f"{lv['tortuosity']}, change {lv.get('tortuosity_rel_change')}, "
              f"{lv['iterations']} iterations, {lv['solve_seconds']:.1f} s")
    ext = (j["extrapolated"] or {}).get("tortuosity")
    print(f"    converged {ref['converged']} ({ref['reason'] or 'tau change below tol'}); "
          f"cross-checks: linear extrapolation {ext}, Richardson "
          f"{ref['tortuosity_richardson']}")
    por = j["porosities"]
    print(f"    porosity: sphere sum {100 * por['sphere_sum']:.2f} %, voxel "
          f"{100 * por['voxel']:.2f} %, mass balance {100 * por['mass_balance']:.2f} %; "
          f"pair overlaps {100 * por['pair_overlap']:.2f} % of the volume (AM-CB "
          f"{100 * por['pair_overlap_am_cb']:.2f} %), plate caps {100 * por['plate_caps']:.2f} %")
    assert ref["converged"] or ref["reason"], ref  # a stop always says why
    assert abs(por["union_estimate"] - por["voxel"]) < 0.02, por  # the budget closes
res.write_json(OUT / "microstructure.json")

# %% [markdown]
# The sphere-sum porosity (1 - sphere volume / cell volume) counts overlapping volume twice
# and caps pressed into the plates although they lie outside the gap. The summed lens
# volumes of the overlapping pairs (mostly carbon black squeezed into active material) and
# the plate caps close the gap to the voxel porosity up to triple overlaps; the mass
# balance differs from the sphere sum by the builder's whole-particle rounding only.
#
# ## Against depth (Fig. 13 b-d)
# Solid: the converged (finest) level; dotted: the linear extrapolation of the last two
# levels; dashed (porosity): sphere-sum porosity.

# %%
for path in plot_microstructure({"tiny R1": res}, OUT):
    display(Image(filename=str(path), width=380))

# %% [markdown]
# ## What the solver sees
# Mid-plane cross-sections (x-z) of the partial-volume voxel images at the finest level
# (`voxelise`: pore fraction, 1 = pore, 0 = solid), from the bottom plate (z = 0) to the top.

# %%
h = res.snapshots[-1].primary.voxel_size
fig, axes = plt.subplots(1, 2, figsize=(9, 4.2), sharey=True)
for ax, s in zip(axes, (first, last), strict=True):
    img = voxelise(s.position, s.radius, s.material, rec.cell_x, rec.cell_y, s.z_bottom,
                   s.z_top, h, supersample=3)
    ax.imshow(img[:, img.shape[1] // 2, :], origin="lower", cmap="gray",
              extent=(0, to_um(rec.cell_x), 0, to_um(s.z_top - s.z_bottom)))
    ax.set_title(f"{to_um(s.depth):.1f} um: {img.shape} voxels (z, y, x), pore "
                 f"{100 * img.mean():.1f} %", fontsize=9)
    ax.set_xlabel("x [um]")
axes[0].set_ylabel("z above the bottom plate [um]")
fig.tight_layout()
show_figure(fig, OUT / "voxel_sections.png")
