"""Tangential spring-dashpot with Coulomb limit (paper Eqs. 12-18; spec section 3.1-3.2).

    k_t = xi_t 8 G* sqrt(R* delta)       (n > 1; paper Eq. 15), k_t = xi_t k1 for n = 1
    f_ts <- Rot(f_ts) - k_t v_t dt        (incremental history, paper Eqs. 13-14)
    f_td = -beta_t v_t, beta_t = 2 beta_hat sqrt(m* k_t)    ([A] spec 3.1)
    |f_ts + f_td| <= mu_s |f_hys + k_adh delta^chi - f0|   (Thakur 2014 Eq. 13)

Symbols: xi_t = ``contact.tangential_stiffness_ratio`` (default 2/3), mu_s =
``contact.pairs."A-B".friction``. Rot() projects the stored spring onto the current tangent
plane and restores its magnitude.

See also: :mod:`calendaring.engine.laws.eepa` (f_hys and k_adh), :mod:`calendaring.engine.bonds`
(reuses the spring rotation), :mod:`calendaring.engine.laws.rolling`.
"""

import taichi as ti

from calendaring.engine.laws.eepa import power_n


@ti.func
def tangential_stiffness(g_star, r_star, delta, k1, ratio, n: ti.template()):
    """k_t [N m^-1]."""
    kt = 0.0
    if ti.static(n == 1.0):
        kt = ratio * k1
    else:
        kt = ratio * 8.0 * g_star * ti.sqrt(r_star * delta)
    return kt


# Below this fraction x of the squared magnitude removed by the projection, the restoring
# factor 1/sqrt(1 - x) is its series 1 + x/2 + 3x^2/8 (truncation < 5x^3/16 < 4e-19).
SERIES_FRACTION = 1e-6


@ti.func
def rotate_spring(spring, normal):
    """Project the spring onto the plane normal to ``normal`` keeping its magnitude.

    The stored spring lay in the previous step's tangent plane, so the projection removes
    a tiny fraction x = (s.n)^2 / |s|^2 of its squared magnitude: the factor 1/sqrt(1 - x)
    that restores it is then taken from its series, without a root.
    """
    sn = spring.dot(normal)
    s = spring - sn * normal
    m2 = spring.norm_sqr()
    if m2 > 0.0:
        x = sn * sn / m2
        if x < ti.static(SERIES_FRACTION):
            s *= 1.0 + x * (0.5 + 0.375 * x)
        else:
            smag2 = s.norm_sqr()
            if smag2 > 0.0:
                s *= ti.sqrt(m2 / smag2)
    return s


@ti.func
def coulomb_limit(friction, f_hys, k_adh, delta, f0, chi: ti.template()):
    """Largest tangential force magnitude [N] before sliding (Thakur 2014 Eq. 13)."""
    return friction * ti.abs(f_hys + k_adh * power_n(delta, chi) - f0)
