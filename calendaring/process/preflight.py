"""Pre-flight estimate of a calendering run: particles, pool slots, memory, steps and wall
time from the configuration alone, before anything is allocated (host only).

``calendaring run`` and ``calendaring pack`` print the estimate and refuse to start a run
that would not fit the machine: memory beyond what the machine has available (CPU
backend), more than :data:`MAX_STEPS` time steps, or an estimated wall time beyond
``--max-hours``. The refusal is a :class:`ResourceError` (a user error: exit 2) that names
the estimate, its inputs and the limit.

How the figures are made:

- particles per material from the coating mass balance (the recipe of
  :func:`calendaring.process.electrode.recipe`), with ``E[d^3]`` from 4,096 diameters drawn from
  the size distribution with a fixed seed;
- pool slots: ``breakage.pool_capacity``, or the worst case of
  :func:`calendaring.engine.breakage.worst_case_slots` scaled from the same draw;
- memory: :data:`FIXED_BYTES` + slots x (:data:`SLOT_BYTES` + 1.5 x
  ``numerics.pairs_per_particle`` x :data:`PAIR_BYTES`) + the hashed grid. The per-slot
  and per-pair figures were measured on the CPU backend (3 Dec 2026): the Taichi fields a
  ``Simulation`` declares per slot sum to ~410 B, and the resident memory grew by 210 B per
  candidate-pair slot between ``pairs_per_particle`` = 12 and 48 at 80,000 slots; 1.5 is
  the pair table's growth factor; the fixed part allows for the Taichi runtime and the
  host copies;
- steps: the build stages (settling, pre-compaction over at most the domain height,
  relaxation) at the build time step, the stroke at the run time step (``dt`` =
  ``numerics.timestep_fraction`` x the smallest Rayleigh time of the size distributions'
  lower bounds, or ``breakage.fragment_timestep_fraction`` x that of the smallest fragment
  if less) and
  plate speed (:func:`calendaring.process.run.plate_speed`), and the unloading if asked for;
- wall time: particle-steps over :data:`RATE_PER_THREAD` x threads, the calendering rate
  of the production run measured by ``benchmarks/bench_production.py`` on one thread
  (0.8-1.2e6 particle-steps/s, 2 Dec 2026), with perfect scaling over threads. The build
  stages count at their upper bounds (pre-compaction from the top of the domain), so for a
  run from a packed bed the figure errs high (a 100 um sweep-preset run: estimated 30 min,
  measured 13.5 min on one thread); it is a guard against runs that cannot finish, not a
  schedule.

See also: :mod:`calendaring.engine.timestep` (the Rayleigh times),
:mod:`calendaring.process.run` (the stages estimated), :mod:`calendaring.cli` (prints the
estimate).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from calendaring.core.config import SimConfig, available_cores
from calendaring.core.errors import ConfigError

FIXED_BYTES = 0.5e9
SLOT_BYTES = 410.0
PAIR_BYTES = 210.0
PAIR_GROWTH = 1.5
GRID_BYTES_PER_CELL = 16.0
RATE_PER_THREAD = 1.0e6  # particle-steps per second and thread (production run, CPU)
MAX_STEPS = 1e10
DEFAULT_MAX_HOURS = 720.0  # 30 days
SAMPLE = 4096


class ResourceError(ConfigError):
    """A run that would not fit the machine: names the estimate, its inputs and the limit."""

    def __init__(self, what: str, estimate: str, limit: str, why: str) -> None:
        self.key, self.value, self.allowed = what, estimate, limit
        ValueError.__init__(self, f"{what}: the run would need {estimate} ({why}); "
                                  f"allowed {limit}")

    def with_prefix(self, prefix: str) -> ResourceError:
        return self


@dataclass
class Estimate:
    """What a run will need (see the module docstring for how each figure is made)."""

    particles: dict[str, float]  # per material
    pool_slots: float
    memory_bytes: float
    steps: dict[str, float] = field(default_factory=dict)  # per stage
    dt: float = 0.0  # run time step [s]
    plate_speed: float = 0.0  # [m/s]
    threads: int = 1
    wall_seconds: float = 0.0

    @property
    def n_particles(self) -> float:
        return float(sum(self.particles.values()))

    @property
    def total_steps(self) -> float:
        return float(sum(self.steps.values()))

    def line(self) -> str:
        """One line for the run's log."""
        h = self.wall_seconds / 3600
        wall = f"{h:.1f} h" if h >= 1 else f"{self.wall_seconds / 60:.0f} min"
        return (f"estimate: {self.n_particles:,.0f} particles, pool {self.pool_slots:,.0f} "
                f"slots, ~{self.memory_bytes / 1e9:.2f} GB, {self.total_steps:.3g} steps "
                f"(calendering {self.steps.get('calender', 0):.3g}), ~{wall} on "
                f"{self.threads} thread{'s' if self.threads != 1 else ''}")


def _threads(cfg: SimConfig) -> int:
    return cfg.numerics.threads or available_cores()


def estimate(cfg: SimConfig) -> Estimate:
    """The estimate of a run of ``cfg`` (configuration only; nothing allocated)."""
    from calendaring.engine.breakage import breakable_mask, breakage_enabled, worst_case_slots
    from calendaring.engine.timestep import fragment_timestep, rayleigh_time
    from calendaring.process.electrode import diameter_bounds, sample_diameters
    from calendaring.process.run import plate_speed, settle_fall_time

    el, dom, num = cfg.electrode, cfg.domain, cfg.numerics
    names = cfg.material_names
    rng = np.random.default_rng(0)
    area = dom.cell_x * dom.cell_y
    total_mass = el.coating_density * area * el.thickness
    counts, draws = {}, {}
    for name, w in el.composition.items():
        if w <= 0 or name not in el.sizes:
            continue
        d = sample_diameters(el.sizes[name], rng, SAMPLE)
        rho = cfg.materials[name].density
        counts[name] = w * total_mass / (rho * math.pi / 6 * float(np.mean(d**3)))
        draws[name] = d
    n = sum(counts.values())
    slots = n
    breaks = breakage_enabled(cfg)
    brk = breakable_mask(cfg) if breaks else None
    if breaks:
        if cfg.breakage.pool_capacity:
            slots = max(float(cfg.breakage.pool_capacity), n)
        else:
            extra = 0.0
            for name, d in draws.items():
                if brk[names.index(name)]:
                    per = (worst_case_slots(d, np.ones(len(d), bool), cfg.breakage)
                           - len(d)) / len(d)
                    extra += per * counts[name]
            slots = n + extra
    d_cell = max((diameter_bounds(s)[1] for s in el.sizes.values()), default=1e-6)
    reach = d_cell + num.skin
    grid = (dom.cell_x / reach + 1) * (dom.cell_y / reach + 1) * (dom.height / reach + 1)
    memory = (FIXED_BYTES + slots * (SLOT_BYTES + PAIR_GROWTH * num.pairs_per_particle
                                     * PAIR_BYTES) + GRID_BYTES_PER_CELL * grid)

    # time steps: the smallest Rayleigh time over the sizes (and fragments) of the run
    # (as Simulation.compute_timestep: fragments at breakage.fragment_timestep_fraction)
    t_r = [num.timestep_fraction * rayleigh_time(0.5 * diameter_bounds(size)[0],
                                                 cfg.materials[name], num.density_scaling)
           for name, size in el.sizes.items() if name in cfg.materials]
    if breaks:
        t_r += [fragment_timestep(cfg.breakage, cfg.materials[name], num.density_scaling)
                for k, name in enumerate(names) if brk[k]]
    dt = min(t_r) if t_r else math.inf
    dt_build = dt * cfg.build.timestep_fraction / num.timestep_fraction
    steps: dict[str, float] = {}
    b = cfg.build
    if not el.packing:
        steps["settle"] = b.settle_time_factor * settle_fall_time(cfg) / dt_build
    steps["precompact"] = max(dom.height - el.thickness, 0.0) / (b.plate_speed * dt_build)
    steps["relax"] = b.relax_time / dt_build
    # plate speed from a draw with the materials in their proportions
    mix, rho = [], []
    for name, d in draws.items():
        k = max(1, round(SAMPLE * counts[name] / n)) if n > 0 else 1
        mix.append(d[:k])
        rho.append(np.full(len(d[:k]), cfg.materials[name].density * num.density_scaling))
    v = (plate_speed(cfg, np.concatenate(mix), np.concatenate(rho)) if mix
         else cfg.protocol.plate_speed)
    steps["calender"] = cfg.protocol.stroke / (v * dt) if v > 0 else math.inf
    if cfg.protocol.unload:
        vu = cfg.protocol.unload_speed or v
        steps["unload"] = cfg.protocol.stroke / (vu * dt) if vu > 0 else math.inf
    threads = _threads(cfg)
    particle_steps = n * sum(steps.values())
    return Estimate(particles=counts, pool_slots=slots, memory_bytes=memory, steps=steps,
                    dt=dt, plate_speed=v, threads=threads,
                    wall_seconds=particle_steps / (RATE_PER_THREAD * threads))


def available_memory() -> float:
    """Bytes of memory available to a new process (Linux MemAvailable, else physical)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return math.inf


def check(cfg: SimConfig, max_hours: float = DEFAULT_MAX_HOURS,
          memory: float | None = None) -> Estimate:
    """The estimate of ``cfg``; raises :class:`ResourceError` if the run would not fit."""
    est = estimate(cfg)
    d, el = cfg.domain, cfg.electrode
    inputs = (f"{est.n_particles:.3g} particles in a {d.cell_x:.3g} x {d.cell_y:.3g} m cell "
              f"of thickness {el.thickness:.3g} m, {est.pool_slots:.3g} pool slots")
    if cfg.numerics.arch == "cpu":
        have = available_memory() if memory is None else memory
        if est.memory_bytes > have:
            raise ResourceError("memory", f"~{est.memory_bytes / 1e9:.3g} GB", f"<= "
                                f"{have / 1e9:.3g} GB available on this machine", inputs)
    steps = est.total_steps
    why = (f"dt = {est.dt:.3g} s (numerics.timestep_fraction x the smallest Rayleigh time), "
           f"plate speed {est.plate_speed:.3g} m/s over protocol.stroke = "
           f"{cfg.protocol.stroke:.3g} m; stages "
           + ", ".join(f"{k} {v:.3g}" for k, v in est.steps.items()))
    if not steps <= MAX_STEPS:
        raise ResourceError("time steps", f"{steps:.3g} steps", f"<= {MAX_STEPS:.0e}", why)
    if not est.wall_seconds <= max_hours * 3600:
        raise ResourceError("wall time", f"~{est.wall_seconds / 3600:.3g} h on "
                            f"{est.threads} threads", f"<= --max-hours = {max_hours:g} h",
                            f"{inputs}; {steps:.3g} steps")
    return est


__all__ = ["DEFAULT_MAX_HOURS", "Estimate", "ResourceError", "available_memory", "check",
           "estimate"]
