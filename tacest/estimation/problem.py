"""The physics-constrained maximum-likelihood problem as ONE CasADi NLP (2-D).

Decision variables (all scaled to O(1); see :class:`Scales`):

- shared parameters ``theta`` = [shape s (n_s), log(m/m0), log(I / I_uniform), mu_ground, mu_finger]
- per run i, per sample t: pose q[t] (3), velocity v[t] (3); per interval (t-1, t]:
  ground impulses [lambda_n (K), lambda_t (K)] at each shape vertex and finger impulses
  [lambda_n (F), lambda_t (F)] in the contact frame of each finger.

Data (recorded streams, noise levels, homotopy settings) are CasADi *parameters*, so the
NLP is built once per structure (shape, run lengths, fingers) and re-solved with new data.

Loss (whitened residuals, names as written into estimate files)::

    force          (lambda_f / dt - F_meas) / sigma_F                 where a force stream exists
    normal         c (n_meas - n_model) / sigma_n
    contact        c phi_f / sigma_gap  +  (1 - c) min(phi_f, 0) / sigma_gap
    pose           (q - q_obs) / sigma_pose                           where observed
    dynamics       eq. D1 residual / (process · m0 g dt)
    penetration    min(phi_ground, 0) / sigma_pen
    complementarity  lambda_n phi⁺ (eq. C1, relaxed; phi⁺ a smoothed max(phi, 0))
    dissipation    mu lambda_n |s| + lambda_t s  >= 0 (eq. C3, zero at maximal dissipation)

subject to eq. D2 (kinematics, equality), the friction cones (eq. C2), lambda_n >= 0 and
the shape's validity constraints.  Objective = 0.5 Σ w ||r||² + w_c Σ comp + w_d Σ diss
+ priors.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from tacest.dynamics.rigid2d import generalized_impulse, ground_contacts, mass_matrix_diag, perp, point_velocity
from tacest.estimation.config import EstimatorConfig
from tacest.geometry.shapes import Shape, polygon_area_centroid_j, polygon_sd_and_normal_function, rot2

#: squared-residual terms, in the order the stage function returns them
SQUARED_TERMS = ("force", "normal", "contact", "pose", "dynamics", "penetration")
#: penalty terms (non-negative, not squared)
PENALTY_TERMS = ("complementarity", "dissipation")
TERMS = SQUARED_TERMS + PENALTY_TERMS
#: smoothing of |slip| relative to the gap smoothing epsilon: the homotopy's epsilon is
#: in units of the contact-gap sigma for phi and of SLIP_EPS_RATIO · (L per second) for
#: slip, so that eps = 1 smooths |s| over ±2 % of an object length per second (the
#: penalty's bias mu·lambda_n·eps is then small against the measurement terms)
SLIP_EPS_RATIO = 0.02
#: names of the physical parameters in theta after the shape block
PHYS_NAMES = ("log_mass", "log_inertia_ratio", "friction_ground", "friction_finger")


@dataclass(frozen=True)
class RunStructure:
    """What fixes the NLP's structure for one run: samples T and fingers F."""

    T: int
    F: int


def smooth_pos(x, eps):
    """Smoothed max(x, 0): 0.5 (x + sqrt(x² + eps²)); exact as eps → 0."""
    return 0.5 * (x + ca.sqrt(x * x + eps * eps))


def smooth_abs(x, eps):
    """Smoothed |x|: sqrt(x² + eps²)."""
    return ca.sqrt(x * x + eps * eps)


# indices into the per-run global parameter vector
G_NAMES = ("dt", "L", "Lam", "m0", "nx", "ny", "h", "sig_force", "sig_normal", "sig_gap", "sig_proc",
           "sig_pen", "sig_rest", "sig_pos", "sig_ang", "eps", "comp_mult")
G = {n: i for i, n in enumerate(G_NAMES)}


class Problem2D:
    """The NLP for a set of runs of one object (see module docstring).

    Parameters
    ----------
    shape : Shape parameterization (box, polygon:K)
    structures : list of RunStructure, one per run
    config : EstimatorConfig
    """

    def __init__(self, shape: Shape, structures: list[RunStructure], config: EstimatorConfig):
        self.shape = shape
        self.structures = list(structures)
        self.config = config
        self.K = shape.n_vertices
        self.n_shape = shape.n_params
        self.n_theta = self.n_shape + len(PHYS_NAMES)
        self._build()

    # ------------------------------------------------------------------------------
    # layout of the decision vector z and the parameter vector p

    def _layout(self):
        K = self.K
        self.offsets = []
        n = self.n_theta
        for st in self.structures:
            T, F = st.T, st.F
            blk = {"Q": (n, 3 * T)}
            n += 3 * T
            blk["V"] = (n, 3 * T)
            n += 3 * T
            blk["LG"] = (n, 2 * K * (T - 1))
            n += 2 * K * (T - 1)
            blk["LF"] = (n, 2 * F * (T - 1))
            n += 2 * F * (T - 1)
            self.offsets.append(blk)
        self.n_z = n

    def n_data(self, F):
        """Per-sample data length: c_f (2F), v_f (2F), contact (F), n_meas (2F),
        F_meas (2F), w_force (F), w_tact (F), radius (F), q_obs (3), w_pose (1)."""
        return 12 * F + 4

    def _build(self):
        self._layout()
        K = self.K
        cfg = self.config
        z = ca.MX.sym("z", self.n_z)
        theta = z[: self.n_theta]
        s = theta[: self.n_shape]
        lm, lI, mu_g, mu_f = (theta[self.n_shape + i] for i in range(4))

        # parameters: per run, a global block and a data matrix; plus L and m0 shared
        p_parts = []
        self.p_offsets = []
        np_ = 0
        L_sym = ca.MX.sym("L")
        m0_sym = ca.MX.sym("m0")
        p_parts += [L_sym, m0_sym]
        np_ += 2
        run_syms = []
        for st in self.structures:
            gsym = ca.MX.sym("g", len(G_NAMES))
            dsym = ca.MX.sym("d", self.n_data(st.F), st.T)
            self.p_offsets.append((np_, len(G_NAMES), self.n_data(st.F) * st.T))
            np_ += len(G_NAMES) + self.n_data(st.F) * st.T
            p_parts += [gsym, ca.vec(dsym)]
            run_syms.append((gsym, dsym))
        self.n_p = np_
        p = ca.vertcat(*p_parts)

        # physical quantities from theta (computed once, passed to the stage functions)
        V = self.shape.vertices(s, L_sym)  # (K, 2) m
        area, _, J = polygon_area_centroid_j(V)
        mass = m0_sym * ca.exp(lm)
        inertia = mass * (J / area) * ca.exp(lI)
        phys = ca.vertcat(ca.vec(V), mass, inertia, mu_g, mu_f)

        obj_terms = {t: 0 for t in TERMS}
        r_stack = {t: [] for t in SQUARED_TERMS + ("kinematics",)}
        g_list, lbg, ubg = [], [], []
        self.stage_funs = []
        for i, st in enumerate(self.structures):
            gsym, dsym = run_syms[i]
            stage = self._stage_function(st.F)
            self.stage_funs.append(stage)
            off = self.offsets[i]
            T, F = st.T, st.F
            Q = ca.reshape(z[off["Q"][0]: off["Q"][0] + off["Q"][1]], 3, T)
            Vv = ca.reshape(z[off["V"][0]: off["V"][0] + off["V"][1]], 3, T)
            LG = ca.reshape(z[off["LG"][0]: off["LG"][0] + off["LG"][1]], 2 * K, T - 1)
            LF = ca.reshape(z[off["LF"][0]: off["LF"][0] + off["LF"][1]], 2 * F, T - 1)
            mapped = stage.map(T - 1, "serial")
            out = mapped(Q[:, :-1], Vv[:, :-1], Q[:, 1:], Vv[:, 1:], LG, LF, phys, dsym[:, 1:], gsym)
            res = dict(zip(stage.name_out(), out))
            for t in SQUARED_TERMS:
                obj_terms[t] = obj_terms[t] + 0.5 * ca.sumsqr(res[t])
                r_stack[t].append(ca.vec(res[t]))
            r_stack["kinematics"].append(ca.vec(res["g_kin"]))
            for t in PENALTY_TERMS:
                obj_terms[t] = obj_terms[t] + ca.sum2(res[t])
            # sample 0: the object starts at rest and above the ground
            s0 = self._start_function(st.F)
            o0 = dict(zip(s0.name_out(), s0(Q[:, 0], Vv[:, 0], phys, dsym[:, 0], gsym)))
            obj_terms["dynamics"] = obj_terms["dynamics"] + 0.5 * ca.sumsqr(o0["rest"])
            obj_terms["penetration"] = obj_terms["penetration"] + 0.5 * ca.sumsqr(o0["penetration"])
            obj_terms["pose"] = obj_terms["pose"] + 0.5 * ca.sumsqr(o0["pose"])
            obj_terms["contact"] = obj_terms["contact"] + 0.5 * ca.sumsqr(o0["contact"])
            for t, name in (("dynamics", "rest"), ("penetration", "penetration"), ("pose", "pose"),
                            ("contact", "contact")):
                r_stack[t].append(ca.vec(o0[name]))
            g_list += [ca.vec(res["g_kin"]), ca.vec(res["g_cone"])]
            lbg += [np.zeros(3 * (T - 1)), np.zeros((2 * K + 2 * F) * (T - 1))]
            ubg += [np.zeros(3 * (T - 1)), np.full((2 * K + 2 * F) * (T - 1), np.inf)]
        sc = self.shape.constraints(s)
        if sc:
            g_list.append(ca.vertcat(*sc))
            lbg.append(np.zeros(len(sc)))
            ubg.append(np.full(len(sc), np.inf))

        # weights (parameters, so that a config change needs no rebuild)
        w_sym = ca.MX.sym("w", len(TERMS))
        prior_sym = ca.MX.sym("prior", 6 + self.n_shape)  # lm_sigma, lI_sigma, mu0, mu_sigma, shape_sigma, on, s_ref
        self.n_p_total = self.n_p + len(TERMS) + 6 + self.n_shape
        p_all = ca.vertcat(p, w_sym, prior_sym)
        f = 0
        for k, t in enumerate(TERMS):
            f = f + w_sym[k] * obj_terms[t]
        lm_sig, lI_sig, mu0, mu_sig, sh_sig = (prior_sym[i] for i in range(5))
        s_ref = prior_sym[6:]
        f_prior = 0.5 * (lm / lm_sig) ** 2 + 0.5 * (lI / lI_sig) ** 2 \
            + 0.5 * ((mu_g - mu0) / mu_sig) ** 2 + 0.5 * ((mu_f - mu0) / mu_sig) ** 2 \
            + 0.5 * ca.sumsqr((s - s_ref) / sh_sig)
        f = f + prior_sym[5] * f_prior
        self.z_sym, self.p_sym = z, p_all
        self.phys_fun = ca.Function("phys", [z, p_all], [V, mass, inertia, mu_g, mu_f, area])
        self.f = f
        self.g = ca.vertcat(*g_list)
        self.lbg = np.concatenate(lbg)
        self.ubg = np.concatenate(ubg)
        self.term_fun = ca.Function("terms", [z, p_all], [ca.vertcat(*[obj_terms[t] for t in TERMS]), f_prior])
        self.nlp = {"x": z, "p": p_all, "f": f, "g": self.g}
        #: stacked whitened residuals per squared term (for Gauss-Newton information);
        #: "kinematics" holds the eq. D2 constraint values
        self.residual_stack = {t: ca.vertcat(*v) if v else ca.MX.zeros(0) for t, v in r_stack.items()}
        self.weight_sym = w_sym

    # ------------------------------------------------------------------------------
    # per-sample functions (SX, mapped over samples)

    def _unpack_phys(self, phys):
        K = self.K
        V = ca.reshape(phys[: 2 * K], K, 2)
        mass, inertia, mu_g, mu_f = phys[2 * K], phys[2 * K + 1], phys[2 * K + 2], phys[2 * K + 3]
        return V, mass, inertia, mu_g, mu_f

    def _unpack_data(self, d, F):
        i = 0

        def take(n):
            nonlocal i
            out = d[i: i + n]
            i += n
            return out

        c_f = ca.reshape(take(2 * F), 2, F)
        v_f = ca.reshape(take(2 * F), 2, F)
        contact = take(F)
        n_meas = ca.reshape(take(2 * F), 2, F)
        F_meas = ca.reshape(take(2 * F), 2, F)
        w_force = take(F)
        w_tact = take(F)
        radius = take(F)
        q_obs = take(3)
        w_pose = take(1)
        return c_f, v_f, contact, n_meas, F_meas, w_force, w_tact, radius, q_obs, w_pose

    def finger_geometry(self, q, V, c_f, radius, sd_fun):
        """Gap phi_f (m), outward object normal n (2, world) and lever r (2, world, from
        the COM to the contact point) of one finger centre c_f (2, world)."""
        R = rot2(q[2])
        x = q[0:2]
        sd, n_body = sd_fun(R.T @ (c_f - x), V)
        n_w = R @ n_body
        lever = c_f - x - sd * n_w
        return sd - radius, n_w, lever

    def _stage_function(self, F):
        K = self.K
        qp = ca.SX.sym("q_prev", 3)
        vp = ca.SX.sym("v_prev", 3)
        qs = ca.SX.sym("q", 3)
        vs = ca.SX.sym("v", 3)
        lg = ca.SX.sym("lam_ground", 2 * K)
        lf = ca.SX.sym("lam_finger", 2 * F)
        phys = ca.SX.sym("phys", 2 * K + 4)
        d = ca.SX.sym("d", self.n_data(F))
        g = ca.SX.sym("g", len(G_NAMES))
        dt, L, Lam = g[G["dt"]], g[G["L"]], g[G["Lam"]]
        eps = g[G["eps"]]
        V, mass, inertia, mu_g, mu_f = self._unpack_phys(phys)
        c_f, v_f, contact, n_meas, F_meas, w_force, w_tact, radius, q_obs, w_pose = self._unpack_data(d, F)
        # unscale: q = [x/L, y/L, angle], v = [vx/L, vy/L, omega] per second
        unscale = ca.vertcat(L, L, 1)
        q, q_prev = qs * unscale, qp * unscale
        v, v_prev = vs * unscale, vp * unscale
        n_g = ca.vertcat(g[G["nx"]], g[G["ny"]])
        t_g = perp(n_g)
        phi, slip, levers = ground_contacts(q, v, V, n_g, g[G["h"]])
        gen = ca.SX.zeros(3)
        comp = 0
        diss = 0
        cone = []
        pen = []
        v_scale = L  # m/s: one object length per second
        eps_slip = SLIP_EPS_RATIO * eps  # smoothing of |slip|, in units of v_scale
        for k in range(K):
            ln, lt = lg[k], lg[K + k]
            gen += generalized_impulse(levers[k], Lam * (ln * n_g + lt * t_g))
            comp += ln * smooth_pos(phi[k] / g[G["sig_gap"]], eps)
            diss += mu_g * ln * smooth_abs(slip[k] / v_scale, eps_slip) + lt * slip[k] / v_scale
            cone += [mu_g * ln - lt, mu_g * ln + lt]
            pen.append(ca.fmin(phi[k], 0) / g[G["sig_pen"]])
        sd_fun = polygon_sd_and_normal_function(K)
        r_force, r_normal, r_contact = [], [], []
        for f in range(F):
            phi_f, n_w, lever = self.finger_geometry(q, V, c_f[:, f], radius[f], sd_fun)
            t_w = perp(n_w)
            ln, lt = lf[f], lf[F + f]
            imp = Lam * (-ln * n_w + lt * t_w)  # impulse ON the object, world frame
            gen += generalized_impulse(lever, imp)
            slip_f = ca.dot(t_w, point_velocity(v, lever) - v_f[:, f])
            diss += mu_f * ln * smooth_abs(slip_f / v_scale, eps_slip) + lt * slip_f / v_scale
            cone += [mu_f * ln - lt, mu_f * ln + lt]
            r_force.append(w_force[f] * (imp / dt - F_meas[:, f]) / g[G["sig_force"]])
            r_normal.append(w_tact[f] * contact[f] * (n_meas[:, f] - n_w) / g[G["sig_normal"]])
            r_contact.append(w_tact[f] * (contact[f] * phi_f + (1 - contact[f]) * ca.fmin(phi_f, 0)) / g[G["sig_gap"]])
        # eq. D1: M (v - v_prev) - dt m g_vec - J^T lambda, gravity along -n_g
        M = mass_matrix_diag(mass, inertia)
        grav = ca.vertcat(-9.81 * n_g * mass * dt, 0)
        r_dyn_raw = M * (v - v_prev) - grav - gen
        sig_lin = g[G["sig_proc"]] * g[G["m0"]] * 9.81 * dt
        r_dyn = r_dyn_raw / ca.vertcat(sig_lin, sig_lin, sig_lin * L / 2)
        g_kin = (qs - qp) / dt - vs  # eq. D2, scaled (per second in units of L)
        r_pose = w_pose * (q - q_obs) / ca.vertcat(g[G["sig_pos"]], g[G["sig_pos"]], g[G["sig_ang"]])
        outs = {
            "force": ca.vertcat(*r_force) if F else ca.SX.zeros(0),
            "normal": ca.vertcat(*r_normal) if F else ca.SX.zeros(0),
            "contact": ca.vertcat(*r_contact) if F else ca.SX.zeros(0),
            "pose": r_pose,
            "dynamics": r_dyn,
            "penetration": ca.vertcat(*pen),
            "complementarity": comp * g[G["comp_mult"]],
            "dissipation": diss,
            "g_kin": g_kin,
            "g_cone": ca.vertcat(*cone),
        }
        names = list(outs)
        return ca.Function(f"stage_K{K}_F{F}", [qp, vp, qs, vs, lg, lf, phys, d, g],
                           [outs[n] for n in names],
                           ["q_prev", "v_prev", "q", "v", "lam_ground", "lam_finger", "phys", "d", "g"], names)

    def _start_function(self, F):
        """Terms at sample 0: rest (v ≈ 0), penetration, pose observation, finger gap."""
        K = self.K
        qs = ca.SX.sym("q", 3)
        vs = ca.SX.sym("v", 3)
        phys = ca.SX.sym("phys", 2 * K + 4)
        d = ca.SX.sym("d", self.n_data(F))
        g = ca.SX.sym("g", len(G_NAMES))
        L = g[G["L"]]
        V, *_ = self._unpack_phys(phys)
        c_f, v_f, contact, n_meas, F_meas, w_force, w_tact, radius, q_obs, w_pose = self._unpack_data(d, F)
        q = qs * ca.vertcat(L, L, 1)
        v = vs * ca.vertcat(L, L, 1)
        n_g = ca.vertcat(g[G["nx"]], g[G["ny"]])
        phi, _, _ = ground_contacts(q, v, V, n_g, g[G["h"]])
        pen = ca.vertcat(*[ca.fmin(p, 0) / g[G["sig_pen"]] for p in phi])
        rest = v / ca.vertcat(g[G["sig_rest"]], g[G["sig_rest"]], g[G["sig_rest"]] / L * 2)
        r_pose = w_pose * (q - q_obs) / ca.vertcat(g[G["sig_pos"]], g[G["sig_pos"]], g[G["sig_ang"]])
        sd_fun = polygon_sd_and_normal_function(K)
        r_contact = []
        for f in range(F):
            phi_f, _, _ = self.finger_geometry(q, V, c_f[:, f], radius[f], sd_fun)
            r_contact.append(w_tact[f] * (contact[f] * phi_f + (1 - contact[f]) * ca.fmin(phi_f, 0)) / g[G["sig_gap"]])
        return ca.Function("start", [qs, vs, phys, d, g],
                           [rest, pen, r_pose, ca.vertcat(*r_contact) if F else ca.SX.zeros(0)],
                           ["q", "v", "phys", "d", "g"], ["rest", "penetration", "pose", "contact"])

    # ------------------------------------------------------------------------------
    # helpers to slice z

    def run_blocks(self, z, i):
        """Unscaled-free views (scaled values) of run i: Q (3, T), V (3, T), LG (2K, T-1), LF (2F, T-1)."""
        st = self.structures[i]
        off = self.offsets[i]
        z = np.asarray(z, float).reshape(-1)

        def blk(name, rows):
            a, n = off[name]
            return z[a: a + n].reshape(-1, rows).T

        return blk("Q", 3), blk("V", 3), blk("LG", 2 * self.K), blk("LF", 2 * st.F)

    def set_run_blocks(self, z, i, Q=None, V=None, LG=None, LF=None):
        off = self.offsets[i]
        for name, arr in (("Q", Q), ("V", V), ("LG", LG), ("LF", LF)):
            if arr is not None:
                a, n = off[name]
                z[a: a + n] = np.asarray(arr, float).T.reshape(-1)
        return z
