# ---
# jupyter:
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 00 Quickstart: one calendering run from Python
#
# **Purpose.** The shortest path through the engine: build and calender the `tiny` preset
# (a 25 x 25 um cell, 25 um coating, 6.5 um stroke, Tavares breakage on) from Python, read
# the run file back with `calendaring.process.runfile.read_run`, plot the pressure-depth curve and
# print a summary.
#
# **Inputs.** None (the preset ships with the package). Outputs go to
# `notebooks/_out/00_quickstart/` (or `$CALENDARING_NOTEBOOK_OUT/00_quickstart/`).
#
# **Expected run time.** Under 1 minute on 2 CPU cores (26 s measured on a 2-core machine
# shared with a sweep; the `tiny` run is most of it, up to 2 minutes under heavier load).
# The tiny preset is a test configuration, not physics.

# %%
import json
import time

import matplotlib.pyplot as plt
import numpy as np

import calendaring
from calendaring import (
    load_preset,
    notebook_output,
    read_run,
    run,
    show_figure,
    summary,
    to_mpa,
    to_um,
)

OUT = notebook_output("00_quickstart")
print(f"calendaring {calendaring.__version__}; outputs in {OUT}")

# %% [markdown]
# ## Run the `tiny` preset
# `load_preset` returns the frozen, validated configuration (SI units); `run` builds the
# electrode, bonds it, calenders it and writes the HDF5 run file atomically.

# %%
cfg = load_preset("tiny")
print(f"cell {to_um(cfg.domain.cell_x):g} x {to_um(cfg.domain.cell_y):g} um, coating "
      f"{to_um(cfg.electrode.thickness):g} um, stroke {to_um(cfg.protocol.stroke):g} um, "
      f"plate speed {cfg.protocol.plate_speed:g} m/s, breakage {cfg.breakage.enabled}")

run_file = OUT / "tiny.h5"
run_file.unlink(missing_ok=True)
t0 = time.perf_counter()
run(cfg, run_file, progress=False, preset="tiny")
print(f"wrote {run_file} in {time.perf_counter() - t0:.1f} s")

# %% [markdown]
# ## Read it back
# `read_run` validates the file (format, schema version, config hash, units of every
# dataset) and returns a typed `RunRecord` in SI units.

# %%
rec = read_run(run_file)
p = rec.pressure
print(f"{len(p['depth'])} pressure samples, {len(rec.series['depth'])} series rows, "
      f"{len(rec.snapshots)} snapshots at "
      f"{[round(to_um(s.depth), 2) for s in rec.snapshots]} um, "
      f"{len(rec.breakage['parent_id'])} breakage events")

# %%
fig, ax = plt.subplots(figsize=(6, 4))
ax.plot(to_um(p["depth"]), to_mpa(p["value"]), lw=0.8, label="top plate (per step)")
ax.plot(to_um(rec.series["depth"]), to_mpa(rec.series["bottom_pressure"]), "--",
        label="bottom plate (row mean)")
ev = rec.breakage["depth"]
ax.plot(to_um(ev), np.interp(to_um(ev), to_um(p["depth"]), to_mpa(p["value"])), "rx", ms=4,
        label="breakage events")
ax.set_xlabel("calendering depth [um]")
ax.set_ylabel("pressure [MPa]")
ax.set_title(f"tiny preset, seed {rec.seed}")
ax.legend(fontsize=8)
fig.tight_layout()
show_figure(fig, OUT / "pressure_depth.png")

# %% [markdown]
# ## Summary
# `calendaring.cli.summary` is what `calendaring inspect` prints (SI values); the
# pressures are shown here in MPa.

# %%
s = summary(rec)
print(f"counts: {s['counts']}, porosity at h0 {100 * s['porosity_at_thickness']:.2f} %, "
      f"final porosity {100 * s['final_porosity']:.2f} %")
print(f"dt {s['dt']:.3e} s, plate speed {s['plate_speed']:g} m/s, bonds created "
      f"{s['bonds_created']}, intact at the end {s['bonds_intact_final']}")
for depth, value in s["pressure_at"].items():
    print(f"pressure at {depth}: {to_mpa(value):.1f} MPa")
print(f"peak pressure {to_mpa(s['peak_pressure']):.1f} MPa; {s['breakage_events']} breakage "
      f"events, {s['fragments']} fragments; wall time of the run {s['wall_seconds']:.1f} s")
(OUT / "summary.json").write_text(json.dumps(s, indent=1, default=str))
