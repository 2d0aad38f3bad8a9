"""The 2-D stage model: one sample interval's whitened residuals as CasADi functions,
and the layouts of their inputs (parameters, lifted physical quantities, data, settings).

What the NLP maps over every sample (tacest.estimation.problem2d), what the information
differentiates (tacest.information) and what the forward prediction solves step by step
(tacest.information.expected) are the functions built here, from one
:class:`StageModel2D` per shape, effect set and structural switches.

Loss terms of one interval (t-1, t] (whitened residuals, names as written into estimate
files; every term is squared, so that a Gauss–Newton Hessian models the whole loss)::

    force          (lambda_f / dt - F_meas) / sigma_F                 where a force stream exists
    normal         c (n_meas - n_model) / sigma_n
    contact        c phi_f / sigma_gap  +  (1 - c) min~(phi_f) (fingertip gap / no overlap,
                   at the interval's end)
    pose           (q - q_obs) / sigma_pose                           where observed
    dynamics       eq. D1 residual M(v - v_prev) - dt f_ext - Jᵀλ, whitened as process
                   noise on the velocity change of a reference body (m_ref, I_ref)
    penetration    min~(phi_ground) with tolerance sigma_pen
    cone           min~(mu lambda_n ∓ lambda_t) / sigma_comp, ground vertices and fingertips (eq. C2)
                   (min~ is a one-sided smooth penalty, ≈ 0 at the limit: see laws.one_sided)
    complementarity  lambda_n psi / sigma_comp (eq. C1, relaxed): psi = x / (x + 1) with
                   x = phi⁺ + vn⁺, phi⁺ a softplus of (phi / sigma_gap - 1) (gap beyond one
                   tolerance), vn⁺ one of (vn / sigma_v - 1) (the vertex separating faster than
                   one process sigma: velocity-level complementarity); psi saturates at 1 so
                   that a vertex far above the ground costs lambda_n, not lambda_n · phi (the
                   unbounded bilinear form makes IPOPT's Hessian badly indefinite); with
                   noise.complementarity_reach > 0, + lambda_n max~(phi - reach, 0) / reach:
                   an impulse far above the ground grows with the height (off by default)
    dissipation    (mu lambda_n |s| + lambda_t s) / sigma_diss (eq. C3, maximal dissipation:
                   0 when friction opposes the slip s at the cone's limit, or when sticking);
                   sigma_diss at the fingertips (slip from filtered positions), the tighter
                   sigma_diss_g at the ground vertices
    occam          the Occam term of pose-observed samples (tacest.model.occam; a penalty)

The flags, forces and normals of the tactile stream describe the interval (t-1, t]
(SPEC), so a fingertip's impulse acts in the contact frame and at the lever of the
interval's middle (pose and fingertip position averaged over its ends); the ground's
impulses act at its end (implicit Euler).

Ground and finger friction are both impulses (variables) inside the Coulomb cone with a
maximal-dissipation residual, as in the violation-implicit loss of ContactNets: every
term is polynomial in the impulses and the slip, so the Gauss–Newton model stays valid
across stick–slip transitions (a closed-form regularized Coulomb law, mu lambda_n s /
|s|_eps, is stiff as 1/eps and made IPOPT crawl), and static friction is represented
exactly.  Impulse residuals are whitened in units of a fixed reference weight m0·g·dt
(the dynamics by a fixed reference body): a whitening that scaled with the estimated
mass would itself pull the mass estimate.

Effects (tacest.model.registry) add parameters (after PHYS_NAMES in theta, appended to
phys), per-sample states, and terms, through the hooks of tacest.model.effect.Effect,
called in the registry's order at the points named in :meth:`StageModel2D.stage_function`.
"""

from __future__ import annotations

from collections import namedtuple

import casadi as ca
import numpy as np

from tacest.dynamics.laws import (CONE_TOLERANCE, SLIP_EPS, contact_residual, dissipation_shortfall,
                                  ground_gap_indicator, one_sided, reach_excess)
from tacest.dynamics.rigid2d import generalized_impulse, ground_contacts, mass_matrix_diag, perp, point_velocity
from tacest.geometry.shapes import Shape, polygon_area_centroid_j, polygon_sd_and_normal_function, rot2
from tacest.model.effect import parameter_table, physics_gain, sensor_reading
from tacest.model.occam import OCCAM_TOUCH_SHARPNESS, occam_free_weights, pose_occam
from tacest.model.priors import N_PRIOR_FIXED, parameter_prior_residual
from tacest.model.registry import names_of, resolve

#: squared-residual terms, in the order the stage function returns them
SQUARED_TERMS = ("force", "normal", "contact", "pose", "dynamics", "penetration", "complementarity",
                 "dissipation", "cone")
#: loss terms of a run's first sample (rest, penetration, pose, finger gap) and the
#: start-function outputs holding them
START_TERM_OUTPUTS = (("dynamics", "rest"), ("penetration", "penetration"), ("pose", "pose"), ("contact", "contact"))
#: penalty terms (non-negative, not squared; their exact Hessian enters every Hessian
#: model): the Occam term of a pose-observed trajectory (tacest.model.occam)
PENALTY_TERMS = ("occam",)
#: every loss term, in the order of the weight vector (config.weights has one per name)
TERMS = SQUARED_TERMS + PENALTY_TERMS
#: the terms that measure how far a fit violates its own model (rigid-body dynamics,
#: contact and friction), as opposed to the measurement terms
PHYSICS_TERMS = ("dynamics", "penetration", "complementarity", "dissipation", "cone")
#: names of the physical parameters in theta after the shape block
PHYS_NAMES = ("log_mass", "log_inertia_ratio", "friction_ground", "friction_finger")

#: the per-sample data of one interval, unpacked (StageModel2D.unpack_data; the layout
#: of StageModel2D.n_data)
StageData = namedtuple("StageData", ("c_f", "v_f", "contact", "n_meas", "F_meas", "w_force", "w_tact", "radius",
                                     "c_f_start", "ends", "q_obs", "w_pose"))
#: entries of a run's global vector g (settings and run constants; see
#: tacest.estimation.data.global_vector): sample period, scales, the reference impulse
#: Lam = m0·g·dt, ground normal and height, noise sigmas, homotopy multipliers, the
#: reference body, the rest weight, the complementarity's reach, and the run's gravity:
#: its magnitude (m/s², the unit of the process noise) and its vector (gx, gy) m/s²
G_NAMES = ("dt", "L", "Lam", "m0", "nx", "ny", "h", "sig_force", "sig_normal", "sig_gap", "sig_proc",
           "sig_pen", "sig_rest", "sig_pos", "sig_ang", "eps", "comp_mult", "dyn_mult", "sig_comp", "sig_diss",
           "m_ref", "I_ref", "sig_diss_g", "w_rest", "reach", "grav", "gx", "gy")
G = {n: i for i, n in enumerate(G_NAMES)}


def consecutive_slices(vector):
    """take(n) -> the next n entries of vector (CasADi or numpy), in order."""
    i = 0

    def take(n):
        nonlocal i
        out = vector[i: i + n]
        i += n
        return out

    return take


def stage_local_variables(ins):
    """The local variables y (a column) of a stage function's inputs ``ins`` (its
    sx_in()): [q_prev, v_prev, q, v, lam_ground, lam_finger, phys, s_prev, s] (the
    states are empty without effects that have some); data d and globals g are not."""
    qp, vp, q, v, lg, lf, phys, _d, _g, sp, s = ins
    return ca.vertcat(qp, vp, q, v, lg, lf, phys, sp, s)


def start_local_variables(ins):
    """The local variables [q, v, phys, s] of a start function's inputs (its sx_in())."""
    q, v, phys, _d, _g, s = ins
    return ca.vertcat(q, v, phys, s)


class Stage2DContext:
    """What the effects' 2-D hooks read and change while one sample's residuals are
    built (tacest.model.effect.Effect): scaled effect values ``u`` {effect: {parameter:
    SX}}, states ``s_prev``/``s`` {effect: SX rows}, the run's settings (``g`` vector,
    ``dt`` s, ``L`` m, ``m0`` kg, ``grav`` m/s², ``h`` m, ``sig_v`` m/s), the kinematics
    (``q``, ``q_start``, ``v``, ``v_prev``; ``V`` (K, 2) m; ``n_g``; ``levers``), and
    what the hooks change: ``phi_c``, ``vn_c`` (gaps m and normal velocities m/s the
    ground laws see), ``mu_g``, ``impulse_levers``, ``plate`` ((sink m, rate m/s) of a
    moving ground), ``dynamics_rows`` / ``rest_rows`` {effect: [SX]} (extra rows of the
    dynamics term), ``outputs`` {name: SX} (extra stage outputs)."""

    def __init__(self, **kw):
        self.dynamics_rows = {}
        self.rest_rows = {}
        self.outputs = {}
        self.plate = None
        self.__dict__.update(kw)


class StageModel2D:
    """The 2-D model of one object: the per-sample residual functions (SX) for a shape,
    a set of effects and the structural switches, and their input layouts.

    Parameters
    ----------
    shape : Shape parameterization (box, polygon:K)
    effects : effect names (or Effect objects) modelled as extra parameters; canonical
        order (tacest.model.registry)
    reach_on : build the complementarity's reach term (noise.complementarity_reach > 0)
    with_occam : build the Occam term of pose-observed samples
    """

    def __init__(self, shape: Shape, effects=(), reach_on: bool = False, with_occam: bool = False):
        self.shape = shape
        self.K = shape.n_vertices
        self.n_shape = shape.n_params
        self.effect_objects = resolve(effects, 2)
        #: names of the modelled effects, canonical order
        self.effects = names_of(self.effect_objects)
        self.reach_on = bool(reach_on)
        self.with_occam = bool(with_occam)
        #: [(Effect, EffectParameter)] of the effect block (theta after PHYS_NAMES, phys
        #: after its 2K + 4 physical entries)
        self.effect_params = parameter_table(self.effect_objects, self.K, 2)
        self.n_eff = len(self.effect_params)
        #: "effect.parameter" -> index within the effect block
        self.eff_index = {f"{e.name}.{p.name}": j for j, (e, p) in enumerate(self.effect_params)}
        self.n_theta = self.n_shape + len(PHYS_NAMES) + self.n_eff
        self.n_phys = 2 * self.K + 4 + self.n_eff
        #: per-sample states: effect name -> slice of the state vector (rows)
        self.state_slices = {}
        n = 0
        for e in self.effect_objects:
            rows = e.state_rows(self.K, 2)
            if rows:
                self.state_slices[e.name] = slice(n, n + rows)
                n += rows
        self.n_state = n
        self._stage_cache = {}
        self._start_cache = {}
        self.phys_sx = self.phys_function()

    # ------------------------------------------------------------------------------
    # layouts

    def n_data(self, F):
        """Per-sample data length: c_f (2F), v_f (2F), contact (F), n_meas (2F),
        F_meas (2F), w_force (F), w_tact (F), radius (F), c_f_start (2F) (the fingertip
        at the interval's start), ends (F) (1 at the last sample of a touch,
        data.touch_ends), q_obs (3), w_pose (1)."""
        return 15 * F + 4

    def unpack_data(self, d, F):
        take = consecutive_slices(d)
        c_f = ca.reshape(take(2 * F), 2, F)
        v_f = ca.reshape(take(2 * F), 2, F)
        contact = take(F)
        n_meas = ca.reshape(take(2 * F), 2, F)
        F_meas = ca.reshape(take(2 * F), 2, F)
        w_force = take(F)
        w_tact = take(F)
        radius = take(F)
        c_f_start = ca.reshape(take(2 * F), 2, F)
        ends = take(F)
        q_obs = take(3)
        w_pose = take(1)
        return StageData(c_f, v_f, contact, n_meas, F_meas, w_force, w_tact, radius, c_f_start, ends, q_obs, w_pose)

    def unpack_phys(self, phys, L, m0):
        """(V (K, 2) m, mass kg, inertia kg·m², mu_ground, mu_finger) from a scaled phys vector."""
        K = self.K
        V = ca.reshape(phys[: 2 * K], K, 2) * L
        return V, phys[2 * K] * m0, phys[2 * K + 1] * m0 * L * L, phys[2 * K + 2], phys[2 * K + 3]

    def effect_values(self, vector, offset):
        """{effect name: {parameter: value}} of the effect block of ``vector`` (theta:
        offset n_shape + 4; phys: offset 2K + 4)."""
        out = {e.name: {} for e in self.effect_objects}
        for j, (e, p) in enumerate(self.effect_params):
            out[e.name][p.name] = vector[offset + j]
        return out

    def states(self, s):
        """{effect name: its rows of a state vector s}."""
        return {name: s[sl] for name, sl in self.state_slices.items()}

    def state_lower_bounds(self) -> np.ndarray:
        """(n_state,) lower bound of every state row."""
        lo = np.full(self.n_state, -np.inf)
        for e in self.effect_objects:
            if e.name in self.state_slices:
                lo[self.state_slices[e.name]] = e.state_lower()
        return lo

    # ------------------------------------------------------------------------------
    # parameters

    def phys_function(self):
        """SX Function (theta, L, m0) -> scaled phys = [vec(V) / L (2K), mass / m0,
        inertia / (m0 L²), mu_g, mu_f, effect parameters]: the lifted physical
        quantities (the problem holds them as variables with phys = phys(theta), so that
        every per-sample Hessian block is local)."""
        th = ca.SX.sym("theta", self.n_theta)
        L = ca.SX.sym("L")
        m0 = ca.SX.sym("m0")
        s = th[: self.n_shape]
        lm, lI, mu_g, mu_f = (th[self.n_shape + i] for i in range(4))
        V = self.shape.vertices(s, L)
        area, _, J = polygon_area_centroid_j(V)
        mass = m0 * ca.exp(lm)
        inertia = mass * (J / area) * ca.exp(lI)
        u = th[self.n_shape + len(PHYS_NAMES):]
        values = self.effect_values(th, self.n_shape + len(PHYS_NAMES))
        for e in self.effect_objects:
            V = e.body_vertices_2d(V, values[e.name], L)
        return ca.Function("phys_of_theta", [th, L, m0],
                           [ca.vertcat(ca.vec(V) / L, mass / m0, inertia / (m0 * L * L), mu_g, mu_f, u)])

    #: length of the fixed part of the prior vector (tacest.model.priors.PRIOR_HEAD); then
    #: the effect priors (centre, sigma per parameter), s_ref
    N_PRIOR_FIXED = N_PRIOR_FIXED

    def n_prior(self):
        return self.N_PRIOR_FIXED + 2 * self.n_eff + self.n_shape

    def prior_residual(self, theta, prior):
        """Whitened residuals (SX) of theta's priors under the prior vector (see n_prior):
        log mass, log inertia ratio, both frictions (tacest.model.priors), the shape's pull
        toward s_ref (tacest.model.priors.parameter_prior_residual), the effect parameters.
        Their weight (the head's "on") is applied by the problem."""
        s = theta[: self.n_shape]
        lm, lI, mu_g, mu_f = (theta[self.n_shape + i] for i in range(4))
        a = self.N_PRIOR_FIXED
        s_ref = prior[a + 2 * self.n_eff:]
        effects = [(theta[self.n_shape + len(PHYS_NAMES) + j] - prior[a + 2 * j]) / prior[a + 2 * j + 1]
                   for j in range(self.n_eff)]
        return ca.vertcat(parameter_prior_residual(lm, lI, mu_g, mu_f, s - s_ref, prior), *effects)

    def prior_gauss_newton(self, theta, prior):
        """(n_theta, n_theta) SX: JᵀJ of :meth:`prior_residual` (the priors' Gauss–Newton
        Hessian, without their weight "on")."""
        J = ca.jacobian(self.prior_residual(theta, prior), theta)
        return ca.mtimes(J.T, J)

    def prior_expression(self, theta, prior):
        """Negative log prior (SX) of theta under the prior vector (see n_prior): half the
        squared :meth:`prior_residual`."""
        return 0.5 * ca.sumsqr(self.prior_residual(theta, prior))

    def effect_priors(self, config, L) -> np.ndarray:
        """(2 n_eff,) [centre, sigma] of every effect parameter's prior (scaled)."""
        out = []
        for e, p in self.effect_params:
            out += list(e.prior(p, config, L))
        return np.asarray(out, float)

    # ------------------------------------------------------------------------------
    # geometry

    @staticmethod
    def finger_geometry(q, V, c_f, radius, sd_fun):
        """Gap phi_f (m), outward object normal n (2, world) and lever r (2, world, from
        the COM to the contact point) of one finger centre c_f (2, world)."""
        R = rot2(q[2])
        x = q[0:2]
        sd, n_body = sd_fun(R.T @ (c_f - x), V)
        n_w = R @ n_body
        lever = c_f - x - sd * n_w
        return sd - radius, n_w, lever

    # ------------------------------------------------------------------------------
    # per-sample functions (SX, mapped over samples)

    def stage_function(self, F):
        """The residuals of one interval (t-1, t] for F fingers (cached per F).

        Inputs: q_prev, v_prev, q, v (3 each, scaled: [x/L, y/L, angle], per second),
        lam_ground (2K: normal then tangential, units of m0·g·dt), lam_finger (2F: each
        finger's impulse on the object, world [x, y]), phys, d (n_data(F)), g (G_NAMES),
        s_prev, s (n_state).  Outputs: the loss terms (TERMS), g_kin (eq. D2), and
        diagnostics (see the end of this function)."""
        if F not in self._stage_cache:
            self._stage_cache[F] = self._build_stage(F)
        return self._stage_cache[F]

    def _build_stage(self, F):
        K = self.K
        qp, vp, qs, vs = (ca.SX.sym(n, 3) for n in ("q_prev", "v_prev", "q", "v"))
        lg = ca.SX.sym("lam_ground", 2 * K)
        lf = ca.SX.sym("lam_finger", 2 * F)
        phys = ca.SX.sym("phys", self.n_phys)
        d = ca.SX.sym("d", self.n_data(F))
        g = ca.SX.sym("g", len(G_NAMES))
        sp = ca.SX.sym("s_prev", self.n_state)
        ss = ca.SX.sym("s", self.n_state)
        dt, L, grav = g[G["dt"]], g[G["L"]], g[G["grav"]]
        V, mass, inertia, mu_g, mu_f = self.unpack_phys(phys, L, g[G["m0"]])
        data = self.unpack_data(d, F)
        q_obs, w_pose = data.q_obs, data.w_pose
        # unscale: q = [x/L, y/L, angle], v = [vx/L, vy/L, omega] per second
        unscale = ca.vertcat(L, L, 1)
        q, q_start = qs * unscale, qp * unscale
        v, v_prev = vs * unscale, vp * unscale
        n_g = ca.vertcat(g[G["nx"]], g[G["ny"]])
        phi, slip, levers = ground_contacts(q, v, V, n_g, g[G["h"]])
        u = self.effect_values(phys, 2 * K + 4)
        # a factor on every force and the mass the physics residuals see (force_scale)
        gain = physics_gain(self.effect_objects, u)
        # gaps (m) and normal velocities (m/s) of the vertices at the end of the interval
        # seen by the ground contact laws (penetration, complementarity): the geometric
        # ones unless an effect moves the ground or relaxes the laws
        ctx = Stage2DContext(
            K=K, g=g, u=u, s_prev=self.states(sp), s=self.states(ss), dt=dt, L=L, m0=g[G["m0"]], grav=grav,
            h=g[G["h"]], g_sig_proc=g[G["sig_proc"]], q=q, q_start=q_start, v=v, v_prev=v_prev, V=V, n_g=n_g,
            levers=levers, lam_ground=lg, phi_c=list(phi),
            vn_c=[ca.dot(n_g, point_velocity(v, levers[k])) for k in range(K)],
            sig_v=g[G["sig_proc"]] * grav * dt,  # m/s: process noise of a velocity change
            mu_g=mu_g, impulse_levers=levers, gain=gain, mass=mass, inertia=inertia)
        for e in self.effect_objects:
            e.ground_surface_2d(ctx)
        for e in self.effect_objects:
            e.ground_friction_2d(ctx)
        for e in self.effect_objects:
            e.impacts_2d(ctx)
        gen, comp, pen, cone, diss = self._ground_laws(ctx, lg, slip)
        fingers = self._finger_terms(ctx, F, lf, data, mu_f)
        gen += fingers["gen"]
        cone += fingers["cone"]
        diss += fingers["diss"]
        for e in self.effect_objects:  # forces on the body over the interval (drag, damping)
            extra = e.body_impulse_2d(ctx)
            if extra is not None:
                gen += extra
        r_dyn, occam = self._dynamics_terms(ctx, gen, data, fingers["rows"], F)
        g_kin = (qs - qp) / dt - vs  # eq. D2, scaled (per second in units of L)
        r_pose = w_pose * (q - q_obs) / ca.vertcat(g[G["sig_pos"]], g[G["sig_pos"]], g[G["sig_ang"]])
        empty = ca.SX.zeros(0)
        outs = {
            "force": ca.vertcat(*fingers["force"]) if F else empty,
            "normal": ca.vertcat(*fingers["normal"]) if F else empty,
            "contact": ca.vertcat(*fingers["contact"]) if F else empty,
            "pose": r_pose,
            "dynamics": r_dyn,
            "penetration": ca.vertcat(*pen),
            "complementarity": ca.sqrt(g[G["comp_mult"]]) * ca.vertcat(*comp) / g[G["sig_comp"]],
            "dissipation": ca.vertcat(*diss) / g[G["sig_diss"]],
            "cone": ca.vertcat(*cone) / g[G["sig_comp"]],
            "occam": occam,
            "g_kin": g_kin,
            # diagnostics only (not in the loss): tangential ground impulses (scaled) and
            # finger impulses on the object (N·s, world); the ground contacts' geometric
            # gaps (m) and slip velocities (m/s), the ground friction coefficient and the
            # object's weight in units of the reference weight (for the active-set rows
            # of the information, tacest.estimation.uncertainty)
            "lam_t_ground": lg[K:],
            "imp_finger": ca.vertcat(*fingers["impulse"]) if F else empty,
            "phi_ground": ca.vertcat(*phi),
            "slip_ground": ca.vertcat(*slip),
            "mu_ground": ctx.mu_g,
            "weight": mass / g[G["m0"]],
            **ctx.outputs,  # the effects' own (e.g. restitution's impact_target)
        }
        names = list(outs)
        return ca.Function(f"stage_K{K}_F{F}", [qp, vp, qs, vs, lg, lf, phys, d, g, sp, ss],
                           [outs[n] for n in names],
                           ["q_prev", "v_prev", "q", "v", "lam_ground", "lam_finger", "phys", "d", "g", "s_prev", "s"],
                           names)

    def _ground_laws(self, ctx, lg, slip):
        """The ground vertices' impulses and laws of one interval: (generalized impulse
        (3,), complementarity, penetration, cone and dissipation residual lists)."""
        K, g, L, gain, eps = self.K, ctx.g, ctx.L, ctx.gain, ctx.g[G["eps"]]
        Lam, n_g, sig_v = g[G["Lam"]], ctx.n_g, ctx.sig_v
        t_g = perp(n_g)
        mu_g, phi_c, vn_c = ctx.mu_g, ctx.phi_c, ctx.vn_c
        eps_slip = SLIP_EPS  # m/s, smoothing of |slip|
        gen = ca.SX.zeros(3)
        comp, pen, cone, diss = [], [], [], []
        for k in range(K):
            ln, lt = lg[k], lg[K + k]
            gen += generalized_impulse(ctx.impulse_levers[k], Lam * (ln * n_g + lt * t_g))
            # eq. C2 (Coulomb cone) as a smooth penalty and eq. C3 (maximal dissipation:
            # friction opposes the slip with all the cone allows) as a whitened residual,
            # both in units of the reference weight m0·g·dt like the impulses: whitened
            # relative to the object's own weight instead, a heavy object would make
            # every friction violation cheap (and a heavy, slippery fit win).  A sticking
            # vertex (slip 0) may carry any friction inside the cone.
            cone += [one_sided(gain * (mu_g * ln - lt), CONE_TOLERANCE) * CONE_TOLERANCE,
                     one_sided(gain * (mu_g * ln + lt), CONE_TOLERANCE) * CONE_TOLERANCE]
            diss.append(gain * dissipation_shortfall(mu_g, ln, lt, slip[k] / L, eps_slip / L)
                        * g[G["sig_diss"]] / g[G["sig_diss_g"]])
            # smoothed gap in units of sig_gap, shifted by one: within about one sig_gap of
            # the ground a vertex counts as touching (see ground_gap_indicator)
            gap = ground_gap_indicator(phi_c[k], g[G["sig_gap"]], eps)
            # ... and a vertex that carries load does not separate from the ground
            # (velocity-level complementarity, inelastic contact): an indicator of its
            # normal velocity beyond one process sigma.  Without it, the position-level
            # tolerance lets loaded vertices hop within sig_gap, and the normal impulses
            # do positive work: heavy, slippery fits "vibrate" along the ground between
            # touches (a 25 kg box moved by a 0.9 N push)
            sep = ground_gap_indicator(vn_c[k], sig_v, eps)
            # saturating (bounded curvature far from the ground); in units of the
            # reference weight m0·g·dt, like every impulse (see the cone above).  With a
            # reach (noise.complementarity_reach > 0; the term is built only then) an impulse
            # at a vertex higher than the reach also costs its height over the reach in
            # reaches: no action at a distance (a saturating law alone prices a flying
            # vertex carrying sigma_comp of the weight at one sigma at any height)
            if self.reach_on:
                far = reach_excess(phi_c[k], g[G["reach"]])
                comp.append(gain * ln * ((gap + sep) / (1 + gap + sep) + far))
            else:  # the plain law, expression for expression (IPOPT's path unchanged)
                comp.append(gain * ln * (gap + sep) / (1 + gap + sep))
            pen.append(one_sided(phi_c[k], g[G["sig_pen"]]))
        return gen, comp, pen, cone, diss

    def _finger_terms(self, ctx, F, lf, data, mu_f):
        """Each fingertip's residuals of one interval: {"gen": generalized impulse (3,),
        "cone", "diss", "force", "normal", "contact", "impulse" (N·s on the object, world):
        lists, "rows": (normal, lever) of each contact frame, for the Occam term}."""
        K, g, L, gain, dt = self.K, ctx.g, ctx.L, ctx.gain, ctx.dt
        Lam, q, q_start, v, V = g[G["Lam"]], ctx.q, ctx.q_start, ctx.v, ctx.V
        c_f, v_f, contact, n_meas, F_meas, w_force, w_tact, radius, c_f_start, ends = data[:10]
        eps_slip = SLIP_EPS  # m/s, smoothing of |slip|
        gen = ca.SX.zeros(3)
        cone, diss = [], []
        sd_fun = polygon_sd_and_normal_function(K)
        r_force, r_normal, r_contact, imp_finger = [], [], [], []
        finger_rows = []  # (normal, lever) of each finger's contact frame, for the Occam term
        for f in range(F):
            # the gap over the interval (the contact flag, see contact_residual); the
            # contact frame n_w and lever of the impulse at its middle: the measured force
            # and normal are averages over the interval (SPEC), and a fingertip sliding
            # over a corner turns the normal within one interval (the end's frame put the
            # average force outside the friction cone there)
            phi_f, _, _ = self.finger_geometry(q, V, c_f[:, f], radius[f], sd_fun)
            phi_f_start, _, _ = self.finger_geometry(q_start, V, c_f_start[:, f], radius[f], sd_fun)
            _, n_w, lever = self.finger_geometry((q_start + q) / 2, V, (c_f_start[:, f] + c_f[:, f]) / 2,
                                                 radius[f], sd_fun)
            t_w = perp(n_w)
            finger_rows.append((n_w, lever))
            # finger impulse ON the object: a free world-frame vector, held in the friction
            # cone of the model's contact frame (eq. C2).  Fingertips often stick to the
            # object, and the measured fingertip velocity is noisy, so friction here is
            # not a closed-form law but a cone plus a maximal-dissipation penalty (eq. C3)
            imp_s = ca.vertcat(lf[2 * f], lf[2 * f + 1])
            imp = Lam * imp_s
            ln = -ca.dot(imp_s, n_w)
            lt = ca.dot(imp_s, t_w)
            slip_f = ca.dot(t_w, point_velocity(v, lever) - v_f[:, f]) / L  # object lengths per second
            diss.append(gain * dissipation_shortfall(mu_f, ln, lt, slip_f, eps_slip / L))
            # friction cone |lambda_t| <= mu lambda_n (and lambda_n >= 0) as a smooth penalty
            cone += [one_sided(gain * (mu_f * ln - lt), CONE_TOLERANCE) * CONE_TOLERANCE,
                     one_sided(gain * (mu_f * ln + lt), CONE_TOLERANCE) * CONE_TOLERANCE]
            imp_finger.append(imp)
            gen += generalized_impulse(lever, imp)
            r_force.append(w_force[f] * (sensor_reading(self.effect_objects, ctx, imp / dt) - F_meas[:, f]) / g[G["sig_force"]])
            r_normal.append(w_tact[f] * contact[f] * (n_meas[:, f] - n_w) / g[G["sig_normal"]])
            r_contact.append(contact_residual(phi_f, contact[f], w_tact[f], g[G["sig_gap"]],
                                              phi_start=phi_f_start, ends=ends[f]))
        return {"gen": gen, "cone": cone, "diss": diss, "force": r_force, "normal": r_normal, "contact": r_contact,
                "impulse": imp_finger, "rows": finger_rows}

    def _dynamics_terms(self, ctx, gen, data, finger_rows, F):
        """The dynamics residual (eq. D1 and the effects' own laws) and the Occam term of
        one interval."""
        K, g, L, gain, dt, eps = self.K, ctx.g, ctx.L, ctx.gain, ctx.dt, ctx.g[G["eps"]]
        v, v_prev, V, n_g, levers, sig_v = ctx.v, ctx.v_prev, ctx.V, ctx.n_g, ctx.levers, ctx.sig_v
        mass, inertia = ctx.mass, ctx.inertia
        contact, q_obs, w_pose = data.contact, data.q_obs, data.w_pose
        # eq. D1 divided by the mass matrix, whitened as process noise on the velocity
        # change: (v - v_prev) - dt g_vec - M⁻¹ J^T lambda, g_vec the run's gravity.
        # (Whitening the impulse form by a fixed scale would let a light object move for free.)
        M = mass_matrix_diag(mass, inertia)
        M_ref = ca.vertcat(g[G["m_ref"]], g[G["m_ref"]], g[G["I_ref"]])
        grav_dv = ca.vertcat(g[G["gx"]] * dt, g[G["gy"]] * dt, 0)
        r_dyn_raw = gain * (M * ((v - v_prev) - grav_dv) - gen) / M_ref
        r_dyn = ca.sqrt(g[G["dyn_mult"]]) * r_dyn_raw / ca.vertcat(sig_v, sig_v, sig_v / (L / 2))
        for e in self.effect_objects:  # the effects' own laws, whitened like the dynamics
            rows = ctx.dynamics_rows.get(e.name)
            if rows:
                r_dyn = ca.vertcat(r_dyn, ca.sqrt(g[G["dyn_mult"]]) * ca.vertcat(*rows))
        occam = ca.SX.zeros(1)
        if self.with_occam:
            # the Occam term of a pose-observed sample (pose_occam): tracking indices of the
            # translations and the rotation, from the process sd of each velocity change
            # (M floored far below any real mass: a trial step of the solver through a
            # degenerate shape may make the inertia <= 0, and the log NaN)
            M_pos = ca.fmax(gain * M, 1e-9 * M_ref)
            log_s = ca.log(sig_v * M_ref / M_pos / ca.vertcat(1, 1, L / 2)) - 0.5 * ca.log(g[G["dyn_mult"]])
            log_lam = log_s + ca.log(dt / ca.vertcat(g[G["sig_pos"]], g[G["sig_pos"]], g[G["sig_ang"]]))
            # priced only in the directions no contact holds (occam_free_weights: the
            # ground vertices by how close they are to the ground at the observed pose,
            # the fingers by their flag): there a contact impulse, not the mass, absorbs
            # a velocity change.  The observed pose, not the fitted one: with the fitted
            # gaps the term paid a light object to put its vertices on the ground (a
            # bouncing box's fit then oscillated between held and free and never
            # converged)
            phi_obs, _, _ = ground_contacts(q_obs, v, V, n_g, g[G["h"]])
            touch = [ca.exp(-OCCAM_TOUCH_SHARPNESS * ground_gap_indicator(phi_obs[k], g[G["sig_gap"]], eps))
                     for k in range(K)]
            free = occam_free_weights([(n_g, levers[k]) for k in range(K)] + finger_rows,
                                      touch + [contact[f] for f in range(F)], L / 2)
            occam = w_pose * sum(free[k] * pose_occam(log_lam[k]) for k in range(3))
        return r_dyn, occam

    def start_function(self, F):
        """Terms at sample 0 (cached per F): rest (v ≈ 0, weighted by the run's w_rest: 0
        for a run that starts pose-observed, data.starts_at_rest), penetration, pose
        observation, finger gap; the effects' start rows join the rest term."""
        if F not in self._start_cache:
            self._start_cache[F] = self._build_start(F)
        return self._start_cache[F]

    def _build_start(self, F):
        K = self.K
        qs = ca.SX.sym("q", 3)
        vs = ca.SX.sym("v", 3)
        phys = ca.SX.sym("phys", self.n_phys)
        d = ca.SX.sym("d", self.n_data(F))
        g = ca.SX.sym("g", len(G_NAMES))
        s0 = ca.SX.sym("s", self.n_state)
        L = g[G["L"]]
        V, *_ = self.unpack_phys(phys, L, g[G["m0"]])
        c_f, v_f, contact, n_meas, F_meas, w_force, w_tact, radius, c_f_start, _, q_obs, w_pose = \
            self.unpack_data(d, F)
        q = qs * ca.vertcat(L, L, 1)
        v = vs * ca.vertcat(L, L, 1)
        n_g = ca.vertcat(g[G["nx"]], g[G["ny"]])
        phi, _, _ = ground_contacts(q, v, V, n_g, g[G["h"]])
        w_rest = g[G["w_rest"]]
        rest = w_rest * v / ca.vertcat(g[G["sig_rest"]], g[G["sig_rest"]], g[G["sig_rest"]] / L * 2)
        ctx = Stage2DContext(K=K, g=g, u=self.effect_values(phys, 2 * K + 4), s=self.states(s0), dt=g[G["dt"]],
                             L=L, m0=g[G["m0"]], grav=g[G["grav"]], g_sig_proc=g[G["sig_proc"]],
                             mass_ratio=phys[2 * K], w_rest=w_rest, phi=phi)
        for e in self.effect_objects:
            e.start_2d(ctx)
        phi = ctx.phi
        for e in self.effect_objects:
            rows = ctx.rest_rows.get(e.name)
            if rows:
                rest = ca.vertcat(rest, *rows)
        pen = ca.vertcat(*[one_sided(p, g[G["sig_pen"]]) for p in phi])
        r_pose = w_pose * (q - q_obs) / ca.vertcat(g[G["sig_pos"]], g[G["sig_pos"]], g[G["sig_ang"]])
        sd_fun = polygon_sd_and_normal_function(K)
        r_contact = []
        for f in range(F):
            phi_f, _, _ = self.finger_geometry(q, V, c_f[:, f], radius[f], sd_fun)
            r_contact.append(contact_residual(phi_f, contact[f], w_tact[f], g[G["sig_gap"]]))
        return ca.Function("start", [qs, vs, phys, d, g, s0],
                           [rest, pen, r_pose, ca.vertcat(*r_contact) if F else ca.SX.zeros(0)],
                           ["q", "v", "phys", "d", "g", "s"], ["rest", "penetration", "pose", "contact"])
