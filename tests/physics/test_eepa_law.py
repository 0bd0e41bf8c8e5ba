"""EEPA normal law (calendaring.engine.laws.eepa) against analytic values.

Spec references: physics-spec.md section 2 (2.1 stiffnesses, 2.2 hysteretic force, 2.3 adhesion
map, 2.4 damping) and section 9 checks T1 (EEPA loop, work ratio) and T3 (adhesion).

The laws are ``@ti.func``; the library's host evaluator ``eepa.evaluate`` maps them over
numpy arrays of overlaps in one kernel, and two small ``@ti.kernel``s here call the adhesion
modes and the damping coefficient directly. The exponents are the static
Python constants n = chi = 1.5. The contact history (delta_max) is the running maximum of the
prescribed overlap path, computed on the host exactly as calendaring.engine.forces does
(``dmax = max(delta_max, delta)``).
"""

import math

import numpy as np
import pytest
import taichi as ti

from calendaring.core.config import SimConfig
from calendaring.engine.contact_params import damping_ratio, reduced_modulus
from calendaring.engine.laws import eepa
from calendaring.engine.laws.eepa import (
    ADHESION_DIRECT,
    ADHESION_JKR_R,
    ADHESION_SURFACE_ENERGY_AP,
    DAMPING_LITERAL_K1,
    DAMPING_TANGENT_SQRT56,
    eepa_adhesion_stiffness,
    eepa_damping_coefficient,
)

N_EXP = 1.5  # loading exponent n (static)
CHI = 1.5  # adhesive exponent chi (static)

F64_1D = ti.types.ndarray(dtype=ti.f64, ndim=1)

# Output columns of evaluate() below (the order of eepa.LAW_OUTPUTS).
C_F, C_POT, C_K1, C_K2, C_DP, C_KADH = range(6)


@ti.kernel
def _kadh_modes(out: F64_1D, delta_p: ti.f64, r_star: ti.f64, k2: ti.f64, gamma: ti.f64,
                kadh_direct: ti.f64):
    """k_adh of the three adhesion modes: [surface_energy_ap, jkr_R, direct_kadh]."""
    out[0] = eepa_adhesion_stiffness(delta_p, r_star, k2, gamma, kadh_direct, N_EXP, CHI,
                                     ADHESION_SURFACE_ENERGY_AP)
    out[1] = eepa_adhesion_stiffness(delta_p, r_star, k2, gamma, kadh_direct, N_EXP, CHI,
                                     ADHESION_JKR_R)
    out[2] = eepa_adhesion_stiffness(delta_p, r_star, k2, gamma, kadh_direct, N_EXP, CHI,
                                     ADHESION_DIRECT)


@ti.kernel
def _damping(out: F64_1D, m_star: ti.f64, k1: ti.f64, delta: ti.f64, beta_hat: ti.f64):
    """beta_n: [n=1.5 tangent_sqrt56, n=1.5 literal_k1, n=1 tangent_sqrt56]."""
    out[0] = eepa_damping_coefficient(m_star, k1, delta, beta_hat, N_EXP, DAMPING_TANGENT_SQRT56)
    out[1] = eepa_damping_coefficient(m_star, k1, delta, beta_hat, N_EXP, DAMPING_LITERAL_K1)
    out[2] = eepa_damping_coefficient(m_star, k1, delta, beta_hat, 1.0, DAMPING_TANGENT_SQRT56)


def evaluate(delta, dmax, e_star, r_star, lam, gamma=0.0, f0=0.0):
    """The law (mode surface_energy_ap) at each delta through ``eepa.evaluate``, as columns
    C_F ... C_KADH; dmax may be a scalar (fixed history) or an array."""
    res = eepa.evaluate(delta, dmax, e_star=e_star, r_star=r_star, plasticity_ratio=lam,
                        surface_energy=gamma, pull_off_force=f0, n=N_EXP, chi=CHI)
    return np.stack([res[k] for k in eepa.LAW_OUTPUTS], axis=1)


def trapezoid_cumulative(f, x):
    """Cumulative trapezoid integral of f over x (starting at 0)."""
    return np.concatenate(([0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(x))))


# ----------------------------------------------------------------- pair data (spec 1.1, 1.2)
CFG = SimConfig()
AM = CFG.materials["AM"]
CB = CFG.materials["CB"]
E_AM_AM = reduced_modulus(AM, AM)  # spec 1.2: 8.957e10 Pa
E_CB_CB = reduced_modulus(CB, CB)  # spec 1.2: 3.385e8 Pa
R_AM_AM = 1.935e-6  # R* of two AM particles with d = 7.74 um [m]
R_CB_CB = 0.75e-6  # R* of two CB particles with d = 3 um [m]
DMAX = 0.1e-6  # maximum overlap used by the loops [m]


def k1_analytic(e_star, r_star):
    """k1 = (4/3) E* sqrt(R*) (spec 2.1, n = 1.5)."""
    return 4.0 / 3.0 * e_star * math.sqrt(r_star)


def work_ratio_closed_form(lam, n=N_EXP):
    """W2/W1 of spec 9 T1."""
    return (1 - lam ** ((n + 1) / n) - (n + 1) * lam * (1 - lam ** (1 / n))) / (1 - lam)


# ----------------------------------------------------------------- stiffness / Hertz limit


def test_am_am_reduced_modulus_and_k1_match_spec_table():
    """Spec 1.2: AM-AM E* = 8.957e10 Pa, k1 = 1.661e8 N m^-1.5 (4 significant figures)."""
    np.testing.assert_allclose(E_AM_AM, 8.957e10, rtol=3e-4)  # 4 figures
    out = evaluate([1e-8], DMAX, E_AM_AM, R_AM_AM, 0.0)
    np.testing.assert_allclose(out[0, C_K1], 1.661e8, rtol=1e-3)
    np.testing.assert_allclose(out[0, C_K1], k1_analytic(E_AM_AM, R_AM_AM), rtol=1e-13)
    np.testing.assert_allclose(out[0, C_K2], out[0, C_K1], rtol=1e-15)  # lambda = 0: k2 = k1


def test_hertz_limit_lambda_zero_no_adhesion():
    """lambda_p = 0, Delta gamma = 0: F = (4/3) E* sqrt(R*) delta^1.5 on loading AND unloading."""
    up = np.linspace(0.0, DMAX, 501)
    path = np.concatenate((up, up[::-1]))
    out = evaluate(path, np.maximum.accumulate(path), E_AM_AM, R_AM_AM, 0.0, gamma=5.0)
    hertz = 4.0 / 3.0 * 8.957e10 * math.sqrt(R_AM_AM) * path**1.5
    # E* is quoted to 4 figures in the spec: 1e-3 relative.
    np.testing.assert_allclose(out[:, C_F], hertz, rtol=1e-3, atol=0.0)
    exact = k1_analytic(E_AM_AM, R_AM_AM) * path**1.5
    np.testing.assert_allclose(out[:, C_F], exact, rtol=1e-12, atol=0.0)
    # delta_p = 0 -> no adhesion even with Delta gamma > 0 (spec 2.3: fresh elastic contact).
    np.testing.assert_array_equal(out[:, C_KADH], 0.0)


# ----------------------------------------------------------------- T1 loop


@pytest.mark.parametrize("lam, ratio", [(0.8, 0.8618), (0.9, 0.9322), (0.975, 0.9833)])
def test_plastic_overlap_zero_force_point(lam, ratio):
    """T1: unloading force reaches zero at delta_p = lambda^(1/n) delta_max (spec values)."""
    out = evaluate([DMAX], DMAX, E_CB_CB, R_CB_CB, lam)
    dp = out[0, C_DP]
    np.testing.assert_allclose(dp / DMAX, ratio, rtol=1e-4)  # spec values to 4 figures
    np.testing.assert_allclose(dp, lam ** (1.0 / N_EXP) * DMAX, rtol=1e-13)
    f = evaluate([dp, dp * (1 + 1e-6), dp * (1 - 1e-6)], DMAX, E_CB_CB, R_CB_CB, lam)[:, C_F]
    fscale = k1_analytic(E_CB_CB, R_CB_CB) * DMAX**N_EXP
    np.testing.assert_allclose(f[0], 0.0, atol=1e-12 * fscale)
    assert f[1] > 0.0
    assert f[2] == 0.0  # no adhesion, f0 = 0: clipped at zero, never negative


@pytest.mark.parametrize("lam", [0.5, 0.8, 0.9, 0.975])
def test_t1_load_unload_reload_loop(lam):
    """T1: delta 0 -> dmax -> 0 -> dmax -> 1.2 dmax -> 0, f0 = 0, no adhesion, n = 1.5."""
    m = 2001
    load = np.linspace(0.0, DMAX, m)
    unload = load[::-1]
    beyond = np.linspace(DMAX, 1.2 * DMAX, m)
    final = np.linspace(1.2 * DMAX, 0.0, m)
    path = np.concatenate((load, unload, load, beyond, final))
    hist = np.maximum.accumulate(path)
    out = evaluate(path, hist, E_CB_CB, R_CB_CB, lam)
    f = out[:, C_F]
    k1 = k1_analytic(E_CB_CB, R_CB_CB)
    k2 = k1 / (1 - lam)
    np.testing.assert_allclose(out[:, C_K2], k2, rtol=1e-13)
    fscale = k1 * DMAX**N_EXP
    seg = [f[i * m:(i + 1) * m] for i in range(5)]

    # virgin loading on k1
    np.testing.assert_allclose(seg[0], k1 * load**N_EXP, rtol=1e-12, atol=1e-15 * fscale)
    # unloading on the k2 line, zero below delta_p (no adhesion)
    dp = lam ** (1 / N_EXP) * DMAX
    expected_unload = np.where(unload >= dp, k2 * (unload**N_EXP - dp**N_EXP), 0.0)
    np.testing.assert_allclose(seg[1], expected_unload, rtol=1e-9, atol=1e-12 * fscale)
    assert np.all(seg[1][unload < dp] == 0.0)
    assert np.all(seg[1] >= 0.0)
    # reloading retraces the k2 line exactly ...
    np.testing.assert_allclose(seg[2], seg[1][::-1], rtol=1e-14, atol=0.0)
    # ... stays below the virgin curve and rejoins it exactly at delta_max
    inner = (load > dp) & (load < DMAX * (1 - 1e-6))
    assert np.all(seg[2][inner] < k1 * load[inner] ** N_EXP)
    np.testing.assert_allclose(seg[2][-1], k1 * DMAX**N_EXP, rtol=1e-12)
    # beyond delta_max: virgin branch again, delta_max follows the overlap
    np.testing.assert_allclose(seg[3], k1 * beyond**N_EXP, rtol=1e-12)
    # final unloading from 1.2 delta_max: new delta_p = lambda^(1/n) 1.2 delta_max
    dp2 = lam ** (1 / N_EXP) * 1.2 * DMAX
    np.testing.assert_allclose(out[-1, C_DP], dp2, rtol=1e-13)
    expected_final = np.where(final >= dp2, k2 * (final**N_EXP - dp2**N_EXP), 0.0)
    np.testing.assert_allclose(seg[4], expected_final, rtol=1e-9, atol=1e-12 * fscale)


@pytest.mark.parametrize(
    "lam, reference", [(0.5, 0.44494), (0.8, 0.17064), (0.9, 0.08429), (0.975, 0.02089)]
)
def test_work_ratio(lam, reference):
    """T1: W2/W1 from a fine numerical integration of the law = closed form = spec values."""
    m = 40001
    load = np.linspace(0.0, DMAX, m)
    unload = load[::-1]
    path = np.concatenate((load, unload))
    out = evaluate(path, np.maximum.accumulate(path), E_AM_AM, R_AM_AM, lam)
    w1 = np.trapezoid(out[:m, C_F], load)
    w2 = -np.trapezoid(out[m:, C_F], unload)  # work given back while unloading
    k1 = k1_analytic(E_AM_AM, R_AM_AM)
    np.testing.assert_allclose(w1, k1 * DMAX ** (N_EXP + 1) / (N_EXP + 1), rtol=1e-7)
    closed = work_ratio_closed_form(lam)
    np.testing.assert_allclose(w2 / w1, closed, rtol=1e-6)
    # the spec quotes five decimals: half a unit in the last place
    np.testing.assert_allclose(closed, reference, rtol=0, atol=5e-6)
    np.testing.assert_allclose(w2 / w1, reference, rtol=0, atol=5e-6)


# ----------------------------------------------------------------- T3 adhesion


class _T3:
    """Non-degenerate CB-CB-like adhesive case (spec 2.3, 9 T3)."""

    lam = 0.975
    gamma = 60.0  # J m^-2
    r_star = R_CB_CB
    e_star = E_CB_CB
    dmax = DMAX
    k1 = k1_analytic(E_CB_CB, R_CB_CB)
    k2 = k1 / (1 - lam)
    dp = lam ** (1 / N_EXP) * DMAX
    f_pull = 1.5 * math.pi * gamma * math.sqrt(R_CB_CB * dp)
    cap = k2 * dp**N_EXP
    dmin = (dp**N_EXP - f_pull / k2) ** (1 / N_EXP)
    kadh = f_pull / dmin**CHI


def test_t3_case_is_not_capped():
    """The cap min(1.5 pi dgamma a_p, k2 delta_p^n) must not be active in the T3 case."""
    np.testing.assert_allclose(E_CB_CB, 3.385e8, rtol=3e-4)  # spec 1.2 (4 figures)
    assert _T3.f_pull < 0.5 * _T3.cap
    assert 0.0 < _T3.dmin < _T3.dp


def test_t3_adhesion_stiffness_and_pull_off():
    """k_adh = F_pull / delta_min^chi and min force = -(3/2) pi dgamma sqrt(R* delta_p)."""
    t = _T3
    m = 200001
    load = np.linspace(0.0, t.dmax, 2001)
    unload = np.linspace(t.dmax, 0.0, m)
    path = np.concatenate((load, unload))
    out = evaluate(path, np.maximum.accumulate(path), t.e_star, t.r_star, t.lam, t.gamma)
    np.testing.assert_allclose(out[-1, C_DP], t.dp, rtol=1e-13)
    np.testing.assert_allclose(out[-1, C_KADH], t.kadh, rtol=1e-10)
    f_un = out[2001:, C_F]
    # minimum over a fine unloading path: never below -F_pull, within one grid step of it
    assert f_un.min() >= -t.f_pull * (1 + 1e-12)
    np.testing.assert_allclose(f_un.min(), -t.f_pull, rtol=2e-4)
    step = t.dmax / (m - 1)
    assert abs(unload[np.argmin(f_un)] - t.dmin) <= step
    # exactly at delta_min (closed form of spec 2.3)
    f_at = evaluate([t.dmin], t.dmax, t.e_star, t.r_star, t.lam, t.gamma)[0, C_F]
    np.testing.assert_allclose(f_at, -t.f_pull, rtol=1e-10)


def test_t3_force_continuous_at_delta_min_and_vanishes_at_contact():
    """F continuous at delta_min (k2 line meets the adhesive floor); F -> f0 as delta -> 0+."""
    t = _T3
    eps = 1e-9
    d = np.array([t.dmin * (1 - eps), t.dmin, t.dmin * (1 + eps)])
    f = evaluate(d, t.dmax, t.e_star, t.r_star, t.lam, t.gamma)[:, C_F]
    np.testing.assert_allclose(f, -t.f_pull, rtol=1e-7)
    # branch values on either side: floor below, k2 line above
    np.testing.assert_allclose(f[0], -t.kadh * d[0] ** CHI, rtol=1e-10)
    np.testing.assert_allclose(f[2], t.k2 * (d[2] ** N_EXP - t.dp**N_EXP), rtol=1e-9)
    small = t.dmin * np.array([1e-3, 1e-6, 1e-9])
    for f0 in (0.0, -2.0e-6):
        fs = evaluate(small, t.dmax, t.e_star, t.r_star, t.lam, t.gamma, f0=f0)[:, C_F]
        np.testing.assert_allclose(fs, f0 - t.kadh * small**CHI, rtol=1e-10)
        np.testing.assert_allclose(fs[-1], f0, rtol=0, atol=1e-12 * t.f_pull)


def test_adhesion_modes_jkr_and_direct():
    """jkr_R: F_pull = 1.5 pi dgamma R*; direct_kadh: the configured k_adh; zero if delta_p = 0."""
    t = _T3
    out = np.zeros(3)
    _kadh_modes(out, t.dp, t.r_star, t.k2, t.gamma, 123.0)
    np.testing.assert_allclose(out[0], t.kadh, rtol=1e-10)
    f_jkr = 1.5 * math.pi * t.gamma * t.r_star
    assert f_jkr < t.cap
    dmin_jkr = (t.dp**N_EXP - f_jkr / t.k2) ** (1 / N_EXP)
    np.testing.assert_allclose(out[1], f_jkr / dmin_jkr**CHI, rtol=1e-10)
    np.testing.assert_allclose(out[2], 123.0, rtol=1e-15)
    _kadh_modes(out, 0.0, t.r_star, t.k2, t.gamma, 123.0)
    np.testing.assert_array_equal(out[:2], 0.0)  # fresh elastic contact: no adhesion


def test_capped_adhesion_gives_zero_kadh():
    """Spec 2.3: capped F_pull = k2 delta_p^n -> delta_min = 0 -> k_adh = 0 (no adhesion)."""
    t = _T3
    dmax = np.geomspace(1e-11, 1.0e-8, 200)  # all in the capped regime for CB-CB
    dp = t.lam ** (1 / N_EXP) * dmax
    assert np.all(1.5 * math.pi * t.gamma * np.sqrt(t.r_star * dp) > t.k2 * dp**N_EXP)
    out = evaluate(1e-3 * dp, dmax, t.e_star, t.r_star, t.lam, t.gamma)
    np.testing.assert_array_equal(out[:, C_KADH], 0.0)
    np.testing.assert_array_equal(out[:, C_F], 0.0)


# ----------------------------------------------------------------- potential


@pytest.mark.parametrize(
    "e_star, r_star, lam, gamma",
    [(E_AM_AM, R_AM_AM, 0.8, 0.0), (E_CB_CB, R_CB_CB, 0.975, 60.0),
     (E_CB_CB, R_CB_CB, 0.9, 20.0)],
    ids=["no-adhesion", "adhesion-cbcb", "adhesion-lam0.9"],
)
def test_potential_equals_integral_of_force(e_star, r_star, lam, gamma):
    """eepa_potential(delta) = integral_0^delta f_hys (delta_max fixed) to 1e-6 relative."""
    m = 400001
    grid = np.linspace(0.0, DMAX, m)
    out = evaluate(grid, DMAX, e_star, r_star, lam, gamma)
    integral = trapezoid_cumulative(out[:, C_F], grid)
    dp = lam ** (1 / N_EXP) * DMAX
    w1 = k1_analytic(e_star, r_star) * DMAX ** (N_EXP + 1) / (N_EXP + 1)
    if gamma > 0.0:
        picks = [0.2 * dp, 0.5 * dp, 0.95 * dp, dp, 0.995 * DMAX, DMAX]
    else:
        picks = [0.5 * (dp + DMAX), 0.995 * DMAX, DMAX]
        below = out[grid <= dp, C_POT]
        np.testing.assert_array_equal(below, 0.0)  # no force (f0 = 0) below delta_p
        # at delta_max the stored energy is W2 of T1
        np.testing.assert_allclose(out[-1, C_POT], work_ratio_closed_form(lam) * w1, rtol=1e-10)
    idx = [round(p / DMAX * (m - 1)) for p in picks]
    pot = out[idx, C_POT]
    ref = integral[idx]
    assert np.all(np.abs(ref) > 1e-5 * w1)  # keep away from a sign change of the integral
    np.testing.assert_allclose(pot, ref, rtol=1e-6)
    if gamma > 0.0:
        assert np.all(ref < 0.0)  # the adhesive well dominates the stored energy here


# ----------------------------------------------------------------- damping


def test_normal_damping_coefficient():
    """Spec 2.4: tangent_sqrt56 and literal_k1 damping coefficients."""
    beta_hat = damping_ratio(0.25)
    np.testing.assert_allclose(beta_hat, 0.4037, rtol=1e-4)
    d = 7.74e-6
    m = AM.density * math.pi * d**3 / 6.0
    m_star = 0.5 * m
    k1 = k1_analytic(E_AM_AM, R_AM_AM)
    delta = 2.0e-8
    out = np.zeros(3)
    _damping(out, m_star, k1, delta, beta_hat)
    k_eff = 1.5 * k1 * math.sqrt(delta)  # n k1 delta^(n-1)
    tangent = 2.0 * math.sqrt(5.0 / 6.0) * beta_hat * math.sqrt(m_star * k_eff)
    np.testing.assert_allclose(out[0], tangent, rtol=1e-12)
    ln_e = math.log(0.25)
    literal = math.sqrt(4.0 * m_star * k1 / (1.0 + (math.pi / ln_e) ** 2))
    np.testing.assert_allclose(out[1], literal, rtol=1e-12)
    # n = 1: 2 beta_hat sqrt(m* k1) is exactly paper Eq. 10
    np.testing.assert_allclose(out[2], literal, rtol=1e-12)


def test_host_evaluator_follows_the_path_history_and_rejects_bad_input():
    """eepa.evaluate without delta_max takes the running maximum of the path (the engine's
    history), and names the key, value and range of a bad argument."""
    from calendaring.core.errors import ConfigError

    path = np.concatenate([np.linspace(0, DMAX, 40), np.linspace(DMAX, 0.3 * DMAX, 20)])
    auto = eepa.evaluate(path, e_star=E_CB_CB, r_star=R_CB_CB, plasticity_ratio=0.5,
                         surface_energy=0.05)
    given = eepa.evaluate(path, np.maximum.accumulate(path), e_star=E_CB_CB, r_star=R_CB_CB,
                          plasticity_ratio=0.5, surface_energy=0.05)
    for key in eepa.LAW_OUTPUTS:
        np.testing.assert_array_equal(auto[key], given[key])
    # unloading from DMAX: on the k2 line, below the virgin curve k1 delta^1.5
    k1 = k1_analytic(E_CB_CB, R_CB_CB)
    assert np.all(auto["force"][41:] < k1 * path[41:] ** 1.5)
    np.testing.assert_allclose(auto["delta_p"][-1], 0.5 ** (1 / 1.5) * DMAX, rtol=1e-12)
    for kwargs, key in (({"adhesion_mode": "glue"}, "adhesion_mode"),
                        ({"plasticity_ratio": 1.0}, "plasticity_ratio"),
                        ({"r_star": -1.0}, "r_star")):
        args = {"e_star": E_CB_CB, "r_star": R_CB_CB, **kwargs}
        with pytest.raises(ConfigError) as err:
            eepa.evaluate(path, **args)
        assert err.value.key == key
