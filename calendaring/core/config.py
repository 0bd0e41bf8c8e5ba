"""Simulation configuration: frozen dataclasses loaded strictly from TOML or dicts.

Host-only module: it imports neither taichi nor torch. Every value is SI. An unknown key,
a wrong type or an out-of-range value raises :class:`~calendaring.core.errors.ConfigError`
naming the dotted key, the value and the allowed range.

Defaults are the paper's (Chen et al., Tables 1 and 4) as resolved in the physics
specification (``physics-spec.md`` sections 1, 2, 3 and 6). Choices the paper leaves
open are marked ``[A]`` in the field comments; each is a named key so it can be switched
and is recorded in every run file through the config JSON.

Example:
    >>> cfg = load_config_dict({"numerics": {"timestep_fraction": 0.02}})
    >>> cfg.numerics.timestep_fraction
    0.02

See also: :mod:`calendaring.engine.simulation` (what the configuration drives),
:mod:`calendaring.process.runfile` (the config JSON kept in every run file).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import tomllib
import types
import typing
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from calendaring.core.errors import ConfigError

ADHESION_MODES = ("surface_energy_ap", "jkr_R", "direct_kadh")
DAMPING_MODES = ("tangent_sqrt56", "literal_k1")
ARCHES = ("cpu", "cuda", "auto")
PRECISIONS = ("f64",)


FLOAT_LIMIT = 1e30  # no SI quantity of a calendering run comes near: beyond it is a typo
INT_LIMIT = 2**62  # every integer key fits a 64-bit device integer with room to add
SEED_MAX = 2**32 - 1  # numerics.seed seeds NumPy's generators: an unsigned 32-bit value
THREADS_MAX = 4096


def available_cores() -> int:
    """The cores this process may run on: its CPU affinity (``taskset``, a batch system's
    cpuset, a pinned test worker), else every core of the machine. ``numerics.threads = 0``
    means this many."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # no affinity interface (macOS, Windows)
        return os.cpu_count() or 1


def _check(key: str, value: float, ok: bool, allowed: str) -> None:
    if not ok or (isinstance(value, float) and math.isnan(value)):
        raise ConfigError(key, value, allowed)


@dataclass(frozen=True, slots=True, kw_only=True)
class MaterialConfig:
    """Elastic solid (paper Table 1). SI units."""

    density: float  # rho [kg m^-3]
    youngs_modulus: float  # E [Pa]
    poisson_ratio: float  # nu [-], -1 < nu < 0.5
    breakable: bool = False  # particles of this material may break (breakage issue)

    def __post_init__(self) -> None:
        _check("density", self.density, self.density > 0, "> 0 kg/m^3")
        _check("youngs_modulus", self.youngs_modulus, self.youngs_modulus > 0, "> 0 Pa")
        _check(
            "poisson_ratio", self.poisson_ratio, -1.0 < self.poisson_ratio < 0.5, "in (-1, 0.5)"
        )

    @property
    def shear_modulus(self) -> float:
        """G = E / (2 (1 + nu)) [Pa]."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))


@dataclass(frozen=True, slots=True, kw_only=True)
class PairConfig:
    """Contact parameters of one pair of materials (EEPA + friction + rolling). SI units."""

    plasticity_ratio: float  # lambda_p = 1 - k1/k2 [-], 0 <= lambda_p < 1 (0 -> Hertz)
    surface_energy: float = 0.0  # Delta gamma [J m^-2], >= 0 (0 -> no adhesion)
    restitution: float = 0.25  # e [-], 0 < e <= 1 (paper: 0.25 for all pairs)
    friction: float = 0.12  # mu_s [-], >= 0 (paper: 0.12)
    rolling_friction: float = 0.01  # mu_r [-], >= 0 (paper: 0.01)
    pull_off_force: float = 0.0  # f0 [N], <= 0 (EEPA constant pull-off; [A] 0)
    adhesion_stiffness: float = 0.0  # k_adh [N m^-chi], used only by adhesion_mode direct_kadh

    def __post_init__(self) -> None:
        _check(
            "plasticity_ratio",
            self.plasticity_ratio,
            0.0 <= self.plasticity_ratio < 1.0,
            "in [0, 1)",
        )
        _check("surface_energy", self.surface_energy, self.surface_energy >= 0, ">= 0 J/m^2")
        _check("restitution", self.restitution, 0.0 < self.restitution <= 1.0, "in (0, 1]")
        _check("friction", self.friction, self.friction >= 0, ">= 0")
        _check("rolling_friction", self.rolling_friction, self.rolling_friction >= 0, ">= 0")
        _check("pull_off_force", self.pull_off_force, self.pull_off_force <= 0, "<= 0 N")
        _check(
            "adhesion_stiffness", self.adhesion_stiffness, self.adhesion_stiffness >= 0, ">= 0"
        )


def _paper_materials() -> dict[str, MaterialConfig]:
    # Paper Table 1: NMC622 active material (AM) and carbon black (CB).
    return {
        "AM": MaterialConfig(
            density=4740.0, youngs_modulus=168.30e9, poisson_ratio=0.246, breakable=True
        ),
        "CB": MaterialConfig(density=2200.0, youngs_modulus=0.65e9, poisson_ratio=0.200),
    }


def _paper_pairs() -> dict[str, PairConfig]:
    # Plasticity ratios and surface energies: Schreiner et al. 2020, quoted by the paper.
    return {
        "AM-AM": PairConfig(plasticity_ratio=0.8, surface_energy=5.0),
        "AM-CB": PairConfig(plasticity_ratio=0.9, surface_energy=20.0),
        "CB-CB": PairConfig(plasticity_ratio=0.975, surface_energy=60.0),
    }


def _paper_plate_pairs() -> dict[str, PairConfig]:
    # [A] spec section 6: the particle's own-pair plasticity ratio, no adhesion.
    return {
        "AM": PairConfig(plasticity_ratio=0.8, surface_energy=0.0),
        "CB": PairConfig(plasticity_ratio=0.975, surface_energy=0.0),
    }


@dataclass(frozen=True, slots=True, kw_only=True)
class PlatesConfig:
    """The two calendering plates (paper: steel roll on top, aluminium foil below)."""

    top: MaterialConfig = field(
        default_factory=lambda: MaterialConfig(
            density=7900.0, youngs_modulus=208e9, poisson_ratio=0.3
        )
    )
    bottom: MaterialConfig = field(
        default_factory=lambda: MaterialConfig(
            density=2700.0, youngs_modulus=69e9, poisson_ratio=0.3
        )
    )


@dataclass(frozen=True, slots=True, kw_only=True)
class ContactConfig:
    """EEPA normal law, tangential spring and rolling resistance (spec sections 2-3)."""

    loading_exponent: float = 1.5  # n [-]: 1 (linear EEPA) or 1.5 (Hertzian EEPA)
    adhesive_exponent: float = 1.5  # chi [-] of the adhesive branch ([A] chi = n)
    tangential_stiffness_ratio: float = 2.0 / 3.0  # xi_t [-], k_t = xi_t 8 G* sqrt(R* delta)
    adhesion_mode: str = "surface_energy_ap"  # [A] Delta gamma -> k_adh map, spec 2.3
    damping_mode: str = "tangent_sqrt56"  # [A] normal damping form, spec 2.4
    pairs: dict[str, PairConfig] = field(default_factory=_paper_pairs)  # keys "A-B"
    plate_pairs: dict[str, PairConfig] = field(default_factory=_paper_plate_pairs)  # keys "A"

    def __post_init__(self) -> None:
        n = self.loading_exponent
        _check("loading_exponent", n, n in (1.0, 1.5), "1.0 or 1.5")
        chi = self.adhesive_exponent
        _check("adhesive_exponent", chi, 1.0 <= chi <= 2.0, "in [1, 2]")
        xi = self.tangential_stiffness_ratio
        _check("tangential_stiffness_ratio", xi, 0.0 < xi <= 2.0, "in (0, 2]")
        _check("adhesion_mode", self.adhesion_mode, self.adhesion_mode in ADHESION_MODES,
               f"one of {ADHESION_MODES}")
        _check("damping_mode", self.damping_mode, self.damping_mode in DAMPING_MODES,
               f"one of {DAMPING_MODES}")


@dataclass(frozen=True, slots=True, kw_only=True)
class DomainConfig:
    """Periodic cell (x, y) bounded in z by the plates. SI units."""

    cell_x: float = 100e-6  # periodic length along x [m]
    cell_y: float = 100e-6  # periodic length along y [m]
    height: float = 200e-6  # z extent of the domain above the bottom plate [m]
    gravity: float = 9.81  # magnitude of gravitational acceleration along -z [m s^-2]

    def __post_init__(self) -> None:
        _check("cell_x", self.cell_x, self.cell_x > 0, "> 0 m")
        _check("cell_y", self.cell_y, self.cell_y > 0, "> 0 m")
        _check("height", self.height, self.height > 0, "> 0 m")
        _check("gravity", self.gravity, self.gravity >= 0, ">= 0 m/s^2")


@dataclass(frozen=True, slots=True, kw_only=True)
class NumericsConfig:
    """Backend, time step and safety limits."""

    arch: str = "cpu"  # Taichi backend: cpu, cuda or auto
    precision: str = "f64"  # floating-point precision of the state (f64 only, see README)
    threads: int = 0  # CPU threads (0 = every core this process may use)
    seed: int = 0  # random seed of the run
    timestep_fraction: float = 0.04  # dt / Rayleigh time of the smallest particle [-]
    density_scaling: float = 1.0  # mass scaling factor s (rho -> s rho) [-]; recorded in outputs
    skin: float = 0.3e-6  # Verlet skin [m]
    rebuild_check_interval: int = 10  # steps between host checks of the device flags
    steps_per_launch: int = 1024  # CPU: most steps per kernel launch (1 = one launch per step)
    max_overlap_fraction: float = 0.5  # stop if overlap > this x smaller radius [-]
    pairs_per_particle: int = 12  # initial candidate-pair capacity per particle slot
    # re-store the particles along the space-filling curve (dead slots dropped) at the end
    # of the replacement step where the slots appended since the last sort (fragments)
    # reach this fraction of the slots sorted then (0 = never)
    resort_fraction: float = 0.1
    track_energy: bool = True  # accumulate the energy ledger every step
    offline_cache: bool = True  # keep compiled kernels on disk

    def __post_init__(self) -> None:
        _check("arch", self.arch, self.arch in ARCHES, f"one of {ARCHES}")
        _check("precision", self.precision, self.precision in PRECISIONS,
               f"one of {PRECISIONS} (f32 needs an f64 parity test first)")
        _check("threads", self.threads, 0 <= self.threads <= THREADS_MAX,
               f"in [0, {THREADS_MAX}] (0 = all cores)")
        _check("seed", self.seed, 0 <= self.seed <= SEED_MAX, f"an integer in [0, {SEED_MAX}]")
        f = self.timestep_fraction
        _check("timestep_fraction", f, 0.0 < f <= 0.3, "in (0, 0.3]")
        s = self.density_scaling
        _check("density_scaling", s, 1.0 <= s <= 1e8, "in [1, 1e8]")
        _check("skin", self.skin, self.skin > 0, "> 0 m")
        k = self.rebuild_check_interval
        _check("rebuild_check_interval", k, 1 <= k <= 1000, "in [1, 1000]")
        n = self.steps_per_launch
        _check("steps_per_launch", n, 1 <= n <= 4096, "in [1, 4096]")
        o = self.max_overlap_fraction
        _check("max_overlap_fraction", o, 0.0 < o <= 2.0, "in (0, 2]")
        p = self.pairs_per_particle
        _check("pairs_per_particle", p, 1 <= p <= 1000, "in [1, 1000]")
        r = self.resort_fraction
        _check("resort_fraction", r, 0.0 <= r <= 10.0, "in [0, 10] (0 = never)")


SIZE_DISTRIBUTIONS = ("constant", "normal", "lognormal", "table")
TABLE_BASES = ("number", "volume")
BOND_CRITERIA = ("tension", "abs")


@dataclass(frozen=True, slots=True, kw_only=True)
class SizeConfig:
    """Sphere-diameter distribution of one material. SI units.

    ``normal`` and ``lognormal`` take the mean and standard deviation of the diameter and are
    truncated to [``min``, ``max``] by resampling; ``table`` reads a CSV file with columns
    ``diameter_m,fraction`` (fractions by number or by volume, ``table_basis``).
    """

    distribution: str = "constant"  # constant | normal | lognormal | table
    mean: float = 3.0e-6  # mean diameter [m] (the diameter of a constant distribution)
    std: float = 0.0  # standard deviation of the diameter [m]
    min: float = 0.0  # smallest diameter kept [m] (0 = mean - 4 std, at least mean/10)
    max: float = 0.0  # largest diameter kept [m] (0 = mean + 4 std)
    table: str = ""  # CSV file for distribution = "table"
    table_basis: str = "number"  # the table's fractions: by number or by volume

    def __post_init__(self) -> None:
        _check("distribution", self.distribution, self.distribution in SIZE_DISTRIBUTIONS,
               f"one of {SIZE_DISTRIBUTIONS}")
        _check("mean", self.mean, self.mean > 0, "> 0 m")
        _check("std", self.std, self.std >= 0, ">= 0 m")
        _check("min", self.min, 0 <= self.min <= self.mean or self.distribution == "table",
               f"in [0, mean = {self.mean}] m")
        _check("max", self.max, self.max == 0 or self.max >= self.mean
               or self.distribution == "table", f"0 (automatic) or >= mean = {self.mean} m")
        if self.distribution in ("normal", "lognormal"):
            _check("std", self.std, self.std > 0, f"> 0 m for a {self.distribution} distribution")
        if self.distribution == "table":
            _check("table", self.table, bool(self.table), "a CSV path (diameter_m,fraction)")
        _check("table_basis", self.table_basis, self.table_basis in TABLE_BASES,
               f"one of {TABLE_BASES}")

    @property
    def bounds(self) -> tuple[float, float]:
        """(smallest, largest) diameter that can be drawn [m] (table: from the file)."""
        if self.distribution == "constant":
            return self.mean, self.mean
        lo = self.min if self.min > 0 else max(self.mean - 4 * self.std, 0.1 * self.mean)
        hi = self.max if self.max > 0 else self.mean + 4 * self.std
        return lo, hi


def _paper_sizes() -> dict[str, SizeConfig]:
    # Paper section 2.1: AM ~ N(7.74, 1.35) um observed in [4.94, 10.69] um; CB 3 um.
    return {
        "AM": SizeConfig(distribution="normal", mean=7.74e-6, std=1.35e-6, min=4.94e-6,
                         max=10.69e-6),
        "CB": SizeConfig(distribution="constant", mean=3.0e-6),
    }


@dataclass(frozen=True, slots=True, kw_only=True)
class ElectrodeConfig:
    """The coating to build (paper section 2.1): composition by mass sets the particle counts."""

    thickness: float = 75e-6  # coating thickness before calendering, h0 [m]
    coating_density: float = 2560.0  # coating (bulk) density at h0 [kg m^-3]
    composition: dict[str, float] = field(
        default_factory=lambda: {"AM": 0.94, "CB": 0.06})  # mass fractions, sum 1
    sizes: dict[str, SizeConfig] = field(default_factory=_paper_sizes)
    packing: str = ""  # start from this packing (CSV or LAMMPS data) instead of building

    def __post_init__(self) -> None:
        _check("thickness", self.thickness, self.thickness > 0, "> 0 m")
        _check("coating_density", self.coating_density, self.coating_density > 0, "> 0 kg/m^3")
        for k, w in self.composition.items():
            _check(f"composition.{k}", w, 0.0 <= w <= 1.0, "a mass fraction in [0, 1]")
        total = sum(self.composition.values())
        _check("composition", dict(self.composition), abs(total - 1.0) <= 1e-6,
               f"mass fractions summing to 1 (100 %), got {total:.6g}")


@dataclass(frozen=True, slots=True, kw_only=True)
class BuildConfig:
    """How the loose bed is made before calendering ([A]; recorded in every run file).

    Real gravity would need milliseconds of settling (1e7 steps), so the settling stage uses
    an amplified body force and an initial downward velocity, at a coarser time step; the bed
    is then pre-compacted by the top plate to the coating thickness and relaxed.
    """

    settle_acceleration: float = 1.0e5  # body force during settling [m s^-2] (replaces g)
    settle_velocity: float = 1.0  # initial downward velocity of every particle [m s^-1]
    settle_time_factor: float = 1.5  # settling time / free-fall time over the domain [-]
    plate_speed: float = 2.0  # pre-compaction speed of the top plate [m s^-1]
    relax_time: float = 5.0e-6  # plate held at h0, real gravity [s]
    timestep_fraction: float = 0.2  # dt / Rayleigh time during the build stages [-]
    max_insert_tries: int = 500  # random-insertion attempts per sphere

    def __post_init__(self) -> None:
        _check("settle_acceleration", self.settle_acceleration, self.settle_acceleration >= 0,
               ">= 0 m/s^2")
        _check("settle_velocity", self.settle_velocity, self.settle_velocity >= 0, ">= 0 m/s")
        _check("settle_time_factor", self.settle_time_factor, 0 < self.settle_time_factor <= 20,
               "in (0, 20]")
        _check("plate_speed", self.plate_speed, self.plate_speed > 0, "> 0 m/s")
        _check("relax_time", self.relax_time, self.relax_time >= 0, ">= 0 s")
        f = self.timestep_fraction
        _check("timestep_fraction", f, 0.0 < f <= 0.3, "in (0, 0.3]")
        _check("max_insert_tries", self.max_insert_tries, self.max_insert_tries >= 1, ">= 1")


@dataclass(frozen=True, slots=True, kw_only=True)
class BondsConfig:
    """Carbon-black virtual bonds (Potyondy-Cundall parallel bonds, spec section 4)."""

    enabled: bool = True
    materials: list[str] = field(default_factory=lambda: ["CB"])  # a bond needs one of these
    radius_ratio: float = 1.5  # xi_b: bond if |x_A - x_B| <= xi_b (R_A + R_B) [-]
    disk_scale: float = 1.0  # lambda_b: R_b = lambda_b min(R_A, R_B) [-] ([A] 1)
    normal_stiffness: float = 3.5e13  # S_n [N m^-3]
    shear_stiffness: float = 3.5e13  # S_t [N m^-3] ([A] = S_n)
    normal_strength: float = 5.0e7  # sigma_c [Pa]
    shear_strength: float = 5.0e7  # tau_c [Pa] ([A] = sigma_c)
    normal_criterion: str = "tension"  # tension (P&C, EDEM) or abs (paper Eq. 28 literal)

    def __post_init__(self) -> None:
        _check("radius_ratio", self.radius_ratio, 1.0 <= self.radius_ratio <= 3.0, "in [1, 3]")
        _check("disk_scale", self.disk_scale, 0.0 < self.disk_scale <= 1.0, "in (0, 1]")
        for key in ("normal_stiffness", "shear_stiffness", "normal_strength", "shear_strength"):
            v = getattr(self, key)
            _check(key, v, v > 0, "> 0")
        _check("normal_criterion", self.normal_criterion,
               self.normal_criterion in BOND_CRITERIA, f"one of {BOND_CRITERIA}")


TRUNCATION_MODES = ("ratio", "percentile", "complement")
SIBLING_INITS = ("force_free", "fresh")
EVENT_END_RULES = ("quiet", "release")


@dataclass(frozen=True, slots=True, kw_only=True)
class BreakageConfig:
    """Tavares UFRJ breakage of the breakable materials (paper 2.2, spec section 5). SI units.

    The first eight keys are the paper's calibration parameters (Table 2), defaults from its
    Table 4; percentages are given in percent as in the paper. The rest are [A] choices of
    the physics specification (sections 5.4-5.10 and 6).
    """

    enabled: bool = True  # false = the no-breakage control (paper R0); --no-breakage
    damage_constant: float = 5.549  # gamma [-] (damage law, Eq. 36)
    e_inf: float = 2161.0  # E_inf [J/kg] (size effect, Eq. 33)
    d0: float = 9.396e-6  # d0 [m] (size effect, Eq. 33)
    phi: float = 2.587  # phi [-] (size effect, Eq. 33)
    sigma_e: float = 0.947  # sigma_E [-]: std of ln E* (Eq. 31)
    alpha_percentage: float = 34.274  # A [%]: largest t10 (Eq. 39)
    b_prime: float = 0.030  # b' [-]: t10 slope (Eq. 39)
    truncation_ratio: float = 89.928  # R_t [%] (Eq. 31 upper truncation)
    truncation_mode: str = "ratio"  # [A] E_max = R_t E50 | percentile | complement (spec 10.1)
    device_youngs_modulus: float = 208e9  # [A] surface the fracture energies were measured on
    device_poisson_ratio: float = 0.3  # (steel; Eq. 33-34 k_s)
    shear_weight: float = 0.0  # c_t [-] of Eq. 38 ([A] 0: normal work only)
    min_specific_energy: float = 0.0  # E_min [J/kg]: weaker events cause no damage ([A] 0)
    event_end_steps: int = 10  # N_end of the "quiet" rule [steps]
    # [A] when a particle's loading event ends (spec 5.4): "quiet" (the spec's rule) after
    # event_end_steps steps in a row without a loading contact, or with no contact; "release"
    # once no contact presses on the particle (every repulsive hysteretic force zero:
    # separated, or unloaded to the plastic overlap). In a jostling bed "quiet" ends events at
    # a rate per unit of time, so breakage depends on the plate speed; "release" has no time
    # scale (the presets use it; benchmarks/README, "Loading events and the plate speed")
    event_end_rule: str = "quiet"
    min_fragment_diameter: float = 2.0e-6  # d_min [m]: smallest fragment (spec 5.9)
    min_breakable_diameter: float = 4.0e-6  # d_break,min [m]: smaller particles never break
    sibling_init: str = "force_free"  # [A] overlapping fragments start force-free | fresh
    placement_candidates: int = 200  # random centres tried per fragment (spec 5.10)
    relax_iterations: int = 100  # sibling-overlap relaxation sweeps inside the parent
    fragment_timestep_fraction: float = 0.1  # dt <= this x Rayleigh time of a d_min fragment
    pool_capacity: int = 0  # particle slots (0 = the worst case: every fragment at d_min)
    max_breaks_per_step: int = 256  # parents replaced in one step (more wait one step)

    def __post_init__(self) -> None:
        pos = (("damage_constant", "> 0"), ("e_inf", "> 0 J/kg"), ("d0", "> 0 m"),
               ("phi", "> 0"), ("sigma_e", "> 0"), ("b_prime", "> 0"),
               ("min_fragment_diameter", "> 0 m"), ("device_youngs_modulus", "> 0 Pa"))
        for key, allowed in pos:
            v = getattr(self, key)
            _check(key, v, v > 0, allowed)
        _check("alpha_percentage", self.alpha_percentage, 0 < self.alpha_percentage <= 100,
               "in (0, 100] %")
        _check("truncation_ratio", self.truncation_ratio, 0 < self.truncation_ratio <= 100,
               "in (0, 100] %")
        _check("truncation_mode", self.truncation_mode, self.truncation_mode in TRUNCATION_MODES,
               f"one of {TRUNCATION_MODES}")
        if self.truncation_mode == "complement":
            _check("truncation_ratio", self.truncation_ratio, self.truncation_ratio < 100,
                   "< 100 % with truncation_mode = complement (E_max = E50 / (1 - R_t))")
        _check("device_poisson_ratio", self.device_poisson_ratio,
               -1 < self.device_poisson_ratio < 0.5, "in (-1, 0.5)")
        _check("shear_weight", self.shear_weight, 0 <= self.shear_weight <= 1, "in [0, 1]")
        _check("min_specific_energy", self.min_specific_energy, self.min_specific_energy >= 0,
               ">= 0 J/kg")
        _check("event_end_steps", self.event_end_steps, 1 <= self.event_end_steps <= 10**6,
               "in [1, 1e6]")
        _check("event_end_rule", self.event_end_rule, self.event_end_rule in EVENT_END_RULES,
               f"one of {EVENT_END_RULES}")
        _check("min_breakable_diameter", self.min_breakable_diameter,
               self.min_breakable_diameter >= 2 * self.min_fragment_diameter,
               f">= 2 x min_fragment_diameter = {2 * self.min_fragment_diameter} m (two "
               "fragments of at least d_min each)")
        _check("sibling_init", self.sibling_init, self.sibling_init in SIBLING_INITS,
               f"one of {SIBLING_INITS}")
        _check("placement_candidates", self.placement_candidates,
               1 <= self.placement_candidates <= 10**5, "in [1, 1e5]")
        _check("relax_iterations", self.relax_iterations, 0 <= self.relax_iterations <= 10**5,
               "in [0, 1e5]")
        f = self.fragment_timestep_fraction
        _check("fragment_timestep_fraction", f, 0 < f <= 0.3, "in (0, 0.3]")
        _check("pool_capacity", self.pool_capacity, self.pool_capacity >= 0,
               ">= 0 (0 = worst case)")
        _check("max_breaks_per_step", self.max_breaks_per_step,
               1 <= self.max_breaks_per_step <= 10**6, "in [1, 1e6]")


@dataclass(frozen=True, slots=True, kw_only=True)
class ProtocolConfig:
    """Calendering stroke, plate speed, optional pressure target and unloading."""

    stroke: float = 19.5e-6  # top-plate travel from h0 [m] (the maximum travel if servo)
    plate_speed: float = 0.0  # [m s^-1]; 0 = from inertial_number at reference_pressure
    inertial_number: float = 1.0e-3  # target I = (v/h) d_mean sqrt(rho / P_ref) [-]
    reference_pressure: float = 1.0e6  # P_ref of the plate-speed rule [Pa]
    target_pressure: float = 0.0  # > 0: stop the stroke when the top pressure reaches it [Pa]
    unload: bool = False  # after the stroke, lift the plate until it loses contact
    unload_speed: float = 0.0  # [m s^-1]; 0 = the loading speed
    snapshot_depths: list[float] = field(
        default_factory=lambda: [0.0, 5e-6, 10e-6, 15e-6, 19.5e-6])  # [m]

    def __post_init__(self) -> None:
        _check("stroke", self.stroke, self.stroke > 0, "> 0 m")
        _check("plate_speed", self.plate_speed, self.plate_speed >= 0, ">= 0 m/s (0 = auto)")
        _check("inertial_number", self.inertial_number, 0 < self.inertial_number <= 1,
               "in (0, 1]")
        _check("reference_pressure", self.reference_pressure, self.reference_pressure > 0,
               "> 0 Pa")
        _check("target_pressure", self.target_pressure, self.target_pressure >= 0,
               ">= 0 Pa (0 = calender to the stroke)")
        _check("unload_speed", self.unload_speed, self.unload_speed >= 0, ">= 0 m/s")
        for d in self.snapshot_depths:
            _check("snapshot_depths", list(self.snapshot_depths), 0 <= d <= self.stroke,
                   f"depths in [0, stroke = {self.stroke}] m")


@dataclass(frozen=True, slots=True, kw_only=True)
class OutputConfig:
    """What a run records, and how often it checkpoints."""

    record_spacing: float = 0.05e-6  # plate travel between rows of the series/ group [m]
    pressure_stride: int = 1  # steps per pressure/ sample (1 = every step; > 1 = block mean)
    checkpoint_interval: float = 600.0  # wall seconds between checkpoints (0 = never)
    snapshot_bonds: bool = True  # store the bond network in every snapshot

    def __post_init__(self) -> None:
        _check("record_spacing", self.record_spacing, self.record_spacing > 0, "> 0 m")
        _check("pressure_stride", self.pressure_stride, 1 <= self.pressure_stride <= 10**6,
               "in [1, 1e6]")
        _check("checkpoint_interval", self.checkpoint_interval, self.checkpoint_interval >= 0,
               ">= 0 s (0 = never)")


@dataclass(frozen=True, slots=True, kw_only=True)
class SimConfig:
    """Everything the DEM engine needs. See README "Configuration"."""

    domain: DomainConfig = field(default_factory=DomainConfig)
    materials: dict[str, MaterialConfig] = field(default_factory=_paper_materials)
    plates: PlatesConfig = field(default_factory=PlatesConfig)
    contact: ContactConfig = field(default_factory=ContactConfig)
    numerics: NumericsConfig = field(default_factory=NumericsConfig)
    electrode: ElectrodeConfig = field(default_factory=ElectrodeConfig)
    build: BuildConfig = field(default_factory=BuildConfig)
    bonds: BondsConfig = field(default_factory=BondsConfig)
    breakage: BreakageConfig = field(default_factory=BreakageConfig)
    protocol: ProtocolConfig = field(default_factory=ProtocolConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def __post_init__(self) -> None:
        names = list(self.materials)
        if not names:
            raise ConfigError("materials", {}, "at least one material")
        for name in names:
            if "-" in name or not name:
                raise ConfigError(f"materials.{name}", name, "a non-empty name without '-'")
        needed = {pair_key(a, b) for a in names for b in names}
        for key in self.contact.pairs:
            a, _, b = key.partition("-")
            if a not in names or b not in names:
                raise ConfigError(f"contact.pairs.{key}", key, f"pairs of {names}")
        given = {pair_key(*k.split("-", 1)) for k in self.contact.pairs}
        for key in sorted(needed - given):
            raise ConfigError(f"contact.pairs.{key}", None, "a [contact.pairs] entry per pair")
        for key in self.contact.plate_pairs:
            if key not in names:
                raise ConfigError(f"contact.plate_pairs.{key}", key, f"one of {names}")
        for name in names:
            if name not in self.contact.plate_pairs:
                raise ConfigError(f"contact.plate_pairs.{name}", None, "an entry per material")

    def check_run(self) -> SimConfig:
        """Cross-section checks of a calendering run (electrode, protocol, domain, bonds).

        The engine alone does not need them (tests build arbitrary cells); the run builder
        and the CLI call this before doing anything. Returns ``self``.
        """
        names = self.material_names
        el, pr, d = self.electrode, self.protocol, self.domain
        for key in el.composition:
            if key not in names:
                raise ConfigError(f"electrode.composition.{key}", key, f"one of {names}")
        for key, w in el.composition.items():
            if w > 0 and key not in el.sizes:
                raise ConfigError(f"electrode.sizes.{key}", None,
                                  "a size distribution for every material in the composition")
        for key in el.sizes:
            if key not in names:
                raise ConfigError(f"electrode.sizes.{key}", key, f"one of {names}")
        for key in self.bonds.materials:
            if key not in names:
                raise ConfigError("bonds.materials", list(self.bonds.materials),
                                  f"names among {names}")
        if pr.stroke >= el.thickness:
            raise ConfigError("protocol.stroke", pr.stroke,
                              f"< electrode.thickness = {el.thickness} m")
        if el.thickness >= d.height:
            raise ConfigError("electrode.thickness", el.thickness,
                              f"< domain.height = {d.height} m")
        d_max = max((s.bounds[1] for s in el.sizes.values() if s.distribution != "table"),
                    default=0.0)
        if d_max >= el.thickness - pr.stroke:
            raise ConfigError("protocol.stroke", pr.stroke,
                              f"a final thickness h0 - stroke above the largest diameter "
                              f"{d_max} m")
        d_bond = max((s.bounds[1] for k, s in el.sizes.items()
                      if k in self.bonds.materials and s.distribution != "table"), default=0.0)
        reach = max(d_max + self.numerics.skin,
                    self.bonds.radius_ratio * 0.5 * (d_bond + d_max) if self.bonds.enabled else 0)
        for key, length in (("domain.cell_x", d.cell_x), ("domain.cell_y", d.cell_y)):
            if length < 2.0 * reach:
                raise ConfigError(key, length, f">= {2.0 * reach:.4g} m (twice the longest "
                                  "contact or bond reach, for the periodic minimum image)")
        return self

    @property
    def material_names(self) -> list[str]:
        """Material names in index order (index 0 first)."""
        return list(self.materials)

    def pair(self, a: str, b: str) -> PairConfig:
        """Contact parameters of the pair (a, b), order-insensitive."""
        for key, value in self.contact.pairs.items():
            x, _, y = key.partition("-")
            if {x, y} == {a, b} and (x == y) == (a == b):
                return value
        raise KeyError(f"no contact.pairs entry for {a}-{b}")


def pair_key(a: str, b: str) -> str:
    """Canonical pair key ("AM-CB" and "CB-AM" -> "AM-CB")."""
    return "-".join(sorted((a, b)))


# ---------------------------------------------------------------- strict loading


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(tp: Any, value: Any, key: str) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(key, value, f"a table of {tp.__name__} fields")
        return _from_dict(tp, value, key)
    if origin is dict:
        _, vt = typing.get_args(tp)
        if not isinstance(value, dict):
            raise ConfigError(key, value, "a table")
        return {str(k): _convert(vt, v, f"{key}.{k}") for k, v in value.items()}
    if origin is list:
        (et,) = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(key, value, "a list")
        return [_convert(et, v, f"{key}[{i}]") for i, v in enumerate(value)]
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _convert(args[0], value, key)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(key, value, "a number")
        if not math.isfinite(value) or abs(value) > FLOAT_LIMIT:
            raise ConfigError(key, value, f"a finite number of magnitude <= {FLOAT_LIMIT:g}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(key, value, "an integer")
        if not -INT_LIMIT <= value <= INT_LIMIT:
            raise ConfigError(key, value, f"an integer in [-{INT_LIMIT}, {INT_LIMIT}]")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(key, value, "true or false")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(key, value, "a string")
        return value
    raise TypeError(f"unsupported config type {_type_name(tp)} at {key}")


def _from_dict(cls: type, data: dict, prefix: str = "") -> Any:
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    for k in data:
        if k not in names:
            full = f"{prefix}.{k}" if prefix else str(k)
            raise ConfigError(full, data[k], f"one of the keys {sorted(names)}")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name in data:
            key = f"{prefix}.{f.name}" if prefix else f.name
            kwargs[f.name] = _convert(hints[f.name], data[f.name], key)
    try:
        return cls(**kwargs)
    except ConfigError as err:
        raise err.with_prefix(prefix) from None
    except TypeError as err:  # a required field is missing
        raise ConfigError(prefix or cls.__name__, data, f"all required fields ({err})") from None


def _merge(base: dict, update: dict) -> dict:
    out = dict(base)
    for k, v in update.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def to_dict(cfg: Any) -> dict:
    """Plain nested dict of a config (JSON- and TOML-serialisable)."""
    return dataclasses.asdict(cfg)


def load_config_dict(data: dict, base: SimConfig | None = None) -> SimConfig:
    """Build a :class:`SimConfig` from a nested dict layered over ``base`` (default: paper).

    Tables given in ``data`` replace only the keys they name, so a TOML file may set one
    value and keep every other default.
    """
    base_dict = to_dict(base if base is not None else SimConfig())
    return _from_dict(SimConfig, _merge(base_dict, data))


CONFIG_SUFFIXES = (".toml", ".json")


def load_config(path: str | Path, base: SimConfig | None = None) -> SimConfig:
    """Read a TOML file, or a JSON one (e.g. a run file's or a dataset's ``config_json``,
    to rerun exactly that problem), strictly (see :func:`load_config_dict`)."""
    path = Path(path)
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
        except (ValueError, UnicodeDecodeError) as err:
            raise ConfigError(str(path), "<file>", f"valid JSON ({err})") from None
        if not isinstance(data, dict):
            raise ConfigError(str(path), "<file>", "a JSON object of config tables")
        return load_config_dict(data, base)
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(str(path), "<file>", f"valid TOML ({err})") from None
    return load_config_dict(data, base)


def parse_override(text: str) -> tuple[str, Any]:
    """Parse ``key=value`` (value in TOML syntax; bare words are strings)."""
    if "=" not in text:
        raise ConfigError(text, text, "the form key=value")
    key, raw = (s.strip() for s in text.split("=", 1))
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return key, value


def format_override(key: str, value: Any) -> str:
    """``key=value`` with the value in TOML syntax: the inverse of :func:`parse_override`,
    for ``--set`` arguments of ``calendaring run`` subprocesses."""

    def toml(v: Any) -> str:
        v = v.item() if hasattr(v, "item") else v  # NumPy scalars to Python
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list | tuple):
            return "[" + ", ".join(toml(x) for x in v) + "]"
        if isinstance(v, int):
            return str(v)
        return repr(float(v))

    return f"{key}={toml(value)}"


def with_overrides(cfg: SimConfig, overrides: dict[str, Any]) -> SimConfig:
    """Return ``cfg`` with dotted-key overrides applied, e.g. ``{"numerics.seed": 3}``."""
    data = to_dict(cfg)
    for dotted, value in overrides.items():
        node = data
        parts = dotted.split(".")
        for i, part in enumerate(parts[:-1]):
            if not isinstance(node, dict) or part not in node:
                raise ConfigError(".".join(parts[: i + 1]), value, "an existing config table")
            node = node[part]
        if not isinstance(node, dict) or parts[-1] not in node:
            raise ConfigError(dotted, value, "an existing config key")
        node[parts[-1]] = value
    return _from_dict(SimConfig, data)


def config_json(cfg: Any) -> str:
    """Canonical JSON (sorted keys) of a config."""
    return json.dumps(to_dict(cfg), sort_keys=True, separators=(",", ":"))


def config_hash(cfg: Any) -> str:
    """sha256 of the canonical JSON: the run ID of a configuration."""
    return hashlib.sha256(config_json(cfg).encode()).hexdigest()


def config_text_hash(text: str) -> str:
    """sha256 of a stored configuration text (what :func:`config_hash` gave when it was
    written). Readers check a file's ``config_hash`` against its own text, not against the
    text this version would write: a key added since (with its default) must not make older
    files look edited."""
    return hashlib.sha256(str(text).encode()).hexdigest()


def config_hash_excluding(cfg: Any, keys: Sequence[str]) -> str:
    """sha256 of the configuration without the dotted ``keys`` (whole sections or single
    keys): what two configurations must share for a settled bed or a dataset to be shared."""
    d = json.loads(config_json(cfg))
    for dotted in keys:
        *path, last = dotted.split(".")
        node = d
        for part in path:
            node = node.get(part, {})
        node.pop(last, None)
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()


PRESETS = ("paper", "quick", "rve", "sweep", "tiny")


def preset_path(name: str) -> Path:
    """Path of a preset TOML shipped inside the package."""
    if name not in PRESETS:
        raise ConfigError("--preset", name, f"one of {PRESETS}")
    return Path(__file__).resolve().parents[1] / "presets" / f"{name}.toml"


def load_preset(name: str) -> SimConfig:
    """The preset's configuration (paper defaults plus the preset's TOML)."""
    return load_config(preset_path(name))
