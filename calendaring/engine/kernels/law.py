"""The contact law of one contact, evaluated from a contact table: the normal EEPA force
with adhesion and plasticity, damping, the tangential spring with Coulomb's limit, and the
stored elastic energy (spec 2-3). Shared by particle pairs (:mod:`.pairs`) and particle-plate
contacts (:mod:`.particles`), and by the energy ledger (:mod:`.ledger`).

See also: :mod:`calendaring.engine.laws` (the pure laws this maps over table columns).
"""

import taichi as ti

from calendaring.engine.contact_params import COL
from calendaring.engine.laws.eepa import (
    DAMPING_TANGENT_SQRT56,
    eepa_adhesion_stiffness,
    eepa_damping_coefficient,
    eepa_hysteretic_force,
    eepa_loading_stiffness,
    eepa_potential,
    power_n,
)
from calendaring.engine.laws.tangential import coulomb_limit, rotate_spring, tangential_stiffness


class ContactLaw:
    """``_law`` and ``_stored``: the static switches ``n``, ``chi``, ``xi_t``,
    ``adhesion_mode``, ``damping_mode``, ``adhesive``, ``plastic`` and ``track_energy``."""

    @ti.func
    def _law(self, tab: ti.template(), a, b, delta, delta_prev, nrm, v_rel, m_star, r_star, sr,
             dt, delta_max, spring, fhys_prev, no_adhesion):
        """Contact force of one contact (spec 2-3), shared by particle pairs and plates
        (``m_star``, ``r_star``: reduced mass and radius; ``sr`` = sqrt(r_star)).

        Returns the force on body i, the tangential force, f_hys, the updated history, the
        normal force magnitude, the energy increments (damping n/t, friction, hysteresis) and
        the stressing-work increment of the contact (spec 5.4: repulsive hysteretic work plus
        ``breakage.shear_weight`` x tangential spring work). ``no_adhesion`` switches the
        adhesive terms off (force-free sibling fragments until they first separate).
        """
        n = ti.static(self.n)
        chi = ti.static(self.chi)
        # n = 1.5 with the default damping: sqrt(delta) taken once and both damping
        # coefficients from one root, sqrt(m* sqrt(R* delta)) (the factors are table
        # columns): five square roots fewer per contact than the general forms
        hertz = ti.static(n == 1.5)
        fused = ti.static(n == 1.5 and self.damping_mode == DAMPING_TANGENT_SQRT56)
        e_star = tab[a, b, COL["e_star"]]
        beta_hat = tab[a, b, COL["beta_hat"]]
        k1 = 0.0
        sd = 0.0
        if ti.static(hertz):
            sd = ti.sqrt(delta)
            k1 = (4.0 / 3.0) * e_star * sr
        else:
            k1 = eepa_loading_stiffness(e_star, r_star, n)
        dmax = ti.max(delta_max, delta)
        # compiled without the terms that every contact of the model has at zero (no
        # adhesion: f0 = k_adh = 0; no plasticity: k2 = k1, delta_p = 0): the same numbers,
        # f_hys = k1 delta^n to the bit
        f0 = 0.0
        k2 = k1
        delta_p = 0.0
        k_adh = 0.0
        if ti.static(self.plastic):
            k2 = k1 * tab[a, b, COL["unloading_factor"]]
            delta_p = tab[a, b, COL["plastic_factor"]] * dmax  # lambda_p^(1/n) delta_max
        if ti.static(self.adhesive):
            f0 = tab[a, b, COL["pull_off_force"]]
            k_adh = eepa_adhesion_stiffness(delta_p, r_star, k2,
                                            tab[a, b, COL["surface_energy"]],
                                            tab[a, b, COL["adhesion_stiffness"]], n, chi,
                                            ti.static(self.adhesion_mode))
            if no_adhesion:
                f0 = 0.0
                k_adh = 0.0
        f_hys = 0.0
        if ti.static(self.adhesive or self.plastic):
            f_hys = eepa_hysteretic_force(delta, delta_p, k1, k2, k_adh, f0, n, chi)
        elif ti.static(hertz):
            f_hys = k1 * (delta * sd)
        else:
            f_hys = k1 * power_n(delta, n)
        beta_n = 0.0
        k_t = 0.0
        beta_t = 0.0
        if ti.static(fused):
            root = ti.sqrt(m_star * sr * sd)
            beta_n = tab[a, b, COL["normal_damping_factor"]] * root
            k_t = ti.static(8.0 * self.xi_t) * tab[a, b, COL["g_star"]] * sr * sd
            beta_t = tab[a, b, COL["tangential_damping_factor"]] * root
        else:
            beta_n = eepa_damping_coefficient(m_star, k1, delta, beta_hat, n,
                                              ti.static(self.damping_mode))
            k_t = tangential_stiffness(tab[a, b, COL["g_star"]], r_star, delta, k1,
                                       ti.static(self.xi_t), n)
            beta_t = 2.0 * beta_hat * ti.sqrt(m_star * k_t)
        delta_dot = v_rel.dot(nrm)
        f_nd = beta_n * delta_dot
        f_n = f_hys + f_nd
        v_t = v_rel - delta_dot * nrm
        s_old = rotate_spring(spring, nrm)
        s = s_old - k_t * v_t * dt
        f_t = s - beta_t * v_t
        limit = 0.0
        if ti.static(self.adhesive):
            limit = coulomb_limit(tab[a, b, COL["friction"]], f_hys, k_adh, delta, f0, chi)
        else:
            limit = tab[a, b, COL["friction"]] * ti.abs(f_hys)
        friction_loss = 0.0
        damp_t = beta_t * v_t.norm_sqr() * dt
        ft2 = f_t.norm_sqr()
        # Sliding (the spring sits on the Coulomb limit): about half the contacts of a
        # compacting bed slide, at random, so the root and the quotient are taken for
        # every contact and the test only selects values (a branch around them was
        # mispredicted often enough to cost ~10 % of the pair loop)
        s_new = ti.sqrt(limit * limit / ti.max(ft2, 1e-300)) * f_t
        slide = ft2 > limit * limit
        if ti.static(self.track_energy):  # |s_new| = limit when sliding; selected, too
            friction_loss = ti.select(slide & (k_t > 0.0),
                                      (s.norm_sqr() - limit * limit) / (2.0 * k_t), 0.0)
        s = ti.select(slide, s_new, s)
        f_t = ti.select(slide, s_new, f_t)
        damp_t = ti.select(slide, 0.0, damp_t)
        force_i = -f_n * nrm + f_t
        hyst = 0.5 * (fhys_prev + f_hys) * (delta - delta_prev)
        work = 0.0
        if ti.static(self.breakage):
            work = 0.5 * (ti.max(fhys_prev, 0.0) + ti.max(f_hys, 0.0)) * (delta - delta_prev)
            if ti.static(self.shear_weight > 0.0):
                work += ti.static(self.shear_weight) * (-0.5) * (s_old + s).dot(v_t) * dt
        return (force_i, f_t, f_hys, dmax, s, ti.abs(f_n), f_nd * delta_dot * dt, damp_t,
                friction_loss, hyst, work)

    @ti.func
    def _stored(self, tab: ti.template(), a, b, delta, r_star, delta_max):
        n = ti.static(self.n)
        chi = ti.static(self.chi)
        e = 0.0
        if delta > 0.0:
            k1 = eepa_loading_stiffness(tab[a, b, COL["e_star"]], r_star, n)
            k2 = k1 * tab[a, b, COL["unloading_factor"]]  # as the contact law has it
            dmax = ti.max(delta_max, delta)
            delta_p = tab[a, b, COL["plastic_factor"]] * dmax  # lambda_p^(1/n) delta_max
            k_adh = eepa_adhesion_stiffness(delta_p, r_star, k2, tab[a, b, COL["surface_energy"]],
                                            tab[a, b, COL["adhesion_stiffness"]], n, chi,
                                            ti.static(self.adhesion_mode))
            e = eepa_potential(delta, delta_p, k2, k_adh, tab[a, b, COL["pull_off_force"]], n,
                               chi)
        return e
