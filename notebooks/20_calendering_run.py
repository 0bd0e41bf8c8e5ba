# ---
# jupyter:
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 20 A calendering run: pressure, porosity and the bond network
#
# **Purpose.** One calendering run of the `tiny` preset and what its run file records
# against calendering depth: the pressure-depth curve (the quantity of paper Figs. 8 and
# 13a), porosity and coordination, bond counts by state (intact, failed in tension or
# shear, removed with a broken particle), side views of the bed at the snapshot depths
# (paper Fig. 1), the bond network by state (Fig. 6) and the particle-scale normal force
# against AM diameter (Fig. 7). Everything is read from the run file's datasets through
# `calendaring.process.runfile.read_run`.
#
# **Inputs.** None: the run is made here (`tiny` preset, seed 0; outputs in
# `notebooks/_out/20_calendering_run/` or `$CALENDARING_NOTEBOOK_OUT`).
#
# **Expected run time.** Under 1 minute on 2 CPU cores (34 s measured on a 2-core machine
# shared with a sweep; the run is most of it, up to 2 minutes under heavier load). The `tiny`
# preset (25 um cell, 25 um coating, 6.5 um stroke at 2 m/s, coarse time step) is a test
# configuration: the paper's figures are at 19.5 um of a 75 um coating (`quick` / `paper`).

# %%
import time

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import LineCollection

from analysis.render import BOND_COLOURS, bond_segments
from calendaring import load_preset, notebook_output, read_run, run, show_figure, to_mpa, to_um

OUT = notebook_output("20_calendering_run")

# %%
run_file = OUT / "tiny.h5"
run_file.unlink(missing_ok=True)
t0 = time.perf_counter()
run(load_preset("tiny"), run_file, progress=False, preset="tiny")
rec = read_run(run_file)
s = rec.series
print(f"run in {time.perf_counter() - t0:.1f} s: {rec.info['n_particles']} particles "
      f"{rec.info['build']['counts']}, {rec.info['bonds_created']} bonds, "
      f"dt = {rec.info['dt']:.3e} s, {len(rec.breakage['parent_id'])} breakage events")

# %% [markdown]
# ## Pressure against depth
# `pressure/` holds the top- and bottom-plate pressure at every step (the tiny preset
# records every step); `series/` holds row means every `output.record_spacing` of travel.

# %%
p = rec.pressure
fig, ax = plt.subplots(figsize=(6, 4))
ax.plot(to_um(p["depth"]), to_mpa(p["value"]), lw=0.6, color="0.7", label="top plate, per step")
ax.plot(to_um(s["depth"]), to_mpa(s["top_pressure"]), lw=1.5, label="top plate, row mean")
ax.plot(to_um(s["depth"]), to_mpa(s["bottom_pressure"]), "--", lw=1.2,
        label="bottom plate, row mean")
for snap in rec.snapshots:
    ax.axvline(to_um(snap.depth), color="0.85", lw=0.6, zorder=0)
ax.set_xlabel("calendering depth [um]")
ax.set_ylabel("pressure [MPa]")
ax.legend(fontsize=8)
ax.set_title("pressure-depth curve (grey lines: snapshots)", fontsize=9)
fig.tight_layout()
show_figure(fig, OUT / "pressure_depth.png")
for d in (2e-6, 4e-6, rec.stroke):
    print(f"top pressure at {to_um(d):.1f} um: {to_mpa(rec.pressure_at(d)):.1f} MPa")

# %% [markdown]
# ## Porosity, coordination and bonds against depth

# %%
fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
depth = to_um(s["depth"])
axes[0].plot(depth, 100 * s["porosity"], label="series (sphere volume / gap)")
axes[0].plot([to_um(sn.depth) for sn in rec.snapshots],
             [100 * sn.porosity(rec.cell_x, rec.cell_y) for sn in rec.snapshots], "o",
             label="snapshots")
axes[0].set_ylabel("porosity [%]")
axes[0].legend(fontsize=8)
axes[1].plot(depth, s["coordination"])
axes[1].set_ylabel("coordination number [-]")
for key, label in (("bonds_intact", "intact"), ("bonds_failed_normal", "failed in tension"),
                   ("bonds_failed_shear", "failed in shear"),
                   ("bonds_removed", "removed with a broken particle")):
    axes[2].plot(depth, s[key], label=label)
axes[2].set_ylabel("bonds")
axes[2].legend(fontsize=8)
for ax in axes:
    ax.set_xlabel("calendering depth [um]")
fig.tight_layout()
show_figure(fig, OUT / "porosity_coordination_bonds.png")
print(f"porosity {100 * s['porosity'][0]:.2f} % -> {100 * s['porosity'][-1]:.2f} %; bonds: "
      f"{int(s['bonds_intact'][0])} intact at the start, at the end {int(s['bonds_intact'][-1])}"
      f" intact, {int(s['bonds_failed_normal'][-1])} failed in tension, "
      f"{int(s['bonds_failed_shear'][-1])} in shear, {int(s['bonds_removed'][-1])} removed")

# %% [markdown]
# ## Bond states per snapshot
# Each snapshot stores the bond network (`snapshots/<k>/bonds`: ids, state, normal force).

# %%
names = ("intact", "failed in tension", "failed in shear", "removed")
table = np.array([np.bincount(np.asarray(sn.bonds["state"], int), minlength=4)[:4]
                  for sn in rec.snapshots])
print(f"{'depth [um]':>10s}" + "".join(f"{n:>20s}" for n in names))
for sn, row in zip(rec.snapshots, table, strict=True):
    print(f"{to_um(sn.depth):10.2f}" + "".join(f"{v:20d}" for v in row))

# %% [markdown]
# ## Side views (Fig. 1) and the bond network (Fig. 6)
# Particles projected on the x-z plane (AM coloured by diameter, CB grey), and bond segments
# from `analysis.render.bond_segments` (intact blue, failed in tension red, in shear orange,
# touching pairs that were never bonded light grey) at the first and last snapshot.

# %%
first, last = rec.snapshots[0], rec.snapshots[-1]
fig, axes = plt.subplots(1, 4, figsize=(15, 4.6), sharey=True)
am = rec.config.material_names.index("AM")
for ax, sn in zip(axes[:2], (first, last), strict=True):
    order = np.argsort(sn.position[:, 1])  # back to front
    for i in order:
        colour = plt.cm.viridis((2 * sn.radius[i] - 4e-6) / 8e-6) if sn.material[i] == am \
            else "0.6"
        ax.add_patch(plt.Circle((to_um(sn.position[i, 0]), to_um(sn.position[i, 2])),
                                to_um(sn.radius[i]), color=colour, ec="k", lw=0.2))
    ax.axhline(to_um(sn.z_top), color="k", lw=2)
    ax.axhline(to_um(sn.z_bottom), color="k", lw=2)
    ax.set_title(f"particles at {to_um(sn.depth):.1f} um ({len(sn.radius)})", fontsize=9)
for ax, sn in zip(axes[2:], (first, last), strict=True):
    seg = bond_segments(rec, sn)
    for name, sg in seg.items():
        colour = "0.8" if name == "contact, never bonded" else BOND_COLOURS[name]
        ax.add_collection(LineCollection(to_um(sg[:, :, [0, 2]]), colors=colour, lw=0.8))
        ax.plot([], [], color=colour, label=f"{name} ({len(sg)})")
    ax.axhline(to_um(sn.z_top), color="k", lw=2)
    ax.axhline(to_um(sn.z_bottom), color="k", lw=2)
    ax.legend(fontsize=7, loc="upper right")
    ax.set_title(f"bond network at {to_um(sn.depth):.1f} um", fontsize=9)
for ax in axes:
    ax.set_xlim(-5, to_um(rec.cell_x) + 5)
    ax.set_aspect("equal")
    ax.set_xlabel("x [um]")
axes[0].set_ylabel("z [um]")
axes[0].set_ylim(to_um(first.z_bottom) - 5, to_um(first.z_top) + 5)
fig.tight_layout()
show_figure(fig, OUT / "side_views_bonds.png")

# %% [markdown]
# ## Particle-scale normal force against AM diameter (Fig. 7)
# `snapshots/<k>/normal_force` is the total contact normal force on each particle.

# %%
later = [sn for sn in rec.snapshots if sn.depth > 0]
fig, axes = plt.subplots(1, len(later), figsize=(4 * len(later), 3.5), sharey=True)
for ax, sn in zip(np.atleast_1d(axes), later, strict=True):
    sel = sn.material == am
    frag = sel & (sn.parent_id >= 0)
    ax.scatter(to_um(2 * sn.radius[sel & ~frag]), 1e3 * sn.normal_force[sel & ~frag], s=10,
               label="original AM")
    ax.scatter(to_um(2 * sn.radius[frag]), 1e3 * sn.normal_force[frag], s=10, marker="x",
               label="fragments")
    ax.set_xlabel("AM diameter [um]")
    ax.set_title(f"{to_um(sn.depth):.1f} um", fontsize=9)
np.atleast_1d(axes)[0].set_ylabel("total contact normal force [mN]")
np.atleast_1d(axes)[0].legend(fontsize=8)
fig.tight_layout()
show_figure(fig, OUT / "force_vs_diameter.png")
sn = rec.snapshots[-1]
sel = sn.material == am
n_frag = int((sn.parent_id[sel] >= 0).sum())
print(f"at {to_um(sn.depth):.1f} um: {int(sel.sum())} AM particles ({n_frag} fragments), "
      f"largest particle normal force {1e3 * sn.normal_force[sel].max():.2f} mN")
