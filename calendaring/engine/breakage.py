"""Tavares UFRJ breakage: host-side formulas (paper section 2.2, physics-spec section 5).

Host-only (NumPy/SciPy, no Taichi). The device kernels in :mod:`calendaring.engine.breakage_kernels`
use the same formulas; the tests hold both to the analytic values of spec section 9.

- Fracture energy of a particle (Eqs. 31-32, spec 5.2): an upper-truncated lognormal,

      P(E) = 1/2 [1 + erf((ln E* - ln E50) / (sqrt(2) sigma_E))],  E* = E_max E / (E_max - E)

  with the truncation ``E_max = c E50``: ``c = R_t/100`` (``truncation_mode = "ratio"``, the
  default), ``c = exp(sigma_E Phi^-1(R_t/100))`` (``"percentile"``) or ``1 / (1 - R_t/100)``
  (``"complement"``).
- Size effect and device correction (Eqs. 33-34, spec 5.3):
  ``E50(d) = E_inf / (1 + k_p/k_s) [1 + (d0/d)^phi]``, ``k = E / (1 - nu^2)``, ``k_s`` the
  surface the fracture energies were measured on (steel by default).
- Damage (Eqs. 35-36, spec 5.5): ``D = [2 gamma x / (2 gamma - 5 D + 5)]^(2 gamma / 5)``,
  ``x = E_event / E_f``, ``E_f <- E_f (1 - D)``.
- Breakage index (Eq. 39, spec 5.7): ``t10 = A/100 [1 - exp(-b' E_k / E50)]`` and the t_n
  family ``t_n = 1 - (1 - t10)^(9 / (n - 1))`` (spec 5.8).

See also: :mod:`calendaring.engine.contact_params` (the plane-strain moduli ``k``),
:mod:`calendaring.process.preflight` (the worst-case pool slots).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtr, ndtri

from calendaring.core.config import BreakageConfig, MaterialConfig, SimConfig
from calendaring.engine.contact_params import plane_strain_modulus

# Size ratios x = d / d_parent of the t_n knots (spec 5.8), coarse to fine.
TN_SIZES = (2, 4, 10, 25, 50, 75)


def device_factor(material: MaterialConfig, cfg: BreakageConfig) -> float:
    """1 / (1 + k_p / k_s) of Eq. 33 (0.5606 for NMC622 on steel)."""
    k_p = plane_strain_modulus(material)
    k_s = cfg.device_youngs_modulus / (1 - cfg.device_poisson_ratio**2)
    return 1.0 / (1.0 + k_p / k_s)


def e50(diameter, material: MaterialConfig, cfg: BreakageConfig):
    """Median fracture energy E50 [J/kg] of particles of ``diameter`` [m] (Eq. 33)."""
    d = np.asarray(diameter, dtype=float)
    return cfg.e_inf * device_factor(material, cfg) * (1.0 + (cfg.d0 / d) ** cfg.phi)


def truncation_factor(cfg: BreakageConfig) -> float:
    """c in E_max = c E50 (``inf`` for an untruncated distribution)."""
    r = cfg.truncation_ratio / 100.0
    if cfg.truncation_mode == "ratio":
        return r
    if cfg.truncation_mode == "percentile":
        return math.inf if r >= 1.0 else math.exp(cfg.sigma_e * float(ndtri(r)))
    return 1.0 / (1.0 - r)


def fracture_energy_cdf(energy, e50_value, factor: float, sigma: float):
    """P(E) of the upper-truncated lognormal (Eq. 31 resolved; 1 at and above E_max)."""
    e = np.asarray(energy, dtype=float)
    e_max = factor * np.asarray(e50_value, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        e_star = np.where(np.isinf(e_max), e, e_max * e / (e_max - e))
        z = (np.log(e_star) - np.log(e50_value)) / sigma
    out = ndtr(z)
    out = np.where(e <= 0, 0.0, out)
    return np.where(np.isfinite(e_max) & (e >= e_max), 1.0, out)


def fracture_energy_median(e50_value, factor: float):
    """Median of the truncated distribution: E50 E_max / (E50 + E_max) [J/kg]."""
    if math.isinf(factor):
        return np.asarray(e50_value, float)
    return np.asarray(e50_value, float) * factor / (1.0 + factor)


def damage(x, gamma: float):
    """Root D of the damage law for energy ratios ``x`` (bisection, 60 halvings)."""
    x = np.asarray(x, dtype=float)
    lo = np.zeros_like(x)
    hi = np.ones_like(x)
    p = 2.0 * gamma / 5.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        g = mid - (2.0 * gamma * x / (2.0 * gamma - 5.0 * mid + 5.0)) ** p
        neg = g < 0
        lo = np.where(neg, mid, lo)
        hi = np.where(neg, hi, mid)
    return np.where(x >= 1.0, 1.0, np.where(x <= 0.0, 0.0, 0.5 * (lo + hi)))


def t10(energy, e50_value, cfg: BreakageConfig):
    """Breakage index t10 (fraction) at specific stressing energy ``energy`` [J/kg]."""
    return cfg.alpha_percentage / 100.0 * (1.0 - np.exp(-cfg.b_prime * np.asarray(energy)
                                                       / np.asarray(e50_value)))


def tn(t10_value, n):
    """Closed-form t_n family (spec 5.8): mass fraction finer than d_parent / n."""
    return 1.0 - (1.0 - np.asarray(t10_value, float)) ** (9.0 / (np.asarray(n, float) - 1.0))


def max_fragments(d_parent_max: float, cfg: BreakageConfig) -> int:
    """Largest number of fragments one breakage can produce (scratch sizing).

    The fines (diameter d_min) hold at most (d_p/d_min)^3 spheres and each coarser class
    rounds up by at most one sphere.
    """
    return int((d_parent_max / cfg.min_fragment_diameter) ** 3 * (1 + 1e-9)) + len(TN_SIZES) + 3


def worst_case_slots(diameter: np.ndarray, breakable: np.ndarray, cfg: BreakageConfig) -> int:
    """Particle slots ever used if every breakable particle is ground down to d_min.

    A particle of diameter d ends in at most L = (d/d_min)^3 leaves (every fragment is at
    least d_min, volume is conserved); its breakage tree then has at most 2L - 1 nodes, so it
    uses at most 2L - 2 new slots.
    """
    d = np.asarray(diameter, float)
    b = np.asarray(breakable, bool) & (d >= cfg.min_breakable_diameter)
    leaves = np.floor((d[b] / cfg.min_fragment_diameter) ** 3 * (1 + 1e-9))
    return int(len(d) + np.sum(np.maximum(2 * leaves - 2, 0)))


def breakable_mask(cfg: SimConfig) -> np.ndarray:
    """Per material index: particles of this material may break."""
    return np.array([cfg.materials[n].breakable for n in cfg.material_names], bool)


def breakage_enabled(cfg: SimConfig) -> bool:
    """Breakage is switched on and some material can break."""
    return bool(cfg.breakage.enabled and breakable_mask(cfg).any())


__all__ = ["TN_SIZES", "breakable_mask", "breakage_enabled", "damage", "device_factor", "e50",
           "fracture_energy_cdf", "fracture_energy_median", "max_fragments", "t10", "tn",
           "truncation_factor", "worst_case_slots"]
