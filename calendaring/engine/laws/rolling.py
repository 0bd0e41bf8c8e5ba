"""Rolling resistance: EDEM's constant directional torque (Sakaguchi 1993; Ai et al. 2011
type A; paper Eq. 19, spec 3.3).

    tau_r,i = - mu_r |f_hys| |r_i| omega_hat_i

summed over the contacts of particle i. [A] anti-chatter guard: no torque below
|omega| = 1e-12 rad/s, and the total is capped so that one step cannot reverse the spin
(|tau| dt / I <= |omega|).

See also: :mod:`calendaring.engine.laws.tangential`, :mod:`calendaring.engine.kernels.particles`
(applies the torque per particle).
"""

import taichi as ti

OMEGA_EPS = 1e-12  # rad/s


@ti.func
def rolling_torque(magnitude, omega, inv_inertia, dt):
    """Total rolling torque [N m] of a particle from its summed magnitude sum_c mu_r|f||r|."""
    w = omega.norm()
    tau = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
    if w > OMEGA_EPS and magnitude > 0.0:
        cap = w / (dt * inv_inertia) if inv_inertia > 0.0 else magnitude
        tau = -ti.min(magnitude, cap) * omega / w
    return tau
