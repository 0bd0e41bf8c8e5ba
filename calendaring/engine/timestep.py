"""Rayleigh time step (host-only; spec section 1.3).

The time step is always computed, never typed in: ``dt = fraction * T_R(smallest particle)``
with the EDEM definition

    T_R = pi R sqrt(rho / G) / (0.1631 nu + 0.8766)

(EDEM "Estimate Simulation Time"; Li, Xu & Thornton 2005). With density scaling ``s`` the
particle density entering both the masses and ``T_R`` is ``s rho``.

See also: :mod:`calendaring.engine.simulation` (fixes the time step when a run starts),
:mod:`calendaring.process.preflight` (step counts from the same Rayleigh times).
"""

from __future__ import annotations

import math

import numpy as np

from calendaring.core.config import BreakageConfig, MaterialConfig


def rayleigh_time(radius: float, material: MaterialConfig, density_scaling: float = 1.0) -> float:
    """Rayleigh time [s] of a sphere of ``radius`` [m] made of ``material``."""
    rho = material.density * density_scaling
    nu = material.poisson_ratio
    return math.pi * radius * math.sqrt(rho / material.shear_modulus) / (0.1631 * nu + 0.8766)


def fragment_timestep(breakage: BreakageConfig, material: MaterialConfig,
                      density_scaling: float = 1.0) -> float:
    """The time step fragments of a breakable ``material`` allow [s]:
    ``breakage.fragment_timestep_fraction`` x the Rayleigh time of the smallest fragment
    (``breakage.min_fragment_diameter``)."""
    return breakage.fragment_timestep_fraction * rayleigh_time(
        0.5 * breakage.min_fragment_diameter, material, density_scaling)


def critical_timestep(
    radii: np.ndarray,
    material_index: np.ndarray,
    materials: list[MaterialConfig],
    fraction: float,
    density_scaling: float = 1.0,
    min_radius: dict[int, float] | None = None,
) -> float:
    """``fraction`` x the smallest Rayleigh time over the given particles [s].

    Args:
        radii: particle radii [m].
        material_index: material index of each particle.
        materials: material list in index order.
        fraction: dt / T_R (the paper uses 0.04).
        density_scaling: mass scaling factor s.
        min_radius: optional extra radius per material that may appear later (e.g. the
            smallest fragment), included in the minimum.
    """
    candidates = []
    radii = np.asarray(radii, dtype=float)
    material_index = np.asarray(material_index)
    for m, mat in enumerate(materials):
        sel = radii[material_index == m]
        if sel.size:
            candidates.append(rayleigh_time(float(sel.min()), mat, density_scaling))
        if min_radius and m in min_radius:
            candidates.append(rayleigh_time(min_radius[m], mat, density_scaling))
    if not candidates:
        raise ValueError("critical_timestep needs at least one particle or a min_radius")
    return fraction * min(candidates)
