"""The 3-D physics-constrained maximum-likelihood problem as ONE CasADi NLP: the stage
model (tacest.model.stage3d) assembled over the runs laid end to end.

The decision variables are the POSES of every sample (the kinematics are eliminated, see
tacest.model.stage3d); ONE stage function is mapped over all dynamic intervals of all
runs, one start function over the runs.  Decision vector z (all scaled to O(1); L length
scale, m0 mass scale)::

    theta  = [s (n_s) shape, log(m / m0), c (6) log-Cholesky of Sigma / (m L²),
              mu_ground, mu_finger, effect parameters]
    P      (7, S):  per sample [p / L (3), q (4)]
    U      (K, M):  per dynamic interval, ground impulse variable of each vertex:
                    lambda_n = softplus(u) in units of m0 g dt (stage3d.impulse_of)
    LF     (3F, M): per dynamic interval, each finger's impulse ON the object, world
                    frame, in units of m0 g dt

Loss: 0.5 |r|² of the stacked whitened residuals (each term times the square root of its
weight) plus the priors: a nonlinear least-squares problem with simple bounds, no
equality constraints.  The Lagrangian Hessian is lam_f (Jᵀ J + [exact only] Σ r_i ∇² r_i)
+ a Levenberg–Marquardt ridge, assembled from small per-interval blocks
(tacest.estimation.assembly); the per-sample functions are compiled to C when a compiler
is available (tacest.estimation.kernels).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from tacest.estimation.assembly import LazyHessians, assemble_hessian, scatter_matrix
from tacest.estimation.config import EstimatorConfig
from tacest.estimation.kernels import compile_functions
from tacest.geometry.shapes3d import Shape3D
from tacest.model.stage3d import G3_NAMES, NP, STAGE_TERMS, START_TERMS, TERMS3D, Layout3D, StageModel3D

HESSIAN_MODES = ("gauss-newton", "exact")


class Problem3D(StageModel3D):
    """The 3-D NLP for a set of runs of one object (see module docstring).

    Parameters
    ----------
    shape : Shape3D (box, polytope:K)
    layout : Layout3D (run lengths, fingers)
    config : EstimatorConfig
    effects : effect names modelled as extra parameters (tacest.model.registry)
    """

    def __init__(self, shape: Shape3D, layout: Layout3D, config: EstimatorConfig, effects=()):
        super().__init__(shape, layout.F, effects)
        self.layout = layout
        self.config = config
        lay = layout
        self.x_offset = self.n_theta
        self.u_offset = self.x_offset + NP * lay.S
        self.lf_offset = self.u_offset + self.K * lay.M
        self.n_z = self.lf_offset + 3 * self.F * lay.M
        #: (M, n_poses) sample indices of each dynamic interval's stage window, oldest first
        self.windows = lay.windows(self.n_poses)
        self.first = lay.first
        self._build()

    # ------------------------------------------------------------------------------
    # layout of z

    def x_index(self, samples):
        """(len(samples), 7) z indices of the poses of the given samples."""
        return self.x_offset + NP * np.asarray(samples, int)[:, None] + np.arange(NP)

    def u_index(self, intervals):
        return self.u_offset + self.K * np.asarray(intervals, int)[:, None] + np.arange(self.K)

    def lf_index(self, intervals):
        return self.lf_offset + 3 * self.F * np.asarray(intervals, int)[:, None] + np.arange(3 * self.F)

    def split(self, z):
        """numpy views: theta (n_theta,), X (7, S), U (K, M), LF (3F, M)."""
        z = np.asarray(z, float).reshape(-1)
        lay = self.layout
        X = z[self.x_offset: self.u_offset].reshape(lay.S, NP).T
        U = z[self.u_offset: self.lf_offset].reshape(lay.M, self.K).T
        LF = z[self.lf_offset:].reshape(lay.M, 3 * self.F).T
        return z[: self.n_theta], X, U, LF

    def join(self, theta, X, U, LF):
        return np.concatenate([np.asarray(theta, float).reshape(-1), np.asarray(X, float).T.reshape(-1),
                               np.asarray(U, float).T.reshape(-1), np.asarray(LF, float).T.reshape(-1)])

    def split_parameters(self, p):
        """(D (n_d, S), g (n_g,), w (n_terms,)) from a parameter vector."""
        p = np.asarray(p, float).reshape(-1)
        nD = self.n_d * self.layout.S
        ng = len(G3_NAMES)
        return p[:nD].reshape(self.layout.S, self.n_d).T, p[nD: nD + ng], p[nD + ng: nD + ng + len(TERMS3D)]

    # ------------------------------------------------------------------------------
    # building

    def _build(self):
        lay, K, F = self.layout, self.K, self.F
        S, M, R = lay.S, lay.M, len(lay.lengths)
        z = ca.MX.sym("z", self.n_z)
        theta = z[: self.n_theta]
        X = ca.reshape(z[self.x_offset: self.u_offset], NP, S)
        U = ca.reshape(z[self.u_offset: self.lf_offset], K, M)
        LF = ca.reshape(z[self.lf_offset:], 3 * F, M) if F else ca.MX(0, M)
        D = ca.MX.sym("D", self.n_d, S)
        gsym = ca.MX.sym("g", len(G3_NAMES))
        w_sym = ca.MX.sym("w", len(TERMS3D))
        prior_sym = ca.MX.sym("prior", self.n_prior())
        ridge_sym = ca.MX.sym("ridge")
        p_all = ca.vertcat(ca.vec(D), gsym, w_sym, prior_sym, ridge_sym)
        self.n_p = p_all.shape[0]
        f0, f1 = list(self.first), list(self.first + 1)

        # per-interval and per-start functions (SX); the NLP maps them over all samples
        self.stage_fun = self._stage_function()
        self.start_fun = self._start_function()
        self.res_fun, self.res_rows = self._residual_function(self.stage_fun, STAGE_TERMS)
        self.res0_fun, self.res0_rows = self._residual_function(self.start_fun, START_TERMS)
        th_sx = ca.SX.sym("theta", self.n_theta)
        pr_sx = ca.SX.sym("prior", self.n_prior())
        self.prior_fun = ca.Function("prior3d", [th_sx, pr_sx], [self.prior_residual(th_sx, pr_sx)])
        jr = self._jacobian_function(self.res_fun, self.n_poses + 3)
        j0 = self._jacobian_function(self.res0_fun, 3)
        # compiled to C once per machine when a compiler is available (kernels.py)
        self.kernel_tag = f"tacest3d_{self.shape.name.replace(':', '')}_{'_'.join(self.effects) or 'plain'}_F{F}"
        kern = compile_functions([self.res_fun, self.res0_fun, jr, j0], self.kernel_tag + "_base",
                                 derivatives=(self.res_fun.name(), self.res0_fun.name()))
        res_k, res0_k = kern[self.res_fun.name()], kern[self.res0_fun.name()]
        jr_k, j0_k = kern[jr.name()], kern[j0.name()]

        poses, D_win = self.stage_window_arguments(X, D)
        stage_args = poses + [U, LF, theta, D_win, gsym]
        start_args = [X[:, f0], X[:, f1], theta, D[:, f0], D[:, f1], gsym]
        r_stage = res_k.map(M, "serial")(*stage_args, w_sym)  # (n_r, M)
        r_start = res0_k.map(R, "serial")(*start_args, w_sym)  # (n_r0, R)
        r_prior = self.prior_fun(theta, prior_sym)
        r_all = ca.vertcat(ca.vec(r_stage), ca.vec(r_start), r_prior)
        f = 0.5 * ca.sumsqr(r_all)
        self.g = ca.MX(0, 1)
        self.lbg = np.zeros(0)
        self.ubg = np.zeros(0)
        self.z_sym, self.p_sym, self.f = z, p_all, f
        self.nlp = {"x": z, "p": p_all, "f": f, "g": self.g}
        self.weight_sym = w_sym

        # global sparse Jacobian of the whitened residuals from per-sample blocks
        th_idx = np.arange(self.n_theta)[None]
        y_stage = np.hstack([self.x_index(self.windows[:, k]) for k in range(self.n_poses)]
                            + [self.u_index(np.arange(M)), self.lf_index(np.arange(M)), np.repeat(th_idx, M, 0)])
        y_start = np.hstack([self.x_index(self.first), self.x_index(self.first + 1), np.repeat(th_idx, R, 0)])
        n_r, n_r0, n_rp = self.res_rows, self.res0_rows, self.prior_fun.size1_out(0)
        rows_stage = np.arange(M)[:, None] * n_r + np.arange(n_r)
        rows_start = M * n_r + np.arange(R)[:, None] * n_r0 + np.arange(n_r0)
        rows_prior = (M * n_r + R * n_r0 + np.arange(n_rp))[None]
        th_sx2 = ca.SX.sym("theta", self.n_theta)
        pr_sx2 = ca.SX.sym("prior", self.n_prior())
        jp = ca.Function("jac_prior3d", [th_sx2, pr_sx2], [ca.jacobian(self.prior_fun(th_sx2, pr_sx2), th_sx2)])
        self.n_res = M * n_r + R * n_r0 + n_rp
        #: rows of the data residuals (everything but the prior) in r_all / J_all
        self.n_res_data = M * n_r + R * n_r0
        J_all = scatter_matrix([
            (jr_k.map(M, "serial")(*stage_args, w_sym), jr.sparsity_out(0), rows_stage, y_stage),
            (j0_k.map(R, "serial")(*start_args, w_sym), j0.sparsity_out(0), rows_start, y_start),
            (jp(theta, prior_sym), jp.sparsity_out(0), rows_prior, th_idx),
        ], self.n_res, self.n_z)
        #: Function (z, p) -> (r (n_res,), J (n_res, n_z) sparse): all whitened residuals
        self.residual_jacobian = ca.Function("r_jac3d", [z, p_all], [r_all, J_all])
        #: IPOPT settings on top of estimation/solver.py's: the acceptable complementarity
        #: is checked on unscaled values, here in units of the loss (a chi-square sum over
        #: thousands of whitened residuals whose gradient entries reach 1e4, so that
        #: IPOPT's gradient scaling of ~1e-2 turns the barrier's mu = 1e-5 into ~1e-3).
        #: One loss unit is half a squared sigma: negligible against the loss's spread.
        self.nlpsol_options = {"ipopt": {"acceptable_compl_inf_tol": 1.0,
                                         "acceptable_tol": float(self.config.solver3d.acceptable_tol)}}

        # Lagrangian Hessian models: lam_f Jᵀ J (+ Σ r_i ∇² r_i in "exact" mode) + ridge
        lam_f = ca.MX.sym("lam_f")
        lam_g = ca.MX.sym("lam_g", 0)
        ridge = assemble_hessian([(ca.repmat(ridge_sym * lam_f, 1, self.n_z), ca.Sparsity.dense(1, 1),
                                   np.arange(self.n_z)[:, None])], self.n_z)
        H_gn = lam_f * ca.triu(ca.mtimes(J_all.T, J_all)) + ridge

        def exact():
            """The exact model adds Σ_i r_i ∇² r_i (built and compiled on first use)."""
            h2 = self._second_order_function(self.res_fun, self.n_poses + 3)
            h20 = self._second_order_function(self.res0_fun, 3)
            h2p = self._second_order_function(self.prior_fun, 1)
            k2 = compile_functions([h2, h20], self.kernel_tag + "_exact")
            second = assemble_hessian([
                (k2[h2.name()].map(M, "serial")(*stage_args, w_sym, r_stage), h2.sparsity_out(0), y_stage),
                (k2[h20.name()].map(R, "serial")(*start_args, w_sym, r_start), h20.sparsity_out(0), y_start),
                (h2p(theta, prior_sym, r_prior), h2p.sparsity_out(0), th_idx),
            ], self.n_z)
            return H_gn + lam_f * second

        #: {"gauss-newton" | "exact": Function (x, p, lam_f, lam_g) -> upper triangle of
        #: the Lagrangian Hessian model}, for nlpsol's hess_lag option
        self.hess_lag = LazyHessians({"gauss-newton": lambda: H_gn, "exact": exact}, name="nlp_hess_l",
                                     ins=[z, p_all, lam_f, lam_g])

    # ------------------------------------------------------------------------------
    # derivative building blocks (SX, per sample)

    def _residual_function(self, fun, terms):
        """SX Function (inputs of fun..., w) -> the stacked residual: sqrt(w_t) r_t of the
        given terms, then fun's quaternion-norm residuals (one per pose it takes); and its
        length."""
        ins = fun.sx_in()
        w = ca.SX.sym("w", len(TERMS3D))
        out = dict(zip(fun.name_out(), fun(*ins)))
        r = ca.vertcat(*[ca.sqrt(w[TERMS3D.index(t)]) * out[t] for t in terms], out["quat_norm"])
        return ca.Function(f"res_{fun.name()}", ins + [w], [r]), r.shape[0]

    @staticmethod
    def _jacobian_function(res_fun, n_y):
        """SX Function (inputs...) -> sparse Jacobian of res_fun's output with respect to
        its first n_y inputs stacked (the sample's local variables)."""
        ins = res_fun.sx_in()
        return ca.Function(f"jac_{res_fun.name()}", ins, [ca.jacobian(res_fun(*ins), ca.vertcat(*ins[:n_y]))])

    @staticmethod
    def _second_order_function(res_fun, n_y):
        """SX Function (inputs..., c) -> Σ_i c_i ∇² r_i with respect to the local
        variables: the part of the exact Hessian of 0.5 |r|² that Gauss–Newton drops,
        evaluated with c = r."""
        ins = res_fun.sx_in()
        r = res_fun(*ins)
        c = ca.SX.sym("c", r.shape[0])
        return ca.Function(f"h2_{res_fun.name()}", ins + [c], [ca.hessian(ca.dot(c, r), ca.vertcat(*ins[:n_y]))[0]])

    def direct_residual_functions(self):
        """(res: stage inputs with lambda_n in place of u -> r (n_r,); jac: -> dense (n_r, K)
        Jacobian of r with respect to lambda_n, constant: r is affine in lambda_n for held
        poses and parameters)."""
        res, _ = self._residual_function(self._stage_function(direct=True), STAGE_TERMS)
        ins = res.sx_in()
        return res, ca.Function("jac_ln3d", ins, [ca.densify(ca.jacobian(res(*ins), ins[self.n_poses]))])

    def stage_window_arguments(self, X, D):
        """The pose inputs of the stage over every dynamic interval (n_poses arrays (7, M),
        oldest first) and the interval's data D (n_d, M), from X (7, S) and D (n_d, S)
        (numpy arrays, or the NLP's CasADi symbols)."""
        win = self.windows
        return [X[:, win[:, k].tolist()] for k in range(self.n_poses)], D[:, win[:, -1].tolist()]
