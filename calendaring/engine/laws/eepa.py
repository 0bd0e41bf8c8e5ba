"""Edinburgh Elasto-Plastic Adhesive (EEPA) normal contact law.

Model (paper Eqs. 3-11, resolved in physics-spec section 2; Thakur et al. 2014,
Granular Matter 16:383, doi:10.1007/s10035-014-0506-4; LAMMPS ``epa_nonlinear``):

    f_hys = f0 + clamp(k2 (delta^n - delta_p^n), -k_adh delta^chi, k1 delta^n)
    delta_p = lambda_p^(1/n) delta_max

Symbols:

| paper     | code              | config key                               | unit        |
|-----------|-------------------|------------------------------------------|-------------|
| n         | n                 | contact.loading_exponent                 | -           |
| chi       | chi               | contact.adhesive_exponent                | -           |
| lambda_p  | plasticity_ratio  | contact.pairs."A-B".plasticity_ratio     | -           |
| Delta gam | surface_energy    | contact.pairs."A-B".surface_energy       | J m^-2      |
| f0        | f0                | contact.pairs."A-B".pull_off_force       | N           |
| k1, k2    | k1, k2            | derived: k1 = (4/3) E* R*^(2-n), k2 = k1/(1-lambda_p) | N m^-n |
| k_adh     | k_adh             | derived from Delta gamma (spec 2.3) or direct | N m^-chi |

Branches: virgin loading (delta >= delta_max) on k1; un/re-loading on the k2 line; adhesive
floor -k_adh delta^chi. With lambda_p = 0 and Delta gamma = 0 the law is exactly Hertz
(k2 = k1, delta_p = 0), the mode used to compare with LIGGGHTS.

Adhesion map [A] (spec 2.3, mode ``surface_energy_ap``): a_p = sqrt(R* delta_p),
F_pull = min(1.5 pi Delta gamma a_p, k2 delta_p^n), delta_min = (delta_p^n - F_pull/k2)^(1/n),
k_adh = F_pull / delta_min^chi. Mode ``jkr_R`` uses F_pull = 1.5 pi Delta gamma R*; mode
``direct_kadh`` takes k_adh from the config.

Normal damping [A] (spec 2.4): f_nd = beta_n delta_dot with beta_n = 2 g_n beta_hat
sqrt(m* k_eff), k_eff = n k1 delta^(n-1), g_n = 1 (n = 1) or sqrt(5/6) (n = 1.5);
``literal_k1`` plugs k1 into paper Eq. 10 as printed.

See also: :mod:`calendaring.engine.laws.tangential` (the Coulomb limit on this law's force),
:mod:`calendaring.engine.contact_params` (the per-pair constants).
"""

import math

import numpy as np
import taichi as ti

ADHESION_SURFACE_ENERGY_AP = 0
ADHESION_JKR_R = 1
ADHESION_DIRECT = 2
DAMPING_TANGENT_SQRT56 = 0
DAMPING_LITERAL_K1 = 1


@ti.func
def power_n(x, n: ti.template()):
    """x^n for the static exponents used here (1, 1.5, 2 fast paths)."""
    r = x
    if ti.static(n == 1.5):
        r = x * ti.sqrt(x)
    elif ti.static(n == 2.0):
        r = x * x
    elif ti.static(n != 1.0):
        r = ti.pow(x, n)
    return r


@ti.func
def eepa_loading_stiffness(e_star, r_star, n: ti.template()):
    """k1 [N m^-n] (paper Eq. 5 resolved: 2E*R* for n = 1, (4/3)E*R*^(2-n) for n > 1)."""
    k1 = 0.0
    if ti.static(n == 1.0):
        k1 = 2.0 * e_star * r_star
    elif ti.static(n == 1.5):
        k1 = (4.0 / 3.0) * e_star * ti.sqrt(r_star)
    else:
        k1 = (4.0 / 3.0) * e_star * ti.pow(r_star, 2.0 - n)
    return k1


@ti.func
def eepa_plastic_overlap(delta_max, plasticity_ratio, n: ti.template()):
    """delta_p = lambda_p^(1/n) delta_max [m] (spec 2.2)."""
    return ti.pow(plasticity_ratio, 1.0 / n) * delta_max


@ti.func
def eepa_adhesion_stiffness(delta_p, r_star, k2, surface_energy, kadh_direct,
                            n: ti.template(), chi: ti.template(), mode: ti.template()):
    """k_adh [N m^-chi] from the surface energy (spec 2.3) or taken directly."""
    k_adh = 0.0
    if ti.static(mode == ADHESION_DIRECT):
        k_adh = kadh_direct
    else:
        f_pull = 0.0
        if ti.static(mode == ADHESION_SURFACE_ENERGY_AP):
            f_pull = 1.5 * math.pi * surface_energy * ti.sqrt(r_star * delta_p)
        else:
            f_pull = 1.5 * math.pi * surface_energy * r_star
        dpn = power_n(delta_p, n)
        reach = k2 * dpn
        # Capped case F_pull >= k2 delta_p^n: delta_min = 0 and k_adh = 0 (spec 2.3). It is
        # tested directly: delta_p^n - F_pull/k2 can round to a tiny positive number and give
        # a huge k_adh (an adhesive force persisting down to delta -> 0).
        if f_pull > 0.0 and f_pull < reach * (1.0 - 1e-9):
            if ti.static(chi == n):  # delta_min^chi = delta_min^n: no root to take
                k_adh = f_pull * k2 / (reach - f_pull)  # = F_pull / (dpn - F_pull / k2)
            else:
                delta_min = ti.pow(dpn - f_pull / k2, 1.0 / n)
                k_adh = f_pull / power_n(delta_min, chi)
    return k_adh


@ti.func
def eepa_hysteretic_force(delta, delta_p, k1, k2, k_adh, f0, n: ti.template(), chi: ti.template()):
    """f_hys [N], repulsive positive (paper Eq. 4 as a clamp, spec 2.2)."""
    dn = power_n(delta, n)
    return f0 + ti.min(ti.max(k2 * (dn - power_n(delta_p, n)), -k_adh * power_n(delta, chi)),
                       k1 * dn)


@ti.func
def eepa_damping_coefficient(m_star, k1, delta, beta_hat, n: ti.template(), mode: ti.template()):
    """beta_n [N s m^-1] (spec 2.4)."""
    beta = 0.0
    if ti.static(mode == DAMPING_LITERAL_K1):
        beta = 2.0 * beta_hat * ti.sqrt(m_star * k1)
    elif ti.static(n == 1.0):
        beta = 2.0 * beta_hat * ti.sqrt(m_star * k1)
    elif ti.static(n == 1.5):  # k_eff = 1.5 k1 delta^0.5 without a pow call
        beta = 2.0 * ti.sqrt(5.0 / 6.0) * beta_hat * ti.sqrt(m_star * 1.5 * k1 * ti.sqrt(delta))
    else:
        k_eff = n * k1 * ti.pow(delta, n - 1.0)
        beta = 2.0 * ti.sqrt(5.0 / 6.0) * beta_hat * ti.sqrt(m_star * k_eff)
    return beta


@ti.func
def eepa_adhesive_crossing(delta_p, k2, k_adh, n: ti.template(), chi: ti.template()):
    """Overlap x in [0, delta_p] where the k2 line meets the adhesive floor (bisection)."""
    lo = 0.0
    hi = delta_p
    if k_adh > 0.0:
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            h = k2 * (power_n(mid, n) - power_n(delta_p, n)) + k_adh * power_n(mid, chi)
            if h < 0.0:
                lo = mid
            else:
                hi = mid
    return 0.5 * (lo + hi) if k_adh > 0.0 else delta_p


@ti.func
def eepa_potential(delta, delta_p, k2, k_adh, f0, n: ti.template(), chi: ti.template()):
    """Energy [J] released by unloading from delta to separation along the current branch.

    Integral of f_hys from 0 to delta with delta_max fixed (delta <= delta_max): the elastic
    energy stored in the contact, used by the energy ledger.
    """
    x_c = eepa_adhesive_crossing(delta_p, k2, k_adh, n, chi)
    e = f0 * delta
    lo = ti.min(delta, x_c)
    e -= k_adh * power_n(lo, chi) * lo / (chi + 1.0)
    if delta > x_c:
        dpn = power_n(delta_p, n)
        e += k2 * ((power_n(delta, n) * delta - power_n(x_c, n) * x_c) / (n + 1.0)
                   - dpn * (delta - x_c))
    return e


# ---------------------------------------------------------------------- host-side evaluation
ADHESION_MODES = {"surface_energy_ap": ADHESION_SURFACE_ENERGY_AP, "jkr_R": ADHESION_JKR_R,
                  "direct_kadh": ADHESION_DIRECT}
LAW_OUTPUTS = ("force", "potential", "k1", "k2", "delta_p", "k_adh")  # columns of _law_on_host


@ti.kernel
def _law_on_host(delta: ti.types.ndarray(dtype=ti.f64, ndim=1),
                 dmax: ti.types.ndarray(dtype=ti.f64, ndim=1),
                 out: ti.types.ndarray(dtype=ti.f64, ndim=2), e_star: ti.f64, r_star: ti.f64,
                 lam: ti.f64, gamma: ti.f64, kadh_direct: ti.f64, f0: ti.f64,
                 n: ti.template(), chi: ti.template(), mode: ti.template()):
    for i in range(delta.shape[0]):
        k1 = eepa_loading_stiffness(e_star, r_star, n)
        k2 = k1 / (1.0 - lam)
        dp = eepa_plastic_overlap(dmax[i], lam, n)
        kadh = eepa_adhesion_stiffness(dp, r_star, k2, gamma, kadh_direct, n, chi, mode)
        out[i, 0] = eepa_hysteretic_force(delta[i], dp, k1, k2, kadh, f0, n, chi)
        out[i, 1] = eepa_potential(delta[i], dp, k2, kadh, f0, n, chi)
        out[i, 2] = k1
        out[i, 3] = k2
        out[i, 4] = dp
        out[i, 5] = kadh


def evaluate(delta, delta_max=None, *, e_star: float, r_star: float,
             plasticity_ratio: float = 0.0, surface_energy: float = 0.0,
             pull_off_force: float = 0.0, adhesion_stiffness: float = 0.0, n: float = 1.5,
             chi: float = 1.5, adhesion_mode: str = "surface_energy_ap") -> dict:
    """The EEPA normal law on the host: the engine's own ``ti.func``s mapped over overlaps.

    Args:
        delta: overlaps [m] (1-D).
        delta_max: the contact's largest overlap so far [m], per overlap or one value; None:
            the running maximum of ``delta`` (a loading path, as the engine tracks it).
        e_star, r_star: reduced modulus [Pa] and radius [m] of the pair.
        plasticity_ratio: lambda_p in [0, 1) (0 with no adhesion: Hertz).
        surface_energy: Delta gamma [J m^-2]; pull_off_force: f0 [N];
            adhesion_stiffness: k_adh [N m^-chi] of mode ``direct_kadh``.
        n, chi: loading and adhesive exponents (each distinct pair compiles once).
        adhesion_mode: ``surface_energy_ap``, ``jkr_R`` or ``direct_kadh``.

    Returns:
        ``{name: array}`` for :data:`LAW_OUTPUTS`: force [N] (repulsive positive), the
        elastic energy released by unloading to separation [J], k1, k2 [N m^-n], delta_p [m]
        and k_adh [N m^-chi]. Taichi is started on the CPU when it is not running.
    """
    from calendaring.core.errors import ConfigError
    from calendaring.engine.backend import current_backend, init_taichi

    if adhesion_mode not in ADHESION_MODES:
        raise ConfigError("adhesion_mode", adhesion_mode, f"one of {sorted(ADHESION_MODES)}")
    if not 0.0 <= plasticity_ratio < 1.0:
        raise ConfigError("plasticity_ratio", plasticity_ratio, "in [0, 1)")
    for key, v in (("e_star", e_star), ("r_star", r_star), ("n", n), ("chi", chi)):
        if not (math.isfinite(v) and v > 0):
            raise ConfigError(key, v, "a finite number > 0")
    d = np.ascontiguousarray(np.atleast_1d(np.asarray(delta, dtype=np.float64)))
    if d.ndim != 1:
        raise ConfigError("delta", f"array of shape {d.shape}", "a 1-D array of overlaps")
    hist = np.maximum.accumulate(d) if delta_max is None else delta_max
    hist = np.ascontiguousarray(np.broadcast_to(np.asarray(hist, dtype=np.float64), d.shape))
    if current_backend() is None:
        init_taichi(arch="cpu")
    out = np.zeros((d.size, len(LAW_OUTPUTS)))
    _law_on_host(d, hist, out, float(e_star), float(r_star), float(plasticity_ratio),
                 float(surface_energy), float(adhesion_stiffness), float(pull_off_force),
                 float(n), float(chi), ADHESION_MODES[adhesion_mode])
    return {name: out[:, k] for k, name in enumerate(LAW_OUTPUTS)}
