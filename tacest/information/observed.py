"""Observed (Gauss–Newton) information of the parameters from CasADi's symbolic Jacobians.

With r(z) the stacked whitened residuals (each term times sqrt of its weight) and J its
Jacobian with respect to the free decision variables z = (theta, states, impulses),
the observed information is I = Jᵀ J.  The states and impulses are nuisance variables:
the information of theta (and the final pose of the last run) is the Schur complement

    I_θ = I_θθ - I_θx (I_xx + δ I)⁻¹ I_xθ,

with the nuisance columns scaled to unit norm first (I_xx then has a unit diagonal) and
δ a tiny ridge on that scaled block, for directions the squared residuals do not see
(e.g. impulse splits among ground vertices that only the complementarity penalties
decide); see :func:`schur_information`.  The
kinematic equality constraints (eq. D2) enter as residuals with a tight sigma
(:data:`KINEMATICS_SIGMA`), their Gauss–Newton stand-in.  The lifted physical
quantities ``phys`` are tied to theta by the equality phys = phys(theta): the residuals
see theta only through them, so their Jacobian columns are folded into theta's by the
chain rule, J_θ ← J_θ + J_phys ∂phys/∂θ (:func:`fold_lifted_parameters`), and they are
not nuisance variables.

Active-set rows.  The estimator's contact laws are relaxed for the solver's sake: a
loaded vertex may sit within a fraction of a millimetre of the ground at small cost, and
the maximal-dissipation residual is flat to second order at zero slip (its gradient is
the friction impulse times the slip).  Linearized there, a resting object is free to
drift and tilt: on a box at rest after three pokes the final position came out uncertain
by 4-15 cm, so that every new poke looked as if it first had to find the object again,
and a touch on an untouched face taught no more than one on a known face.  The
information is therefore taken on the active set of the fit, as for constrained
estimation: at every interval, a ground vertex that carries load (normal impulse at least
:data:`ACTIVE_LOAD_FRACTION` of the object's weight) adds the row gap / sigma_pen (it is
on the ground, to the tolerated penetration), and one that also sticks (slip below the
estimator's slip smoothing SLIP_EPS, friction inside :data:`ACTIVE_CONE_FRACTION` of the
cone) adds slip / SLIP_EPS (it does not move).  The rows carry no weight where the
contact is open or sliding, so sliding and lift-off stay as the relaxed laws describe
them.  Their weights are fixed at the linearization point (:func:`active_weights`).
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from tacest.estimation.problem import (SLIP_EPS, SQUARED_TERMS, START_TERM_OUTPUTS, TERMS, start_local_variables,
                                       stage_local_variables)

#: scaled units (L per second) of the stand-in residual for eq. D2; 1e-4 is far tighter
#: than any measurement, so it acts as the constraint without dominating the conditioning
KINEMATICS_SIGMA = 1e-4
#: ridge on the nuisance block after its columns are scaled to unit norm (unit
#: diagonal).  The block mixes rows of very different weights (eq. D2 over
#: KINEMATICS_SIGMA: entries ~1e4; ground-impulse splits seen only through the
#: complementarity penalties: ~1e-3), so a ridge relative to its largest entry (the
#: earlier 1e-10 · max diag ~ 1e-2) pinned the weakly seen nuisance directions and
#: leaked spurious information into theta: after one press from above, a box's width
#: came out known to 0.8 mm when the objective's profile over the width is flat
#: (4.89 to 5.10 from 44 to 160 mm wide).  On the unit diagonal, 1e-12 and 1e-14 give
#: the same sigmas to 2 % there (width 0.14 m), so 1e-12 is below every direction the
#: data see and well above rounding
RIDGE = 1e-12


#: a ground vertex is in the active set when its normal impulse is at least this
#: fraction of the object's weight per interval (a box resting on two vertices carries
#: half on each; a vertex grazing the ground while the object tips carries little)
ACTIVE_LOAD_FRACTION = 0.05
#: ... and sticks when its friction impulse is inside this fraction of the cone (at the
#: cone's edge it is about to slide, which the dissipation residual describes)
ACTIVE_CONE_FRACTION = 0.95


def active_weights(phi, slip, lam_n, lam_t, mu, weight, sig_pen):
    """(2K, N) weights of the active-set rows (module docstring) of N intervals.

    phi, slip : (K, N) ground gaps (m) and slip velocities (m/s); lam_n, lam_t : (K, N)
    normal and tangential ground impulses (units of the reference weight m0·g·dt);
    mu : (N,) ground friction; weight : (N,) the object's weight in those units;
    sig_pen : (N,) m, the tolerated penetration.  Rows [gap weights (1/m); slip weights
    (s/m)]; 0 where the vertex is not loaded, or (slip rows) not sticking.
    """
    loaded = lam_n >= ACTIVE_LOAD_FRACTION * np.asarray(weight)[None, :]
    stick = loaded & (np.abs(slip) <= SLIP_EPS) & (np.abs(lam_t) <= ACTIVE_CONE_FRACTION * np.asarray(mu)[None, :] * lam_n)
    return np.concatenate([loaded / np.asarray(sig_pen)[None, :], stick / SLIP_EPS], axis=0)


def contact_state_function(stage):
    """SX Function (the stage's inputs) -> (phi (K,) m, slip (K,) m/s, mu, weight): what
    :func:`active_weights` needs besides the impulses."""
    ins = stage.sx_in()
    out = dict(zip(stage.name_out(), stage(*ins)))
    return ca.Function("contact_state", list(ins), [out["phi_ground"], out["slip_ground"], out["mu_ground"],
                                                    out["weight"]])


def stage_active_weights(cstate, N, args, n_k):
    """(2K, N) :func:`active_weights` of N intervals from the mapped contact-state
    function ``cstate`` (a callable of the stage's 9 inputs returning (phi, slip, mu,
    weight) as (K, N), (K, N), (1, N), (1, N) arrays); args : the stage's inputs with
    the ground impulses (2K, N) at index 4 and the global vector g at index 8."""
    from tacest.estimation.problem import G

    phi, slip, mu, weight = (np.asarray(a, float) for a in cstate(*args))
    lg = np.asarray(args[4], float).reshape(2 * n_k, N)
    g = np.asarray(args[8], float)
    sig_pen = g[G["sig_pen"]] if g.ndim == 1 else g[G["sig_pen"], :]
    return active_weights(phi.reshape(n_k, N), slip.reshape(n_k, N), lg[:n_k], lg[n_k:], mu.reshape(N),
                          weight.reshape(N), np.broadcast_to(sig_pen, (N,)))


def stage_residual_jacobian(stage):
    """SX Function (the stage's inputs, w, a) -> (r, J): one interval's whitened
    residuals (each squared term times sqrt of its weight, then eq. D2 over
    KINEMATICS_SIGMA, then the active-set rows a ⊙ [gaps; slips] with a from
    :func:`active_weights`) and their dense Jacobian with respect to the interval's
    local variables y (problem.stage_local_variables: [q_prev, v_prev, q, v,
    lam_ground, lam_finger, phys, s_prev, s])."""
    ins = stage.sx_in()
    w = ca.SX.sym("w", len(TERMS))
    out = dict(zip(stage.name_out(), stage(*ins)))
    K = out["phi_ground"].shape[0]
    a = ca.SX.sym("a", 2 * K)
    r = ca.vertcat(*[ca.sqrt(w[TERMS.index(t)]) * ca.vec(out[t]) for t in SQUARED_TERMS],
                   out["g_kin"] / KINEMATICS_SIGMA,
                   a * ca.vertcat(out["phi_ground"], out["slip_ground"]))
    y = stage_local_variables(ins)
    return ca.Function("stage_rj", [*ins, w, a], [ca.densify(r), ca.densify(ca.jacobian(r, y))])


def start_residual_jacobian(start):
    """SX Function (the start function's inputs, w) -> (r, J): a run's first-sample
    whitened residuals (START_TERM_OUTPUTS) and their dense Jacobian with respect to its
    local variables [q, v, phys, s] (problem.start_local_variables)."""
    ins = start.sx_in()
    w = ca.SX.sym("w", len(TERMS))
    out0 = dict(zip(start.name_out(), start(*ins)))
    r0 = ca.vertcat(*[ca.sqrt(w[TERMS.index(t)]) * ca.vec(out0[name]) for t, name in START_TERM_OUTPUTS])
    return ca.Function("start_rj", [*ins, w],
                       [ca.densify(r0), ca.densify(ca.jacobian(r0, start_local_variables(ins)))])


class _ResidualJacobian:
    """(z, p) -> (r (m,) DM, J (m, n_z) sparse DM) of the stacked whitened residuals
    (each squared term times the square root of its weight, then eq. D2 over
    KINEMATICS_SIGMA), assembled from per-sample Jacobians of the stage and start
    functions (SX, evaluated numerically): O(T), no symbolic Jacobian of the whole NLP.
    Rows are grouped per sample; JᵀJ does not depend on their order."""

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


def residual_jacobian_function(problem):
    """Callable (z, p) -> (r, J) of the stacked whitened residuals (see
    :class:`_ResidualJacobian`); cached per problem."""
    if getattr(problem, "_rjac", None) is None:
        problem._rjac = _ResidualJacobian(problem)
    return problem._rjac


def phys_jacobian_function(problem):
    """CasADi Function (theta, L, m0) -> ∂phys/∂theta (n_phys, n_theta); cached per problem."""
    if getattr(problem, "_dphys", None) is None:
        th = ca.SX.sym("theta", problem.n_theta)
        L, m0 = ca.SX.sym("L"), ca.SX.sym("m0")
        problem._dphys = ca.Function("dphys", [th, L, m0], [ca.jacobian(problem.phys_sx(th, L, m0), th)])
    return problem._dphys


def fold_lifted_parameters(problem, J, z, p):
    """J (m, n_z) sparse with the columns of the lifted ``phys`` block folded into theta's
    (J_θ + J_phys ∂phys/∂θ at z) and zeroed; L and m0 are the first two entries of p."""
    J = sp.csc_matrix(J)
    n_theta, a, n_phys = problem.n_theta, problem.phys_offset, problem.n_phys
    p = np.asarray(p, float).reshape(-1)
    D = np.asarray(phys_jacobian_function(problem)(np.asarray(z, float)[:n_theta], p[0], p[1]))
    J_theta = J[:, :n_theta] + J[:, a: a + n_phys] @ sp.csc_matrix(D)
    return sp.hstack([J_theta, J[:, n_theta:a], sp.csc_matrix((J.shape[0], n_phys)), J[:, a + n_phys:]],
                     format="csc")


def schur_information(A, B) -> np.ndarray:
    """(n_a, n_a) information of the kept columns with the nuisance ones marginalized:
    AᵀA − AᵀB (BᵀB + δI)⁻¹ BᵀA, computed with B's columns scaled to unit norm (zero
    columns left as they are) and δ = :data:`RIDGE`.

    A : (m, n_a) dense or sparse Jacobian columns of the kept variables;
    B : (m, n_x) sparse Jacobian columns of the nuisance variables.
    """
    return _schur(A, B)[0]


def _schur(A, B, g_a=None, g_b=None):
    """(schur_information(A, B), reduced gradient): with a gradient (g_a (n_a,), g_b
    (n_x,)) of some other function of the same variables, also its gradient with the
    nuisance variables moved along the data's best response, g_a − AᵀB (BᵀB + δI)⁻¹ g_b
    (same scaling and ridge); None without one."""
    A = sp.csc_matrix(A)
    I_aa = (A.T @ A).toarray()
    if B.shape[1] == 0:
        return 0.5 * (I_aa + I_aa.T), (None if g_a is None else np.asarray(g_a, float))
    B = sp.csc_matrix(B)
    norms = np.sqrt(np.asarray(B.multiply(B).sum(axis=0)).ravel())
    norms[norms == 0] = 1.0
    Bs = B @ sp.diags(1.0 / norms)
    I_xx = (Bs.T @ Bs).tocsc()
    I_xa = (Bs.T @ A).toarray()
    lu = spla.splu((I_xx + RIDGE * sp.identity(I_xx.shape[0], format="csc")).tocsc())
    I_s = I_aa - I_xa.T @ lu.solve(I_xa)
    g_r = None
    if g_a is not None:
        g_r = np.asarray(g_a, float) - I_xa.T @ lu.solve(np.asarray(g_b, float) / norms)
    return 0.5 * (I_s + I_s.T), g_r


def information_names(est):
    """Row names of the reported information matrix (physical parameters + final pose)."""
    shape = est.shape
    if shape.name == "box":
        shape_names = ["width", "height"]
    else:
        shape_names = [f"vertex{k}_{c}" for k in range(shape.n_vertices) for c in "xy"]
    from tacest.estimation.augment import effect_info_names

    return shape_names + ["mass", "inertia_log_ratio", "friction_ground", "friction_finger"] \
        + (effect_info_names(est.problem) if getattr(getattr(est, "problem", None), "n_eff", 0) else []) \
        + ["final_x", "final_y", "final_angle"]


def penalty_gradient_function(problem):
    """CasADi Function (z, p) -> gradient (n_z,) of the weighted penalty (Occam) terms of
    the objective; cached per problem."""
    if getattr(problem, "_gpen", None) is None:
        problem._gpen = ca.Function("gpen", [problem.z_sym, problem.p_sym],
                                    [ca.gradient(problem.f_penalty_reference, problem.z_sym)])
    return problem._gpen


def prior_hessian_function(problem):
    """CasADi Function (theta, prior) -> Hessian (n_theta, n_theta) of the objective's
    parameter priors (problem.prior_fun: the weak priors of shape, mass, inertia,
    frictions and effect parameters) in the scaled theta, without their on/off flag;
    built on theta alone (SX), cached per problem."""
    if getattr(problem, "_hprior", None) is None:
        th = ca.SX.sym("theta", problem.n_theta)
        pv = ca.SX.sym("prior", problem.prior_fun.size1_in(1))
        H, _ = ca.hessian(problem.prior_fun(th, pv), th)
        problem._hprior = ca.Function("hprior", [th, pv], [ca.densify(H)])
    return problem._hprior


def prior_values(problem, p) -> np.ndarray:
    """The prior vector (lm_sigma, lI_sigma, mu0, mu_sigma, shape_sigma, on/off, s_ref) of
    the NLP's parameter vector p (problem.py: p_all = [data, weights, prior, ridge])."""
    a = problem.n_p + len(TERMS)
    return np.asarray(p, float).reshape(-1)[a: a + problem.prior_fun.size1_in(1)]


#: relative eigenvalue of the information scaled to a unit diagonal (D^-1/2 I D^-1/2,
#: unit-free) at or below which a direction counts as flat, undetermined by the data: a
#: condition number of 1e10, far beyond what a fit's data resolve (finite differences
#: and IPOPT's tolerances give 1e-6..1e-8)
FLAT_RCOND = 1e-10
#: loading (of the unit-norm eigenvector, scaled units) of a parameter on flat
#: directions above which its std is infinite: along a flat direction it would have at
#: least FLAT_LOADING / sqrt(FLAT_RCOND) = 100 times the std it has with the others
#: held, i.e. the data do not determine it.  A parameter outside the flat directions
#: loads on them by rounding only (1e-8 and below)
FLAT_LOADING = 1e-3


def _std_of(I_phys, free, names):
    """({name: one-sigma}, cov (n, n)) from an information matrix.

    Over the free rows, the information is scaled to a unit diagonal and split into its
    eigen-directions: cov is the pseudo-inverse that drops the flat ones (eigenvalue at
    or below FLAT_RCOND of the largest; NaN outside the free block), and a parameter
    that loads on a flat direction (by more than FLAT_LOADING) gets an infinite std, as
    one without information or held does.  (A plain pseudo-inverse drops the flat
    directions silently and reports such a parameter with the small std it has with the
    others held, e.g. force_scale's gain against the mass.)  Where the eigen-solver
    fails: every std NaN and cov None."""
    n = len(names)
    cov = np.full_like(I_phys, np.nan)
    var = np.full(n, np.inf)
    idx = np.nonzero(free)[0]
    A = I_phys[np.ix_(idx, idx)]
    diag = np.diag(A).copy()
    has = diag > 0
    scale = np.sqrt(np.where(has, diag, 1.0))
    S = A / np.outer(scale, scale)
    S[~has, :] = 0.0
    S[:, ~has] = 0.0
    try:
        w, U = np.linalg.eigh(0.5 * (S + S.T))
    except np.linalg.LinAlgError:
        return {name: float("nan") for name in names}, None
    flat = w <= FLAT_RCOND * max(float(w.max()) if w.size else 0.0, 0.0)
    cov_s = (U[:, ~flat] / w[~flat]) @ U[:, ~flat].T
    cov_f = cov_s / np.outer(scale, scale)
    cov[np.ix_(idx, idx)] = cov_f
    loading = np.sqrt(np.sum(U[:, flat] ** 2, axis=1))
    determined = has & (loading <= FLAT_LOADING) & (np.diag(cov_f) > 0)
    var[idx[determined]] = np.diag(cov_f)[determined]
    std = {name: float(np.sqrt(var[k])) for k, name in enumerate(names)}
    return std, cov


def observed_information(est, z, lbx=None, ubx=None, penalty_shift=False, posterior=False):
    """(I (n, n), names (n,), std {name: sigma}) at the solution z of an ImplicitEstimator.

    Parameters are in physical units: lengths m, mass kg, inertia as log ratio to the
    uniform-density value, friction dimensionless, effect parameters as in
    tacest.estimation.augment, final pose m / rad.  Fixed variables
    (bounds equal) get zero information and infinite std.

    With ``penalty_shift``, a fourth item {name: shift}: how far the data alone would
    move each parameter from z, to first order, without the penalty (Occam) terms of the
    objective, I⁻¹ ∇penalty (the penalty's gradient with the nuisance variables
    following the data, :func:`_schur`), in the units above.  At the fit the data's and
    the penalty's gradients cancel: a shift of several std says the penalty, not the
    data, put the parameter where it is (see the estimator's identifiability check).
    A problem without penalty terms (no pose-observed run) has every shift 0, and its
    gradient is not computed.

    With ``posterior``, a last item {name: sigma}: the one-sigma uncertainty of the
    posterior, from the data's information plus the priors' (their Hessian at z, same
    units): what a user should read as the uncertainty of an estimate.  The data's own
    std (the third item) is what says whether the data determine a parameter; along a
    direction the data leave flat its pseudo-inverse drops that direction and is too
    small (force_scale's gain × mass: with a weighed mass the gain came out ± 0.005
    where the 2 % weighing error alone allows ± 0.026), while the posterior counts the
    prior that holds it.
    """
    pr = est.problem
    rj = residual_jacobian_function(pr)
    _, J = rj(z, est.p_final)
    J = J.sparse() if hasattr(J, "sparse") else sp.csc_matrix(np.array(J))
    J = fold_lifted_parameters(pr, sp.csc_matrix(J), z, est.p_final)
    n_theta = pr.n_theta
    last = len(pr.structures) - 1
    qa = pr.offsets[last]["Q"][0] + 3 * (pr.structures[last].T - 1)
    keep = list(range(n_theta)) + [qa, qa + 1, qa + 2]
    if lbx is None:
        lbx, ubx = est.variable_bounds()
    # held: equal bounds, or an interval of a few PIN_HALF_WIDTH (estimator.py) around a value
    fixed = np.asarray(ubx) - np.asarray(lbx) <= 1e-8
    n = pr.n_z
    is_keep = np.zeros(n, bool)
    is_keep[keep] = True
    is_keep[pr.phys_offset: pr.phys_offset + pr.n_phys] = True  # folded into theta, not nuisance
    nuis = np.nonzero(~is_keep & ~fixed)[0]
    g_a = g_b = None
    if penalty_shift and pr.with_occam:
        gp = np.asarray(penalty_gradient_function(pr)(z, est.p_final), float).reshape(1, -1)
        gp = np.asarray(fold_lifted_parameters(pr, sp.csc_matrix(gp), z, est.p_final).todense()).ravel()
        g_a, g_b = gp[keep], gp[nuis]
    I_s, g_r = _schur(J[:, keep], J[:, nuis], g_a, g_b)
    # scaled -> physical units: z_scaled = D · physical  =>  I_phys = D I D
    L = est.scales.L
    V, mass, *_ = est.physical(z)
    d = np.ones(len(keep))
    d[: pr.n_shape] = 1.0 / L
    d[pr.n_shape] = 1.0 / mass  # d log m / d m
    d[n_theta: n_theta + 2] = 1.0 / L
    if pr.n_eff:  # effect parameters (tacest.estimation.augment)
        from tacest.estimation.augment import effect_info_factors

        a = n_theta - pr.n_eff
        d[a: n_theta] = effect_info_factors(pr, np.asarray(z, float)[:n_theta], L, est.scales.m0)
    I_phys = I_s * np.outer(d, d)
    kept_fixed = fixed[keep]
    I_phys[kept_fixed, :] = 0.0
    I_phys[:, kept_fixed] = 0.0
    names = information_names(est)
    free = ~kept_fixed
    std, cov = _std_of(I_phys, free, names)
    extra = []
    if penalty_shift:
        shift = {name: (0.0 if not pr.with_occam else float("nan")) for name in names}
        if pr.with_occam and cov is not None and g_r is not None:
            # in physical units: I_phys = D I_s D, the gradient g_phys = D g_r
            delta = cov[np.ix_(free, free)] @ (d[free] * g_r[free])
            for k, value in zip(np.nonzero(free)[0], delta):
                shift[names[k]] = float(value)
        extra.append(shift)
    if posterior:
        pv = prior_values(pr, est.p_final)
        H = pv[5] * np.asarray(prior_hessian_function(pr)(np.asarray(z, float)[:n_theta], pv), float)
        # the priors act on theta only; held rows are left out by _std_of's free block
        P_phys = np.zeros_like(I_phys)
        P_phys[:n_theta, :n_theta] = H * np.outer(d[:n_theta], d[:n_theta])
        extra.append(_std_of(I_phys + P_phys, free, names)[0])
    return (I_phys, names, std, *extra)
