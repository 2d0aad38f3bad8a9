"""The 2-D physics-constrained maximum-likelihood problem as ONE CasADi NLP: the stage
model (tacest.model.stage2d) assembled over a set of runs.

Decision variables (all scaled to O(1); see tacest.estimation.data.Scales):

- shared parameters ``theta`` = [shape s (n_s), log(m/m0), log(I / I_uniform), mu_ground,
  mu_finger, effect parameters]
- lifted physical quantities ``phys`` = [V / L (2K), m / m0, I / (m0 L²), mu_ground,
  mu_finger, effect parameters] with the equality constraint phys = phys(theta)
- per run i, per sample t: pose q[t] (3), velocity v[t] (3); per interval (t-1, t]:
  ground impulses [lambda_n (K), lambda_t (K)] at each shape vertex and, per finger,
  its impulse on the object as a world-frame vector [x, y] (all scaled by m0 g dt);
  per sample, the effects' states (S block; none without such effects).

Data (recorded streams, noise levels, homotopy settings) are CasADi *parameters*, so the
NLP is built once per structure (shape, effects, run lengths, fingers) and re-solved with
new data.  The loss terms are the stage model's; the objective is
0.5 Σ w ||r||² over the squared terms + Σ w · penalty + the priors.

Non-penetration and the fingertip cone are smooth penalties rather than inequality
constraints: hard ones made IPOPT's filter trade huge objective increases for tiny
feasibility gains, and hinge penalties are invisible to a Gauss–Newton model until
crossed.  The problem is subject to eq. D2 (kinematics, equality), lambda_n >= 0 and
the shape's validity constraints.  Its Lagrangian Hessian (Gauss–Newton or exact) is
assembled from small dense per-sample blocks (tacest.estimation.assembly).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import casadi as ca
import numpy as np
import scipy.sparse as sp

from tacest.estimation.assembly import LazyHessians, assemble_hessian
from tacest.estimation.config import EstimatorConfig
from tacest.estimation.kernels import compile_functions
from tacest.geometry.shapes import Shape, polygon_area_centroid_j
from tacest.model.jacobians2d import (contact_state_function, stage_active_weights, stage_residual_jacobian,
                                      start_residual_jacobian)
from tacest.model.priors import ON
from tacest.model.stage2d import (G, G_NAMES, PENALTY_TERMS, PHYS_NAMES, SQUARED_TERMS, START_TERM_OUTPUTS, TERMS,
                                  StageModel2D, start_local_variables, stage_local_variables)

#: Hessian models built for every problem (see Problem2D._local_hessian)
HESSIAN_MODES = ("gauss-newton", "exact")


@dataclass(frozen=True)
class RunStructure:
    """What fixes the NLP's structure for one run: samples T, fingers F, and whether
    its poses are observed (the Occam term is built only for problems with such runs)."""

    T: int
    F: int
    observed: bool = False


class Problem2D(StageModel2D):
    """The NLP for a set of runs of one object (see module docstring).

    Parameters
    ----------
    shape : Shape parameterization (box, polygon:K)
    structures : list of RunStructure, one per run
    config : EstimatorConfig (the structural switches: the reach term, the Occam term)
    effects : effect names modelled as extra parameters (tacest.model.registry)
    """

    def __init__(self, shape: Shape, structures: list[RunStructure], config: EstimatorConfig, effects=()):
        # the complementarity's reach term is built only when configured, the Occam term
        # only where it is weighted and some run's poses are observed (it prices
        # pose-observed samples only): structural choices, part of the solver cache's key
        super().__init__(shape, effects, reach_on=config.noise.complementarity_reach > 0,
                         with_occam=config.weights.occam > 0 and any(s.observed for s in structures))
        self.structures = list(structures)
        self.config = config
        self._layout()
        self._build()

    # ------------------------------------------------------------------------------
    # layout of the decision vector z and the parameter vector p

    def _layout(self):
        K = self.K
        self.offsets = []
        self.phys_offset = self.n_theta
        n = self.n_theta + self.n_phys
        for st in self.structures:
            T, F = st.T, st.F
            blk = {}
            for name, size in (("Q", 3 * T), ("V", 3 * T), ("LG", 2 * K * (T - 1)), ("LF", 2 * F * (T - 1)),
                               ("S", self.n_state * T)):
                blk[name] = (n, size)
                n += size
            self.offsets.append(blk)
        self.n_z = n

    def _build(self):
        z = ca.MX.sym("z", self.n_z)
        self.z_sym = z
        theta = z[: self.n_theta]
        phys = z[self.phys_offset: self.phys_offset + self.n_phys]
        # parameters: L and m0 shared, then per run a global block and a data matrix,
        # then the term weights, the prior vector and the Levenberg–Marquardt ridge
        L_sym, m0_sym = ca.MX.sym("L"), ca.MX.sym("m0")
        p_parts = [L_sym, m0_sym]
        self.p_offsets = []
        n_p = 2
        run_syms = []
        for st in self.structures:
            gsym = ca.MX.sym("g", len(G_NAMES))
            dsym = ca.MX.sym("d", self.n_data(st.F), st.T)
            self.p_offsets.append((n_p, len(G_NAMES), self.n_data(st.F) * st.T))
            n_p += len(G_NAMES) + self.n_data(st.F) * st.T
            p_parts += [gsym, ca.vec(dsym)]
            run_syms.append((gsym, dsym))
        self.n_p = n_p
        w_sym = ca.MX.sym("w", len(TERMS))
        prior_sym = ca.MX.sym("prior", self.n_prior())
        ridge_sym = ca.MX.sym("ridge")
        self.n_p_total = self.n_p + len(TERMS) + self.n_prior() + 1
        p_all = ca.vertcat(*p_parts, w_sym, prior_sym, ridge_sym)
        self.p_sym, self.weight_sym = p_all, w_sym
        lam_f = ca.MX.sym("lam_f")
        # lifted physical quantities: phys = phys(theta), so that every per-sample Hessian
        # block is local (the shape's nonlinear map enters only the small theta block)
        lam_lift = ca.MX.sym("lam_lift", self.n_phys)
        acc = _Accumulator(self.n_phys, lam_lift)
        acc.constrain(phys - self.phys_sx(theta, L_sym, m0_sym), np.zeros(self.n_phys), np.zeros(self.n_phys))
        for i, st in enumerate(self.structures):
            self._build_run(i, st, z, phys, run_syms[i], w_sym, lam_f, acc)
        f_prior, shared = self._build_theta_terms(theta, prior_sym, lam_f, lam_lift, L_sym, m0_sym, acc)
        # Levenberg–Marquardt damping of the Hessian model (not of the objective): a ridge
        # parameter times lam_f on every variable, so the Gauss–Newton steps stay local
        for blocks in shared.values():
            blocks.append((ca.repmat(ridge_sym * lam_f, 1, self.n_z), ca.Sparsity.dense(1, 1),
                           np.arange(self.n_z)[:, None]))
        f = 0
        for k, t in enumerate(TERMS):
            f = f + w_sym[k] * acc.obj_terms[t]
        f = f + prior_sym[ON] * f_prior
        #: the same objective through the SX per-sample functions (not compiled): CasADi
        #: differentiates it to any order, so tests check the Hessian models against it
        #: (compiled kernels carry first derivatives only)
        self.f_reference = prior_sym[ON] * f_prior
        for t in SQUARED_TERMS:
            self.f_reference = self.f_reference + w_sym[TERMS.index(t)] * 0.5 * ca.sumsqr(ca.vertcat(*acc.r_stack[t]))
        #: the weighted penalty terms alone, through the SX functions (tests)
        self.f_penalty_reference = sum(w_sym[TERMS.index(t)] * sum(acc.penalty_sx[t]) for t in PENALTY_TERMS)
        self.f_reference = self.f_reference + self.f_penalty_reference
        V, mass, inertia, mu_g, mu_f = self.unpack_phys(self.phys_sx(theta, L_sym, m0_sym), L_sym, m0_sym)
        area, _, _ = polygon_area_centroid_j(V)
        self.phys_fun = ca.Function("phys", [z, p_all], [V, mass, inertia, mu_g, mu_f, area])
        self.f = f
        self.g = ca.vertcat(*acc.g_list)
        self.lbg = np.concatenate(acc.lbg)
        self.ubg = np.concatenate(acc.ubg)
        self.term_fun = ca.Function("terms", [z, p_all], [ca.vertcat(*[acc.obj_terms[t] for t in TERMS]), f_prior])
        self.nlp = {"x": z, "p": p_all, "f": f, "g": self.g}
        lam_g = ca.vertcat(*acc.lam_g_parts)
        #: {"gauss-newton" | "exact": CasADi Function (x, p, lam_f, lam_g) -> upper triangle
        #: of the Lagrangian Hessian model}, for nlpsol's hess_lag option, each built when
        #: first asked for (the exact one serves only solves configured to use it)
        self.hess_lag = LazyHessians(
            {mode: (lambda mode=mode: assemble_hessian(acc.hess_blocks[mode] + shared[mode], self.n_z))
             for mode in HESSIAN_MODES}, name="nlp_hess_l", ins=[z, p_all, lam_f, lam_g])
        #: stacked whitened residuals per squared term (for Gauss-Newton information);
        #: "kinematics" holds the eq. D2 constraint values
        self.residual_stack = {t: ca.vertcat(*v) if v else ca.MX.zeros(0) for t, v in acc.r_stack.items()}

    def _build_run(self, i, st, z, phys, run_sym, w_sym, lam_f, acc):
        """Run i's terms, its kinematic constraints and its Hessian blocks into ``acc``."""
        gsym, dsym = run_sym
        T, F, K = st.T, st.F, self.K
        stage = self.stage_function(F)
        start = self.start_function(F)
        # the loss and its gradient run through compiled copies (kernels.py); the SX
        # functions stay for the Hessian builders and the residual stack (information)
        kern = self._compiled([stage, start], f"F{F}", derivatives=(stage.name(), start.name()))
        stage_k, start_k = kern[stage.name()], kern[start.name()]
        off = self.offsets[i]

        def block(name, rows, cols):
            a, n = off[name]
            return ca.reshape(z[a: a + n], rows, cols)

        Q, Vv = block("Q", 3, T), block("V", 3, T)
        LG, LF, S = block("LG", 2 * K, T - 1), block("LF", 2 * F, T - 1), block("S", self.n_state, T)
        stage_args = (Q[:, :-1], Vv[:, :-1], Q[:, 1:], Vv[:, 1:], LG, LF, phys, dsym[:, 1:], gsym,
                      S[:, :-1], S[:, 1:])
        res = dict(zip(stage.name_out(), stage_k.map(T - 1, "serial")(*stage_args)))
        res_sx = dict(zip(stage.name_out(), stage.map(T - 1, "serial")(*stage_args)))
        for t in SQUARED_TERMS:
            acc.obj_terms[t] = acc.obj_terms[t] + 0.5 * ca.sumsqr(res[t])
            acc.r_stack[t].append(ca.vec(res_sx[t]))
        # eq. D2 (linear) directly in MX: its Jacobian is then not taken through the
        # per-sample functions (the stage's g_kin output is the same expression)
        g_kin = (Q[:, 1:] - Q[:, :-1]) / gsym[G["dt"]] - Vv[:, 1:]
        acc.r_stack["kinematics"].append(ca.vec(g_kin))
        for t in PENALTY_TERMS:
            acc.obj_terms[t] = acc.obj_terms[t] + ca.sum2(res[t])
            acc.penalty_sx[t].append(ca.sum2(res_sx[t]))
        # sample 0: the object starts at rest and above the ground
        start_args = (Q[:, 0], Vv[:, 0], phys, dsym[:, 0], gsym, S[:, 0])
        o0 = dict(zip(start.name_out(), start_k(*start_args)))
        o0_sx = dict(zip(start.name_out(), start(*start_args)))
        for t, name in START_TERM_OUTPUTS:
            acc.obj_terms[t] = acc.obj_terms[t] + 0.5 * ca.sumsqr(o0[name])
            acc.r_stack[t].append(ca.vec(o0_sx[name]))
        lam_kin = ca.MX.sym("lam_kin", 3, T - 1)
        acc.constrain(ca.vec(g_kin), np.zeros(3 * (T - 1)), np.zeros(3 * (T - 1)), ca.vec(lam_kin))
        # Hessian blocks of the Lagrangian, one small dense block per sample
        for mode in HESSIAN_MODES:
            hs = self._stage_hessian_function(stage, mode)
            h0 = self._start_hessian_function(start, mode)
            if mode == "gauss-newton":  # the default model: compiled (the exact one on demand only)
                kh = self._compiled([hs, h0], f"F{F}_hess_gn")
                hs, h0 = kh[hs.name()], kh[h0.name()]
            idx_s, idx_0 = self._stage_indices(i), self._start_indices(i)
            Hs = hs.map(T - 1, "serial")(*stage_args, w_sym, lam_f, lam_kin)
            acc.hess_blocks[mode].append((Hs, ca.Sparsity.dense(idx_s.shape[1], idx_s.shape[1]), idx_s))
            H0 = h0(*start_args, w_sym, lam_f)
            acc.hess_blocks[mode].append((H0, ca.Sparsity.dense(idx_0.shape[1], idx_0.shape[1]), idx_0))

    def _build_theta_terms(self, theta, prior_sym, lam_f, lam_lift, L_sym, m0_sym, acc):
        """The priors and the shape's validity constraints (theta only): returns the prior
        (MX) and {Hessian mode: [the theta block of the Hessian]}; the constraints go into
        ``acc``."""
        theta_sx = ca.SX.sym("theta", self.n_theta)
        sc = self.shape.constraints(theta_sx[: self.n_shape])
        n_sc = len(sc)
        prior_sx = ca.SX.sym("prior", self.n_prior())
        f_prior_sx = self.prior_expression(theta_sx, prior_sx)
        lam_sc = ca.MX.sym("lam_shape", n_sc)
        lam_sc_sx = ca.SX.sym("lam_shape", n_sc)
        g_sc_sx = ca.vertcat(*sc) if n_sc else ca.SX.zeros(0)
        self.prior_fun = ca.Function("prior", [theta_sx, prior_sx], [f_prior_sx])
        lf_sx = ca.SX.sym("lam_f")
        lam_lift_sx = ca.SX.sym("lam_lift", self.n_phys)
        L_sx, m0_sx = ca.SX.sym("L"), ca.SX.sym("m0")
        lag_rest = -ca.dot(lam_lift_sx, self.phys_sx(theta_sx, L_sx, m0_sx))
        if n_sc:
            lag_rest = lag_rest + ca.dot(lam_sc_sx, g_sc_sx)
        # the priors: exact second derivatives in the exact model, JᵀJ of their residuals in
        # the Gauss-Newton one (as every squared term; the log-normal friction prior's exact
        # second derivative is negative above e times its median, and IPOPT stalled there)
        weight = lf_sx * prior_sx[ON]
        h_prior = {"exact": ca.hessian(weight * f_prior_sx, theta_sx)[0],
                   "gauss-newton": weight * self.prior_gauss_newton(theta_sx, prior_sx)}
        h_rest = ca.hessian(lag_rest, theta_sx)[0]
        args = [theta, prior_sym, lam_f, lam_sc, lam_lift, L_sym, m0_sym]
        shared = {}
        for mode in HESSIAN_MODES:
            h_theta = ca.Function("hess_theta", [theta_sx, prior_sx, lf_sx, lam_sc_sx, lam_lift_sx, L_sx, m0_sx],
                                  [ca.densify(h_rest + h_prior[mode])])
            shared[mode] = [(h_theta(*args), ca.Sparsity.dense(self.n_theta, self.n_theta),
                             np.arange(self.n_theta)[None, :])]
        if n_sc:
            acc.constrain(ca.Function("g_shape", [theta_sx], [g_sc_sx])(theta), np.zeros(n_sc),
                          np.full(n_sc, np.inf), lam_sc)
        return self.prior_fun(theta, prior_sym), shared

    def _compiled(self, funs, part, derivatives=()):
        """{name: Function}: the SX functions funs compiled to C (tacest.estimation.kernels;
        as given without a compiler).  The tag names the shape, effects and part, so that
        every structure's kernels are compiled once per machine and cached."""
        tag = f"tacest2d_{self.shape.name.replace(':', '')}_{'_'.join(self.effects) or 'plain'}_{part}"
        return compile_functions(funs, tag, derivatives=derivatives)

    # ------------------------------------------------------------------------------
    # Lagrangian Hessian from small per-sample blocks (built in O(T))

    def _stage_hessian_function(self, stage, mode):
        """SX Function: dense Hessian of one sample's Lagrangian contribution with respect
        to its local variables y = [q_prev, v_prev, q, v, lam_ground, lam_finger, phys,
        s_prev, s] (stage_local_variables; the order of _stage_indices)."""
        ins = stage.sx_in()
        w = ca.SX.sym("w", len(TERMS))
        lam_f = ca.SX.sym("lam_f")
        lk = ca.SX.sym("lam_kin", 3)
        out = dict(zip(stage.name_out(), stage(*ins)))
        H = self._local_hessian(out, stage_local_variables(ins), w, lam_f, mode, extra=ca.dot(lk, out["g_kin"]))
        return ca.Function("hess_stage", [*ins, w, lam_f, lk], [H])

    def _start_hessian_function(self, start, mode):
        ins = start.sx_in()
        w = ca.SX.sym("w", len(TERMS))
        lam_f = ca.SX.sym("lam_f")
        out = dict(zip(start.name_out(), start(*ins)))
        H = self._local_hessian(out, start_local_variables(ins), w, lam_f, mode, names=dict(START_TERM_OUTPUTS))
        return ca.Function("hess_start", [*ins, w, lam_f], [H])

    @staticmethod
    def _local_hessian(out, y, w, lam_f, mode, extra=0, names=None):
        """Dense local Hessian of lam_f · (weighted loss) + extra with respect to y.

        Gauss–Newton (mode "gauss-newton"): the squared terms contribute J_rᵀ J_r
        (positive semi-definite, the right model of a least-squares objective far from a
        zero-residual fit), the penalty terms and the constraints their exact second
        derivatives.  Mode "exact": everything exact.  names maps loss terms to the
        output names holding them.
        """
        names = names or {t: t for t in TERMS}
        if mode == "exact":
            lag = 0
            for k, t in enumerate(TERMS):
                if t not in names:
                    continue
                o = out[names[t]]
                lag = lag + w[k] * (0.5 * ca.sumsqr(o) if t in SQUARED_TERMS else o)
            return ca.densify(ca.hessian(lam_f * lag + extra, y)[0])
        r = ca.vertcat(*[ca.sqrt(w[TERMS.index(t)]) * ca.vec(out[names[t]]) for t in SQUARED_TERMS if t in names])
        J = ca.jacobian(r, y)
        rest = extra
        for k, t in enumerate(TERMS):
            if t in PENALTY_TERMS and t in names:
                rest = rest + lam_f * w[k] * out[names[t]]
        H = lam_f * ca.mtimes(J.T, J)
        if not (isinstance(rest, (int, float)) and rest == 0):
            H = H + ca.hessian(rest, y)[0]
        return ca.densify(H)

    def _stage_indices(self, i):
        """(T-1, n_y) global z indices of each sample's local variables (see above)."""
        st, off, K = self.structures[i], self.offsets[i], self.K
        T, F = st.T, st.F
        t = np.arange(1, T)[:, None]
        q_prev = off["Q"][0] + 3 * (t - 1) + np.arange(3)
        v_prev = off["V"][0] + 3 * (t - 1) + np.arange(3)
        q = off["Q"][0] + 3 * t + np.arange(3)
        v = off["V"][0] + 3 * t + np.arange(3)
        lg = off["LG"][0] + 2 * K * (t - 1) + np.arange(2 * K)
        lf = off["LF"][0] + 2 * F * (t - 1) + np.arange(2 * F)
        ph = np.repeat(self.phys_offset + np.arange(self.n_phys)[None, :], T - 1, 0)
        s_prev = off["S"][0] + self.n_state * (t - 1) + np.arange(self.n_state)
        s = off["S"][0] + self.n_state * t + np.arange(self.n_state)
        return np.hstack([q_prev, v_prev, q, v, lg, lf, ph, s_prev, s])

    def _start_indices(self, i):
        off = self.offsets[i]
        return np.concatenate([off["Q"][0] + np.arange(3), off["V"][0] + np.arange(3),
                               self.phys_offset + np.arange(self.n_phys),
                               off["S"][0] + np.arange(self.n_state)])[None, :]

    # ------------------------------------------------------------------------------
    # helpers to slice z

    @property
    def stage_funs(self):
        """The stage function of every run (one per finger count, shared)."""
        return [self.stage_function(st.F) for st in self.structures]

    @property
    def start_funs(self):
        return [self.start_function(st.F) for st in self.structures]

    def run_blocks(self, z, i):
        """Views (scaled values) of run i: Q (3, T), V (3, T), LG (2K, T-1) ground impulses
        [normal (K); tangential (K)], LF (2F, T-1)."""
        st = self.structures[i]
        off = self.offsets[i]
        z = np.asarray(z, float).reshape(-1)

        def blk(name, rows):
            a, n = off[name]
            return z[a: a + n].reshape(-1, rows).T

        LF = blk("LF", 2 * st.F) if st.F else np.zeros((0, st.T - 1))
        return blk("Q", 3), blk("V", 3), blk("LG", 2 * self.K), LF

    def state_block(self, z, i):
        """(n_state, T) the per-sample states of run i (the effects' rows, in
        state_slices); no rows without such effects."""
        a, n = self.offsets[i]["S"]
        return np.asarray(z, float).reshape(-1)[a: a + n].reshape(self.structures[i].T, self.n_state).T

    def stage_arguments(self, z, i, D, g):
        """The stage function's inputs for every interval of run i (mapped over T-1):
        from z (scaled decision vector), D (n_data, T) the run's data matrix and g its
        global vector."""
        Q, V, LG, LF = self.run_blocks(z, i)
        S = self.state_block(z, i)
        phys = np.asarray(z, float).reshape(-1)[self.phys_offset: self.phys_offset + self.n_phys]
        return (Q[:, :-1], V[:, :-1], Q[:, 1:], V[:, 1:], LG, LF, phys, D[:, 1:], g, S[:, :-1], S[:, 1:])

    def start_arguments(self, z, i, D, g):
        """The start function's inputs of run i (see stage_arguments)."""
        Q, V, _, _ = self.run_blocks(z, i)
        phys = np.asarray(z, float).reshape(-1)[self.phys_offset: self.phys_offset + self.n_phys]
        return (Q[:, 0], V[:, 0], phys, D[:, 0], g, self.state_block(z, i)[:, 0])

    def set_run_blocks(self, z, i, Q=None, V=None, LG=None, LF=None, S=None):
        """Write run i's blocks into z (scaled values, shapes as run_blocks and
        state_block give them).  New ground impulses LG without states S set the states
        where their effects start them under those impulses (a soft ground's plate at
        rest under its load, with the values z holds; zeros otherwise)."""
        off = self.offsets[i]
        if LG is not None and S is None and self.n_state:
            T = np.asarray(LG).shape[1] + 1
            S = np.zeros((self.n_state, T))
            u = self.effect_values(np.asarray(z, float), self.n_shape + len(PHYS_NAMES))
            mass_ratio = float(np.exp(z[self.n_shape]))  # m / m0
            for e in self.effect_objects:
                if e.name in self.state_slices:
                    rows = e.initial_states_2d(u[e.name], mass_ratio, np.asarray(LG, float)[: self.K], self.K)
                    if rows is not None:
                        S[self.state_slices[e.name]] = rows
        for name, arr in (("Q", Q), ("V", V), ("LG", LG), ("LF", LF), ("S", S)):
            if arr is not None:
                a, n = off[name]
                z[a: a + n] = np.asarray(arr, float).T.reshape(-1)
        return z

    def settle_states(self, z, i, D, g):
        """z with run i's states of effects that set them from the motion (e.g.
        restitution's impact memory: Effect.settled_output) set sample by sample to what
        their laws give along z's trajectory (D, g: the run's data matrix and global
        vector).  Each sample's value depends on the previous one (the interval after an
        impact is no new impact), so a start with such states at 0 leaves the impulse
        stage a nonconvex problem in them, and on a tumbling landing it settled on a
        leaked 0.2 m/s that hid the real impact of the next sample.  z is returned as it
        is without such effects."""
        settled = [(e, self.state_slices[e.name]) for e in self.effect_objects
                   if e.settled_output and e.name in self.state_slices]
        if not settled:
            return z
        T = self.structures[i].T
        S = self.state_block(z, i).copy()
        for _, sl in settled:
            S[sl] = 0.0
        qp, vp, q, v, lg, lf, phys, d, g_, _, _ = self.stage_arguments(z, i, D, g)
        stage = self.stage_funs[i]
        names = stage.name_out()
        for t in range(1, T):
            j = t - 1
            out = stage(qp[:, j], vp[:, j], q[:, j], v[:, j], lg[:, j], lf[:, j], phys, d[:, j], g_, S[:, j], S[:, t])
            for e, sl in settled:
                S[sl, t] = np.asarray(out[names.index(e.settled_output)]).ravel()
        return self.set_run_blocks(z, i, S=S)


    # ------------------------------------------------------------------------------
    # derivatives for the information (tacest.estimation.uncertainty)

    @cached_property
    def residual_jacobian(self):
        """Callable (z, p) -> (r, J) of the stacked whitened residuals with the active-set
        rows (:class:`ResidualJacobian2D`)."""
        return ResidualJacobian2D(self)

    @cached_property
    def phys_jacobian(self):
        """CasADi Function (theta, L, m0) -> ∂phys/∂theta (n_phys, n_theta)."""
        th = ca.SX.sym("theta", self.n_theta)
        L, m0 = ca.SX.sym("L"), ca.SX.sym("m0")
        return ca.Function("dphys", [th, L, m0], [ca.jacobian(self.phys_sx(th, L, m0), th)])

    @cached_property
    def penalty_gradient(self):
        """CasADi Function (z, p) -> gradient (n_z,) of the weighted penalty (Occam) terms."""
        return ca.Function("gpen", [self.z_sym, self.p_sym], [ca.gradient(self.f_penalty_reference, self.z_sym)])

    @cached_property
    def _prior_hessian_function(self):
        th = ca.SX.sym("theta", self.n_theta)
        pv = ca.SX.sym("prior", self.n_prior())
        return ca.Function("hprior", [th, pv], [ca.densify(self.prior_gauss_newton(th, pv))])

    def prior_values(self, p) -> np.ndarray:
        """The prior vector (see StageModel2D.n_prior) of a parameter vector p."""
        a = self.n_p + len(TERMS)
        return np.asarray(p, float).reshape(-1)[a: a + self.n_prior()]

    def prior_hessian(self, theta, p) -> np.ndarray:
        """(n_theta, n_theta) Gauss–Newton Hessian (JᵀJ of their residuals) of the
        objective's parameter priors (scaled theta), with their on/off flag, under the
        parameter vector p: the priors' information (the log-normal friction prior's
        exact Hessian turns negative above e times its median)."""
        pv = self.prior_values(p)
        return pv[ON] * np.asarray(self._prior_hessian_function(np.asarray(theta, float), pv), float)


class ResidualJacobian2D:
    """(z, p) -> (r (m,) DM, J (m, n_z) sparse DM) of the stacked whitened residuals
    (each squared term times the square root of its weight, then eq. D2 over
    KINEMATICS_SIGMA and the active-set rows, tacest.model.jacobians2d), assembled from
    per-sample Jacobians of the stage and start functions (SX, evaluated numerically):
    O(T), no symbolic Jacobian of the whole NLP.  Rows are grouped per sample; JᵀJ does
    not depend on their order."""

    def __init__(self, problem):
        self.pr = problem
        self.stage_jac = [stage_residual_jacobian(stage) for stage in problem.stage_funs]
        self.contact_state = [contact_state_function(stage) for stage in problem.stage_funs]
        self.start_jac = [start_residual_jacobian(start) for start in problem.start_funs]

    def __call__(self, z, p):
        pr = self.pr
        z = np.asarray(z, float).reshape(-1)
        p = np.asarray(p, float).reshape(-1)
        w = p[pr.n_p: pr.n_p + len(TERMS)]
        r_parts, rows, cols, vals = [], [], [], []
        m = 0
        for i, st in enumerate(pr.structures):
            off, n_g, n_d = pr.p_offsets[i]
            g = p[off: off + n_g]
            D = p[off + n_g: off + n_g + n_d].reshape(st.T, -1).T
            args = pr.stage_arguments(z, i, D, g)
            a = stage_active_weights(self.contact_state[i].map(st.T - 1), st.T - 1, args, pr.K)
            r, J = self.stage_jac[i].map(st.T - 1)(*args, w, a)
            r = np.asarray(r)  # (n_r, T-1)
            J = np.asarray(J).reshape(r.shape[0], -1, st.T - 1, order="F")  # (n_r, n_y, T-1)
            idx = pr._stage_indices(i)  # (T-1, n_y)
            n_r = J.shape[0]
            row = m + np.arange(st.T - 1)[None, None, :] * n_r + np.arange(n_r)[:, None, None]
            rows.append(np.broadcast_to(row, J.shape).ravel())
            cols.append(np.broadcast_to(idx.T[None, :, :], J.shape).ravel())
            vals.append(J.ravel())
            r_parts.append(r.T.ravel())
            m += n_r * (st.T - 1)
            r0, J0 = self.start_jac[i](*pr.start_arguments(z, i, D, g), w)
            r0, J0 = np.asarray(r0).ravel(), np.asarray(J0)
            idx0 = pr._start_indices(i)[0]
            rows.append(np.repeat(m + np.arange(len(r0)), len(idx0)))
            cols.append(np.tile(idx0, len(r0)))
            vals.append(J0.ravel())
            r_parts.append(r0)
            m += len(r0)
        rows, cols, vals = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
        keep = vals != 0
        Jm = sp.csc_matrix((vals[keep], (rows[keep], cols[keep])), shape=(m, pr.n_z))
        Jm.sum_duplicates()
        Jm.sort_indices()
        J_dm = ca.DM(ca.Sparsity(m, pr.n_z, Jm.indptr.tolist(), Jm.indices.tolist()), Jm.data)
        return ca.DM(np.concatenate(r_parts)), J_dm


class _Accumulator:
    """What the per-run builders add up: objective terms, residual stacks (SX through
    the uncompiled functions), constraints with their bounds and symbolic multipliers,
    Hessian blocks per model."""

    def __init__(self, n_lift, lam_lift):
        self.obj_terms = {t: 0 for t in TERMS}
        self.r_stack = {t: [] for t in SQUARED_TERMS + ("kinematics",)}
        self.penalty_sx = {t: [] for t in PENALTY_TERMS}
        self.g_list, self.lbg, self.ubg, self.lam_g_parts = [], [], [], []
        self.hess_blocks = {mode: [] for mode in HESSIAN_MODES}
        self._lift = (n_lift, lam_lift)

    def constrain(self, g, lb, ub, lam=None):
        """Append constraints g (MX) with bounds and their multiplier symbols (the lifting
        constraints' on the first call)."""
        self.g_list.append(g)
        self.lbg.append(lb)
        self.ubg.append(ub)
        self.lam_g_parts.append(self._lift[1] if lam is None else lam)
