"""Per-pair contact constants derived from the configuration (host-only; spec 0, 1.2, 2.4).

The device kernels read these from a small table indexed by (material a, material b) for
particle pairs and by (material, plate) for particle-plate contacts. Everything that does not
depend on the particle radii or masses is computed here once:

- ``1/E* = (1 - nu_i^2)/E_i + (1 - nu_j^2)/E_j``
- ``1/G* = (2 - nu_i)/G_i + (2 - nu_j)/G_j``
- ``beta_hat = -ln e / sqrt(ln^2 e + pi^2)`` (damping ratio from the restitution coefficient)

See also: :mod:`calendaring.engine.kernels.law` (reads the tables per contact),
:mod:`calendaring.engine.laws.eepa` (the normal law these constants feed).
"""

from __future__ import annotations

import math

import numpy as np

from calendaring.core.config import MaterialConfig, PairConfig, SimConfig

# Column layout of the pair table (one row per (a, b) or (material, plate) combination).
COLUMNS = (
    "e_star",  # E* [Pa]
    "g_star",  # G* [Pa]
    "plasticity_ratio",  # lambda_p [-]
    "surface_energy",  # Delta gamma [J m^-2]
    "beta_hat",  # damping ratio from restitution [-]
    "friction",  # mu_s [-]
    "rolling_friction",  # mu_r [-]
    "pull_off_force",  # f0 [N]
    "adhesion_stiffness",  # k_adh for adhesion_mode direct_kadh [N m^-chi]
    "stiffness_partition",  # e_i = k_j / (k_i + k_j): share of pair work taken by body i
    "plastic_factor",  # lambda_p^(1/n): delta_p = plastic_factor * delta_max [-]
    "unloading_factor",  # 1 / (1 - lambda_p): k2 = unloading_factor * k1 [-]
    # n = 1.5 with damping_mode tangent_sqrt56 (the default), both damping coefficients
    # are these factors times sqrt(m* sqrt(R* delta)): beta_n = 2 sqrt(5/6) beta_hat
    # sqrt(m* 1.5 k1 delta^0.5) with k1 = (4/3) E* sqrt(R*), and beta_t = 2 beta_hat
    # sqrt(m* k_t) with k_t = xi_t 8 G* sqrt(R* delta) (spec 2.4, 3.1)
    "normal_damping_factor",  # 2 sqrt(5/6) beta_hat sqrt(2 E*) [kg^0.5 m^-0.5 s^-1]
    "tangential_damping_factor",  # 2 beta_hat sqrt(8 xi_t G*) [kg^0.5 m^-0.5 s^-1]
)
COL = {name: i for i, name in enumerate(COLUMNS)}


def reduced_modulus(a: MaterialConfig, b: MaterialConfig) -> float:
    """E* [Pa] of two elastic solids."""
    inv = (1 - a.poisson_ratio**2) / a.youngs_modulus + (1 - b.poisson_ratio**2) / b.youngs_modulus
    return 1.0 / inv


def reduced_shear_modulus(a: MaterialConfig, b: MaterialConfig) -> float:
    """G* [Pa] of two elastic solids."""
    inv = (2 - a.poisson_ratio) / a.shear_modulus + (2 - b.poisson_ratio) / b.shear_modulus
    return 1.0 / inv


def damping_ratio(restitution: float) -> float:
    """beta_hat = -ln e / sqrt(ln^2 e + pi^2) (spec 2.4); 0 for e = 1."""
    if restitution >= 1.0:
        return 0.0
    ln_e = math.log(restitution)
    return -ln_e / math.sqrt(ln_e**2 + math.pi**2)


def plane_strain_modulus(m: MaterialConfig) -> float:
    """k = E / (1 - nu^2) [Pa] (paper Eq. 34)."""
    return m.youngs_modulus / (1 - m.poisson_ratio**2)


def _row(a: MaterialConfig, b: MaterialConfig, p: PairConfig, n: float,
         xi_t: float) -> list[float]:
    ka, kb = plane_strain_modulus(a), plane_strain_modulus(b)
    e_star, g_star = reduced_modulus(a, b), reduced_shear_modulus(a, b)
    beta_hat = damping_ratio(p.restitution)
    return [
        e_star,
        g_star,
        p.plasticity_ratio,
        p.surface_energy,
        beta_hat,
        p.friction,
        p.rolling_friction,
        p.pull_off_force,
        p.adhesion_stiffness,
        kb / (ka + kb),
        p.plasticity_ratio ** (1.0 / n),
        1.0 / (1.0 - p.plasticity_ratio),
        2.0 * math.sqrt(5.0 / 6.0) * beta_hat * math.sqrt(2.0 * e_star),
        2.0 * beta_hat * math.sqrt(8.0 * xi_t * g_star),
    ]


def pair_table(cfg: SimConfig) -> np.ndarray:
    """Array [n_mat, n_mat, n_col] of particle-particle constants."""
    names = cfg.material_names
    n = len(names)
    out = np.zeros((n, n, len(COLUMNS)))
    for i, a in enumerate(names):
        for j, b in enumerate(names):
            out[i, j] = _row(cfg.materials[a], cfg.materials[b], cfg.pair(a, b),
                             cfg.contact.loading_exponent,
                             cfg.contact.tangential_stiffness_ratio)
    return out


def plate_table(cfg: SimConfig) -> np.ndarray:
    """Array [n_mat, 2, n_col] of particle-plate constants (plate 0 = bottom, 1 = top)."""
    names = cfg.material_names
    out = np.zeros((len(names), 2, len(COLUMNS)))
    for i, a in enumerate(names):
        p = cfg.contact.plate_pairs[a]
        for w, plate in enumerate((cfg.plates.bottom, cfg.plates.top)):
            out[i, w] = _row(cfg.materials[a], plate, p, cfg.contact.loading_exponent,
                             cfg.contact.tangential_stiffness_ratio)
    return out
