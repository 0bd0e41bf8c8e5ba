"""Tangential spring with Coulomb limit and rolling resistance against analytic values.

Spec references: physics-spec.md section 3 (3.1 spring, 3.2 Coulomb limit, 3.3 rolling) and
section 9 check T4. The ``@ti.func`` laws are wrapped in small kernels defined here; the
spring update mirrors calendaring.engine.forces ``_law`` without the dashpot:
``s = rotate_spring(s, n) - k_t v_t dt``; if ``|s| > limit``: ``s = limit s/|s|``.
"""

import math

import numpy as np
import pytest
import taichi as ti

from calendaring.core.config import SimConfig
from calendaring.engine.contact_params import reduced_modulus, reduced_shear_modulus
from calendaring.engine.laws.eepa import (
    ADHESION_SURFACE_ENERGY_AP,
    eepa_adhesion_stiffness,
    eepa_hysteretic_force,
    eepa_loading_stiffness,
    eepa_plastic_overlap,
)
from calendaring.engine.laws.rolling import rolling_torque
from calendaring.engine.laws.tangential import coulomb_limit, rotate_spring, tangential_stiffness

N_EXP = 1.5
CHI = 1.5
XI_T = 2.0 / 3.0  # default tangential_stiffness_ratio

F64_1D = ti.types.ndarray(dtype=ti.f64, ndim=1)
F64_2D = ti.types.ndarray(dtype=ti.f64, ndim=2)


@ti.kernel
def _spring_history(du: F64_1D, out: F64_2D, info: F64_1D, delta: ti.f64, dmax: ti.f64,
                    e_star: ti.f64, g_star: ti.f64, r_star: ti.f64, lam: ti.f64, gamma: ti.f64,
                    f0: ti.f64, friction: ti.f64, ratio: ti.f64, dt: ti.f64):
    """Constant overlap/normal load; step k imposes the tangential displacement du[k] along x.

    out[k] = spring force after step k; info = [k_t, Coulomb limit, f_hys, k_adh].
    """
    ti.loop_config(serialize=True)
    for _ in range(1):
        nrm = ti.Vector([0.0, 0.0, 1.0])
        k1 = eepa_loading_stiffness(e_star, r_star, N_EXP)
        k2 = k1 / (1.0 - lam)
        dp = eepa_plastic_overlap(dmax, lam, N_EXP)
        kadh = eepa_adhesion_stiffness(dp, r_star, k2, gamma, 0.0, N_EXP, CHI,
                                       ADHESION_SURFACE_ENERGY_AP)
        f_hys = eepa_hysteretic_force(delta, dp, k1, k2, kadh, f0, N_EXP, CHI)
        k_t = tangential_stiffness(g_star, r_star, delta, k1, ratio, N_EXP)
        limit = coulomb_limit(friction, f_hys, kadh, delta, f0, CHI)
        info[0] = k_t
        info[1] = limit
        info[2] = f_hys
        info[3] = kadh
        s = ti.Vector([0.0, 0.0, 0.0])
        for k in range(du.shape[0]):
            v_t = ti.Vector([du[k] / dt, 0.0, 0.0])
            s = rotate_spring(s, nrm) - k_t * v_t * dt
            mag = s.norm()
            if mag > limit:
                s = limit * s / mag
            for c in ti.static(range(3)):
                out[k, c] = s[c]


@ti.kernel
def _stiffness(out: F64_1D, g_star: ti.f64, r_star: ti.f64, delta: ti.f64, k1: ti.f64,
               ratio: ti.f64):
    """k_t for n = 1.5 and n = 1."""
    out[0] = tangential_stiffness(g_star, r_star, delta, k1, ratio, 1.5)
    out[1] = tangential_stiffness(g_star, r_star, delta, k1, ratio, 1.0)


@ti.kernel
def _rotate(springs: F64_2D, normals: F64_2D, out: F64_2D):
    for i in range(springs.shape[0]):
        s = ti.Vector([springs[i, 0], springs[i, 1], springs[i, 2]])
        n = ti.Vector([normals[i, 0], normals[i, 1], normals[i, 2]])
        r = rotate_spring(s, n)
        for c in ti.static(range(3)):
            out[i, c] = r[c]


@ti.kernel
def _rolling(mag: F64_1D, omega: F64_2D, inv_inertia: F64_1D, dt: ti.f64, out: F64_2D):
    for i in range(mag.shape[0]):
        w = ti.Vector([omega[i, 0], omega[i, 1], omega[i, 2]])
        tau = rolling_torque(mag[i], w, inv_inertia[i], dt)
        for c in ti.static(range(3)):
            out[i, c] = tau[c]


CFG = SimConfig()
CB = CFG.materials["CB"]
AM = CFG.materials["AM"]
E_CB = reduced_modulus(CB, CB)
G_CB = reduced_shear_modulus(CB, CB)
R_CB = 0.75e-6  # R* of two 3 um CB particles [m]
DMAX = 0.1e-6  # m
LAM = 0.975
GAMMA = 60.0
MU = 0.12  # paper mu_s


def _cbcb_constants():
    """Host-side analytic EEPA constants of the CB-CB adhesive contact (spec 2.1-2.3)."""
    k1 = 4.0 / 3.0 * E_CB * math.sqrt(R_CB)
    k2 = k1 / (1 - LAM)
    dp = LAM ** (1 / N_EXP) * DMAX
    f_pull = 1.5 * math.pi * GAMMA * math.sqrt(R_CB * dp)
    assert f_pull < k2 * dp**N_EXP  # not capped
    dmin = (dp**N_EXP - f_pull / k2) ** (1 / N_EXP)
    kadh = f_pull / dmin**CHI
    return k1, k2, dp, kadh, dmin


def _expected_limit(delta):
    """mu |f_hys + k_adh delta^chi - f0| with f0 = 0 (spec 3.2); delta on the given branch."""
    k1, k2, dp, kadh, _ = _cbcb_constants()
    if delta >= DMAX:
        f_hys = k1 * delta**N_EXP
    else:
        f_hys = max(k2 * (delta**N_EXP - dp**N_EXP), -kadh * delta**CHI)
    return f_hys, MU * abs(f_hys + kadh * delta**CHI)


def _run_history(delta, du):
    out = np.zeros((du.size, 3))
    info = np.zeros(4)
    _spring_history(du, out, info, delta, DMAX, E_CB, G_CB, R_CB, LAM, GAMMA, 0.0, MU, XI_T,
                    1.0e-10)
    return out, info


@pytest.mark.parametrize("branch", ["virgin", "k2-line-tensile"])
def test_t4_coulomb_stick_slip_and_reversal(branch):
    """T4: |F_t| = k_t u up to mu|f_hys + k_adh delta^chi - f0|, then constant; reversal
    unloads with slope k_t and slides at the opposite limit."""
    _k1, _k2, dp, kadh, dmin = _cbcb_constants()
    # virgin: delta = delta_max (f_hys = k1 delta^n > 0); k2 line between delta_min and delta_p
    # where f_hys < 0 (tensile) but above the adhesive floor.
    delta = DMAX if branch == "virgin" else 0.5 * (dmin + dp)
    f_hys_exp, limit_exp = _expected_limit(delta)
    if branch != "virgin":
        assert f_hys_exp < 0.0 and f_hys_exp > -kadh * delta**CHI
    kt_exp = XI_T * 8.0 * G_CB * math.sqrt(R_CB * delta)
    u_slip = limit_exp / kt_exp

    m_out, m_back = 300, 600
    du = np.concatenate((np.full(m_out, 3.0 * u_slip / m_out),
                         np.full(m_back, -6.0 * u_slip / m_back)))
    u = np.cumsum(du)
    out, info = _run_history(delta, du)
    np.testing.assert_allclose(info[0], kt_exp, rtol=1e-12)
    np.testing.assert_allclose(info[2], f_hys_exp, rtol=1e-9)
    np.testing.assert_allclose(info[3], kadh, rtol=1e-10)
    np.testing.assert_allclose(info[1], limit_exp, rtol=1e-9)

    fx = out[:, 0]
    np.testing.assert_array_equal(out[:, 1:], 0.0)  # stays along the displacement axis
    # forward: spring opposes the displacement, |F| = k_t u, then the limit
    fwd_u, fwd_f = u[:m_out], fx[:m_out]
    np.testing.assert_allclose(np.abs(fwd_f), np.minimum(kt_exp * fwd_u, limit_exp),
                               rtol=1e-9)
    assert np.all(fwd_f <= 0.0)
    assert np.sum(fwd_u < u_slip * (1 - 1e-9)) >= 99  # a real stick phase was sampled
    # reversal from u_rev = 3 u_slip: F = -L + k_t (u_rev - u) until +L, then constant
    u_rev = u[m_out - 1]
    back_u, back_f = u[m_out:], fx[m_out:]
    expected = np.minimum(-limit_exp + kt_exp * (u_rev - back_u), limit_exp)
    np.testing.assert_allclose(back_f, expected, rtol=1e-9, atol=1e-9 * limit_exp)
    elastic = (back_u > u_rev - 2 * u_slip * (1 - 1e-6))
    slope = np.diff(back_f[elastic]) / np.diff(back_u[elastic])
    np.testing.assert_allclose(slope, -kt_exp, rtol=1e-6)
    np.testing.assert_allclose(back_f[-1], limit_exp, rtol=1e-12)


def test_coulomb_limit_zero_on_adhesive_floor():
    """On the adhesive branch f_hys = -k_adh delta^chi, so the limit (spec 3.2) is 0: a spring
    increment is truncated to zero."""
    _, _, _, kadh, dmin = _cbcb_constants()
    delta = 0.5 * dmin
    out, info = _run_history(delta, np.full(5, 1e-12))
    np.testing.assert_allclose(info[2], -kadh * delta**CHI, rtol=1e-10)
    np.testing.assert_allclose(info[1], 0.0, atol=1e-12 * kadh * delta**CHI)
    np.testing.assert_allclose(out, 0.0, atol=1e-12 * kadh * delta**CHI)


def test_tangential_stiffness_forms():
    """k_t = xi 8 G* sqrt(R* delta) (n = 1.5) and xi k1 (n = 1)."""
    g_star = reduced_shear_modulus(AM, AM)
    np.testing.assert_allclose(g_star, 1.925e10, rtol=3e-4)  # spec 1.2 (4 figures)
    r_star, delta, k1 = 1.935e-6, 3.0e-8, 1.661e8
    out = np.zeros(2)
    _stiffness(out, g_star, r_star, delta, k1, XI_T)
    np.testing.assert_allclose(out[0], XI_T * 8.0 * g_star * math.sqrt(r_star * delta),
                               rtol=1e-13)
    np.testing.assert_allclose(out[1], XI_T * k1, rtol=1e-15)


def test_rotate_spring_keeps_magnitude_and_is_tangent():
    rng = np.random.default_rng(0)
    springs = rng.normal(size=(64, 3)) * 1e-4
    normals = rng.normal(size=(64, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    out = np.zeros_like(springs)
    _rotate(springs, normals, out)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), np.linalg.norm(springs, axis=1),
                               rtol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", out, normals), 0.0,
                               atol=1e-12 * np.abs(springs).max())
    # the rotated spring stays in the plane spanned by the old spring and the normal, and on
    # the same side as the old spring's tangential part
    proj = springs - np.einsum("ij,ij->i", springs, normals)[:, None] * normals
    cos = np.einsum("ij,ij->i", out, proj) / (np.linalg.norm(out, axis=1)
                                               * np.linalg.norm(proj, axis=1))
    np.testing.assert_allclose(cos, 1.0, rtol=1e-12)
    # a spring already in the tangent plane is unchanged
    tangent = proj.copy()
    out2 = np.zeros_like(tangent)
    _rotate(tangent, normals, out2)
    np.testing.assert_allclose(out2, tangent, rtol=1e-12, atol=1e-14 * np.abs(tangent).max())


def test_rotate_spring_small_tilts_take_the_series_to_the_last_bit():
    """A spring tilted out of the tangent plane by a small angle (the case of every step:
    x = (s.n)^2/|s|^2 ~ 1e-11 in a compacting bed) is restored by the series of
    1/sqrt(1 - x), on either side of the switch to the root at x = SERIES_FRACTION."""
    from calendaring.engine.laws.tangential import SERIES_FRACTION

    rng = np.random.default_rng(1)
    m = 200
    normals = rng.normal(size=(m, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    tangent = rng.normal(size=(m, 3))
    tangent -= np.einsum("ij,ij->i", tangent, normals)[:, None] * normals
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    # x = sin^2(theta) from 1e-16 up to 1e-4, with pairs straddling the switch
    x = np.concatenate([np.logspace(-16, -4, m - 40),
                        SERIES_FRACTION * (1.0 + np.linspace(-1e-3, 1e-3, 40))])
    theta = np.arcsin(np.sqrt(x))
    scale = 10.0 ** rng.uniform(-12, -3, m)  # N or N m: magnitudes of forces and moments
    springs = scale[:, None] * (np.cos(theta)[:, None] * tangent
                                + np.sin(theta)[:, None] * normals)
    out = np.zeros_like(springs)
    _rotate(springs, normals, out)
    mag = np.linalg.norm(springs, axis=1)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), mag, rtol=2e-15)
    np.testing.assert_allclose(np.einsum("ij,ij->i", out, normals) / mag, 0.0, atol=1e-15)
    np.testing.assert_allclose(out / mag[:, None], tangent, rtol=0, atol=3e-15)


def test_rolling_torque_below_cap_capped_and_guard():
    """Spec 3.3: tau = -M omega_hat; |tau| <= |omega|/(dt inv_I); zero for |omega| < 1e-12."""
    d = 7.74e-6
    r = 0.5 * d
    m = AM.density * math.pi * d**3 / 6.0
    inv_i = 1.0 / (0.4 * m * r * r)
    dt = 8.97e-11
    f_hys = 1.0e-3  # N
    mag = 0.01 * f_hys * r  # mu_r |f_hys| |r|
    w_dir = np.array([1.0, -2.0, 2.0]) / 3.0
    cases = [
        (mag, 1.0e4 * w_dir, inv_i),  # fast spin: below the cap
        (mag, 1.0 * w_dir, inv_i),  # slow spin: capped
        (mag, 5.0e-13 * w_dir, inv_i),  # below the 1e-12 rad/s guard
        (0.0, 1.0e4 * w_dir, inv_i),  # no contact torque
        (mag, 1.0 * w_dir, 0.0),  # infinite inertia: no cap
    ]
    mags = np.array([c[0] for c in cases])
    omegas = np.array([c[1] for c in cases])
    invs = np.array([c[2] for c in cases])
    out = np.zeros((len(cases), 3))
    _rolling(mags, omegas, invs, dt, out)

    cap_fast = 1.0e4 / (dt * inv_i)
    assert mag < cap_fast
    np.testing.assert_allclose(out[0], -mag * w_dir, rtol=1e-12)
    cap_slow = 1.0 / (dt * inv_i)
    assert cap_slow < mag
    np.testing.assert_allclose(out[1], -cap_slow * w_dir, rtol=1e-12)
    # one step with the capped torque brings the spin to zero, never reverses it
    w_next = omegas[1] + dt * inv_i * out[1]
    np.testing.assert_allclose(w_next, 0.0, atol=1e-12)
    np.testing.assert_array_equal(out[2], 0.0)
    np.testing.assert_array_equal(out[3], 0.0)
    np.testing.assert_allclose(out[4], -mag * w_dir, rtol=1e-12)
